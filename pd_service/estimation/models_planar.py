"""Planar constant-velocity (CV) model for the linear observer-predictor.

State x = [px, vx, py, vy] (m, m/s, m, m/s): position and velocity per axis, interleaved per
axis like the paper's model (:func:`~.scenarios.paper_model`: [p1, v1, p2, v2]). The two axes
are independent, so A, B and Q are block-diagonal with one 2 x 2 block per axis.

Without commands (``tau=None``, nu = 0) each axis is the discretised continuous white-noise
acceleration model (acceleration a(t) white with spectral density q, m^2/s^3)::

    [p, v](k+1) = [[1, dt], [0, 1]] [p, v](k) + w,   Q_axis = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]

With commands (``tau`` >= 0 given, nu = 2): u = (vx_cmd, vy_cmd), world-frame velocity
set-points (m/s) held over the step, followed through a first-order lag of time constant tau
(s): dv/dt = (v_cmd - v) / tau + a(t). Its exact discretisation, with x = dt / tau,
e = exp(-x) and c = (1 - e) / x (the step mean of the lag's response), is::

    p(k+1) = p + dt (c v + (1 - c) v_cmd)
    v(k+1) = e v + (1 - e) v_cmd
    Q_axis = q [[dt^3 g(x),       dt^2 c^2 / 2],
                [dt^2 c^2 / 2,    dt (1 - e^2) / (2 x)]]
    g(x)   = (1 - 2 (1 - e) / x + (1 - e^2) / (2 x)) / x^2
           = sum_{k>=2} (-1)^k (2^k - 2) x^(k-2) / (k+1)!      (= 1/3 - x/4 + 7 x^2/60 - ...)

which tends to the CV model (and its Q) as tau -> infinity. tau = 0 (velocity = set-point at
once) leaves the velocity without memory, so the acceleration noise vanishes; it is refused.
A body-frame command (a Twist's linear.x, angular.z) is not linear in this state: use the
``"unicycle"`` model of the unscented backend for that.
"""

from __future__ import annotations

import math

import numpy as np

from .checks import as_nonnegative
from .model import LinearModel

#: Rows of H for the usual planar sensors on [px, vx, py, vy].
H_POSITION = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
H_VELOCITY = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
H_POSITION.setflags(write=False)
H_VELOCITY.setflags(write=False)

#: Below this dt / tau, g(x) is summed from its series (the closed form cancels).
_SERIES_BELOW = 0.5
_SERIES_TERMS = 24


def white_accel_block(dt: float, q: float) -> np.ndarray:
    """Q of one axis of the CV model: q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (dt s, q m^2/s^3)."""
    return q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


def _g(x: float) -> float:
    """(1 - 2 (1 - e^-x) / x + (1 - e^-2x) / (2 x)) / x^2, without cancellation for small x."""
    if x < _SERIES_BELOW:
        return sum((-1) ** k * (2**k - 2) * x ** (k - 2) / math.factorial(k + 1)
                   for k in range(2, _SERIES_TERMS))
    return (1.0 + 2.0 * math.expm1(-x) / x - math.expm1(-2.0 * x) / (2.0 * x)) / (x * x)


def lagged_axis(dt: float, tau: float, q: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (2, 2), B (2, 1), Q (2, 2)) of one axis with a velocity set-point through a lag tau."""
    x = dt / tau
    e = math.exp(-x)
    c = -math.expm1(-x) / x
    A = np.array([[1.0, dt * c], [0.0, e]])
    B = np.array([[dt * (1.0 - c)], [1.0 - e]])
    Q = q * np.array([[dt**3 * _g(x), dt**2 * c * c / 2.0],
                      [dt**2 * c * c / 2.0, dt * -math.expm1(-2.0 * x) / (2.0 * x)]])
    return A, B, Q


def planar_cv(period_s: float, q: float, tau: float | None = None) -> LinearModel:
    """The planar CV model on [px, vx, py, vy]. period_s (s) > 0, q (m^2/s^3) >= 0 the
    acceleration noise density (same on both axes); ``tau`` (s) > 0: velocity commands
    (vx_cmd, vy_cmd) through a first-order lag, None: no input (pure CV)."""
    dt = as_nonnegative(period_s, "period_s", strict=True)
    qq = as_nonnegative(q, "q", strict=False)
    if tau is None:
        A2 = np.array([[1.0, dt], [0.0, 1.0]])
        B2 = np.zeros((2, 0))
        Q2 = white_accel_block(dt, qq)
    else:
        A2, B2, Q2 = lagged_axis(dt, as_nonnegative(tau, "tau", strict=True), qq)
    Z = np.zeros((2, 2))
    A = np.block([[A2, Z], [Z, A2]])
    Q = np.block([[Q2, Z], [Z, Q2]])
    B = np.zeros((4, 2 * B2.shape[1]))
    B[0:2, 0:B2.shape[1]] = B2
    B[2:4, B2.shape[1]:] = B2
    return LinearModel(A=A, B=B, Q=Q)
