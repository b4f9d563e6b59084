"""Mode models on the planar state x = [xi, xi_dot, eta, eta_dot, omega] (m, m/s, m, m/s, rad/s).

Both are registered in the nonlinear model registry, so a session can pick them by name::

    cv = make_model("imm_cv", period_s=0.1, sigma_accel=0.003)
    ct = make_model("imm_ct", period_s=0.1, sigma_accel=0.0016, sigma_turn_step=np.radians(0.2))

Constant velocity (CV), white acceleration noise a ~ N(0, sigma_accel^2) per axis; the turn
rate is reset to 0 each step plus a small noise so the covariance stays invertible (the
information filter needs P^{-1})::

    [xi, xi_dot]+   = F2 [xi, xi_dot]   + G2 a_xi,     F2 = [[1, T], [0, 1]],  G2 = [T^2/2, T]
    [eta, eta_dot]+ = F2 [eta, eta_dot] + G2 a_eta
    omega+          = 0 + w_omega,                     w_omega ~ N(0, sigma_omega^2)

Coordinated turn (CT) with unknown rate omega (positive = counter-clockwise)::

    xi+      = xi + sin(wT)/w xi_dot - (1 - cos(wT))/w eta_dot
    xi_dot+  = cos(wT) xi_dot - sin(wT) eta_dot
    eta+     = eta + (1 - cos(wT))/w xi_dot + sin(wT)/w eta_dot
    eta_dot+ = sin(wT) xi_dot + cos(wT) eta_dot
    omega+   = omega + b,         b ~ N(0, sigma_turn_step^2)        (rad/s per step), or
    omega+   = omega + T b,       b ~ N(0, sigma_turn_accel^2)       (rad/s^2)

with the same G2 acceleration noise. As w -> 0 the CT map tends to the CV map (series used for
|w| < 1e-12 rad/s).

Both maps take any interval: the models' ``flow(tau)`` is the same map over tau (a sample taken
inside a step; exact: CV and CT compose over sub-intervals), with noise Q tau / T (the
per-step Q spread evenly over the step, an approximation of the WNA block's tau^3 shape).

The transition functions accept batches: x of shape (..., 5) -> (..., 5) (flagged
``vectorized``). ``u`` is unused (the models have no input, nu = 0); ``k`` is the step.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..checks import as_positive
from ..nonlinear.registry import NonlinearModel, register_model

#: State layout.
XI, XI_DOT, ETA, ETA_DOT, OMEGA = range(5)
N_STATE = 5
_SMALL_OMEGA = 1e-12


def _accel_block(T: float, sigma: float) -> np.ndarray:
    """Covariance of G2 a for one axis: sigma^2 [[T^4/4, T^3/2], [T^3/2, T^2]]."""
    g = np.array([T * T / 2.0, T])
    return sigma * sigma * np.outer(g, g)


def cv_transition(x: np.ndarray, T: float) -> np.ndarray:
    """CV map without noise: positions advance by T * velocity, omega := 0. Shape (..., 5)."""
    x = np.asarray(x, dtype=float)
    out = np.empty_like(x)
    out[..., XI] = x[..., XI] + T * x[..., XI_DOT]
    out[..., XI_DOT] = x[..., XI_DOT]
    out[..., ETA] = x[..., ETA] + T * x[..., ETA_DOT]
    out[..., ETA_DOT] = x[..., ETA_DOT]
    out[..., OMEGA] = 0.0
    return out


def ct_transition(x: np.ndarray, T: float) -> np.ndarray:
    """Coordinated-turn map without noise (exact for constant speed and rate). Shape (..., 5)."""
    x = np.asarray(x, dtype=float)
    w = x[..., OMEGA]
    wT = w * T
    s, c = np.sin(wT), np.cos(wT)
    small = np.abs(w) < _SMALL_OMEGA
    w_safe = np.where(small, 1.0, w)
    # sin(wT)/w -> T - w^2 T^3 / 6 ;  (1 - cos(wT))/w = 2 sin^2(wT/2)/w -> w T^2 / 2
    # (the half-angle form has no cancellation for small wT)
    a = np.where(small, T - w * w * T**3 / 6.0, s / w_safe)
    b = np.where(small, w * T * T / 2.0, 2.0 * np.sin(0.5 * wT) ** 2 / w_safe)
    vx, vy = x[..., XI_DOT], x[..., ETA_DOT]
    out = np.empty_like(x)
    out[..., XI] = x[..., XI] + a * vx - b * vy
    out[..., XI_DOT] = c * vx - s * vy
    out[..., ETA] = x[..., ETA] + b * vx + a * vy
    out[..., ETA_DOT] = s * vx + c * vy
    out[..., OMEGA] = w
    return out


@register_model("imm_cv")
def imm_cv(
    period_s: float = 0.1, sigma_accel: float = 0.003, sigma_omega: float = 1e-4
) -> NonlinearModel:
    """Constant velocity. period_s (s), sigma_accel (m/s^2), sigma_omega (rad/s: std of the
    turn rate after its reset to 0; small, it only keeps P invertible)."""
    T = as_positive(period_s, "period_s")
    sa = as_positive(sigma_accel, "sigma_accel")
    so = as_positive(sigma_omega, "sigma_omega")
    Q = np.zeros((N_STATE, N_STATE))
    blk = _accel_block(T, sa)
    Q[np.ix_([XI, XI_DOT], [XI, XI_DOT])] = blk
    Q[np.ix_([ETA, ETA_DOT], [ETA, ETA_DOT])] = blk
    Q[OMEGA, OMEGA] = so * so
    Q.setflags(write=False)
    def f(x: np.ndarray, u: object, k: int) -> np.ndarray:
        return cv_transition(x, T)

    def flow(tau: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        return lambda x, u: cv_transition(x, tau)

    return NonlinearModel(name="imm_cv", n=N_STATE, nu=0, f=f, Q=Q, vectorized=True,
                          flow=flow, period_s=T)


@register_model("imm_ct")
def imm_ct(
    period_s: float = 0.1,
    sigma_accel: float = 0.0016,
    sigma_turn_accel: float | None = None,
    sigma_turn_step: float | None = None,
) -> NonlinearModel:
    """Coordinated turn with unknown rate. period_s (s), sigma_accel (m/s^2).

    Turn-rate noise, give at most one:

    * ``sigma_turn_step`` (rad/s): std of the rate's increment per step, omega+ = omega + b
      (Gamma_omega = 1). Default 0.2 deg/s = 0.00349 rad/s.
    * ``sigma_turn_accel`` (rad/s^2): white turn acceleration, omega+ = omega + T b
      (Gamma_omega = T), i.e. an increment std of T * sigma_turn_accel per step.
    """
    T = as_positive(period_s, "period_s")
    sa = as_positive(sigma_accel, "sigma_accel")
    if sigma_turn_accel is not None and sigma_turn_step is not None:
        raise ValueError("imm_ct: give at most one of sigma_turn_accel and sigma_turn_step")
    if sigma_turn_accel is not None:
        q_omega = (T * as_positive(sigma_turn_accel, "sigma_turn_accel")) ** 2
    else:
        step = np.radians(0.2) if sigma_turn_step is None else sigma_turn_step
        q_omega = as_positive(step, "sigma_turn_step") ** 2
    Q = np.zeros((N_STATE, N_STATE))
    blk = _accel_block(T, sa)
    Q[np.ix_([XI, XI_DOT], [XI, XI_DOT])] = blk
    Q[np.ix_([ETA, ETA_DOT], [ETA, ETA_DOT])] = blk
    Q[OMEGA, OMEGA] = q_omega
    Q.setflags(write=False)
    def f(x: np.ndarray, u: object, k: int) -> np.ndarray:
        return ct_transition(x, T)

    def flow(tau: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        return lambda x, u: ct_transition(x, tau)

    return NonlinearModel(name="imm_ct", n=N_STATE, nu=0, f=f, Q=Q, vectorized=True,
                          flow=flow, period_s=T)


def heading(x: np.ndarray) -> np.ndarray:
    """Course angle atan2(eta_dot, xi_dot) in rad, shape (...,) from x (..., 5)."""
    x = np.asarray(x)
    return np.arctan2(x[..., ETA_DOT], x[..., XI_DOT])
