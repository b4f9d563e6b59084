"""Between wire messages and the estimators' numbers: what a message stands for, and whether
it fits its session. Builds no model and no estimator (that is :mod:`pd_service.backends`,
which also gives a session's command dimension).

- :func:`measurement_step` / :func:`command_step`: the integer step a message stands for;
- :func:`check_measurement` / :func:`check_command`: does the message fit its session?
  (raise :class:`WireError` naming the field);
- :func:`check_key`: does the message agree with the key it arrived on?
- :func:`prediction_from`: estimator output -> Prediction message (with
  :func:`pd_service.wire.encode`: the reference of a Prediction's bytes);
- :class:`PredictionEncoder`: estimator output, x and P already packed -> the same
  Prediction's bytes, directly (the daemon's hot path: no model object; its per-message part
  in C, ``_encode.c``, where the hot path runs compiled).

Time: ``step_of(t_ns) = floor((t_ns - epoch_ns) / period_ns)`` in exact integer arithmetic; a
continuous-time spec also gives the offset into the step in seconds
(:meth:`SessionSpec.sample_at`, :meth:`SessionSpec.command_at`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, SupportsInt

import msgpack
import numpy as np
from numpy.typing import NDArray

from pd_service.native import kernel

from .codec import MAX_MESSAGE_BYTES, encode
from .errors import WireError
from .keys import KeyError_, ParsedKey, parse_key
from .messages import (
    Command,
    LinearModelSpec,
    Measurement,
    Message,
    Prediction,
    SessionSpec,
    UnscentedModelSpec,
)


class PredictedMoments(Protocol):
    """What a prediction is made of (e.g. :class:`pd_service.estimation.PredictedState`):
    x(step) ~ (x (n,), P (n, n)), ``newest_step`` the newest sample that contributed.
    The steps may be numpy integers (SupportsInt: this module, compiled by mypyc, reads them
    with int())."""

    @property
    def step(self) -> SupportsInt: ...

    @property
    def x(self) -> NDArray[np.float64]: ...

    @property
    def P(self) -> NDArray[np.float64]: ...

    @property
    def newest_step(self) -> SupportsInt | None: ...


def measurement_time(msg: Measurement, spec: SessionSpec) -> tuple[int, float]:
    """(sample step s, offset in s into it): ``(msg.step, 0.0)``, or
    :meth:`SessionSpec.sample_at` (t_ns) (s may be < 0 for a time before the epoch;
    :func:`check_measurement` refuses that)."""
    if msg.step is not None:
        return msg.step, 0.0
    assert msg.t_ns is not None  # guaranteed by Measurement's validator
    return spec.sample_at(msg.t_ns)


def measurement_step(msg: Measurement, spec: SessionSpec) -> int:
    """Sample step s of :func:`measurement_time`."""
    return measurement_time(msg, spec)[0]


def command_time(msg: Command, spec: SessionSpec) -> tuple[int, float]:
    """(apply step j, offset in s into it): ``(msg.step, 0.0)``, or
    :meth:`SessionSpec.command_at` (issued_ns): ``floor((issued_ns - epoch_ns) /
    period_ns) + lead``, at the same offset for a continuous-time model."""
    if msg.step is not None:
        return msg.step, 0.0
    assert msg.issued_ns is not None  # guaranteed by Command's validator
    return spec.command_at(msg.issued_ns)


def command_step(msg: Command, spec: SessionSpec) -> int:
    """Apply step j of :func:`command_time`."""
    return command_time(msg, spec)[0]


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


def check_command(msg: Command, spec: SessionSpec, r: int) -> None:
    """Raise WireError unless ``msg`` fits ``spec``: same session, u of dimension r (the
    session's command dimension, :func:`pd_service.backends.command_dim`), apply step >= 0."""
    if msg.session != spec.session:
        raise WireError(f"Command.session: {msg.session!r} is not session {spec.session!r}")
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


def _checked(pred: PredictedMoments, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """x, P of ``pred`` as float64 arrays (views if they already are); WireError unless
    x is (n,), P (n, n)."""
    x = np.asarray(pred.x, dtype=np.float64)
    P = np.asarray(pred.P, dtype=np.float64)
    if x.shape != (n,) or P.shape != (n, n):
        raise WireError(f"Prediction: expected x ({n},) and P ({n}, {n}), "
                        f"got {x.shape} and {P.shape}")
    return x, P


def _fields(pred: PredictedMoments, spec: SessionSpec, session: str, seq: int, made_ns: int,
            counters: Mapping[str, int], x: object, P: object, term: int) -> dict[str, Any]:
    """The Prediction's fields in wire order, ``t_ns = epoch_ns + step * period_ns``."""
    step = int(pred.step)
    return {
        "v": 1,
        "session": session,
        "seq": int(seq),
        "step": step,
        "t_ns": spec.time_of(step),
        "x": x,
        "P": P,
        "newest_step": None if pred.newest_step is None else int(pred.newest_step),
        "made_ns": int(made_ns),
        "counters": {str(k): int(v) for k, v in counters.items()},
        "term": int(term),
    }


def prediction_from(
    pred: PredictedMoments,
    spec: SessionSpec,
    session: str,
    seq: int,
    made_ns: int,
    counters: Mapping[str, int],
    term: int = 0,
) -> Prediction:
    """Wrap the estimator's output as a Prediction, ``t_ns = epoch_ns + step * period_ns``,
    published with ownership ``term``.

    With :func:`pd_service.wire.encode`, the reference of a Prediction's bytes (the
    daemon's :class:`PredictionEncoder` writes the same). Shapes and finiteness are checked
    and the arrays are copied (the estimator may reuse its buffers), but the PSD check of P
    is skipped
    (the estimator produces P = A P A^T + Q, symmetric PSD up to rounding, far inside the
    1e-9 tolerance a decoder applies). Raises WireError on a bad shape or non-finite value.
    """
    x, P = _checked(pred, spec.n)
    if not (np.isfinite(x).all() and np.isfinite(P).all()):
        raise WireError("Prediction: the estimate is not finite (NaN or infinity)")
    x, P = np.array(x), np.array(P)
    x.flags.writeable = False
    P.flags.writeable = False
    return Prediction.model_construct(**_fields(pred, spec, session, seq, made_ns, counters, x, P,
                                                term))


#: The C form of :meth:`PredictionEncoder.encode_packed`'s per-message part (None: Python).
_ENCODE = kernel("pd_service.wire._encode")

#: msgpack's packing, shared by every encoder: a Packer holds a 256 KiB buffer, too much per
#: session (docs/performance.md). Shared safely: the worker is its one user, and packing
#: plain values runs in C, holding the GIL throughout.
_PACK = msgpack.Packer(use_bin_type=True).pack


class PredictionEncoder:
    """One session's Prediction encoder: ``encode(prediction_from(...))``, byte for byte,
    without building the model (the daemon's publish loop: no dict of the fields).

    The msgpack map is written as its parts: the constant ones (the map header, the keys,
    ``v``, ``session``, the shapes of x and P) are packed once, here; per message only seq,
    step, t_ns (``epoch_ns + step * period_ns``), the data of x (n,) and P (n, n) (row-major
    floats, packed by the caller), newest_step, made_ns, the counters and the term are
    packed. Raises
    WireError for packed values of the wrong length, or when the message cannot fit in
    ``MAX_MESSAGE_BYTES`` even in the codec's compact form.
    Where the hot path runs compiled, :meth:`encode_packed` writes the message in one call
    of the C kernel ``_encode.c``; the Python form is its reference (the same bytes).
    """

    def __init__(self, spec: SessionSpec, session: str) -> None:
        pk = _PACK
        n = spec.n
        self.spec, self.session, self.n = spec, session, n
        self._epoch, self._period = spec.epoch_ns, spec.period_ns
        # a fixmap of the 11 fields, in the order of Prediction's fields (_fields)
        self._head = b"\x8b" + pk("v") + pk(1) + pk("session") + pk(session) + pk("seq")
        self._k_step, self._k_t = pk("step"), pk("t_ns")
        self._k_x = pk("x") + b"\x82" + pk("shape") + pk([n]) + pk("data")
        self._k_P = pk("P") + b"\x82" + pk("shape") + pk([n, n]) + pk("data")
        self._k_newest, self._k_made, self._k_counters = pk("newest_step"), pk("made_ns"), \
            pk("counters")
        self._k_term = pk("term")
        #: the constant pieces around the values, in message order (the C form's ``parts``)
        self._parts = (self._head, self._k_step, self._k_t, self._k_x, self._k_P,
                       self._k_newest, self._k_made, self._k_counters, self._k_term)
        # the lengths of x's and P's packed values: an array header, 9 bytes per float64
        self._x_len, self._P_len = len(pk([0.0] * n)), len(pk([0.0] * (n * n)))

    def encode_packed(self, pred: PredictedMoments, x_data: bytes, P_data: bytes, seq: int,
                      made_ns: int, counters: Mapping[str, int], term: int = 0) -> bytes:
        """The Prediction of x(pred.step) ~ (x, P) published with ownership ``term``,
        encoded: ``x_data`` and ``P_data`` the msgpack arrays of x's n and P's n * n floats
        (row-major), as ``msgpack.packb(list)`` writes them, checked finite by the caller (the
        daemon's health check, :func:`pd_service.service.health.inspect_packed`). Their
        lengths are checked here."""
        if len(x_data) != self._x_len or len(P_data) != self._P_len:
            n = self.n
            raise WireError(f"Prediction: expected x ({n},) and P ({n}, {n}) packed in "
                            f"{self._x_len} and {self._P_len} bytes, got {len(x_data)} and "
                            f"{len(P_data)}")
        if type(counters) is not dict:
            counters = {str(k): int(v) for k, v in counters.items()}
        step = int(pred.step)
        newest = pred.newest_step
        t_ns = self._epoch + step * self._period
        # the same bytes in one C call; None: a value it does not take (the Python form then)
        data = None if _ENCODE is None else _ENCODE.prediction(
            self._parts, seq, step, t_ns, x_data, P_data, newest, made_ns, counters, term)
        if data is None:
            pk = _PACK
            data = b"".join((
                self._head, pk(int(seq)), self._k_step, pk(step), self._k_t, pk(t_ns),
                self._k_x, x_data, self._k_P, P_data,
                self._k_newest, pk(None if newest is None else int(newest)),
                self._k_made, pk(int(made_ns)), self._k_counters, pk(counters),
                self._k_term, pk(int(term))))
        if len(data) > MAX_MESSAGE_BYTES:  # the codec's compact form, or its refusal
            data = encode(prediction_from(pred, self.spec, self.session, seq, made_ns,
                                          counters, term))
        return data

