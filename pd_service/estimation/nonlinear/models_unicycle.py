"""Planar unicycle / differential-drive robot, registered as ``"unicycle"``.

State s = (x, y, yaw, v, w): pose in the world (odometry) frame (m, m, rad) and the body's
forward speed and yaw rate (m/s, rad/s). Input u = (v_cmd, w_cmd) (m/s, rad/s): a
geometry_msgs/Twist's ``linear.x`` and ``angular.z``, held over the step and applied as
velocity set-points through first-order lags with time constants tau_v, tau_w (s).

One step of length dt (exact for the lags; tau = 0 means no lag, the set-point at once)::

    e_v = exp(-dt / tau_v),  a_v = (tau_v / dt) (1 - e_v)       (a_v = 0 when tau_v = 0)
    v(k+1) = v_cmd + (v - v_cmd) e_v                            (same for w with tau_w)
    vbar   = v_cmd + (v - v_cmd) a_v                            mean of v(t) over the step
    wbar   = w_cmd + (w - w_cmd) a_w                            mean of w(t) over the step

and the pose follows the exact arc of constant (vbar, wbar) over dt, written in its chord form
so that wbar -> 0 needs no division by the yaw rate::

    dpsi = wbar dt,   d = vbar dt S(dpsi),   S(a) = sin(a/2) / (a/2)  (S(0) = 1)
    x(k+1)   = x + d cos(yaw + dpsi/2)
    y(k+1)   = y + d sin(yaw + dpsi/2)
    yaw(k+1) = wrap(yaw + dpsi)

(identical to x + vbar/wbar (sin(yaw + dpsi) - sin(yaw)), y - vbar/wbar (cos(yaw + dpsi) -
cos(yaw)) for wbar != 0, and to the straight step for wbar = 0). The yaw is exact for any
command (it integrates w(t) exactly); the position is exact whenever v and w are constant over
the step (the steady state, or a straight line at any speed profile: then d = the exact
distance); while both speeds change it is the arc of their step means. Process noise is
additive, Q = diag of 5 values (or a 5 x 5 matrix) per step. The model's ``flow(tau)`` is the same
map over any tau in (0, period_s] (a sample taken inside a step), with noise Q tau / period_s.

:func:`unicycle` supplies the exact Jacobian and accepts batches X (N, 5).

Sensors (selected by name; z = h(x) + v, R the defaults below unless the session gives its own):

====================  ===========================  ==========================================
name                  z                             default R
====================  ===========================  ==========================================
``"odom"``            (x, y, yaw, v, w)             diag(0.01^2, 0.01^2, 0.01^2, 0.01^2, 0.01^2)
``"odom_twist"``      (v, w)                        diag(0.01^2, 0.01^2)
``"imu"``             (w): the gyro's yaw rate      diag(0.01^2)
``"pose"``            (x, y, yaw): external fix     diag(0.05^2, 0.05^2, 0.02^2)
``"position"``        (x, y): external fix          diag(0.05^2, 0.05^2)
====================  ===========================  ==========================================

``"odom"`` treats the odometry pose as an absolute measurement in the state's frame; for a
wheel odometry whose pose drifts, use ``"odom_twist"``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..checks import as_nonnegative
from .models_omni import _diag_or_matrix
from .registry import MeasurementModel, NonlinearModel, batched, register_model, wrap_angle

#: State layout.
X, Y, YAW, V, W = range(5)
N_STATE = 5
UNICYCLE_Q0 = (1e-6, 1e-6, 1e-6, 1e-4, 4e-4)

#: name -> (measured state indices, default R diagonal)
UNICYCLE_SENSORS: dict[str, tuple[tuple[int, ...], tuple[float, ...]]] = {
    "odom": ((X, Y, YAW, V, W), (1e-4, 1e-4, 1e-4, 1e-4, 1e-4)),
    "odom_twist": ((V, W), (1e-4, 1e-4)),
    "imu": ((W,), (1e-4,)),
    "pose": ((X, Y, YAW), (2.5e-3, 2.5e-3, 4e-4)),
    "position": ((X, Y), (2.5e-3, 2.5e-3)),
}

#: Below this |dpsi / 2| (rad) dS/da uses its series (the closed form cancels).
_SMALL_HALF_ANGLE = 1e-2


def chord_factor(a: np.ndarray) -> np.ndarray:
    """S(a) = sin(a/2) / (a/2), S(0) = 1: chord length / arc length of an arc of angle a (rad)."""
    return np.sinc(np.asarray(a, dtype=float) / (2.0 * np.pi))


def chord_factor_derivative(a: np.ndarray) -> np.ndarray:
    """dS/da = (h cos h - sin h) / (2 h^2), h = a/2; series -h/6 + h^3/60 - h^5/1680 for small h."""
    h = 0.5 * np.asarray(a, dtype=float)
    small = np.abs(h) < _SMALL_HALF_ANGLE
    hs = np.where(small, 1.0, h)
    closed = (hs * np.cos(hs) - np.sin(hs)) / (2.0 * hs * hs)
    h2 = h * h
    series = h * (-1.0 / 6.0 + h2 * (1.0 / 60.0 - h2 / 1680.0))
    return np.where(small, series, closed)


def lag_factors(tau: float, dt: float) -> tuple[float, float]:
    """(e, a) of a first-order lag of time constant tau (s) over dt (s): e = exp(-dt/tau) the
    decay of the end value, a = (tau/dt)(1 - e) that of the step mean (both 0 for tau = 0)."""
    if tau == 0.0:
        return 0.0, 0.0
    x = dt / tau
    return float(np.exp(-x)), float(-np.expm1(-x) / x)


class UnicycleDynamics:
    """The step map and its Jacobian, batched over rows of S (N, 5); u = (v_cmd, w_cmd)."""

    def __init__(self, period_s: float, tau_v: float, tau_w: float) -> None:
        dt = as_nonnegative(period_s, "period_s", strict=True)
        tv = as_nonnegative(tau_v, "tau_v", strict=False)
        tw = as_nonnegative(tau_w, "tau_w", strict=False)
        self.dt = dt
        self.e_v, self.a_v = lag_factors(tv, dt)
        self.e_w, self.a_w = lag_factors(tw, dt)

    def _means(self, S: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        vc, wc = float(u[0]), float(u[1])
        return vc + (S[:, V] - vc) * self.a_v, wc + (S[:, W] - wc) * self.a_w

    def step(self, S: np.ndarray, u: np.ndarray) -> np.ndarray:
        """s(k+1) (N, 5) from s(k) (N, 5) and u (2,)."""
        u = _command(u)
        dt = self.dt
        vbar, wbar = self._means(S, u)
        dpsi = wbar * dt
        d = vbar * dt * chord_factor(dpsi)
        mid = S[:, YAW] + 0.5 * dpsi
        out = np.empty_like(S)
        out[:, X] = S[:, X] + d * np.cos(mid)
        out[:, Y] = S[:, Y] + d * np.sin(mid)
        out[:, YAW] = wrap_angle(S[:, YAW] + dpsi)
        out[:, V] = u[0] + (S[:, V] - u[0]) * self.e_v
        out[:, W] = u[1] + (S[:, W] - u[1]) * self.e_w
        return out

    def step_jac(self, S: np.ndarray, u: np.ndarray) -> np.ndarray:
        """d s(k+1) / d s(k), (N, 5, 5). With phi = yaw + dpsi/2, d = vbar dt S(dpsi)::

            dx+/dyaw = -d sin phi,   dx+/dv = a_v dt S cos phi,
            dx+/dw   = a_w dt (vbar dt S'(dpsi) cos phi - d sin(phi) / 2)
            dy+/dyaw =  d cos phi,   dy+/dv = a_v dt S sin phi,
            dy+/dw   = a_w dt (vbar dt S'(dpsi) sin phi + d cos(phi) / 2)
            dyaw+/dw = a_w dt,  dv+/dv = e_v,  dw+/dw = e_w,  dx+/dx = dy+/dy = dyaw+/dyaw = 1
        """
        u = _command(u)
        dt = self.dt
        vbar, wbar = self._means(S, u)
        dpsi = wbar * dt
        sf = chord_factor(dpsi)
        dsf = chord_factor_derivative(dpsi)
        d = vbar * dt * sf
        mid = S[:, YAW] + 0.5 * dpsi
        c, s = np.cos(mid), np.sin(mid)
        J = np.zeros((S.shape[0], N_STATE, N_STATE))
        J[:, X, X] = J[:, Y, Y] = J[:, YAW, YAW] = 1.0
        J[:, X, YAW] = -d * s
        J[:, Y, YAW] = d * c
        J[:, X, V] = self.a_v * dt * sf * c
        J[:, Y, V] = self.a_v * dt * sf * s
        ddw = vbar * dt * dsf  # d(d)/d(dpsi)
        J[:, X, W] = self.a_w * dt * (ddw * c - 0.5 * d * s)
        J[:, Y, W] = self.a_w * dt * (ddw * s + 0.5 * d * c)
        J[:, YAW, W] = self.a_w * dt
        J[:, V, V] = self.e_v
        J[:, W, W] = self.e_w
        return J




def _command(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=float).reshape(-1)
    if u.shape != (2,):
        raise ValueError(f"u: expected (v_cmd, w_cmd), got shape {u.shape}")
    return u


def _selection_sensor(name: str, idx: tuple[int, ...], R_diag: tuple[float, ...]) -> MeasurementModel:
    """z = s[idx] (+ v): a linear selection of state entries, as a vectorised sensor."""
    H = np.zeros((len(idx), N_STATE))
    H[np.arange(len(idx)), list(idx)] = 1.0
    H.setflags(write=False)
    cols = list(idx)
    R = np.diag(np.asarray(R_diag, dtype=float))
    R.setflags(write=False)
    angles = tuple(i for i, j in enumerate(idx) if j == YAW)
    return MeasurementModel(
        name=name,
        h=batched(lambda Xs: Xs[:, cols].copy()),
        R=R,
        angles=angles,
        jac=batched(lambda Xs: np.broadcast_to(H, (Xs.shape[0],) + H.shape).copy()),
        vectorized=True,
    )


@register_model("unicycle")
def unicycle(
    period_s: float = 0.02,
    tau_v: float = 0.25,
    tau_w: float = 0.15,
    Q: object = None,
) -> NonlinearModel:
    """Differential-drive robot. period_s (s), tau_v / tau_w (s, >= 0; 0 = no lag), ``Q``
    5 diagonal values (or a 5x5 matrix) per step, default :data:`UNICYCLE_Q0` =
    diag(1e-6 m^2, 1e-6 m^2, 1e-6 rad^2, 1e-4 (m/s)^2, 4e-4 (rad/s)^2)."""
    dyn = UnicycleDynamics(period_s, tau_v, tau_w)

    def flow(tau: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        part = UnicycleDynamics(tau, tau_v, tau_w)  # the same exact arc and lags over tau
        return batched(lambda Xs, u: part.step(Xs, u))

    Qm = _diag_or_matrix(UNICYCLE_Q0 if Q is None else Q, "Q", N_STATE)
    sensors = {name: _selection_sensor(name, idx, R) for name, (idx, R) in UNICYCLE_SENSORS.items()}
    return NonlinearModel(
        name="unicycle", n=N_STATE, nu=2,
        f=batched(lambda Xs, u, k: dyn.step(Xs, u)), Q=Qm, sensors=sensors, angles=(YAW,),
        jac=batched(lambda Xs, u, k: dyn.step_jac(Xs, u)), vectorized=True,
        flow=flow, period_s=dyn.dt)
