"""Every message of the pd-service protocol, as strict pydantic v2 models.

All messages are frozen, refuse unknown fields, never coerce types (a float is not an int, a
bool is not a number), and carry the schema version ``v`` (always 1 for now). Arrays are
read-only float64 numpy arrays in Python and ``{"shape", "data"}`` maps on the wire (see
:mod:`pd_service.wire.arrays`). Integers are bounded to int64 so any language can hold them.

Units: times are integer nanoseconds on the shared clock (``*_ns``), steps are integer
indices of the session's step grid, ``step = floor((t_ns - epoch_ns) / period_ns)``;
latencies are microseconds (``*_us``); physical quantities are in whatever units the
session's model uses.

Covariances (Q, P0, R, P) must be symmetric positive semi-definite within
``PSD_RTOL = 1e-9`` relative to ``max(1, max|M|)`` (:func:`pd_service.wire.arrays.psd_problem`).

These models only check what one message can know on its own. Whether a Measurement or a
Command fits its session (sensor known, dimensions) is checked by
:func:`pd_service.wire.convert.check_measurement` / ``check_command``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    PrivateAttr,
    StringConstraints,
    Tag,
    model_validator,
)
from pydantic_core import PydanticCustomError

from .arrays import MAX_DIM, Matrix, Vector, psd_problem
from .keys import NAME_PATTERN

SCHEMA_VERSION = 1
INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1
MAX_SENSORS = 16
MAX_DELAY_LIMIT = 1000
MAX_LEAD = 10_000
MAX_TEXT = 1024

#: A session, sensor or instance name: ``[a-z0-9][a-z0-9_-]{0,63}``.
Name = Annotated[str, StringConstraints(pattern=f"^{NAME_PATTERN}$")]
Int64 = Annotated[int, Field(ge=INT64_MIN, le=INT64_MAX)]
NonNegInt = Annotated[int, Field(ge=0, le=INT64_MAX)]
PosInt = Annotated[int, Field(ge=1, le=INT64_MAX)]
Counters = dict[Annotated[str, StringConstraints(min_length=1, max_length=64)], Int64]
Text = Annotated[str, StringConstraints(max_length=MAX_TEXT)]
NonNegFloat = Annotated[float, Field(ge=0.0)]


def _invalid(message: str) -> PydanticCustomError:
    return PydanticCustomError("wire_invalid", message)


def _comparable(value: Any) -> Any:
    """A hashable stand-in for a field value (arrays by shape and values)."""
    if isinstance(value, np.ndarray):
        return ("ndarray", value.shape, tuple(value.ravel().tolist()))
    if isinstance(value, WireModel):
        return value._identity()
    if isinstance(value, list | tuple):
        return tuple(_comparable(v) for v in value)
    if isinstance(value, dict):
        return tuple(sorted((k, _comparable(v)) for k, v in value.items()))
    return value


class WireModel(BaseModel):
    """Base of every wire model: strict, frozen, no unknown fields, no NaN/inf floats.

    Equality and hashing compare array fields by shape and values (pydantic's default
    would compare numpy arrays element-wise and fail).
    """

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, allow_inf_nan=False)

    def _identity(self) -> tuple[Any, ...]:
        return (type(self).__name__,) + tuple(
            _comparable(getattr(self, name)) for name in type(self).model_fields
        )

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return self._identity() == other._identity()  # type: ignore[attr-defined]

    def __hash__(self) -> int:
        return hash(self._identity())


def _version_is_int(value: Any) -> Any:
    # Literal[1] alone would take True and 1.0 (both == 1 in Python)
    if type(value) is not int:
        raise _invalid("Input should be 1")
    return value


class Message(WireModel):
    """A top-level message: carries the schema version ``v``."""

    v: Annotated[Literal[1], BeforeValidator(_version_is_int)] = Field(
        1, description="Schema version; always 1.")


# --- session configuration ---------------------------------------------------------------

class SensorSpec(WireModel):
    """One sensor group: z = H x(s) + v, v ~ N(0, R), sampled every ``interval`` steps.

    Rules: H is m x n; R is m x m, symmetric PSD.
    """

    name: Name = Field(description="Sensor name, unique in the session; the sensor key's last chunk.")
    H: Matrix = Field(description="Observation matrix, m x n (m = measurement dimension).")
    R: Matrix = Field(description="Measurement noise covariance, m x m, symmetric PSD.")
    delay: Annotated[int, Field(ge=0, le=MAX_DELAY_LIMIT)] = Field(
        description="Nominal downlink delay in steps (0..max_delay).")
    interval: PosInt = Field(description="Sample interval in steps (1 = every step).")

    @property
    def m(self) -> int:
        """Measurement dimension."""
        return int(self.H.shape[0])

    @model_validator(mode="after")
    def _check(self) -> SensorSpec:
        m = self.H.shape[0]
        if self.R.shape != (m, m):
            raise _invalid(f"R must be {m}x{m} (H has {m} rows), got shape {list(self.R.shape)}")
        problem = psd_problem(self.R)
        if problem:
            raise _invalid(f"R {problem}")
        return self


class LinearModelSpec(WireModel):
    """Linear time-invariant model: x(k+1) = A x(k) + B u(k) + w(k), w ~ N(0, Q).

    Rules: A is n x n; B is n x r (r >= 1); Q is n x n, symmetric PSD.
    """

    kind: Literal["linear"] = Field("linear", description="Model kind (discriminator).")
    A: Matrix = Field(description="State transition, n x n (n <= 64).")
    B: Matrix = Field(description="Input matrix, n x r (r = command dimension).")
    Q: Matrix = Field(description="Process noise covariance, n x n, symmetric PSD.")

    @property
    def n(self) -> int:
        """State dimension."""
        return int(self.A.shape[0])

    @property
    def r(self) -> int:
        """Command (input) dimension."""
        return int(self.B.shape[1])

    @model_validator(mode="after")
    def _check(self) -> LinearModelSpec:
        n = self.A.shape[0]
        if self.A.shape != (n, n):
            raise _invalid(f"A must be square (n x n), got shape {list(self.A.shape)}")
        if self.B.shape[0] != n:
            raise _invalid(f"B must have n={n} rows (A is {n}x{n}), got shape {list(self.B.shape)}")
        if self.Q.shape != (n, n):
            raise _invalid(f"Q must be {n}x{n} (A is {n}x{n}), got shape {list(self.Q.shape)}")
        problem = psd_problem(self.Q)
        if problem:
            raise _invalid(f"Q {problem}")
        return self


def _model_kind(value: Any) -> str | None:
    if isinstance(value, dict):
        kind = value.get("kind", "linear")
        return kind if isinstance(kind, str) else None
    return getattr(value, "kind", None)


#: Every model kind, discriminated by ``kind`` (absent means "linear"). A new kind is one
#: more ``Annotated[NewModelSpec, Tag("new")]`` here, plus its case in ``convert.py``.
ModelSpec = Annotated[
    Annotated[LinearModelSpec, Tag("linear")],
    Discriminator(
        _model_kind,
        custom_error_type="wire_model_kind",
        custom_error_message="model must be a map whose 'kind' is one of: linear",
    ),
]


class SessionSpec(Message):
    """Creates or replaces a session (put on ``pd/<session>/config``).

    Rules: n = model state dimension (1..64); x0 has n values; P0 is n x n; every sensor's
    H has n columns; sensor names are unique; every sensor delay <= max_delay; covariances
    symmetric PSD (tolerance 1e-9 * max(1, max|M|)).
    """

    session: Name = Field(description="Session id.")
    period_ns: PosInt = Field(description="Step period, ns.")
    epoch_ns: Int64 = Field(description="Time of step 0 on the shared clock, ns.")
    model: ModelSpec = Field(description="System model; 'kind' selects the model type.")
    x0: Vector = Field(description="Prior mean of x(0), n.")
    P0: Matrix = Field(description="Prior covariance of x(0), n x n, symmetric PSD.")
    sensors: Annotated[list[SensorSpec], Field(min_length=1, max_length=MAX_SENSORS)] = Field(
        description="Sensor groups (1..16, unique names).")
    lead: Annotated[int, Field(ge=0, le=MAX_LEAD)] = Field(
        description="Prediction lead, steps: the uplink delay plus the shift the observer "
                    "moves there. Predictions target now + lead.")
    max_delay: Annotated[int, Field(ge=0, le=MAX_DELAY_LIMIT)] = Field(
        description="Oldest accepted sample, steps: a sample stamped s is accepted at step "
                    "now iff now - max_delay <= s <= now.")
    publish_every: PosInt = Field(1, description="Publish a Prediction every this many steps.")
    command_hold: Literal["hold", "zero"] = Field(
        "hold", description="A step without a command: hold the last u, or use u = 0.")

    # name -> SensorSpec, rebuilt whenever `sensors` is not the list it was built from
    # (model_copy(update=...) copies private attributes but not their meaning).
    _sensor_index: dict[str, SensorSpec] = PrivateAttr(default_factory=dict)
    _sensor_index_of: list[SensorSpec] | None = PrivateAttr(default=None)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.model.n

    @property
    def r(self) -> int:
        """Command (input) dimension."""
        return self.model.r

    def sensor(self, name: str) -> SensorSpec | None:
        """The sensor called ``name``, or None."""
        if self._sensor_index_of is not self.sensors:
            self._sensor_index = {s.name: s for s in self.sensors}
            self._sensor_index_of = self.sensors
        return self._sensor_index.get(name)

    def step_of(self, t_ns: int) -> int:
        """Step containing time ``t_ns``: floor((t_ns - epoch_ns) / period_ns), exact."""
        return (t_ns - self.epoch_ns) // self.period_ns

    def time_of(self, step: int) -> int:
        """Start time of ``step`` in ns: epoch_ns + step * period_ns."""
        return self.epoch_ns + step * self.period_ns

    @model_validator(mode="after")
    def _check(self) -> SessionSpec:
        n = self.model.n
        if n > MAX_DIM:  # unreachable while MAX_DIM bounds every array axis; kept explicit
            raise _invalid(f"state dimension n={n} exceeds {MAX_DIM}")
        if self.x0.shape != (n,):
            raise _invalid(f"x0 must have n={n} values (model.A is {n}x{n}), got {self.x0.shape[0]}")
        if self.P0.shape != (n, n):
            raise _invalid(f"P0 must be {n}x{n} (model.A is {n}x{n}), got shape {list(self.P0.shape)}")
        problem = psd_problem(self.P0)
        if problem:
            raise _invalid(f"P0 {problem}")
        seen: set[str] = set()
        for i, s in enumerate(self.sensors):
            if s.name in seen:
                raise _invalid(f"sensors[{i}].name {s.name!r} is used twice; names must be unique")
            seen.add(s.name)
            if s.H.shape[1] != n:
                raise _invalid(f"sensors[{i}] ({s.name!r}).H must have n={n} columns, "
                               f"got shape {list(s.H.shape)}")
            if s.delay > self.max_delay:
                raise _invalid(f"sensors[{i}] ({s.name!r}).delay={s.delay} exceeds "
                               f"max_delay={self.max_delay}: every sample would be late")
        return self


# --- streams into the daemon ------------------------------------------------------------

class Measurement(Message):
    """One sensor sample (``pd/<session>/sensor/<name>``): z = H x(s) + v.

    Rules: exactly one of step / t_ns; R, if given, is m x m (m = len(z)) symmetric PSD.
    Against the session: the sensor exists and z has its dimension m.
    """

    session: Name = Field(description="Session id.")
    sensor: Name = Field(description="Sensor name, as in the SessionSpec.")
    seq: NonNegInt = Field(description="Sender's sequence number (per sensor), for reports.")
    step: NonNegInt | None = Field(None, description="Sample step s. Exactly one of step / t_ns.")
    t_ns: Int64 | None = Field(
        None, description="Sample time, ns on the shared clock; s = floor((t_ns - epoch_ns) / "
                          "period_ns). Exactly one of step / t_ns.")
    z: Vector = Field(description="Measured values, m.")
    R: Matrix | None = Field(
        None, description="Noise covariance of this sample only, m x m, symmetric PSD; "
                          "absent = the sensor's R.")

    @model_validator(mode="after")
    def _check(self) -> Measurement:
        if (self.step is None) == (self.t_ns is None):
            raise _invalid("exactly one of step / t_ns must be given"
                           + (", got both" if self.step is not None else ", got neither"))
        if self.R is not None:
            m = self.z.shape[0]
            if self.R.shape != (m, m):
                raise _invalid(f"R must be {m}x{m} (z has {m} values), got shape {list(self.R.shape)}")
            problem = psd_problem(self.R)
            if problem:
                raise _invalid(f"R {problem}")
        return self


class Command(Message):
    """One operator command (``pd/<session>/cmd``): u applies from its apply step on.

    Rules: exactly one of step / issued_ns. Against the session: u has r values (the
    columns of model.B).
    """

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="Sender's sequence number, for reports.")
    step: NonNegInt | None = Field(
        None, description="Apply step: u acts from this step on. Exactly one of step / issued_ns.")
    issued_ns: Int64 | None = Field(
        None, description="Time the operator issued it, ns; apply step = "
                          "floor((issued_ns - epoch_ns) / period_ns) + lead. Exactly one of "
                          "step / issued_ns.")
    u: Vector = Field(description="Command, r values.")

    @model_validator(mode="after")
    def _check(self) -> Command:
        if (self.step is None) == (self.issued_ns is None):
            raise _invalid("exactly one of step / issued_ns must be given"
                           + (", got both" if self.step is not None else ", got neither"))
        return self


# --- streams out of the daemon ----------------------------------------------------------

class Prediction(Message):
    """The predicted state at a target step (``pd/<session>/prediction``).

    Rules: P is n x n (n = len(x)), symmetric PSD.
    """

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="Publisher's sequence number (per session).")
    step: NonNegInt = Field(description="Target step (the step at which a command sent now acts).")
    t_ns: Int64 = Field(description="Start time of the target step, ns: epoch_ns + step * period_ns.")
    x: Vector = Field(description="Predicted state mean, n.")
    P: Matrix = Field(description="Predicted state covariance, n x n, symmetric PSD.")
    newest_step: NonNegInt | None = Field(
        None, description="Newest sample step among the measurements used; nil before any.")
    made_ns: Int64 = Field(description="When the prediction was computed, ns on the shared clock.")
    counters: Counters = Field(default_factory=dict,
                               description="Session counters (accepted, refused by reason, ...).")

    @model_validator(mode="after")
    def _check(self) -> Prediction:
        n = self.x.shape[0]
        if self.P.shape != (n, n):
            raise _invalid(f"P must be {n}x{n} (x has {n} values), got shape {list(self.P.shape)}")
        problem = psd_problem(self.P)
        if problem:
            raise _invalid(f"P {problem}")
        return self


class ErrorReport(Message):
    """Why a message was refused (``pd/<session>/error``, rate-limited by the daemon)."""

    session: Name = Field(description="Session id.")
    key: Annotated[str, StringConstraints(max_length=512)] = Field(
        description="Key expression the refused message arrived on.")
    seq: NonNegInt | None = Field(None, description="seq of the refused message, if it could be read.")
    reason: Text = Field(description="Why it was refused, one readable line.")
    t_ns: Int64 = Field(description="When it was refused, ns on the shared clock.")


class SessionStatus(Message):
    """Reply of ``pd/<session>/status``, and the answer to every config change."""

    session: Name = Field(description="Session id.")
    instance: Name = Field(description="Daemon instance serving the session.")
    state: Literal["active", "restored", "expired", "removed"] = Field(
        description="active; restored (from the state directory after a restart); "
                    "expired (idle too long); removed (config deleted).")
    now_step: Int64 = Field(description="The session's current step.")
    counters: Counters = Field(default_factory=dict, description="Session counters.")
    published: NonNegInt = Field(description="Predictions published so far.")
    latency_p50_us: NonNegFloat = Field(description="Median processing latency, µs.")
    latency_p99_us: NonNegFloat = Field(description="99th percentile processing latency, µs.")
    detail: Text = Field("", description="Free text (e.g. why the session was replaced).")


class ServiceStatus(Message):
    """Reply of ``pd/@service/<instance>/status``."""

    instance: Name = Field(description="Daemon instance id.")
    sessions: list[Name] = Field(description="Sessions this instance serves.")
    counters: Counters = Field(default_factory=dict, description="Service-wide counters.")
    latency_p50_us: NonNegFloat = Field(description="Median processing latency, µs.")
    latency_p99_us: NonNegFloat = Field(description="99th percentile processing latency, µs.")
    uptime_s: NonNegFloat = Field(description="Seconds since the instance started.")
    shard: Annotated[str, StringConstraints(max_length=64)] = Field(
        "", description="Which share of the sessions this instance takes, e.g. '0/2'.")


#: Every top-level message type, in protocol order.
MESSAGE_TYPES: tuple[type[Message], ...] = (
    SessionSpec, Measurement, Command, Prediction, ErrorReport, SessionStatus, ServiceStatus,
)
