"""Unscented Kalman filter steps, with optional sensitivities d/dq_m for the MIT rule.

Time update (one step k -> k+1, input u(k)), sigma points chi_i of N(x, P)::

    Y_i = f(chi_i, u, k),   x- = sum Wm_i Y_i,   P- = sum Wc_i (Y_i - x-)(Y_i - x-)^T + Q

Measurement update at a step with packets z (the present sensors stacked), sigma points
*redrawn* from N(x-, P-), so that the innovation covariance contains Q::

    Z_i = h(chi_i),  z^ = sum Wm_i Z_i,   S = sum Wc_i (Z_i - z^)(Z_i - z^)^T + R
    Pxz = sum Wc_i (chi_i - x-)(Z_i - z^)^T,   K = Pxz S^{-1},   nu = z - z^
    x+ = x- + K nu,   P+ = P- - K Pxz^T

Angles (the model's / sensor's ``angles``) are averaged around the first sigma point and
their residuals and innovations are wrapped to [-pi, pi).

Sensitivities: for adapted diagonal entries q_m of Q (m = 1..p), the filter carries
dx = dx/dq (p, n) and dP = dP/dq (p, n, n) and differentiates every line above::

    d chi_i = dx + c (+/-) dL[:, i],  dL from dP (see :func:`.sigma.cholesky_derivative`)
    dY_i = F(chi_i) d chi_i          (F = df/dx: the model's ``jac``, else central differences)
    dx- = sum Wm dY_i,   dP- = sum Wc (dD_i D_i^T + D_i dD_i^T) + dQ/dq_m   (dQ/dq_m = e_m e_m^T)
    dZ_i = H(chi_i) d chi_i,   dz^ = sum Wm dZ_i,   dS = sum Wc (dDZ DZ^T + DZ dDZ^T)
    dPxz = sum Wc (dDX DZ^T + DX dDZ^T),   dK = (dPxz - K dS) S^{-1},   dnu = -dz^
    dx+ = dx- + dK nu + K dnu,   dP+ = dP- - dK Pxz^T - K dPxz^T

(q treated as a constant parameter of the recursion, as the MIT rule does.)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..estimator_state import check_names, take
from ..linear import block_diag
from ..replay import Packet
from .events import segments, split_packets, splits
from .registry import MeasurementModel, NonlinearModel, wrap_angle
from .sigma import SigmaWeights, cholesky_derivative, sqrt_cov

#: k -> (u(k) (nu,), (offset s, input before) of a command taking effect inside step k or None)
InputsAt = Callable[[int], tuple[np.ndarray, tuple[float, np.ndarray] | None]]


@dataclass(frozen=True, slots=True)
class UKFState:
    """Gaussian estimate: mean ``x`` (n,), covariance ``P`` (n, n); with sensitivities to the
    adapted q_m: ``dx`` (p, n) and ``dP`` (p, n, n), or None when not tracked."""

    x: np.ndarray
    P: np.ndarray
    dx: np.ndarray | None = None
    dP: np.ndarray | None = None

    @property
    def tracked(self) -> bool:
        return self.dx is not None


@dataclass(frozen=True, slots=True)
class InnovationRecord:
    """What a measurement update saw, for adapters. M = stacked measurement dimension.

    ``blocks``: (sensor index, start, stop) of each present sensor's rows in nu / S.
    ``nu`` (M,) innovation, ``S`` (M, M) its predicted covariance (R included), ``K`` (n, M)
    gain, ``gap`` time steps since the previous measurement update (counted from step 0 for
    the first one, so 0 if that is at step 0),
    ``Q`` the process noise used; ``dnu`` (p, M), ``dS`` (p, M, M) sensitivities or None.
    """

    step: int
    blocks: tuple[tuple[int, int, int], ...]
    nu: np.ndarray
    S: np.ndarray
    K: np.ndarray
    gap: int
    Q: np.ndarray
    dnu: np.ndarray | None
    dS: np.ndarray | None


class ModelOps:
    """Batched evaluation of f, h and their Jacobian-vector products over sigma points."""

    #: relative size of the perturbation for central-difference JVPs (no ``jac`` given)
    FD_STEP = 1e-6

    def __init__(self, model: NonlinearModel, sensor_names: Sequence[str]) -> None:
        self.model = model
        self.n = model.n
        self.sensors: list[MeasurementModel] = [model.sensors[s] for s in sensor_names]
        self.x_angles = np.array(sorted(set(model.angles)), dtype=int)
        self.z_angles = [np.array(sorted(set(s.angles)), dtype=int) for s in self.sensors]

    # --- f -----------------------------------------------------------------------------

    def f(self, X: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
        """Y (N, n) = f(X (N, n), u, k) row by row."""
        m = self.model
        Y = m.f(X, u, k) if m.vectorized else np.array([m.f(x, u, k) for x in X])
        Y = np.asarray(Y, dtype=float)
        if Y.shape != X.shape:
            raise ValueError(f"model {m.name!r}: f returned shape {Y.shape}, expected {X.shape}")
        return Y

    def f_over(self, X: np.ndarray, u: np.ndarray, tau: float) -> np.ndarray:
        """Y (N, n) = the model's flow over tau seconds (part of a step) of X (N, n)."""
        m = self.model
        assert m.flow is not None
        fn = m.flow(tau)
        Y = fn(X, u) if m.vectorized else np.array([fn(x, u) for x in X])
        return np.asarray(Y, dtype=float).reshape(X.shape)

    def f_jvp(self, X: np.ndarray, dX: np.ndarray, u: np.ndarray, k: int,
              tau: float | None = None) -> np.ndarray:
        """dY (p, N, n) = F(X_i) dX[j, i] for each direction j (of the flow over ``tau``
        seconds if given: central differences)."""
        m = self.model
        if tau is not None:
            return self._fd_jvp(lambda Z: self.f_over(Z, u, tau), X, dX)
        if m.jac is not None:
            F = m.jac(X, u, k) if m.vectorized else np.array([m.jac(x, u, k) for x in X])
            return np.einsum("iab,pib->pia", F, dX)
        return self._fd_jvp(lambda Z: self.f(Z, u, k), X, dX)

    # --- h -----------------------------------------------------------------------------

    def h(self, i: int, X: np.ndarray) -> np.ndarray:
        """Z (N, m_i) = h_i(X) row by row."""
        s = self.sensors[i]
        Z = s.h(X) if s.vectorized else np.array([s.h(x) for x in X])
        Z = np.asarray(Z, dtype=float).reshape(X.shape[0], -1)
        if Z.shape[1] != s.m:
            raise ValueError(f"sensor {s.name!r}: h returned {Z.shape[1]} values, expected {s.m}")
        return Z

    def h_jvp(self, i: int, X: np.ndarray, dX: np.ndarray) -> np.ndarray:
        s = self.sensors[i]
        if s.jac is not None:
            H = s.jac(X) if s.vectorized else np.array([s.jac(x) for x in X])
            return np.einsum("iab,pib->pia", H, dX)
        return self._fd_jvp(lambda Z: self.h(i, Z), X, dX)

    def _fd_jvp(self, fn, X: np.ndarray, dX: np.ndarray) -> np.ndarray:
        """Central difference along each direction: (fn(X + e d) - fn(X - e d)) / (2 e),
        e chosen so the largest perturbation is FD_STEP * max(1, max|X|)."""
        scale = max(1.0, float(np.max(np.abs(X))))
        out = []
        for d in dX:
            dmax = float(np.max(np.abs(d)))
            if dmax == 0.0:
                out.append(np.zeros_like(fn(X)))
                continue
            e = self.FD_STEP * scale / dmax
            out.append((fn(X + e * d) - fn(X - e * d)) / (2.0 * e))
        return np.array(out)


def _mean(W: np.ndarray, Y: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """sum W_i Y_i; angle components averaged as ref + sum W_i wrap(Y_i - ref), ref = Y_0."""
    m = W @ Y
    if angles.size:
        ref = Y[0, angles]
        m[angles] = wrap_angle(ref + W @ wrap_angle(Y[:, angles] - ref))
    return m


def _resid(Y: np.ndarray, mean: np.ndarray, angles: np.ndarray) -> np.ndarray:
    D = Y - mean
    if angles.size:
        D[:, angles] = wrap_angle(D[:, angles])
    return D


def _wsum_outer(A: np.ndarray, W: np.ndarray, B: np.ndarray) -> np.ndarray:
    """sum_i W_i A_i B_i^T for A (N, a), B (N, b) -> (a, b)."""
    return (A.T * W) @ B


def _dwsum_outer(dA: np.ndarray, W: np.ndarray, B: np.ndarray) -> np.ndarray:
    """sum_i W_i dA_ji B_i^T for dA (p, N, a), B (N, b) -> (p, a, b)."""
    return np.einsum("pia,i,ib->pab", dA, W, B)


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def time_step(ops: ModelOps, w: SigmaWeights, Q: np.ndarray, state: UKFState, u: np.ndarray,
              k: int, dQ: np.ndarray | None = None, tau: float | None = None) -> UKFState:
    """One step x(k) -> x(k+1), or with ``tau`` (s) the part x(t) -> x(t + tau) of step k
    through the model's flow (``Q``, ``dQ`` then the noise over tau). Sensitivities are
    propagated iff ``state.tracked``; ``dQ`` (p, n, n) = dQ/dq_m is then required."""
    x, P = state.x, state.P
    L = sqrt_cov(P)
    X = w.points(x, L)                      # chi_i
    # Y_i = f(chi_i, u, k)
    Y = ops.f(X, u, k) if tau is None else ops.f_over(X, u, tau)
    xm = _mean(w.Wm, Y, ops.x_angles)       # x- = sum Wm_i Y_i
    D = _resid(Y, xm, ops.x_angles)         # Y_i - x-
    Pm = _sym(_wsum_outer(D, w.Wc, D) + Q)  # P- = sum Wc_i D_i D_i^T + Q
    if state.dx is None or state.dP is None:  # not tracked
        return UKFState(xm, Pm)
    dL = cholesky_derivative(L, state.dP)
    dX = w.point_offsets(state.dx, dL)      # d chi_i
    dY = ops.f_jvp(X, dX, u, k, tau)        # dY_i = F(chi_i) d chi_i
    dxm = np.einsum("pia,i->pa", dY, w.Wm)  # dx- = sum Wm_i dY_i
    dD = dY - dxm[:, None, :]
    T = _dwsum_outer(dD, w.Wc, D)
    dPm = T + np.swapaxes(T, 1, 2) + dQ     # dP- = sum Wc (dD D^T + D dD^T) + dQ
    return UKFState(xm, Pm, dxm, dPm)


def measurement_update(ops: ModelOps, w: SigmaWeights, state: UKFState, step: int,
                       packets: Sequence[Packet], gap: int = 1,
                       Q: np.ndarray | None = None) -> tuple[UKFState, InnovationRecord]:
    """Condition x(step) on the stacked packets (sorted by sensor). Sensitivities iff tracked."""
    x, P = state.x, state.P
    L = sqrt_cov(P)
    X = w.points(x, L)                      # redrawn from the predicted N(x-, P-)
    DX = X - x                              # chi_i - x-  (exact offsets +/- c L)
    Zs, zs, Rs, angles, blocks = [], [], [], [], []
    start = 0
    for p in packets:
        s = ops.sensors[p.sensor]
        Zs.append(ops.h(p.sensor, X))
        zs.append(p.z)
        Rs.append(s.R if p.R is None else p.R)
        angles.append(ops.z_angles[p.sensor] + start)
        blocks.append((p.sensor, start, start + s.m))
        start += s.m
    Z = Zs[0] if len(Zs) == 1 else np.hstack(Zs)
    z = zs[0] if len(zs) == 1 else np.concatenate(zs)
    za = angles[0] if len(angles) == 1 else np.concatenate(angles)
    R = Rs[0] if len(Rs) == 1 else block_diag(Rs)
    zhat = _mean(w.Wm, Z, za)               # z^ = sum Wm_i Z_i
    DZ = _resid(Z, zhat, za)
    S = _sym(_wsum_outer(DZ, w.Wc, DZ) + R)  # S = sum Wc DZ DZ^T + R
    Pxz = _wsum_outer(DX, w.Wc, DZ)          # Pxz = sum Wc DX DZ^T
    Sinv = _inv(S)
    K = Pxz @ Sinv                           # K = Pxz S^{-1}
    nu = z - zhat                            # innovation
    if za.size:
        nu[za] = wrap_angle(nu[za])
    xp = x + K @ nu
    if ops.x_angles.size:
        xp[ops.x_angles] = wrap_angle(xp[ops.x_angles])
    Pp = _sym(P - K @ Pxz.T)                 # P+ = P- - K Pxz^T  (= P- - K S K^T)
    dx = dP = dnu = dS = None
    if state.dx is not None and state.dP is not None:  # tracked
        dL = cholesky_derivative(L, state.dP)
        dX = w.point_offsets(state.dx, dL)
        dDX = dX - state.dx[:, None, :]
        dZ = np.concatenate([ops.h_jvp(p.sensor, X, dX) for p in packets], axis=2)
        dzhat = np.einsum("pia,i->pa", dZ, w.Wm)
        dDZ = dZ - dzhat[:, None, :]
        T = _dwsum_outer(dDZ, w.Wc, DZ)
        dS = T + np.swapaxes(T, 1, 2)        # dS = sum Wc (dDZ DZ^T + DZ dDZ^T)
        dPxz = _dwsum_outer(dDX, w.Wc, DZ) + np.swapaxes(_dwsum_outer(dDZ, w.Wc, DX), 1, 2)
        dK = (dPxz - K @ dS) @ Sinv          # dK = (dPxz - K dS) S^{-1}
        dnu = -dzhat
        dx = state.dx + dK @ nu + dnu @ K.T  # dx+ = dx- + dK nu + K dnu
        dP = _sym(state.dP - dK @ Pxz.T - K @ np.swapaxes(dPxz, 1, 2))
    rec = InnovationRecord(step, tuple(blocks), nu, S, K, gap,
                           Q if Q is not None else np.zeros((0, 0)), dnu, dS)
    return UKFState(xp, Pp, dx, dP), rec


def _inv(S: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(S)


class UnscentedBackend:
    """:class:`~pd_service.estimation.replay.Backend` for the UKF; state = :class:`UKFState`.

    ``Q`` is the process noise every propagation uses (the adaptive estimator replaces it on
    the committed horizon); a ``Q_schedule`` k -> Q(k) (n, n), if given, overrides it with a
    known Q for each step k -> k+1. A tracked state (with sensitivities) stays tracked through
    :meth:`propagate`; :meth:`update` drops sensitivities (speculative posteriors never need
    them), :meth:`update_tracked` keeps them and returns the innovation record.

    Packets with an offset inside their step are applied at their own time (:mod:`.events`):
    :meth:`update` then hands on x(step + 1), reading u(step) through ``inputs_at`` (set by
    the estimator: k -> (u(k), the (offset, input before) of a command taking effect inside
    step k, or None)). A model without ``flow`` takes no offsets (the estimator refuses them).
    """

    def __init__(self, ops: ModelOps, weights: SigmaWeights, Q: np.ndarray,
                 dQ: np.ndarray | None = None,
                 Q_schedule: Callable[[int], np.ndarray] | None = None) -> None:
        self.ops = ops
        self.weights = weights
        self.Q = Q
        self.dQ = dQ
        self.Q_schedule = Q_schedule
        self.inputs_at: InputsAt | None = None

    def propagate(self, state: UKFState, step: int, m: int, U: np.ndarray) -> UKFState:
        ops, w, Q, dQ = self.ops, self.weights, self.Q, self.dQ
        sched = self.Q_schedule
        for j in range(m):
            if sched is not None:
                Q = sched(step + j)  # known Q of the step k -> k+1
            state = time_step(ops, w, Q, state, U[j], step + j, dQ)
        return state

    def _through_step(self, state: UKFState, k: int, inside: list[Packet]) -> UKFState:
        """x(k) -> x(k+1) through the packets sampled inside step k (sorted by offset)."""
        ops, w, dQ = self.ops, self.weights, self.dQ
        T = ops.model.period_s
        if self.inputs_at is None:
            raise ValueError("samples inside a step need the estimator's inputs (inputs_at)")
        u, cut = self.inputs_at(k)
        Q = self.Q if self.Q_schedule is None else self.Q_schedule(k)
        for t, tau, group in segments(inside, T, None if cut is None else cut[0]):
            uk = u if cut is None or t >= cut[0] else cut[1]  # the command held at t
            r = tau / T  # noise over tau: Q tau / T
            state = time_step(ops, w, Q * r, state, uk, k, None if dQ is None else dQ * r, tau)
            if group:
                state = measurement_update(ops, w, state, k, group)[0]
        return state

    def update(self, state: UKFState, step: int, packets: list[Packet]) -> UKFState:
        """x(step) conditioned on ``packets``; with packets inside the step, x(step + 1)."""
        start, inside = split_packets(packets, self._splits)
        if state.tracked:
            state = UKFState(state.x, state.P)
        if start:
            state = measurement_update(self.ops, self.weights, state, step, start)[0]
        return self._through_step(state, step, inside) if inside else state

    def update_tracked(self, state: UKFState, step: int, packets: list[Packet],
                       gap: int) -> tuple[UKFState, InnovationRecord | None]:
        """:meth:`update` keeping sensitivities; the record is that of the packets at the
        step's start (None if there are none): the adapter learns from those only."""
        start, inside = split_packets(packets, self._splits)
        rec = None
        if start:
            state, rec = measurement_update(self.ops, self.weights, state, step, start, gap,
                                            self.Q)
        if inside:
            state = self._through_step(state, step, inside)
        return state, rec

    @property
    def _splits(self) -> bool:
        return splits(self.ops.model)

    def moments(self, state: UKFState) -> tuple[np.ndarray, np.ndarray]:
        return state.x, state.P

    def export_state(self, state: UKFState) -> dict[str, np.ndarray]:
        """{"x", "P"} plus {"dx", "dP"} for a tracked state."""
        out = {"x": state.x.copy(), "P": state.P.copy()}
        if state.dx is not None and state.dP is not None:
            out["dx"], out["dP"] = state.dx.copy(), state.dP.copy()
        return out

    def import_state(self, arrays: dict[str, np.ndarray]) -> UKFState:
        """A tracked state iff this backend tracks sensitivities (``dQ`` set)."""
        n = self.ops.n
        if self.dQ is None:
            check_names(arrays, {"x", "P"})
            return UKFState(take(arrays, "x", (n,)), take(arrays, "P", (n, n)))
        p = self.dQ.shape[0]
        check_names(arrays, {"x", "P", "dx", "dP"})
        return UKFState(take(arrays, "x", (n,)), take(arrays, "P", (n, n)),
                        take(arrays, "dx", (p, n)), take(arrays, "dP", (p, n, n)))
