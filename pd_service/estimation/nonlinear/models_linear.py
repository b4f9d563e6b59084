"""A linear model in the nonlinear registry, ``"linear"``: tests and sanity checks.

    x(k+1) = A x(k) + B u(k) + w,  w ~ N(0, Q);     z_i = H_i x + v_i,  v_i ~ N(0, R_i)

On it the unscented filter must equal the Kalman filter exactly (the unscented transform
is exact for affine maps), which is how the UKF machinery is tested.
"""

from __future__ import annotations

import numpy as np

from ..model import LinearModel, Sensor
from .registry import MeasurementModel, NonlinearModel, batched, register_model


def linear_as_nonlinear(model: LinearModel, sensors: list[Sensor]) -> NonlinearModel:
    """Wrap a :class:`LinearModel` and its sensors as a (vectorised) :class:`NonlinearModel`."""
    A, B = model.A, model.B

    def f(X: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
        out = X @ A.T  # x(k+1) = A x + B u
        if B.shape[1]:
            out = out + B @ np.asarray(u, dtype=float)
        return out

    def F(X: np.ndarray, u: np.ndarray, k: int) -> np.ndarray:
        return np.broadcast_to(A, (X.shape[0],) + A.shape).copy()

    meas: dict[str, MeasurementModel] = {}
    for s in sensors:
        H = s.H
        meas[s.name] = MeasurementModel(
            name=s.name,
            h=batched(lambda X, H=H: X @ H.T),
            R=s.R,
            jac=batched(lambda X, H=H: np.broadcast_to(H, (X.shape[0],) + H.shape).copy()),
            vectorized=True,
        )
    return NonlinearModel(name="linear", n=model.n, nu=model.nu, f=batched(f), Q=model.Q,
                          sensors=meas, jac=batched(F), vectorized=True)


@register_model("linear")
def linear(A: object, B: object, Q: object, sensors: dict) -> NonlinearModel:
    """``sensors``: name -> {"H": m x n, "R": m x m} (plain nested lists are fine)."""
    Am = np.asarray(A, dtype=float)
    Bm = np.zeros((Am.shape[0] if Am.ndim else 1, 0)) if B is None else np.asarray(B, float)
    lm = LinearModel(A=Am, B=Bm, Q=np.asarray(Q, dtype=float))
    if not isinstance(sensors, dict) or not sensors:
        raise ValueError("sensors: expected a non-empty map name -> {'H': ..., 'R': ...}")
    sens = []
    for name, spec in sensors.items():
        if not isinstance(spec, dict) or set(spec) != {"H", "R"}:
            raise ValueError(f"sensors[{name!r}]: expected a map with keys 'H' and 'R'")
        sens.append(Sensor(name=name, H=np.asarray(spec["H"], float), R=np.asarray(spec["R"], float)))
        if sens[-1].H.shape[1] != lm.n:
            raise ValueError(f"sensors[{name!r}].H: expected {lm.n} columns")
    return linear_as_nonlinear(lm, sens)
