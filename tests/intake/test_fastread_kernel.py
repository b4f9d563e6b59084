"""The C readers (pd_service/intake/_fastread.c) against their Python form in fastpath.py.

The Python form is the reference: on every payload both must give the same result (None, or
the same seq, step, time and float64 array), except where the C form is documented to be
more cautious (a repeated key, an int beyond 2^53 in a vector): there it must give None, so
the full path decides.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pd_service.intake import MAX_ABS_INPUT
from pd_service.intake.fastpath import _FAST, read_command_py, read_measurement_py
from pd_service.wire import MAX_MESSAGE_BYTES
from tests.intake.test_fastpath import CMD, DIMS, FIELDS, MEAS, ODD, mutated

pytestmark = pytest.mark.skipif(
    _FAST is None, reason="the C kernel is not in use here (PD_SERVICE_PURE=1, or no C "
                          "compiler at install time): the Python form runs everywhere")


def c_meas(payload: bytes, sensor: str = "camera", max_abs: float = MAX_ABS_INPUT):
    m = DIMS.get(sensor)
    return None if m is None else _FAST.read_measurement(
        payload, "s1", sensor, m, max_abs, MAX_MESSAGE_BYTES)


def c_cmd(payload: bytes, max_abs: float = MAX_ABS_INPUT):
    return _FAST.read_command(payload, "s1", 1, max_abs, MAX_MESSAGE_BYTES)


def py_meas(payload: bytes, sensor: str = "camera", max_abs: float = MAX_ABS_INPUT):
    return read_measurement_py(payload, "s1", sensor, DIMS, max_abs)


def py_cmd(payload: bytes, max_abs: float = MAX_ABS_INPUT):
    return read_command_py(payload, "s1", 1, max_abs)


def agree(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return (a[:3] == b[:3] and type(a[1]) is type(b[1]) and type(a[2]) is type(b[2])
            and a[3].dtype == b[3].dtype == np.float64 and a[3].shape == b[3].shape
            and np.array_equal(a[3], b[3]))


def check(payload: bytes, sensor: str = "camera", max_abs: float = MAX_ABS_INPUT) -> None:
    assert agree(c_meas(payload, sensor, max_abs), py_meas(payload, sensor, max_abs)), payload
    assert agree(c_cmd(payload, max_abs), py_cmd(payload, max_abs)), payload


def test_plain_messages_are_read_alike():
    cases = [MEAS, CMD, dict(MEAS, sensor="ranger", z={"shape": [1], "data": [3]}),
             dict(MEAS, z={"shape": [2], "data": [0, -1e12]}),
             {k: v for k, v in MEAS.items() if k not in ("step", "v")} | {"t_ns": -5},
             {k: v for k, v in CMD.items() if k != "step"} | {"issued_ns": 2**63 - 1},
             dict(MEAS, step=None, t_ns=7), dict(CMD, issued_ns=None), dict(MEAS, R=None),
             dict(MEAS, seq=2**63 - 1, step=2**63 - 1)]
    for d in cases:
        data = msgpack.packb(d)
        for sensor in ("camera", "ranger"):
            check(data, sensor)
        assert c_meas(data, d.get("sensor", "camera")) is not None or c_cmd(data) is not None


def test_every_encoding_of_the_same_values_is_read_alike():
    """float32, every int width, map16/map32, str8/16/32 and array16/32 headers."""
    f32 = msgpack.packb(dict(MEAS, z={"shape": [2], "data": [1.5, 0.1]}), use_single_float=True)
    assert c_meas(f32)[3].tolist() == [1.5, float(np.float32(0.1))]
    check(f32)
    base = msgpack.packb(MEAS)
    assert base[0] == 0x86
    body = base[1:]
    for head in (b"\xde\x00\x06", b"\xdf\x00\x00\x00\x06"):
        check(head + body)
        assert c_meas(head + body) is not None
    # str8 / str16 / str32 for a key and the session, array16 / array32 for data
    for old, new in ((b"\xa7session", b"\xd9\x07session"), (b"\xa7session", b"\xda\x00\x07session"),
                     (b"\xa2s1", b"\xdb\x00\x00\x00\x02s1"), (b"\x92", b"\xdc\x00\x02"),
                     (b"\x92", b"\xdd\x00\x00\x00\x02")):
        data = base.replace(old, new, 1)
        assert data != base
        check(data)
        assert c_meas(data) is not None, new
    for seq in (0, 127, 128, 255, 256, 65535, 65536, 2**32, 2**63 - 1):
        for fmt in (b"\xcc", b"\xcd", b"\xce", b"\xcf", b"\xd0", b"\xd1", b"\xd2", b"\xd3"):
            width = {0xcc: 1, 0xcd: 2, 0xce: 4, 0xcf: 8, 0xd0: 1, 0xd1: 2, 0xd2: 4, 0xd3: 8}[fmt[0]]
            signed = fmt[0] >= 0xd0
            try:
                raw = seq.to_bytes(width, "big", signed=signed)
            except OverflowError:
                continue
            data = base.replace(b"\xa3seq\x03", b"\xa3seq" + fmt + raw, 1)
            check(data)
            assert c_meas(data)[0] == seq


@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(FIELDS), st.sampled_from(range(len(ODD))) | st.none()),
                max_size=4),
       st.sampled_from(["camera", "ranger", "lidar"]),
       st.sampled_from([MAX_ABS_INPUT, 1.0, 1e300]))
def test_mutated_messages_are_read_alike(mutations, sensor, max_abs):
    for base in (MEAS, CMD):
        d, data = mutated(base, mutations)
        if data is None:
            continue
        c, py = c_meas(data, sensor, max_abs), py_meas(data, sensor, max_abs)
        if max_abs > 2**53 and c is None and py is not None:  # an int beyond 2^53 in z
            assert any(type(v) is int and abs(v) > 2**53 for v in py[3].tolist() + [
                x for x in d["z"]["data"] if type(x) is int]), d
            continue
        assert agree(c, py), d
        c, py = c_cmd(data, max_abs), py_cmd(data, max_abs)
        if max_abs > 2**53 and c is None and py is not None:
            assert any(type(x) is int and abs(x) > 2**53 for x in d["u"]["data"]), d
            continue
        assert agree(c, py), d


def test_every_cut_and_every_flipped_byte_is_read_alike():
    for data in (msgpack.packb(MEAS), msgpack.packb(CMD),
                 msgpack.packb(dict(MEAS, z={"shape": [2], "data": [0.25, 7]}),
                               use_single_float=True)):
        for n in range(len(data) + 1):
            check(data[:n])
            check(data + data[:n])  # trailing bytes
        for i in range(len(data)):
            for b in (0x00, 0x01, 0x7f, 0x80, 0xa0, 0xc0, 0xc1, 0xc2, 0xc3, 0xc4, 0xca, 0xcb,
                      0xcf, 0xd3, 0xd9, 0xdc, 0xde, 0xe0, 0xff, data[i] ^ 0x01, data[i] ^ 0x20):
                check(data[:i] + bytes([b]) + data[i + 1:])


def test_random_bytes_and_oversize_payloads_are_none():
    rng = np.random.default_rng(3)
    for n in range(0, 400, 3):
        check(rng.bytes(n))
    big = msgpack.packb(dict(MEAS, extra="x" * MAX_MESSAGE_BYTES))
    assert c_meas(big) is None and c_cmd(big) is None
    # at the limit: accepted by size (then refused for its extra key, as the Python form)
    check(msgpack.packb(dict(MEAS, session="s1")) + b"")


def test_cautious_cases_give_none():
    """A repeated key (the Python form takes the last value) and an int beyond 2^53 in a
    vector with a max_abs above it: None, the full path decides."""
    base = msgpack.packb(MEAS)
    dup = b"\x87" + base[1:] + b"\xa3seq\x05"
    assert py_meas(dup) is not None and py_meas(dup)[0] == 5
    assert c_meas(dup) is None
    shape_twice = msgpack.packb(dict(MEAS, z={"shape": [2], "data": [1.0, 2.0]}))
    shape_twice = shape_twice.replace(b"\xa4data", b"\xa5shape", 1)
    check(shape_twice)
    big = msgpack.packb(dict(MEAS, z={"shape": [2], "data": [1.0, 2**53 + 1]}))
    assert py_meas(big, max_abs=1e300) is not None
    assert c_meas(big, max_abs=1e300) is None
    edge = msgpack.packb(dict(MEAS, z={"shape": [2], "data": [-(2**53), 2**53]}))
    check(edge, max_abs=1e300)
    assert c_meas(edge, max_abs=1e300)[3].tolist() == [-(2.0**53), 2.0**53]


def test_bad_arguments_raise_never_crash():
    data = msgpack.packb(MEAS)
    with pytest.raises(TypeError):
        _FAST.read_measurement(data, "s1", "camera", 2, 1.0)
    with pytest.raises(TypeError):
        _FAST.read_measurement(data, b"s1", "camera", 2, 1.0, 100)
    with pytest.raises(TypeError):
        _FAST.read_command(12, "s1", 1, 1.0, 100)
    with pytest.raises(ValueError):
        _FAST.read_command(data, "s1", -1, 1.0, 100)
    assert _FAST.read_measurement(bytearray(data), "s1", "camera", 2, 1e12, 100) is not None
    assert _FAST.read_measurement(memoryview(data), "s1", "camera", 2, math.inf, 100) is not None
