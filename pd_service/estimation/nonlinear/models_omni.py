"""Three-wheel omnidirectional robot (wheels at 120 deg), registered as ``"omni3"``.

State s = (x, y, theta, vx, vy, omega): pose in the world frame (m, m, rad) and its rate
(m/s, m/s, rad/s). Input u = (tau_1, tau_2, tau_3): wheel torques (N m), held over a step.
Wheel i sits at angle delta_i = 2 pi (i - 1) / 3 from the body x axis, at distance L from the
centre; it drives tangentially, so its rim speed is::

    r phi_dot_i = -sin(theta + delta_i) vx + cos(theta + delta_i) vy + L omega,
    i.e. phi_dot = (1/r) W(theta) q_dot,  q = (x, y, theta),  W rows [-s_i, c_i, L]

Lagrange with body mass M, body inertia I, wheel inertia Iw and viscous friction c at each wheel
axle (torque -c phi_dot_i). Because the wheels are 120 deg apart, W^T W = diag(3/2, 3/2, 3 L^2)
does not depend on theta, so the mass matrix is constant and there are no Coriolis terms::

    Meff q_ddot = (1/r) W(theta)^T tau - (c / r^2) W^T W q_dot
    Meff = diag(M + 3 Iw / (2 r^2),  M + 3 Iw / (2 r^2),  I + 3 Iw L^2 / r^2)

The only nonlinearity is theta in the direction of the wheel forces. One step of length dt is
one classical Runge-Kutta (RK4) step with the torque held; :func:`omni3` also supplies the
exact Jacobian of that RK4 map (the chain rule through its four stages), so sensitivities do
not need finite differences. The model's ``flow(tau)`` is one RK4 step of length tau (a
sample taken inside a step), with noise Q tau / dt.

Defaults are the issue's scenario: M = 10 kg, I = 0.25 kg m^2, Iw = 0.01 kg m^2,
r = 0.05 m, L = 0.2 m, c = 0.02 N m s/rad, dt = 0.01 s, pose sensor ``"pose"`` measuring
(x, y, theta) with R = 1e-8 I, Q0 = diag(1e-14, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..checks import as_covariance
from .registry import MeasurementModel, NonlinearModel, batched, register_model

#: The acceleration channels (indices of vx, vy, omega): the entries of Q worth adapting.
OMNI_ACCEL_CHANNELS = (3, 4, 5)
OMNI_Q0 = (1e-14, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5)


class OmniDynamics:
    """Continuous dynamics s_dot = F(s, tau) and its RK4 step, batched over rows of S (N, 6)."""

    def __init__(self, mass: float, inertia: float, wheel_inertia: float, wheel_radius: float,
                 wheel_distance: float, friction: float, period_s: float) -> None:
        for name, v in (("mass", mass), ("inertia", inertia), ("wheel_radius", wheel_radius),
                        ("wheel_distance", wheel_distance), ("period_s", period_s)):
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name}: must be a positive number, got {v!r}")
        for name, v in (("wheel_inertia", wheel_inertia), ("friction", friction)):
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name}: must be a non-negative number, got {v!r}")
        r, L = float(wheel_radius), float(wheel_distance)
        self.r, self.L, self.dt = r, L, float(period_s)
        self.delta = 2.0 * np.pi * np.arange(3) / 3.0
        meff = np.array([mass + 1.5 * wheel_inertia / r**2,
                         mass + 1.5 * wheel_inertia / r**2,
                         inertia + 3.0 * wheel_inertia * L**2 / r**2])
        self.minv = 1.0 / meff
        # (c / r^2) W^T W = (c / r^2) diag(3/2, 3/2, 3 L^2)
        self.damp = friction / r**2 * np.array([1.5, 1.5, 3.0 * L**2])
        self._minv = tuple(float(v) for v in self.minv)
        self._damp = tuple(float(v) for v in self.damp)
        J = np.zeros((6, 6))  # the constant part of dF/ds
        J[0, 3] = J[1, 4] = J[2, 5] = 1.0
        J[3, 3], J[4, 4], J[5, 5] = -self.minv * self.damp
        self._jac_const = J

    def _coeffs(self, tau: np.ndarray) -> tuple[float, float, float]:
        """(a / r, b / r, L sum(tau) / r) with a = sum tau_i cos delta_i, b = sum tau_i sin delta_i,
        so that sum tau_i cos(theta + delta_i) = a cos(theta) - b sin(theta) and
        sum tau_i sin(theta + delta_i) = a sin(theta) + b cos(theta)."""
        tau = np.asarray(tau, dtype=float)
        r = self.r
        return (float(np.cos(self.delta) @ tau) / r, float(np.sin(self.delta) @ tau) / r,
                self.L * float(np.sum(tau)) / r)

    def force(self, theta: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """(1/r) W(theta)^T tau, (N, 3) for theta (N,)."""
        ar, br, fz = self._coeffs(tau)
        c, s = np.cos(theta), np.sin(theta)
        out = np.empty(theta.shape + (3,))
        out[:, 0] = -(ar * s + br * c)   # -(1/r) sum sin(theta + delta_i) tau_i
        out[:, 1] = ar * c - br * s      #  (1/r) sum cos(theta + delta_i) tau_i
        out[:, 2] = fz                   #  (L/r) sum tau_i
        return out

    def deriv(self, S: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """s_dot (N, 6): p_dot = v,  v_dot = Meff^{-1} ((1/r) W^T tau - (c/r^2) W^T W v)."""
        return self._deriv(S, self._coeffs(tau))

    def _deriv(self, S: np.ndarray, co: tuple[float, float, float]) -> np.ndarray:
        ar, br, fz = co
        m0, m1, m2 = self._minv
        d0, d1, d2 = self._damp
        c, s = np.cos(S[:, 2]), np.sin(S[:, 2])
        out = np.empty_like(S)
        out[:, :3] = S[:, 3:]
        out[:, 3] = m0 * (-(ar * s + br * c) - d0 * S[:, 3])
        out[:, 4] = m1 * (ar * c - br * s - d1 * S[:, 4])
        out[:, 5] = m2 * (fz - d2 * S[:, 5])
        return out

    def _deriv_jac(self, S: np.ndarray, co: tuple[float, float, float]) -> np.ndarray:
        """d s_dot / d s, (N, 6, 6)."""
        ar, br, _ = co
        A = np.empty((S.shape[0], 6, 6))
        A[:] = self._jac_const
        c, s = np.cos(S[:, 2]), np.sin(S[:, 2])
        # d/dtheta of (1/r) W^T tau = (1/r) [-sum cos(.) tau_i, -sum sin(.) tau_i, 0]
        A[:, 3, 2] = -self._minv[0] * (ar * c - br * s)
        A[:, 4, 2] = -self._minv[1] * (ar * s + br * c)
        return A

    def step(self, S: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """One RK4 step: s' = s + dt/6 (k1 + 2 k2 + 2 k3 + k4)."""
        h = self.dt
        co = self._coeffs(tau)
        k1 = self._deriv(S, co)
        k2 = self._deriv(S + 0.5 * h * k1, co)
        k3 = self._deriv(S + 0.5 * h * k2, co)
        k4 = self._deriv(S + h * k3, co)
        return S + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    def step_jac(self, S: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Jacobian (N, 6, 6) of :meth:`step`: with A(s) = dF/ds and stages s_j,

            J1 = A(s),  J2 = A(s2)(I + h/2 J1),  J3 = A(s3)(I + h/2 J2),  J4 = A(s4)(I + h J3)
            d s'/d s = I + h/6 (J1 + 2 J2 + 2 J3 + J4)
        """
        h = self.dt
        eye = np.eye(6)
        co = self._coeffs(tau)
        k1 = self._deriv(S, co)
        s2 = S + 0.5 * h * k1
        k2 = self._deriv(s2, co)
        s3 = S + 0.5 * h * k2
        k3 = self._deriv(s3, co)
        s4 = S + h * k3
        J1 = self._deriv_jac(S, co)
        J2 = self._deriv_jac(s2, co) @ (eye + 0.5 * h * J1)
        J3 = self._deriv_jac(s3, co) @ (eye + 0.5 * h * J2)
        J4 = self._deriv_jac(s4, co) @ (eye + h * J3)
        return eye + (h / 6.0) * (J1 + 2.0 * J2 + 2.0 * J3 + J4)


@register_model("omni3")
def omni3(
    period_s: float = 0.01,
    mass: float = 10.0,
    inertia: float = 0.25,
    wheel_inertia: float = 0.01,
    wheel_radius: float = 0.05,
    wheel_distance: float = 0.2,
    friction: float = 0.02,
    Q: object = None,
    R: object = None,
) -> NonlinearModel:
    """The three-wheel omnidirectional robot; ``Q`` (6x6 or 6 diagonal values) defaults to
    Q0, ``R`` (3x3 or 3 diagonal values) of the ``"pose"`` sensor to 1e-8 I."""
    dyn = OmniDynamics(float(mass), float(inertia), float(wheel_inertia), float(wheel_radius),
                       float(wheel_distance), float(friction), float(period_s))
    Qm = _diag_or_matrix(OMNI_Q0 if Q is None else Q, "Q", 6)
    Rm = _diag_or_matrix((1e-8, 1e-8, 1e-8) if R is None else R, "R", 3)

    def f(X: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
        return dyn.step(X, np.asarray(u, dtype=float))

    def flow(tau: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        part = OmniDynamics(float(mass), float(inertia), float(wheel_inertia),
                            float(wheel_radius), float(wheel_distance), float(friction), tau)
        return batched(lambda X, u: part.step(X, np.asarray(u, dtype=float)))  # one RK4 step

    def F(X: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
        return dyn.step_jac(X, np.asarray(u, dtype=float))

    H = np.hstack((np.eye(3), np.zeros((3, 3))))

    def h(X: np.ndarray) -> np.ndarray:
        return X[:, :3].copy()

    def Hjac(X: np.ndarray) -> np.ndarray:
        return np.broadcast_to(H, (X.shape[0], 3, 6)).copy()

    pose = MeasurementModel(name="pose", h=batched(h), R=Rm, angles=(2,), jac=batched(Hjac),
                            vectorized=True)
    return NonlinearModel(name="omni3", n=6, nu=3, f=batched(f), Q=Qm, sensors={"pose": pose},
                          angles=(2,), jac=batched(F), vectorized=True, flow=flow,
                          period_s=float(period_s))


def _diag_or_matrix(value: object, field: str, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 1:
        if arr.shape != (n,):
            raise ValueError(f"{field}: expected {n} diagonal values or an {n}x{n} matrix")
        arr = np.diag(arr)
    M = as_covariance(arr, field, n)
    M.setflags(write=False)
    return M
