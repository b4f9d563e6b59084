"""Model and sensor descriptions for the linear observer-predictor.

System (time steps k are integers)::

    x(k+1) = A x(k) + B u(k) + w(k),      w ~ N(0, Q)
    z_i(s) = H_i x(s) + v_i(s),           v_i ~ N(0, R_i)   (sensor i, sample step s)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .checks import as_covariance, as_matrix


@dataclass(frozen=True, eq=False)
class LinearModel:
    """Time-invariant linear model. Shapes: A (n, n), B (n, r), Q (n, n) symmetric PSD.

    ``B`` may have zero columns (no input). Arrays are copied, validated and made read-only.
    """

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray

    def __post_init__(self) -> None:
        A = as_matrix(self.A, "A", (None, None))
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"A: must be square, got shape {A.shape}")
        if n < 1:
            raise ValueError("A: state dimension must be at least 1")
        B = np.zeros((n, 0)) if self.B is None else as_matrix(self.B, "B", (n, None))
        Q = as_covariance(self.Q, "Q", n)
        for name, arr in (("A", A), ("B", B), ("Q", Q)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def nu(self) -> int:
        """Input dimension (columns of B)."""
        return self.B.shape[1]


@dataclass(frozen=True, eq=False)
class Sensor:
    """A sensor: ``z = H x(s) + v``, ``v ~ N(0, R)``. Shapes: H (m, n), R (m, m).

    ``name`` identifies it in :meth:`ObserverPredictor.add_measurement`.
    """

    name: str
    H: np.ndarray
    R: np.ndarray

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("Sensor.name: must be a non-empty string")
        H = as_matrix(self.H, f"sensor {self.name!r} H", (None, None))
        if H.shape[0] < 1:
            raise ValueError(f"sensor {self.name!r} H: must have at least one row")
        R = as_covariance(self.R, f"sensor {self.name!r} R", H.shape[0])
        for name, arr in (("H", H), ("R", R)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def m(self) -> int:
        """Measurement dimension."""
        return self.H.shape[0]


def check_sensors(model: LinearModel, sensors: Sequence[Sensor]) -> list[Sensor]:
    """Validate a sensor list against ``model``: non-empty, Sensor objects, unique names,
    H with n columns. Returns it as a list; ValueError names the problem."""
    if not isinstance(model, LinearModel):
        raise ValueError("model: expected a LinearModel")
    sensors = list(sensors)
    if not sensors:
        raise ValueError("sensors: at least one sensor is required")
    for s in sensors:
        if not isinstance(s, Sensor):
            raise ValueError("sensors: expected Sensor objects")
        if s.H.shape[1] != model.n:
            raise ValueError(f"sensor {s.name!r} H: expected {model.n} columns, got {s.H.shape[1]}")
    names = [s.name for s in sensors]
    if len(set(names)) != len(names):
        raise ValueError(f"sensors: duplicate names in {names}")
    return sensors
