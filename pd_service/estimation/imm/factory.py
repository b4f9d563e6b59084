"""Plain factory for the daemon: build an :class:`ImmObserverPredictor` from spec-like values.

Everything can come straight from a decoded SessionSpec (names, numbers, lists, dicts)::

    make_imm(
        modes=[{"model": "imm_cv", "params": {"period_s": 0.1, "sigma_accel": 0.003}},
               {"model": "imm_ct", "params": {"period_s": 0.1, "sigma_accel": 0.0016,
                                              "sigma_turn_step": 0.0035}}],
        transition=[[0.995, 0.005], [0.005, 0.995]],
        sensors=[{"name": "st1", "kind": "range_bearing", "station": [9.5, -8.5],
                  "sigma_range": 0.3, "sigma_bearing": 0.0611}],
        variant="imm2", x0=[0, 0.3, 0, 0, 0], P0=np.diag([...]), lead=5, max_delay=20)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from ..nonlinear.registry import MeasurementModel, NonlinearModel, make_model
from . import models as _models  # noqa: F401  (registers imm_cv, imm_ct)
from .filter import VARIANTS, ImmFilter
from .measurements import make_sensor
from .observer import ImmObserverPredictor


def make_mode(spec: NonlinearModel | str | Mapping[str, object]) -> NonlinearModel:
    """A mode model from itself, a registered name, or {"model": name, "params": {...}}."""
    if isinstance(spec, NonlinearModel):
        return spec
    if isinstance(spec, str):
        return make_model(spec)
    if isinstance(spec, Mapping):
        unknown = set(spec) - {"model", "params"}
        if unknown:
            raise ValueError(f"modes: unknown keys {sorted(unknown)} (expected 'model', 'params')")
        name = spec.get("model")
        params = spec.get("params", {}) or {}
        if not isinstance(name, str):
            raise ValueError("modes: each mode needs a 'model' name")
        if not isinstance(params, Mapping):
            raise ValueError(f"mode {name!r} params: expected a mapping")
        return make_model(name, **dict(params))
    raise ValueError(f"modes: expected a model, a name or a mapping, got {type(spec).__name__}")


def make_imm(
    modes: Sequence[NonlinearModel | str | Mapping[str, object]],
    transition: object,
    sensors: Sequence[MeasurementModel | Mapping[str, object]],
    variant: str,
    x0: object,
    P0: object,
    lead: int,
    max_delay: int,
    mu0: object | None = None,
    node: int = 0,
    kappa: float = 0.0,
    command_hold: str = "hold",
) -> ImmObserverPredictor:
    """Build the IMM-UIF observer-predictor.

    modes:       r >= 1 mode models (same n, nu), see :func:`make_mode`.
    transition:  (r, r) row-stochastic Markov matrix, row i = P(next mode | mode i).
    sensors:     measurement models or spec dicts (:func:`.measurements.make_sensor`); their
                 names are the ``sensor`` argument of ``add_measurement``.
    variant:     "single" | "centralised" | "imm1" | "imm2" (see :mod:`.filter`).
    x0, P0:      initial estimate (n,), covariance (n, n) positive definite, for every mode.
    lead:        steps from ``now`` to the predicted step; max_delay: acceptance window (steps).
    mu0:         initial mode probabilities (r,), uniform if None.
    node:        "single": the sensor used; "imm1": the node whose estimate is reported.
    kappa:       sigma-point scaling (n + kappa > 0).
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
    if isinstance(modes, (str, Mapping)) or not isinstance(modes, Sequence):
        raise ValueError("modes: expected a list of mode specs")
    if isinstance(sensors, Mapping) or not isinstance(sensors, Sequence):
        raise ValueError("sensors: expected a list of sensor specs")
    filt = ImmFilter(
        [make_mode(m) for m in modes],
        transition,
        [make_sensor(s) for s in sensors],
        variant=variant,
        node=node,
        kappa=kappa,
    )
    return ImmObserverPredictor(
        filt, x0=x0, P0=P0, lead=lead, max_delay=max_delay, mu0=mu0, command_hold=command_hold
    )
