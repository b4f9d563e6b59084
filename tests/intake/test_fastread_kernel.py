"""The intake's fast path, the C kernel pd_service/intake/_fastread.c, against the full path
(decode into the validated model, then the checks): the reference. Whatever the kernel
accepts, the full path accepts with the same values; plain messages, in every msgpack
encoding of their values, are taken by the kernel; anything else gives None (the full path
decides). Where the kernel is not in use (pure Python) every message takes the full path and
there is nothing to test here.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pd_service.intake import MAX_ABS_INPUT
from pd_service.native import kernel
from pd_service.wire import MAX_MESSAGE_BYTES, Command, Measurement, WireError, decode
from pd_service.wire.convert import (
    check_command,
    check_measurement,
    command_step,
    measurement_step,
)
from tests.service.helpers import paper_spec

_FAST = kernel("pd_service.intake._fastread")

pytestmark = pytest.mark.skipif(
    _FAST is None, reason="the C kernel is not in use here (PD_SERVICE_PURE=1, or no C "
                          "compiler at install time): every message takes the full path")

SPEC = paper_spec("s1", epoch_ns=1_000)
DIMS = {"camera": 2, "ranger": 1}

MEAS = {"v": 1, "session": "s1", "sensor": "camera", "seq": 3, "step": 7,
        "z": {"shape": [2], "data": [1.5, -2.0]}}
CMD = {"v": 1, "session": "s1", "seq": 4, "step": 12, "u": {"shape": [1], "data": [0.5]}}

# values that are wrong (or subtly different) for some field
ODD = [None, True, False, 1, 0, -1, 2**63, 2**63 - 1, -(2**63), -(2**63) - 1, 1.0, 0.5,
       math.nan, math.inf, "", "s1", "s2", "camera", "ranger", "lidar", [], [1], [2], [1, 2],
       {}, {"shape": [2], "data": [1.0, 2.0]}, {"shape": [1], "data": [1]},
       {"shape": [2], "data": [1.0, math.nan]}, {"shape": [2], "data": [1.0, True]},
       {"shape": [2], "data": [1.0, 10**400]}, {"shape": [2], "data": [1.0, 2**1023]},
       {"shape": [2], "data": [1.0, 1e13]}, {"shape": [2], "data": [-1e12, 10**12]},
       {"shape": [2], "data": [1.0, -(10**12) - 1]}, {"shape": [1], "data": [-math.inf]},
       {"shape": [2, 1], "data": [1.0, 2.0]}, {"shape": [2], "data": [1.0]},
       {"shape": [1, 1], "data": [0.25]}, {"shape": [2, 2], "data": [1.0, 0.0, 0.0, 1.0]},
       {"shape": [2], "data": [1.0, 2.0], "x": 1}, {"shape": [True], "data": [1.0]},
       # what only the codec's unpacker limits refuse (the readers use msgpack's defaults)
       b"s1", b"", msgpack.ExtType(5, b"ab"), {"shape": [2], "data": [b"\x00", 1.0]},
       {"shape": [2], "data": [1.0, msgpack.ExtType(1, b"")]}, "s" * 17_000,
       {"shape": [2], "data": [1.0] * 17_000}]
FIELDS = ["v", "session", "sensor", "seq", "step", "t_ns", "z", "R", "u", "issued_ns", "extra"]


def read_measurement(payload: bytes, session: str, sensor: str, dims: dict[str, int],
                     max_abs: float):
    """The kernel as the intake calls it."""
    m = dims.get(sensor)
    return None if m is None else _FAST.read_measurement(
        payload, session, sensor, m, max_abs, MAX_MESSAGE_BYTES)


def read_command(payload: bytes, session: str, r: int, max_abs: float):
    return _FAST.read_command(payload, session, r, max_abs, MAX_MESSAGE_BYTES)


def full_measurement(payload: bytes, sensor: str, max_abs: float = MAX_ABS_INPUT):
    try:
        msg = decode(payload, Measurement)
        if msg.sensor != sensor or msg.session != "s1":
            return None
        check_measurement(msg, SPEC)
    except WireError:
        return None
    if msg.R is not None:
        return "with R"
    if np.abs(msg.z).max(initial=0.0) > max_abs:  # the intake's out_of_range
        return None
    return msg.seq, measurement_step(msg, SPEC), msg.z


def full_command(payload: bytes, max_abs: float = MAX_ABS_INPUT):
    try:
        msg = decode(payload, Command)
        check_command(msg, SPEC, SPEC.model.r)
    except WireError:
        return None
    if np.abs(msg.u).max(initial=0.0) > max_abs:
        return None
    return msg.seq, command_step(msg, SPEC), msg.u


def fast_measurement(payload: bytes, sensor: str, max_abs: float = MAX_ABS_INPUT):
    got = read_measurement(payload, "s1", sensor, DIMS, max_abs)
    if got is None or (got[2] is not None and got[2] < SPEC.epoch_ns):
        return None
    seq, step, t_ns, z = got
    return seq, step if step is not None else SPEC.step_of(t_ns), z


def fast_command(payload: bytes, max_abs: float = MAX_ABS_INPUT):
    got = read_command(payload, "s1", 1, max_abs)
    if got is None:
        return None
    seq, step, issued, u = got
    j = step if step is not None else SPEC.step_of(issued) + SPEC.lead
    return None if j < 0 else (seq, j, u)


def mutated(base: dict, mutations) -> tuple[dict, bytes | None]:
    """``base`` with each (field, index into ODD or None: removed) applied, and its msgpack
    bytes (None if msgpack cannot pack it)."""
    d = dict(base)
    for name, idx in mutations:
        if idx is None:
            d.pop(name, None)
        else:
            d[name] = ODD[idx]
    try:
        return d, msgpack.packb(d)
    except (OverflowError, TypeError):
        return d, None


def same(a, b) -> bool:
    return a[0] == b[0] and a[1] == b[1] and np.array_equal(a[2], b[2]) \
        and a[2].dtype == b[2].dtype == np.float64


def test_plain_messages_take_the_fast_path():
    for sensor, z in (("camera", [1.5, -2.0]), ("ranger", [3]), ("camera", [0, -1e12]),
                      ("ranger", [10**12])):
        d = dict(MEAS, sensor=sensor, z={"shape": [len(z)], "data": z})
        data = msgpack.packb(d)
        assert same(fast_measurement(data, sensor), full_measurement(data, sensor))
    d = dict(MEAS)
    del d["step"], d["v"]
    d["t_ns"] = 1_000 + 3 * SPEC.period_ns + 5
    data = msgpack.packb(d)
    assert fast_measurement(data, "camera")[1] == 3
    assert same(fast_measurement(data, "camera"), full_measurement(data, "camera"))
    c = dict(CMD)
    del c["step"]
    c["issued_ns"] = 1_000 + 2 * SPEC.period_ns
    data = msgpack.packb(c)
    assert fast_command(data)[1] == 2 + SPEC.lead
    assert same(fast_command(data), full_command(data))


@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(FIELDS), st.sampled_from(range(len(ODD))) | st.none()),
                max_size=4),
       st.sampled_from(["camera", "ranger", "lidar"]))
def test_fast_path_never_accepts_what_the_full_path_refuses(mutations, key_sensor):
    for base, is_cmd in ((MEAS, False), (CMD, True)):
        d, data = mutated(base, mutations)
        if data is None:
            continue
        if is_cmd:
            fast, full = fast_command(data), full_command(data)
        else:
            fast, full = fast_measurement(data, key_sensor), full_measurement(data, key_sensor)
        if fast is not None:
            assert full is not None and full != "with R", (d, fast)
            assert same(fast, full), d


def test_garbage_goes_to_the_full_path():
    rng = np.random.default_rng(0)
    for n in range(0, 300, 7):
        data = rng.bytes(n)
        assert read_measurement(data, "s1", "camera", DIMS, MAX_ABS_INPUT) is None
        assert read_command(data, "s1", 1, MAX_ABS_INPUT) is None
    assert read_measurement(b"\x00" * 70_000, "s1", "camera", DIMS, MAX_ABS_INPUT) is None


def test_values_beyond_max_abs_take_the_full_path():
    """The bound is checked on the way in: a value beyond it, NaN or an infinity sends the
    message to the full path (which names the reason), an int or float on it does not."""
    for bad in (1e13, -(10**13), math.nan, math.inf, -math.inf, 10**400):
        d = dict(MEAS, z={"shape": [2], "data": [1.0, bad]})
        try:
            data = msgpack.packb(d)
        except OverflowError:
            continue
        assert read_measurement(data, "s1", "camera", DIMS, MAX_ABS_INPUT) is None, bad
        c = msgpack.packb(dict(CMD, u={"shape": [1], "data": [bad]}))
        assert read_command(c, "s1", 1, MAX_ABS_INPUT) is None, bad
    edge = msgpack.packb(dict(CMD, u={"shape": [1], "data": [-(10**12)]}))
    assert read_command(edge, "s1", 1, MAX_ABS_INPUT)[3].tolist() == [-1e12]
    assert read_command(edge, "s1", 1, 1e11) is None


def c_meas(payload: bytes, sensor: str = "camera", max_abs: float = MAX_ABS_INPUT):
    return read_measurement(payload, "s1", sensor, DIMS, max_abs)


def c_cmd(payload: bytes, max_abs: float = MAX_ABS_INPUT):
    return read_command(payload, "s1", 1, max_abs)


def check(payload: bytes, sensor: str = "camera", max_abs: float = MAX_ABS_INPUT) -> None:
    """What the kernel accepts (as the intake takes it), the full path accepts alike."""
    fast = fast_measurement(payload, sensor, max_abs)
    if fast is not None:
        full = full_measurement(payload, sensor, max_abs)
        assert full is not None and full != "with R" and same(fast, full), payload
    fast = fast_command(payload, max_abs)
    if fast is not None:
        full = full_command(payload, max_abs)
        assert full is not None and same(fast, full), payload


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
        if data is not None:
            check(data, sensor, max_abs)


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
    # at the limit: accepted by size (then refused for its extra key, as the full path)
    check(msgpack.packb(dict(MEAS, session="s1")) + b"")


def test_cautious_cases_give_none():
    """A repeated key and an int beyond 2^53 in a vector with a max_abs above it: None, the
    full path decides."""
    base = msgpack.packb(MEAS)
    dup = b"\x87" + base[1:] + b"\xa3seq\x05"
    assert c_meas(dup) is None
    shape_twice = msgpack.packb(dict(MEAS, z={"shape": [2], "data": [1.0, 2.0]}))
    shape_twice = shape_twice.replace(b"\xa4data", b"\xa5shape", 1)
    check(shape_twice)
    big = msgpack.packb(dict(MEAS, z={"shape": [2], "data": [1.0, 2**53 + 1]}))
    assert full_measurement(big, "camera", max_abs=1e300) is not None
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
