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
