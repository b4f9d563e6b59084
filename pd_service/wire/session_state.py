"""SessionState: what a session's estimator needs to continue exactly, on the wire.

Written by the daemon as a checkpoint (a record of ``<state_dir>/checkpoints.log``) and sent as a
replica to the instance that would take the session over (``pd/@service/<successor>/replica/
<session>``). The estimator-side meaning of every field is
:class:`pd_service.estimation.EstimatorState`; the conversion lives in
:mod:`pd_service.service.handover.checkpoint`.

Arrays of any rank (the IMM's per-mode means are (N, r, n), the UKF's sensitivities
(p, n, n), an adapter's innovation windows (N, p, m)) use :data:`Tensor`:
``{"shape": [d0, ...], "data": [row-major...]}``, finite numbers, rank <= 4.
"""

from __future__ import annotations

import hashlib
import math
from typing import Annotated, Any, Final

import msgpack
import numpy as np
from pydantic import (
    Field,
    PlainSerializer,
    PlainValidator,
    StringConstraints,
    WithJsonSchema,
    model_validator,
)
from pydantic_core import PydanticCustomError

from pd_service.native import kernel_function

from .arrays import NON_FINITE_ERROR, Matrix, Vector, psd_problem, to_wire
from .base import WireModel
from .codec import MAX_MESSAGE_BYTES, encode
from .messages import Counters, Int64, Message, Name, NonNegInt

#: Layout version of the estimator state (``pd_service.estimation.STATE_VERSION``).
STATE_VERSION = 1
#: Largest rank and number of values of one :data:`Tensor`.
MAX_TENSOR_RANK = 4
MAX_TENSOR_SIZE = 16 * 1024
#: Most packets and commands a state carries.
MAX_STATE_ITEMS = 4096

_ArrayName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_.]{0,63}$")]


def _tensor(value: Any) -> np.ndarray:
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "fiu":
            raise PydanticCustomError("wire_array", f"expected a real array, got {value.dtype}")
        arr = np.array(value, dtype=np.float64, order="C", copy=True)
    else:
        if type(value) is not dict or set(value) != {"shape", "data"}:
            raise PydanticCustomError("wire_array", "a tensor is a map with exactly the keys "
                                      "'shape' and 'data'")
        shape, data = value["shape"], value["data"]
        if type(shape) is not list or not all(type(d) is int and d >= 0 for d in shape):
            raise PydanticCustomError("wire_array", "tensor 'shape' must be a list of "
                                      "integers >= 0")
        if type(data) is not list or not all(type(v) in (int, float) for v in data):
            raise PydanticCustomError("wire_array", "tensor 'data' must be a list of numbers")
        if len(data) != math.prod(shape):
            raise PydanticCustomError("wire_array", f"tensor 'data' has {len(data)} values, "
                                      f"shape {shape} needs {math.prod(shape)}")
        arr = np.array(data, dtype=np.float64).reshape(shape)
    if arr.ndim > MAX_TENSOR_RANK or arr.size > MAX_TENSOR_SIZE:
        raise PydanticCustomError("wire_array", f"tensor of shape {list(arr.shape)}: rank <= "
                                  f"{MAX_TENSOR_RANK} and <= {MAX_TENSOR_SIZE} values")
    if not np.isfinite(arr).all():
        raise PydanticCustomError(NON_FINITE_ERROR, "tensor must hold finite numbers only")
    arr.flags.writeable = False
    return arr


#: A float64 array of rank 0..4: wire form ``{"shape": [...], "data": [...]}``.
Tensor = Annotated[
    np.ndarray,
    PlainValidator(_tensor),
    PlainSerializer(to_wire),
    WithJsonSchema({
        "type": "object",
        "description": "An array of rank 0..4, row-major: data holds prod(shape) finite "
                       "numbers.",
        "properties": {
            "shape": {"type": "array", "maxItems": MAX_TENSOR_RANK,
                      "items": {"type": "integer", "minimum": 0}},
            "data": {"type": "array", "maxItems": MAX_TENSOR_SIZE, "items": {"type": "number"}},
        },
        "required": ["shape", "data"],
        "additionalProperties": False,
    }),
]


def spec_fingerprint(spec: Message) -> str:
    """BLAKE2b-256 (hex) of the spec's wire encoding: a state is only restored into a
    session built from the very same spec."""
    return hashlib.blake2b(encode(spec), digest_size=32).hexdigest()


class StatePacket(WireModel):
    """A measurement inside the window: sample ``step``, ``sensor``, z (m,), R override,
    ``offset`` (s after the step's start at which it was sampled)."""

    step: NonNegInt = Field(description="Sample step.")
    sensor: Name = Field(description="Sensor name (from the spec).")
    z: Vector = Field(description="Measurement, m.")
    R: Matrix | None = Field(None, description="Per-sample noise covariance override, m x m.")
    offset: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = Field(
        0.0, description="Seconds after the start of its step at which it was sampled "
                         "(0: on the grid).")


class StateCommand(WireModel):
    """An explicit command inside the window: u applies from ``offset`` s after the start
    of ``step`` on."""

    step: NonNegInt = Field(description="Apply step.")
    u: Tensor = Field(description="Input, nu.")
    offset: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = Field(
        0.0, description="Seconds after the start of its step at which it takes effect.")


class SessionState(Message):
    """A session's estimator state (checkpoint or replica); see docs/protocol.md.

    Rules: P is n x n (n = len(x)), symmetric PSD; base_step <= committed_step; every
    packet's step lies in [committed_step, now_step]; the packets and commands are at most
    4096 each.
    """

    session: Name = Field(description="Session id.")
    instance: Name = Field(description="Instance that wrote the state.")
    spec_fingerprint: Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{64}$")] = Field(
        description="BLAKE2b-256 (hex) of the encoded SessionSpec the estimator was built from.")
    state_version: Annotated[int, Field(ge=1, le=1_000_000)] = Field(
        STATE_VERSION, description="Layout version of the estimator state.")
    kind: Annotated[str, StringConstraints(max_length=64)] = Field(
        description="Estimator class, e.g. ObserverPredictor.")
    made_ns: Int64 = Field(description="When the state was taken, ns on the shared clock.")
    now_step: NonNegInt | None = Field(description="Newest step the estimator had seen.")
    committed_step: NonNegInt = Field(description="First step that could still change.")
    base_step: NonNegInt = Field(description="Step of the committed-horizon estimate.")
    newest_committed: NonNegInt | None = Field(
        None, description="Newest measured step already committed.")
    x: Vector = Field(description="Committed-horizon estimate of x(base_step), n (IMM: the "
                                  "mixture mean).")
    P: Matrix = Field(description="Its covariance, n x n (IMM: the mixture covariance).")
    base: dict[_ArrayName, Tensor] = Field(
        default_factory=dict, description="Further arrays of the backend's state: UKF "
        "sensitivities dx, dP; IMM mode probabilities mu (N, r), per-mode x (N, r, n), "
        "P (N, r, n, n).")
    packets: list[StatePacket] = Field(default_factory=list, max_length=MAX_STATE_ITEMS,
                                       description="Measurements inside the window.")
    u_origin: Tensor = Field(description="Input in effect at base_step, nu.")
    commands: list[StateCommand] = Field(default_factory=list, max_length=MAX_STATE_ITEMS,
                                         description="Explicit commands from base_step on.")
    u_before: Tensor | None = Field(
        None, description="Input in effect before base_step (nu), for a command taking "
                          "effect inside the base step; nil: zeros.")
    counters: Counters = Field(default_factory=dict, description="Estimator counters.")
    extras: dict[_ArrayName, Tensor] = Field(
        default_factory=dict, description="What the estimator learnt: adapted process noise "
        "Q (n, n), last_update (1,), adapter memory adapter.*.")
    session_counters: Counters = Field(default_factory=dict,
                                       description="The session's counters.")
    published: NonNegInt = Field(0, description="Predictions published so far.")
    seq: NonNegInt = Field(0, description="Next Prediction seq.")
    term: NonNegInt = Field(0, description="Ownership term of the writer (Prediction.term): "
                            "the instance resuming from this state takes a newer one.")

    @model_validator(mode="after")
    def _check(self) -> SessionState:
        n = self.x.shape[0]
        if self.P.shape != (n, n):
            raise PydanticCustomError("wire_invalid", f"P must be {n}x{n} (x has {n} values), "
                                      f"got shape {list(self.P.shape)}")
        problem = psd_problem(self.P)
        if problem:
            raise PydanticCustomError("wire_invalid", f"P {problem}")
        if self.base_step > self.committed_step:
            raise PydanticCustomError("wire_invalid", "base_step must be <= committed_step")
        hi = self.now_step if self.now_step is not None else 0
        for p in self.packets:
            if not self.committed_step <= p.step <= hi:
                raise PydanticCustomError("wire_invalid", f"packet step {p.step} outside "
                                          f"[{self.committed_step}, {hi}]")
        return self


class Tensors:
    """Builds the wire forms of float64 arrays (as :data:`Tensor` dumps them) and keeps track of
    whether every value given was finite: one fsum per array, where a walk over the
    finished fields cost a checkpoint more than half of its encoding (~20 of 35 µs for a
    paper session)."""

    __slots__ = ("finite",)

    def __init__(self) -> None:
        self.finite = True

    def __call__(self, a: Any) -> dict[str, Any]:
        arr = np.asarray(a, dtype=np.float64)
        data: list[float] = arr.ravel().tolist()
        if self.finite:
            # fsum of finite values is finite unless it overflows (then look at each); it
            # raises ValueError for inf + -inf
            try:
                ok = math.isfinite(math.fsum(data))
            except (OverflowError, ValueError):
                ok = False
            if not ok:
                self.finite = all(math.isfinite(v) for v in data)
        return {"shape": list(arr.shape), "data": data}

    def rows(self, arrays: list[Any]) -> list[dict[str, Any]]:
        """The wire forms of arrays of one shape (e.g. a state's commands), converted as
        one stack: ~0.2 instead of ~0.8 µs each."""
        if not arrays:
            return []
        try:
            stack = np.asarray(arrays, dtype=np.float64)
        except ValueError:  # not all of one shape: one by one
            return [self(a) for a in arrays]
        if self.finite and not np.isfinite(stack).all():
            self.finite = False
        shape = list(stack.shape[1:])
        return [{"shape": shape.copy(), "data": row}
                for row in stack.reshape(len(arrays), -1).tolist()]


#: ``pack(fields)``: msgpack of a SessionState's fields whose arrays are given as float64
#: numpy arrays, each written in its wire form (pd_service/wire/_encode.c), or None for
#: anything else; None where the hot path runs as pure Python. The caller's Python form
#: (:class:`Tensors` and :func:`pack_state_fields`) is the reference.
PACK_WITH_ARRAYS: Final = kernel_function("pd_service.wire._encode", "pack")


def pack_state_fields(obj: dict[str, Any], finite: bool) -> bytes | None:
    """msgpack of a SessionState's fields in wire order (``SessionState.model_dump()``
    form, built by the caller without the models, its arrays by :class:`Tensors`), or None
    if a number is not finite (``finite``: the Tensors' verdict) or the message would need
    the codec's compact form: the caller then takes the validated path
    (``encode(SessionState(...))``), which also explains the refusal."""
    if not finite:
        return None
    data: bytes = msgpack.packb(obj, use_bin_type=True)
    return data if len(data) <= MAX_MESSAGE_BYTES else None
