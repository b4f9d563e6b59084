"""Model and sensor descriptions for the linear observer-predictor.

System (time steps k are integers)::

    x(k+1) = A x(k) + B u(k) + w(k),      w ~ N(0, Q)
    z_i(s) = H_i x(s) + v_i(s),           v_i ~ N(0, R_i)   (sensor i, sample step s)

A model may also be given in continuous time (:meth:`LinearModel.continuous`: F, G, Qc and
the step period): then A, B, Q are its exact discretisation over one period, and
:meth:`LinearModel.over` gives it over any interval, so samples and commands can act at their
own time inside a step (:mod:`.discretise`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .checks import as_covariance, as_matrix
from .discretise import TAYLOR_NORM, Taylor, van_loan

#: (A (n, n), B (n, nu), Q (n, n)) of a model over one interval.
Discrete = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True, eq=False)
class LinearModel:
    """Time-invariant linear model. Shapes: A (n, n), B (n, r), Q (n, n) symmetric PSD.

    ``B`` may have zero columns (no input). Arrays are copied, validated and made read-only.

    A continuous-time model (:meth:`continuous`) also holds F (n, n), G (n, r), Qc (n, n)
    and ``period`` (s): then A, B, Q = :meth:`over` (period). A discrete one (A, B, Q only)
    cannot be evaluated inside a step: :attr:`continuous_time` is False.
    """

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    F: np.ndarray | None = None
    G: np.ndarray | None = None
    Qc: np.ndarray | None = None
    period: float | None = None
    _over: dict[float, Discrete] = field(default_factory=dict, repr=False, compare=False)
    _taylor: Taylor | None = field(default=None, repr=False, compare=False)

    @classmethod
    def continuous(cls, F: object, G: object, Qc: object, period: float) -> LinearModel:
        """The model dx = (F x + G u) dt + dw, E[dw dw^T] = Qc dt (t in s), stepped every
        ``period`` seconds. Shapes: F (n, n), G (n, r) (r may be 0), Qc (n, n) symmetric PSD
        (a spectral density: units of x^2 / s)."""
        Fm = as_matrix(F, "F", (None, None))
        n = Fm.shape[0]
        if Fm.shape != (n, n) or n < 1:
            raise ValueError(f"F: must be square with n >= 1, got shape {Fm.shape}")
        Gm = np.zeros((n, 0)) if G is None else as_matrix(G, "G", (n, None))
        Qm = as_covariance(Qc, "Qc", n)
        T = float(period)
        if not (math.isfinite(T) and T > 0.0):
            raise ValueError(f"period: must be a positive number of seconds, got {period!r}")
        A, B, Q = van_loan(Fm, Gm, Qm, T)
        return cls(A=A, B=B, Q=Q, F=Fm, G=Gm, Qc=Qm, period=T)

    @property
    def taylor(self) -> Taylor | None:
        """The Taylor polynomials :meth:`over` evaluates (None: Van Loan's exponentials, or a
        discrete model)."""
        return self._taylor

    @property
    def continuous_time(self) -> bool:
        """Whether the model can be evaluated over any interval (:meth:`over`)."""
        return self.F is not None

    def over(self, tau: float) -> Discrete:
        """(A(tau), B(tau), Q(tau)) over ``tau`` seconds, 0 <= tau <= period: the exact
        discretisation, cached per distinct tau (a periodic sensor's stamps fall at a few
        offsets; at most :data:`_OVER_CACHE` of them). A model with ||F||_1 period <= 1/2
        evaluates its Taylor polynomials (:class:`.discretise.Taylor`, one product each,
        exact for a nilpotent F), another one Van Loan's exponentials
        (:func:`.discretise.van_loan`). ValueError for a discrete model or a tau outside."""
        got = self._over.get(tau)
        if got is not None:
            return got
        if self.F is None or self.G is None or self.Qc is None or self.period is None:
            raise ValueError("over: a discrete model (A, B, Q only) has no value inside a step")
        if not (math.isfinite(tau) and 0.0 <= tau <= self.period):
            raise ValueError(f"over: tau must be in [0, {self.period}] s, got {tau!r}")
        tay = self._taylor
        mats = tay.at(tau) if tay is not None else van_loan(self.F, self.G, self.Qc, tau)
        for arr in mats:
            arr.setflags(write=False)
        if len(self._over) < _OVER_CACHE:
            self._over[tau] = mats
        return mats

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
        parts = (self.F, self.G, self.Qc, self.period)
        if any(p is not None for p in parts) and any(p is None for p in parts):
            raise ValueError("F, G, Qc, period: give all four (LinearModel.continuous) or none")
        for given in (self.F, self.G, self.Qc):
            if given is not None:
                given.setflags(write=False)
        if (self.F is not None and self.G is not None and self.Qc is not None
                and self.period is not None
                and float(np.abs(self.F).sum(axis=0).max()) * self.period <= TAYLOR_NORM):
            object.__setattr__(self, "_taylor", Taylor(self.F, self.G, self.Qc))

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def nu(self) -> int:
        """Input dimension (columns of B)."""
        return self.B.shape[1]


#: Distinct intervals :meth:`LinearModel.over` keeps per model (a bound against jittered
#: stamps at arbitrary offsets: each session holds its own model).
_OVER_CACHE = 64


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
