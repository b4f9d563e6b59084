"""Hot-path readers for the two messages the daemon receives most: Measurement and Command.

Each reader accepts only the plainest, unambiguous form of a message that fits its session
(exact Python types, no per-sample R, every value finite, dimensions right) and returns its
fields; for anything else it returns None and the caller takes the full path
(:func:`pd_service.wire.decode` + :func:`pd_service.wire.convert.check_measurement`), which
gives the exact refusal reason. So the fast path can only ever accept what the full path
accepts, with the same values (tested on mutated payloads), at about a third of the cost.

Where the hot path runs compiled, both readers run in the C kernel ``_fastread.c``, which
reads the msgpack bytes directly instead of building a dict first (~2,000 instructions per
message instead of ~20,000); the Python form below is its reference, and the tests run both
on the same payloads.
"""

from __future__ import annotations

from typing import Any, Final

import msgpack
import numpy as np

from pd_service.native import kernel, kernel_function
from pd_service.wire import MAX_MESSAGE_BYTES

#: The C form of both readers (None: the Python form runs).
_FAST: Final = kernel("pd_service.intake._fastread")
_READ_MEASUREMENT: Final = kernel_function("pd_service.intake._fastread", "read_measurement")
_READ_COMMAND: Final = kernel_function("pd_service.intake._fastread", "read_command")
_MAX_BYTES: Final = MAX_MESSAGE_BYTES  # read from a C static, not the module's globals

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
_MEAS_KEYS = frozenset({"v", "session", "sensor", "seq", "step", "t_ns", "z", "R"})
_CMD_KEYS = frozenset({"v", "session", "seq", "step", "issued_ns", "u"})


def _unpack(payload: bytes) -> dict | None:
    if len(payload) > MAX_MESSAGE_BYTES:
        return None
    # msgpack's defaults (raw=False, strict_map_key, lists; every length bounded by the
    # payload's, itself at most MAX_MESSAGE_BYTES), not the codec's tighter limits: passing
    # them costs ~0.25 µs of argument parsing per message, and whatever they would refuse
    # (bin or ext values, more keys, longer strings or arrays) the readers refuse anyway
    try:
        obj = msgpack.unpackb(payload)
    except Exception:
        return None
    return obj if type(obj) is dict else None


def _vector(value: Any, size: int, max_abs: float) -> np.ndarray | None:
    """``{"shape": [size], "data": [size floats/ints, each |v| <= max_abs]}`` -> float64
    array, else None. ``max_abs`` is finite: the one comparison also refuses NaN and
    infinities (every comparison with NaN is false) and ints beyond float64's range."""
    if type(value) is not dict or len(value) != 2:
        return None
    shape, data = value.get("shape"), value.get("data")
    if type(shape) is not list or len(shape) != 1 or type(shape[0]) is not int \
            or shape[0] != size or type(data) is not list or len(data) != size:
        return None
    lo = -max_abs
    for v in data:
        t = type(v)
        if t is not float and t is not int or not lo <= v <= max_abs:
            return None
    return np.array(data, dtype=np.float64)


def _stamp(obj: dict, a: str, b: str, lo_a: int) -> tuple[int | None, int | None] | None:
    """Exactly one of the integer fields a / b (a >= lo_a, b any int64)."""
    va, vb = obj.get(a), obj.get(b)
    if (va is None) == (vb is None):
        return None
    if va is not None:
        return (va, None) if type(va) is int and lo_a <= va <= _INT64_MAX else None
    return (None, vb) if type(vb) is int and _INT64_MIN <= vb <= _INT64_MAX else None


def _common(obj: dict, keys: frozenset[str], session: str) -> int | None:
    """Checks shared by both messages; returns seq or None."""
    if not obj.keys() <= keys:
        return None
    v = obj.get("v", 1)
    if type(v) is not int or v != 1:
        return None
    if type(obj.get("session")) is not str or obj["session"] != session:
        return None
    seq = obj.get("seq")
    if type(seq) is not int or not 0 <= seq <= _INT64_MAX:
        return None
    return seq


def read_measurement(payload: bytes, session: str, sensor: str, dims: dict[str, int],
                     max_abs: float) -> tuple[int, int | None, int | None, np.ndarray] | None:
    """(seq, step, t_ns, z) of a plain Measurement of ``sensor`` in ``session``, else None.

    ``dims`` maps the session's sensor names to their dimension m; every |z_i| is at most
    ``max_abs`` (finite), else None (the full path tells out_of_range from non-finite).
    """
    if _READ_MEASUREMENT is not None:
        m = dims.get(sensor)
        return None if m is None else _READ_MEASUREMENT(
            payload, session, sensor, m, max_abs, _MAX_BYTES)
    return read_measurement_py(payload, session, sensor, dims, max_abs)


def read_measurement_py(payload: bytes, session: str, sensor: str, dims: dict[str, int],
                        max_abs: float) -> tuple[int, int | None, int | None, np.ndarray] | None:
    """:func:`read_measurement`'s Python form: the reference of the C kernel."""
    obj = _unpack(payload)
    if obj is None:
        return None
    seq = _common(obj, _MEAS_KEYS, session)
    if seq is None or obj.get("R") is not None:
        return None
    name = obj.get("sensor")
    if type(name) is not str or name != sensor:
        return None
    m = dims.get(name)
    if m is None:
        return None
    st = _stamp(obj, "step", "t_ns", 0)
    if st is None:
        return None
    z = _vector(obj.get("z"), m, max_abs)
    if z is None:
        return None
    return seq, st[0], st[1], z


def read_command(payload: bytes, session: str, r: int, max_abs: float
                 ) -> tuple[int, int | None, int | None, np.ndarray] | None:
    """(seq, step, issued_ns, u) of a plain Command of ``session`` with r inputs, each
    |u_i| at most ``max_abs`` (finite), else None."""
    if _READ_COMMAND is not None:
        return _READ_COMMAND(payload, session, r, max_abs, _MAX_BYTES)
    return read_command_py(payload, session, r, max_abs)


def read_command_py(payload: bytes, session: str, r: int, max_abs: float
                    ) -> tuple[int, int | None, int | None, np.ndarray] | None:
    """:func:`read_command`'s Python form: the reference of the C kernel."""
    obj = _unpack(payload)
    if obj is None:
        return None
    seq = _common(obj, _CMD_KEYS, session)
    if seq is None:
        return None
    st = _stamp(obj, "step", "issued_ns", 0)
    if st is None:
        return None
    u = _vector(obj.get("u"), r, max_abs)
    if u is None:
        return None
    return seq, st[0], st[1], u
