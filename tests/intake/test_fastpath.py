"""The hot-path readers accept only what the full decoder accepts, with the same values."""

from __future__ import annotations

import math

import msgpack
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pd_service.intake import MAX_ABS_INPUT
from pd_service.intake.fastpath import read_command, read_measurement
from pd_service.wire import Command, Measurement, WireError, decode
from pd_service.wire.convert import (
    check_command,
    check_measurement,
    command_step,
    measurement_step,
)
from tests.service.helpers import paper_spec

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


def full_measurement(payload: bytes, sensor: str):
    try:
        msg = decode(payload, Measurement)
        if msg.sensor != sensor or msg.session != "s1":
            return None
        check_measurement(msg, SPEC)
    except WireError:
        return None
    if msg.R is not None:
        return "with R"
    if np.abs(msg.z).max(initial=0.0) > MAX_ABS_INPUT:  # the intake's out_of_range
        return None
    return msg.seq, measurement_step(msg, SPEC), msg.z


def full_command(payload: bytes):
    try:
        msg = decode(payload, Command)
        check_command(msg, SPEC, SPEC.model.r)
    except WireError:
        return None
    if np.abs(msg.u).max(initial=0.0) > MAX_ABS_INPUT:
        return None
    return msg.seq, command_step(msg, SPEC), msg.u


def fast_measurement(payload: bytes, sensor: str):
    got = read_measurement(payload, "s1", sensor, DIMS, MAX_ABS_INPUT)
    if got is None or (got[2] is not None and got[2] < SPEC.epoch_ns):
        return None
    seq, step, t_ns, z = got
    return seq, step if step is not None else SPEC.step_of(t_ns), z


def fast_command(payload: bytes):
    got = read_command(payload, "s1", 1, MAX_ABS_INPUT)
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
