"""SessionSpec -> estimator, for every model kind: the one place a spec becomes an estimator.

- "linear": :class:`~pd_service.estimation.ObserverPredictor` (LinearModel, [Sensor], x0,
  P0, lead, max_delay, command_hold);
- "unscented": :func:`~pd_service.estimation.nonlinear.make_unscented` with the registered
  model, its params, adapt and sigma settings, the session's sensors in order and their R;
- "imm": :func:`~pd_service.estimation.imm.make_imm` with the modes, transition, variant,
  node, mu0, kappa and the sensors as IMM sensor maps (:func:`imm_sensor`).

What the wire layer cannot check alone (a model that is not registered, a parameter it does
not take, x0 / R of the wrong size for the model) is refused here: any error of the
estimator's constructor becomes a WireError "SessionSpec: refused by the estimator: <reason>".
A valid linear spec is never refused.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from pd_service.estimation import Estimator, LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.imm import make_imm
from pd_service.estimation.nonlinear import make_unscented
from pd_service.wire import (
    ImmModelSpec,
    LinearModelSpec,
    SensorSpec,
    SessionSpec,
    UnscentedModelSpec,
    WireError,
)
from pd_service.wire.convert import estimator_refusal, mode_map, plain_params

__all__ = ["build_estimator", "imm_sensor"]


def build_estimator(spec: SessionSpec) -> Estimator:
    """The session's estimator, by ``spec.model.kind`` (see the module docstring).

    WireError "SessionSpec: refused by the estimator: ..." if the estimator's constructor
    refuses the spec.
    """
    model = spec.model
    try:
        if isinstance(model, LinearModelSpec):
            est: Estimator = ObserverPredictor(
                LinearModel(A=np.array(model.A), B=np.array(model.B), Q=np.array(model.Q)),
                [Sensor(name=s.name, H=np.array(s.H), R=np.array(s.R)) for s in spec.sensors],
                np.array(spec.x0), np.array(spec.P0), spec.lead, spec.max_delay,
                spec.command_hold,
            )
        elif isinstance(model, UnscentedModelSpec):
            est = _unscented(spec, model)
        elif isinstance(model, ImmModelSpec):
            est = _imm(spec, model)
        else:  # a model kind the wire accepts but no backend builds: a programming error
            raise TypeError(f"no backend for model kind {model.kind!r}")
    except WireError:
        raise
    except Exception as exc:  # ValueError, or a registered model's own code failing
        raise estimator_refusal(exc) from None
    if est.n != spec.n:  # the constructors check x0 against the model; kept as a guard
        raise WireError(f"SessionSpec.x0: refused by the estimator: the model has n={est.n} "
                        f"states, x0 has {spec.n}")
    return est


def _unscented(spec: SessionSpec, model: UnscentedModelSpec) -> Estimator:
    adapt = None
    if model.adapt is not None:
        adapt = {k: v for k, v in model.adapt.model_dump().items() if v is not None}
    sigma = None if model.sigma is None else model.sigma.model_dump()
    return make_unscented(
        model.model, plain_params(model.params),
        x0=np.array(spec.x0), P0=np.array(spec.P0),
        lead=spec.lead, max_delay=spec.max_delay, command_hold=spec.command_hold,
        adapt=adapt, sigma=sigma,
        sensors=[s.name for s in spec.sensors],
        sensor_R={s.name: np.array(s.R) for s in spec.sensors},
    )


def imm_sensor(sensor: SensorSpec) -> dict[str, Any]:
    """The IMM factory's sensor map of a "range_bearing" or "position" SensorSpec:
    range-bearing: station, sigma_range = sqrt(R[0, 0]), sigma_bearing = sqrt(R[1, 1]);
    position: R (2, 2)."""
    if sensor.kind == "range_bearing":
        assert sensor.station is not None  # guaranteed by SensorSpec's validator
        return {"name": sensor.name, "kind": "range_bearing",
                "station": [float(v) for v in sensor.station],
                "sigma_range": math.sqrt(float(sensor.R[0, 0])),
                "sigma_bearing": math.sqrt(float(sensor.R[1, 1]))}
    if sensor.kind == "position":
        return {"name": sensor.name, "kind": "position", "R": np.array(sensor.R)}
    raise WireError(f"SessionSpec.sensors: sensor {sensor.name!r} of kind {sensor.kind!r} does not "
                    "fit an IMM model")


def _imm(spec: SessionSpec, model: ImmModelSpec) -> Estimator:
    modes: list[Mapping[str, object]] = [mode_map(m) for m in model.modes]
    return make_imm(
        modes=modes,
        transition=np.array(model.transition),
        sensors=[imm_sensor(s) for s in spec.sensors],
        variant=model.variant,
        x0=np.array(spec.x0), P0=np.array(spec.P0),
        lead=spec.lead, max_delay=spec.max_delay,
        mu0=None if model.mu0 is None else np.array(model.mu0),
        node=model.node, kappa=model.kappa, command_hold=spec.command_hold,
    )
