"""Between wire messages and :mod:`pd_service.estimation`: the only module importing both.

- :func:`spec_to_estimator`: SessionSpec -> the estimator of its model kind
  (``ObserverPredictor``, the unscented or the IMM observer-predictor; all with the same
  API: ``add_measurement``, ``add_command``, ``predict``, ``counters``);
- :func:`command_dim`: the command dimension r of a session (a nonlinear model's is the
  registered model's);
- :func:`measurement_step` / :func:`command_step`: the integer step a message stands for;
- :func:`check_measurement` / :func:`check_command`: does the message fit its session?
  (raise :class:`WireError` naming the field);
- :func:`check_key`: does the message agree with the key it arrived on?
- :func:`prediction_from`: estimator output -> Prediction message;
- :func:`encode_prediction`: estimator output -> the same Prediction's bytes, directly
  (the daemon's hot path: no model object).

Time: ``step_of(t_ns) = floor((t_ns - epoch_ns) / period_ns)`` in exact integer arithmetic.

The nonlinear backends (:mod:`pd_service.estimation.nonlinear`, :mod:`pd_service.estimation.imm`)
are imported on first use, so linear sessions never depend on them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Protocol

import msgpack
import numpy as np

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor

from .codec import MAX_MESSAGE_BYTES
from .errors import WireError
from .keys import KeyError_, ParsedKey, parse_key
from .messages import (
    Command,
    ImmModelSpec,
    LinearModelSpec,
    Measurement,
    Message,
    ModeSpec,
    Prediction,
    SensorSpec,
    SessionSpec,
    UnscentedModelSpec,
)


class _PredictedState(Protocol):
    step: int
    x: np.ndarray
    P: np.ndarray
    newest_step: int | None


def spec_to_estimator(spec: SessionSpec) -> Any:
    """Build the session's estimator from its spec, by ``spec.model.kind``:

    - "linear": :class:`~pd_service.estimation.ObserverPredictor`;
    - "unscented": ``make_unscented`` (:mod:`pd_service.estimation.nonlinear.factory`) with
      the registered model, its params, adapt and sigma settings, the session's sensors in
      order and their R (``sensor_R``);
    - "imm": ``make_imm`` (:mod:`pd_service.estimation.imm.factory`) with the modes,
      transition, variant, node, mu0, kappa and the sensors as the factory's sensor maps
      (range-bearing: station, sigma_range = sqrt(R[0, 0]), sigma_bearing = sqrt(R[1, 1]);
      position: R).

    What the wire layer cannot check alone (a model that is not registered, a parameter it
    does not take, x0 / R of the wrong size for the model) is refused here: any error of the
    factory becomes a WireError "SessionSpec: refused by the estimator: <reason>". A valid
    linear spec is never refused.
    """
    model = spec.model
    try:
        if isinstance(model, LinearModelSpec):
            est: Any = ObserverPredictor(
                LinearModel(A=np.array(model.A), B=np.array(model.B), Q=np.array(model.Q)),
                [Sensor(name=s.name, H=np.array(s.H), R=np.array(s.R)) for s in spec.sensors],
                x0=np.array(spec.x0),
                P0=np.array(spec.P0),
                lead=spec.lead,
                max_delay=spec.max_delay,
                command_hold=spec.command_hold,
            )
        elif isinstance(model, UnscentedModelSpec):
            est = _unscented(spec, model)
        elif isinstance(model, ImmModelSpec):
            est = _imm(spec, model)
        else:  # pragma: no cover - the discriminator admits no other kind
            raise WireError(f"SessionSpec.model: kind {model.kind!r} is not supported")
    except WireError:
        raise
    except ValueError as exc:
        raise WireError(f"SessionSpec: refused by the estimator: {exc}") from None
    except Exception as exc:  # a registered model's own code failing on odd parameters
        raise WireError(f"SessionSpec: refused by the estimator: "
                        f"{type(exc).__name__}: {exc}") from None
    n = getattr(est, "n", spec.n)
    if n != spec.n:  # the factories check x0 against the model; kept as a guard
        raise WireError(f"SessionSpec: refused by the estimator: the model has n={n} states, "
                        f"x0 has {spec.n}")
    return est


def _plain_params(params: Mapping[str, Any]) -> dict[str, Any]:
    """Fresh copies of the parameter values (lists are mutable)."""
    return {k: list(v) if isinstance(v, list) else v for k, v in params.items()}


def _unscented(spec: SessionSpec, model: UnscentedModelSpec) -> Any:
    from pd_service.estimation.nonlinear.factory import make_unscented

    adapt = None
    if model.adapt is not None:
        adapt = {k: v for k, v in model.adapt.model_dump().items() if v is not None}
    sigma = None if model.sigma is None else model.sigma.model_dump()
    return make_unscented(
        model.model, _plain_params(model.params),
        x0=np.array(spec.x0), P0=np.array(spec.P0),
        lead=spec.lead, max_delay=spec.max_delay, command_hold=spec.command_hold,
        adapt=adapt, sigma=sigma,
        sensors=[s.name for s in spec.sensors],
        sensor_R={s.name: np.array(s.R) for s in spec.sensors},
    )


def _mode(mode: ModeSpec) -> dict[str, Any]:
    return {"model": mode.model, "params": _plain_params(mode.params)}


def imm_sensor(sensor: SensorSpec) -> dict[str, Any]:
    """The IMM factory's sensor map of a "range_bearing" or "position" SensorSpec."""
    if sensor.kind == "range_bearing":
        assert sensor.station is not None  # guaranteed by SensorSpec's validator
        return {"name": sensor.name, "kind": "range_bearing",
                "station": [float(v) for v in sensor.station],
                "sigma_range": math.sqrt(float(sensor.R[0, 0])),
                "sigma_bearing": math.sqrt(float(sensor.R[1, 1]))}
    if sensor.kind == "position":
        return {"name": sensor.name, "kind": "position", "R": np.array(sensor.R)}
    raise WireError(f"SessionSpec: sensor {sensor.name!r} of kind {sensor.kind!r} does not "
                    "fit an IMM model")


def _imm(spec: SessionSpec, model: ImmModelSpec) -> Any:
    from pd_service.estimation.imm.factory import make_imm

    return make_imm(
        modes=[_mode(m) for m in model.modes],
        transition=np.array(model.transition),
        sensors=[imm_sensor(s) for s in spec.sensors],
        variant=model.variant,
        x0=np.array(spec.x0), P0=np.array(spec.P0),
        lead=spec.lead, max_delay=spec.max_delay,
        mu0=None if model.mu0 is None else np.array(model.mu0),
        node=model.node, kappa=model.kappa, command_hold=spec.command_hold,
    )


def command_dim(spec: SessionSpec) -> int:
    """Command dimension r: the columns of model.B, or the registered model's input
    dimension (0 for a model without inputs: such a session takes no commands). Builds the
    nonlinear model (not the estimator); WireError if it cannot be built."""
    model = spec.model
    if isinstance(model, LinearModelSpec):
        return model.r
    try:
        if isinstance(model, UnscentedModelSpec):
            from pd_service.estimation.nonlinear import make_model

            return int(make_model(model.model, **_plain_params(model.params)).nu)
        from pd_service.estimation.imm.factory import make_mode

        return int(make_mode(_mode(model.modes[0])).nu)
    except ValueError as exc:
        raise WireError(f"SessionSpec: refused by the estimator: {exc}") from None
    except Exception as exc:
        raise WireError(f"SessionSpec: refused by the estimator: "
                        f"{type(exc).__name__}: {exc}") from None


def measurement_step(msg: Measurement, spec: SessionSpec) -> int:
    """Sample step s: ``msg.step``, or ``floor((t_ns - epoch_ns) / period_ns)`` (may be < 0
    for a time before the epoch; :func:`check_measurement` refuses that)."""
    if msg.step is not None:
        return msg.step
    assert msg.t_ns is not None  # guaranteed by Measurement's validator
    return spec.step_of(msg.t_ns)


def command_step(msg: Command, spec: SessionSpec) -> int:
    """Apply step j: ``msg.step``, or ``floor((issued_ns - epoch_ns) / period_ns) + lead``."""
    if msg.step is not None:
        return msg.step
    assert msg.issued_ns is not None  # guaranteed by Command's validator
    return spec.step_of(msg.issued_ns) + spec.lead


def check_measurement(msg: Measurement, spec: SessionSpec) -> None:
    """Raise WireError unless ``msg`` fits ``spec``: same session, known sensor, z of the
    sensor's dimension m, R (if any) m x m, sample step >= 0."""
    if msg.session != spec.session:
        raise WireError(f"Measurement.session: {msg.session!r} is not session {spec.session!r}")
    sensor = spec.sensor(msg.sensor)
    if sensor is None:
        known = ", ".join(s.name for s in spec.sensors)
        raise WireError(f"Measurement.sensor: unknown sensor {msg.sensor!r} "
                        f"(session {spec.session!r} has: {known})")
    m = sensor.m
    if msg.z.shape[0] != m:
        raise WireError(f"Measurement.z: expected {m} values for sensor {sensor.name!r}, "
                        f"got {msg.z.shape[0]}")
    if msg.R is not None and msg.R.shape != (m, m):  # pragma: no cover - R matches z already
        raise WireError(f"Measurement.R: expected {m}x{m} for sensor {sensor.name!r}, "
                        f"got shape {list(msg.R.shape)}")
    if msg.t_ns is not None and msg.t_ns < spec.epoch_ns:
        raise WireError(f"Measurement.t_ns: {msg.t_ns} is before the session epoch "
                        f"{spec.epoch_ns} (step < 0)")


def check_command(msg: Command, spec: SessionSpec, r: int | None = None) -> None:
    """Raise WireError unless ``msg`` fits ``spec``: same session, u of dimension r,
    apply step >= 0. ``r``: the session's :func:`command_dim`, if already known (else it
    is computed, which builds a nonlinear model)."""
    if msg.session != spec.session:
        raise WireError(f"Command.session: {msg.session!r} is not session {spec.session!r}")
    if r is None:
        r = command_dim(spec)
    if msg.u.shape[0] != r:
        model = spec.model
        if isinstance(model, LinearModelSpec):
            why = f"model.B has {r} columns"
        elif r == 0:
            raise WireError(f"Command.u: session {spec.session!r} takes no commands "
                            f"(its model has no inputs)")
        else:
            name = model.model if isinstance(model, UnscentedModelSpec) else model.modes[0].model
            why = f"model {name!r} has {r} inputs"
        raise WireError(f"Command.u: expected {r} values ({why}), got {msg.u.shape[0]}")
    if msg.issued_ns is not None and command_step(msg, spec) < 0:
        raise WireError(f"Command.issued_ns: {msg.issued_ns} gives apply step "
                        f"{command_step(msg, spec)} < 0")


def check_key(msg: Message, key: str) -> ParsedKey:
    """Parse ``key`` and raise WireError unless ``msg`` belongs there: same session, and for
    a Measurement the sensor named by the key. Returns the parsed key."""
    name = type(msg).__name__
    try:
        parsed = parse_key(key)
    except KeyError_ as exc:
        raise WireError(f"{name}: {exc}") from None
    session = getattr(msg, "session", None)
    if session is not None and session != parsed.session:
        raise WireError(f"{name}.session: {session!r} does not match the key {key!r}")
    if isinstance(msg, Measurement) and msg.sensor != parsed.sensor:
        raise WireError(f"Measurement.sensor: {msg.sensor!r} does not match the key {key!r}")
    return parsed


def prediction_from(
    pred: _PredictedState,
    spec: SessionSpec,
    session: str,
    seq: int,
    made_ns: int,
    counters: Mapping[str, int],
) -> Prediction:
    """Wrap the estimator's output as a Prediction, ``t_ns = epoch_ns + step * period_ns``.

    Fast path for the daemon's hot loop: shapes and finiteness are checked and the arrays
    are copied (the estimator may reuse its buffers), but the PSD check of P is skipped
    (the estimator produces P = A P A^T + Q, symmetric PSD up to rounding, far inside the
    1e-9 tolerance a decoder applies). Raises WireError on a bad shape or non-finite value.
    """
    n = spec.n
    x = np.array(pred.x, dtype=np.float64)
    P = np.array(pred.P, dtype=np.float64)
    if x.shape != (n,) or P.shape != (n, n):
        raise WireError(f"Prediction: expected x ({n},) and P ({n}, {n}), "
                        f"got {x.shape} and {P.shape}")
    if not (np.isfinite(x).all() and np.isfinite(P).all()):
        raise WireError("Prediction: the estimate is not finite (NaN or infinity)")
    x.flags.writeable = False
    P.flags.writeable = False
    step = int(pred.step)
    newest = None if pred.newest_step is None else int(pred.newest_step)
    fields: dict[str, Any] = {
        "v": 1,
        "session": session,
        "seq": int(seq),
        "step": step,
        "t_ns": spec.time_of(step),
        "x": x,
        "P": P,
        "newest_step": newest,
        "made_ns": int(made_ns),
        "counters": {str(k): int(v) for k, v in counters.items()},
    }
    return Prediction.model_construct(**fields)


def encode_prediction(
    pred: _PredictedState,
    spec: SessionSpec,
    session: str,
    seq: int,
    made_ns: int,
    counters: Mapping[str, int],
) -> bytes:
    """``encode(prediction_from(...))``, byte for byte, without building the model.

    For the daemon's publish loop (about 3x cheaper). Same checks as
    :func:`prediction_from`: shapes and finite values; raises WireError otherwise.
    """
    n = spec.n
    x = np.asarray(pred.x, dtype=np.float64)
    P = np.asarray(pred.P, dtype=np.float64)
    if x.shape != (n,) or P.shape != (n, n):
        raise WireError(f"Prediction: expected x ({n},) and P ({n}, {n}), "
                        f"got {x.shape} and {P.shape}")
    xs = x.tolist()
    ps = P.ravel().tolist()
    # finite check: fsum of finite values is finite unless it overflows (then look closer)
    try:
        finite = math.isfinite(math.fsum(xs)) and math.isfinite(math.fsum(ps))
    except OverflowError:
        finite = False
    if not finite and not (np.isfinite(x).all() and np.isfinite(P).all()):
        raise WireError("Prediction: the estimate is not finite (NaN or infinity)")
    step = int(pred.step)
    obj = {
        "v": 1,
        "session": session,
        "seq": int(seq),
        "step": step,
        "t_ns": spec.time_of(step),
        "x": {"shape": [n], "data": xs},
        "P": {"shape": [n, n], "data": ps},
        "newest_step": None if pred.newest_step is None else int(pred.newest_step),
        "made_ns": int(made_ns),
        "counters": {str(k): int(v) for k, v in counters.items()},
    }
    data = msgpack.packb(obj, use_bin_type=True)
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"Prediction: encoded message is {len(data)} bytes, more than the "
                        f"{MAX_MESSAGE_BYTES}-byte limit")
    return data
