"""msgpack codec: ``encode(msg) -> bytes`` and ``decode(data, MsgType) -> MsgType``.

A message is one msgpack map whose keys are the field names (str) and whose values are
msgpack nil / bool / int / float64 / str / array / map; numeric arrays are
``{"shape": [...], "data": [...]}`` maps (:mod:`pd_service.wire.arrays`).

``decode`` raises :class:`WireError` and nothing else for any byte string:

1. size: more than ``MAX_MESSAGE_BYTES`` (64 KiB) is refused before unpacking;
2. unpack: msgpack with per-container limits (``max_array_len``, ``max_map_len``,
   ``max_str_len``; bin and ext types are refused) so a forged length cannot allocate
   much; nesting depth is bounded by the C unpacker's stack (1024 levels, ``StackError``)
   and the validators never recurse into input, so no input can exhaust the Python stack;
   trailing bytes after the map are refused;
3. validation: the model's strict pydantic validation; its first error becomes the reason,
   ``"<Type>.<field path>: <message>"``.

``encode`` raises WireError when the message would exceed 64 KiB. Before giving up it
retries in a compact form where integral float values (e.g. 0.0 and 1.0 in sparse
matrices) are written as msgpack ints (1 byte instead of 9); ``decode`` reads them back as
the same float64 values, so a session spec with large sparse matrices still fits.
"""

from __future__ import annotations

import math
from typing import Any, TypeVar

import msgpack
from pydantic import ValidationError

from .arrays import NON_FINITE_ERROR
from .base import INVALID_ERROR
from .errors import ErrorKind, WireError
from .messages import Message

#: Largest encoded message, bytes.
MAX_MESSAGE_BYTES = 64 * 1024

_UNPACK_LIMITS: dict[str, Any] = {
    "raw": False,
    "strict_map_key": True,
    "use_list": True,
    "max_str_len": 16 * 1024,
    "max_bin_len": 0,
    "max_ext_len": 0,
    "max_array_len": 16 * 1024,
    "max_map_len": 1024,
}

M = TypeVar("M", bound=Message)


def encode(msg: Message) -> bytes:
    """Serialize a wire message to msgpack bytes (at most 64 KiB, else WireError)."""
    if not isinstance(msg, Message):
        raise WireError(f"encode: expected a wire message, got {type(msg).__name__}")
    try:
        obj = msg.model_dump()
        data = msgpack.packb(obj, use_bin_type=True)
        if len(data) > MAX_MESSAGE_BYTES:
            data = msgpack.packb(_compact(obj), use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:  # e.g. a model_construct'ed message
        raise WireError(f"{type(msg).__name__}: cannot encode ({type(exc).__name__}: {exc})") \
            from None
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"{type(msg).__name__}: encoded message is {len(data)} bytes, "
                        f"more than the {MAX_MESSAGE_BYTES}-byte limit")
    return data


def decode(data: bytes | bytearray | memoryview, msg_type: type[M]) -> M:
    """Parse and validate one message of type ``msg_type``; raise WireError on any bad input.

    ``msg_type`` must be one of the message classes (TypeError otherwise: a programming
    error, not bad data).
    """
    if not (isinstance(msg_type, type) and issubclass(msg_type, Message)):
        raise TypeError(f"decode: msg_type must be a wire message class, got {msg_type!r}")
    name = msg_type.__name__
    obj = unpack_map(data, name)
    try:
        return msg_type.model_validate(obj)
    except ValidationError as exc:
        raise WireError(validation_reason(name, exc), error_kind(exc), _readable_seq(obj)) \
            from None
    except RecursionError:  # defensive: validators do not recurse into input
        raise WireError(f"{name}: input nested too deep") from None
    except Exception as exc:  # defensive: the contract is "only WireError comes out"
        raise WireError(f"{name}: invalid ({type(exc).__name__}: {exc})") from None


def _checked_size(data: object, name: str) -> int:
    """The byte size of a message named ``name`` (WireError: not bytes, or over the limit)."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise WireError(f"{name}: expected bytes, got {type(data).__name__}")
    size = len(data) if not isinstance(data, memoryview) else data.nbytes
    if size > MAX_MESSAGE_BYTES:
        raise WireError(f"{name}: message is {size} bytes, more than the "
                        f"{MAX_MESSAGE_BYTES}-byte limit")
    return size


def unpack_map(data: bytes | bytearray | memoryview, name: str) -> dict[str, Any]:
    """The msgpack map of a message named ``name``, unpacked with the codec's limits but not
    validated (WireError if it is no such map): :func:`decode`'s first half, for a reader
    that needs a field or two now and validates the whole message later, if ever."""
    _checked_size(data, name)
    try:
        obj = msgpack.unpackb(data, **_UNPACK_LIMITS)
    except msgpack.ExtraData:
        raise WireError(f"{name}: trailing bytes after the message") from None
    except msgpack.StackError:
        raise WireError(f"{name}: msgpack nesting too deep") from None
    except Exception as exc:  # ValueError, FormatError, TypeError...: any unpack failure
        raise WireError(f"{name}: not valid msgpack ({str(exc) or type(exc).__name__})") from None
    if type(obj) is not dict:
        raise WireError(f"{name}: expected a msgpack map, got {_kind(obj)}")
    return obj


def unpack_fields(data: bytes | bytearray | memoryview, name: str,
                  wanted: frozenset[str]) -> dict[str, Any]:
    """The fields named in ``wanted`` of the msgpack map of a message named ``name``, the
    others skipped without building them (WireError if it is no such map): a reader that
    needs a few small fields of a large message now (a replica's step and term) and
    validates the whole of it later, if ever. What is read has :func:`unpack_map`'s limits;
    what is skipped is only checked to be well-formed msgpack (its content, e.g. a bin value
    :func:`unpack_map` refuses, is judged when the whole message is decoded)."""
    size = _checked_size(data, name)
    head = bytes(data[:1])
    if not head or not (0x80 <= head[0] <= 0x8F or head[0] in (0xDE, 0xDF)):
        raise WireError(f"{name}: expected a msgpack map"
                        + (" (empty message)" if not head else ""))
    u = msgpack.Unpacker(max_buffer_size=max(size, 1), **_UNPACK_LIMITS)
    out: dict[str, Any] = {}
    try:
        u.feed(data)
        n = u.read_map_header()
        if n > _UNPACK_LIMITS["max_map_len"]:
            raise WireError(f"{name}: map of {n} entries, more than "
                            f"{_UNPACK_LIMITS['max_map_len']}")
        for _ in range(n):
            key = u.unpack()
            if type(key) is str and key in wanted:
                out[key] = u.unpack()
            else:
                u.skip()
        trailing = u.tell() != size
    except WireError:
        raise
    except msgpack.StackError:
        raise WireError(f"{name}: msgpack nesting too deep") from None
    except Exception as exc:  # OutOfData, FormatError, ValueError...: any unpack failure
        raise WireError(f"{name}: not valid msgpack ({str(exc) or type(exc).__name__})") from None
    if trailing:
        raise WireError(f"{name}: trailing bytes after the message")
    return out


def validation_reason(type_name: str, exc: ValidationError) -> str:
    """First error of a pydantic ValidationError as ``"<Type>.<path>: <message>"``.

    The path is the error's location plus, for a rule checked across a model's fields
    (:func:`pd_service.wire.base.invalid`), the field it names below that location.
    """
    errors = exc.errors(include_url=False, include_context=True, include_input=False)
    if not errors:  # pragma: no cover - pydantic always reports at least one
        return f"{type_name}: invalid"
    first = errors[0]
    parts = [str(p) for p in first["loc"]]
    msg = first["msg"]
    field = (first.get("ctx") or {}).get("field") if first["type"] == INVALID_ERROR else None
    if field:
        parts.append(str(field))
        msg = msg.removeprefix(f"{field}: ")
    path = ".".join(parts)
    where = f"{type_name}.{path}" if path else type_name
    more = f" (and {len(errors) - 1} more error{'s' if len(errors) > 2 else ''})" \
        if len(errors) > 1 else ""
    return f"{where}: {msg}{more}"


#: pydantic error types that mean "a value is NaN or infinite".
_NON_FINITE_TYPES = frozenset({"finite_number", NON_FINITE_ERROR})


def error_kind(exc: ValidationError) -> ErrorKind:
    """``non_finite`` if any error is a NaN / infinity, else ``malformed`` (by error type)."""
    types = {e["type"] for e in exc.errors(include_url=False, include_context=False,
                                           include_input=False)}
    return "non_finite" if types & _NON_FINITE_TYPES else "malformed"


def _readable_seq(obj: dict[Any, Any]) -> int | None:
    """The message's ``seq`` if it is a valid one on its own (an int in [0, 2^63))."""
    seq = obj.get("seq")
    return seq if type(seq) is int and 0 <= seq < 2**63 else None


def _kind(obj: object) -> str:
    names: dict[type, str] = {list: "array", str: "string"}
    return "nil" if obj is None else names.get(type(obj), type(obj).__name__)


def _compact(obj: Any) -> Any:
    """Copy of a dumped message with integral array values as ints (exact; keeps -0.0)."""
    if isinstance(obj, dict):
        if obj.keys() == {"shape", "data"} and isinstance(obj["data"], list):
            return {"shape": obj["shape"], "data": [_as_int(x) for x in obj["data"]]}
        return {k: _compact(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_compact(v) for v in obj]
    return obj


def _as_int(x: float) -> float | int:
    if x.is_integer() and abs(x) < 2.0**53 and (x != 0.0 or math.copysign(1.0, x) > 0):
        return int(x)
    return x
