"""A from-scratch batch re-filter: the definition the observer-predictor must equal.

Plain Kalman filter, one step at a time, from x0, P0 at step 0 over every accepted packet in
stamp order (sensors within a step in sensor order, sequentially), then predicted forward.
Deliberately naive: no tables, no caching, no shared code with the package.
"""

from __future__ import annotations

import numpy as np


def applied_inputs(commands, nu, steps, hold=True):
    """u(0) .. u(steps - 1) from commands {step: u}: a step without a command holds the last
    one (``hold``, zeros before the first) or applies zeros."""
    us = []
    u_held = np.zeros(nu)
    for k in range(steps):
        if k in commands:
            u = np.asarray(commands[k], float)
            if hold:
                u_held = u
        else:
            u = u_held if hold else np.zeros(nu)
        us.append(u)
    return us


def batch_predict(A, B, Q, sensors, x0, P0, commands, packets, target, hold=True):
    """sensors: list of (H, R); commands: {step: u}; packets: list of (sensor_idx, step, z, R|None).

    Returns (x, P) of x(target).
    """
    n = A.shape[0]
    nu = B.shape[1]
    by_step: dict[int, list] = {}
    for idx, step, z, R in packets:
        by_step.setdefault(step, []).append((idx, np.asarray(z, float), R))
    x = np.array(x0, float)
    P = np.array(P0, float)
    us = applied_inputs(commands, nu, target, hold)
    for k in range(target + 1):
        for idx, z, R in sorted(by_step.get(k, []), key=lambda t: t[0]):
            H, R0 = sensors[idx]
            Rk = R0 if R is None else R
            S = H @ P @ H.T + Rk
            K = P @ H.T @ np.linalg.pinv(S)
            x = x + K @ (z - H @ x)
            P = (np.eye(n) - K @ H) @ P
            P = 0.5 * (P + P.T)
        if k == target:
            break
        x = A @ x + B @ us[k]
        P = A @ P @ A.T + Q
    return x, P


def eigen_discretiser(F, G, Qc):
    """A(tau), B(tau), Q(tau) of dx = (F x + G u) dt + dw, E[dw dw^T] = Qc dt, in closed form
    through the eigendecomposition F = V diag(lam) V^-1 (F diagonalisable): no matrix
    exponential, no series, nothing shared with the package::

        A = V e^{lam tau} V^-1,   B = V diag((e^{lam tau} - 1) / lam) V^-1 G,
        Q = V [(V^-1 Qc V^-H)_ij (e^{(lam_i + conj lam_j) tau} - 1) / (lam_i + conj lam_j)] V^H
    """
    lam, V = np.linalg.eig(np.asarray(F, float))
    Vi = np.linalg.inv(V)
    Gt = Vi @ np.asarray(G, float)
    Qt = Vi @ np.asarray(Qc, float) @ Vi.conj().T
    s = lam[:, None] + lam.conj()[None, :]

    def phi(a, tau):  # (e^{a tau} - 1) / a, tau at a = 0
        out = np.full(a.shape, tau, dtype=complex)
        nz = a != 0
        out[nz] = np.expm1(a[nz] * tau) / a[nz]
        return out

    def at(tau):
        A = (V * np.exp(lam * tau)) @ Vi
        B = V @ (phi(lam, tau)[:, None] * Gt)
        Q = V @ (Qt * phi(s, tau)) @ V.conj().T
        return A.real, B.real, 0.5 * (Q.real + Q.real.T)

    return at


def continuous_batch_predict(discretise, sensors, x0, P0, commands, packets, t_end, nu,
                             period, hold=True):
    """The continuous-discrete Kalman filter from x0, P0 at time 0 over every packet in time
    order, then predicted to ``t_end`` (s): the definition for samples and commands at their
    own times.

    discretise(tau) -> (A, B, Q) over tau seconds; sensors: list of (H, R); commands: list
    of (step, offset_s, u): u from step * period + offset on ("hold"; "zero": u over the
    whole step, the offset ignored, zero elsewhere); packets: list of (sensor_idx, time_s,
    z, R|None), those after t_end ignored. Returns (x, P) of x(t_end).
    """
    n = len(x0)
    x = np.array(x0, float)
    P = np.array(P0, float)
    # the input's change points: (time, u)
    changes = []
    if hold:
        for j, d, u in sorted(commands, key=lambda c: (c[0], c[1])):
            changes.append((j * period + d, np.asarray(u, float)))
    else:
        for j, _, u in sorted(commands, key=lambda c: c[0]):
            changes.append((j * period, np.asarray(u, float)))
            if not any(c[0] == j + 1 for c in commands):
                changes.append(((j + 1) * period, np.zeros(nu)))
    events = [(t, 0, i) for i, (t, _) in enumerate(changes) if t <= t_end]
    events += [(t, 1, (idx, k)) for k, (idx, t, _, _) in enumerate(packets) if t <= t_end]
    events.sort(key=lambda e: (e[0], e[1], e[2]))
    events.append((t_end, 2, 0))
    u = np.zeros(nu)
    t = 0.0
    for te, what, ref in events:
        if te > t:
            A, B, Q = discretise(te - t)
            x = A @ x + B @ u
            P = A @ P @ A.T + Q
            P = 0.5 * (P + P.T)
            t = te
        if what == 0:
            u = changes[ref][1]
        elif what == 1:
            idx, k = ref
            _, _, z, R = packets[k]
            H, R0 = sensors[idx]
            Rk = R0 if R is None else R
            S = H @ P @ H.T + Rk
            K = P @ H.T @ np.linalg.pinv(S)
            x = x + K @ (np.asarray(z, float) - H @ x)
            P = (np.eye(n) - K @ H) @ P
            P = 0.5 * (P + P.T)
    return x, P
