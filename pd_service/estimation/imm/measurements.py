"""Measurement models for the IMM backend (state layout of :mod:`.models`).

* range-bearing from a known station s = (s_xi, s_eta) (m)::

      z = [ sqrt((xi - s_xi)^2 + (eta - s_eta)^2),  atan2(eta - s_eta, xi - s_xi) ]   (m, rad)

  The bearing (index 1) is an angle: innovations and the sigma-point mean wrap it.
* position: z = [xi, eta] (m).

Measurement functions accept batches: x (..., 5) -> z (..., m).

A session spec names sensors with plain dicts, see :func:`make_sensor`::

    {"name": "st1", "kind": "range_bearing", "station": [9.5, -8.5],
     "sigma_range": 0.3, "sigma_bearing": 0.0611}                       # m, rad
    {"name": "st1", "kind": "range_bearing", "station": [9.5, -8.5],
     "R": [[0.09, 0.0], [0.0, 0.0037]]}                                  # m^2, rad^2
    {"name": "cam", "kind": "position", "sigma": 0.05}                   # m
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..checks import as_covariance, as_positive, as_vector
from ..nonlinear.registry import MeasurementModel
from .models import ETA, XI


def range_bearing(
    name: str, station: object, sigma_range: float | None = None,
    sigma_bearing: float | None = None, R: object | None = None,
) -> MeasurementModel:
    """Range (m) and bearing (rad, wrapped) from ``station`` (2,) m; R = diag(sr^2, sb^2),
    or the given diagonal (2, 2) covariance R (as a session spec gives it: no square root)."""
    st = as_vector(station, f"sensor {name!r} station", 2).copy()
    if R is None:
        if sigma_range is None or sigma_bearing is None:
            raise ValueError(f"sensor {name!r}: bad parameters (expected sigma_range and "
                             "sigma_bearing, or R)")
        sr = as_positive(sigma_range, f"sensor {name!r} sigma_range")
        sb = as_positive(sigma_bearing, f"sensor {name!r} sigma_bearing")
        Rm = np.diag([sr * sr, sb * sb])
    elif sigma_range is None and sigma_bearing is None:
        Rm = as_covariance(R, f"sensor {name!r} R", 2)
        if not (Rm[0, 1] == 0.0 == Rm[1, 0] and Rm[0, 0] > 0.0 and Rm[1, 1] > 0.0):
            raise ValueError(f"sensor {name!r} R: must be diagonal with positive entries")
    else:
        raise ValueError(f"sensor {name!r}: give the sigmas or R, not both")
    sx, sy = float(st[0]), float(st[1])

    def h(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        dx = x[..., XI] - sx
        dy = x[..., ETA] - sy
        return np.stack([np.hypot(dx, dy), np.arctan2(dy, dx)], axis=-1)

    Rm.setflags(write=False)
    return MeasurementModel(name=name, h=h, R=Rm, angles=(1,), vectorized=True)


def position(name: str, sigma: float | None = None, R: object | None = None) -> MeasurementModel:
    """Position z = [xi, eta] (m); R = sigma^2 I or the given (2, 2) covariance."""
    if (sigma is None) == (R is None):
        raise ValueError(f"sensor {name!r}: give exactly one of sigma and R")
    if R is None:
        s = as_positive(sigma, f"sensor {name!r} sigma")
        Rm = s * s * np.eye(2)
    else:
        Rm = as_covariance(R, f"sensor {name!r} R", 2)
        if float(np.linalg.eigvalsh(Rm)[0]) <= 0.0:
            raise ValueError(f"sensor {name!r} R: must be positive definite")

    def h(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return np.stack([x[..., XI], x[..., ETA]], axis=-1)

    Rm.setflags(write=False)
    return MeasurementModel(name=name, h=h, R=Rm, angles=(), vectorized=True)


_KINDS = ("range_bearing", "position")


def make_sensor(spec: MeasurementModel | Mapping[str, object]) -> MeasurementModel:
    """A MeasurementModel from itself or a plain spec dict (see module docstring)."""
    if isinstance(spec, MeasurementModel):
        return spec
    if not isinstance(spec, Mapping):
        raise ValueError(
            f"sensors: expected a MeasurementModel or a dict, got {type(spec).__name__}"
        )
    params = dict(spec)
    name = params.pop("name", None)
    kind = params.pop("kind", None)
    if not isinstance(name, str) or not name:
        raise ValueError("sensors: each sensor needs a non-empty 'name'")
    if kind not in _KINDS:
        raise ValueError(f"sensor {name!r} kind: expected one of {_KINDS}, got {kind!r}")
    try:
        if kind == "range_bearing":
            return range_bearing(name, **params)  # type: ignore[arg-type]
        return position(name, **params)  # type: ignore[arg-type]
    except TypeError as exc:
        raise ValueError(f"sensor {name!r}: bad parameters ({exc})") from None
