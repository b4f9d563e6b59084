# ruff: noqa: E501  (the rule table reads best one rule per line)
"""One test per validation rule, checking the reason a person reads.

Most cases go through the wire (msgpack bytes -> decode) so they also check the path in
the reason ("<Type>.<field>: ..."). Python construction raises pydantic's ValidationError
(a ValueError) for the same rules.
"""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from pd_service.wire import (
    MAX_MESSAGE_BYTES,
    PSD_RTOL,
    Command,
    ErrorReport,
    LinearModelSpec,
    Measurement,
    Prediction,
    SensorSpec,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
    WireError,
    decode,
    encode,
    psd_problem,
)
from tests.wire.factories import DELETE, EXAMPLES, paper_spec, set_field


def raw(msg_type) -> dict:
    return msgpack.unpackb(encode(EXAMPLES[msg_type]()))


def reason(msg_type, obj: dict) -> str:
    with pytest.raises(WireError) as info:
        decode(msgpack.packb(obj, use_bin_type=True), msg_type)
    return info.value.reason


def arr(*shape_then_data):
    *shape, data = shape_then_data
    return {"shape": list(shape), "data": list(data)}


def sym(n: int, scale: float = 1.0) -> dict:
    return arr(n, n, (scale * np.eye(n)).ravel().tolist())


M, C, S, P = Measurement, Command, SessionSpec, Prediction

CASES = [
    # (type, path, value, expected text in the reason)
    # -- generic: unknown / missing fields, schema version, strict types, int ranges
    (M, "color", 1, "Measurement.color: Extra inputs are not permitted"),
    (M, "z", DELETE, "Measurement.z: Field required"),
    (M, "v", 2, "Measurement.v: Input should be 1"),
    (M, "v", True, "Measurement.v: Input should be 1"),
    (M, "v", 1.0, "Measurement.v: Input should be 1"),
    (M, b"", 1, "Measurement.b'': Keys should be strings"),
    (M, "seq", 1.0, "Measurement.seq: Input should be a valid integer"),
    (M, "seq", True, "Measurement.seq: Input should be a valid integer"),
    (M, "seq", "1", "Measurement.seq: Input should be a valid integer"),
    (M, "seq", -1, "Measurement.seq: Input should be greater than or equal to 0"),
    (M, "step", -3, "Measurement.step: Input should be greater than or equal to 0"),
    (M, "seq", 2**63, "Measurement.seq: Input should be less than or equal to 9223372036854775807"),
    # -- names
    (M, "session", "S1", "Measurement.session: String should match pattern '^[a-z0-9][a-z0-9_-]{0,63}$'"),
    (M, "session", "", "Measurement.session: String should match pattern"),
    (M, "session", "@service", "Measurement.session: String should match pattern"),
    (M, "session", "a/b", "Measurement.session: String should match pattern"),
    (M, "session", "a" * 65, "Measurement.session: String should match pattern"),
    (M, "sensor", "-camera", "Measurement.sensor: String should match pattern"),
    (M, "session", 5, "Measurement.session: Input should be a valid string"),
    # -- exactly one stamp
    (M, "t_ns", 5, "Measurement.step: exactly one of step / t_ns must be given, got both"),
    (M, "step", None, "Measurement.step: exactly one of step / t_ns must be given, got neither"),
    (C, "issued_ns", 5, "Command.step: exactly one of step / issued_ns must be given, got both"),
    (C, "step", None, "Command.step: exactly one of step / issued_ns must be given, got neither"),
    # -- arrays
    (M, "z", [0.5, 1.5], "Measurement.z: expected an array: a map with 'shape' and 'data' (or a numpy array in Python), got list"),
    (M, "z", None, "Measurement.z: expected an array"),
    (M, "z", {"shape": [2], "data": [1.0, 2.0], "dtype": "f8"}, "Measurement.z: an array is a map with exactly the keys 'shape' and 'data'"),
    (M, "z", {"shape": [2]}, "Measurement.z: an array is a map with exactly the keys 'shape' and 'data'"),
    (M, "z", {"shape": [2.0], "data": [1.0, 2.0]}, "Measurement.z: array 'shape' must be a list of integers"),
    (M, "z", {"shape": 2, "data": [1.0, 2.0]}, "Measurement.z: array 'shape' must be a list of integers"),
    (M, "z", {"shape": [True], "data": [1.0]}, "Measurement.z: array 'shape' must be a list of integers"),
    (M, "z", arr(1, 2, [1.0, 2.0]), "Measurement.z: expected a vector (shape with 1 entry), got shape [1, 2]"),
    (M, "R", arr(4, [1.0] * 4), "Measurement.R: expected a matrix (shape with 2 entries), got shape [4]"),
    (M, "z", arr(0, []), "Measurement.z: every array dimension must be between 1 and 64, got shape [0]"),
    (M, "z", arr(65, [0.0] * 65), "Measurement.z: every array dimension must be between 1 and 64, got shape [65]"),
    (M, "z", arr(2, [1.0, 2.0, 3.0]), "Measurement.z: array 'data' has 3 values but shape [2] needs 2"),
    (M, "z", {"shape": [1], "data": 1.0}, "Measurement.z: array 'data' must be a flat list of numbers, got float"),
    (M, "z", arr(2, [1.0, "2"]), "Measurement.z: array 'data' must hold only numbers, found str"),
    (M, "z", arr(2, [1.0, True]), "Measurement.z: array 'data' must hold only numbers, found bool"),
    (M, "z", arr(2, [1.0, None]), "Measurement.z: array 'data' must hold only numbers, found nil"),
    (M, "z", arr(2, [1.0, [2.0]]), "Measurement.z: array 'data' must hold only numbers, found list"),
    (M, "z", arr(2, [1.0, float("nan")]), "Measurement.z: array 'data' must hold finite numbers only"),
    (M, "z", arr(2, [float("-inf"), 1.0]), "Measurement.z: array 'data' must hold finite numbers only"),
    # -- per-sample R
    (M, "R", arr(2, 3, [1.0] * 6), "Measurement.R: must be 2x2 (z has 2 values), got shape [2, 3]"),
    (M, "R", arr(3, 3, np.eye(3).ravel()), "Measurement.R: must be 2x2 (z has 2 values), got shape [3, 3]"),
    (M, "R", arr(2, 2, [1.0, 0.5, 0.4, 1.0]), "Measurement.R: must be symmetric (max |M - M^T| = 0.1 > tolerance 1e-09)"),
    (M, "R", arr(2, 2, [1.0, 0.0, 0.0, -1.0]), "Measurement.R: must be positive semi-definite (min eigenvalue -1 < -tolerance -1e-09)"),
    # -- prediction
    (P, "P", sym(3), "Prediction.P: must be 4x4 (x has 4 values), got shape [3, 3]"),
    (P, "P", arr(4, 4, -np.eye(4).ravel()), "Prediction.P: must be positive semi-definite"),
    (P, "counters", {"accepted": 1.5}, "Prediction.counters.accepted: Input should be a valid integer"),
    (P, "counters", {"": 1}, "Prediction.counters..[key]: String should have at least 1 character"),
    (P, "newest_step", -1, "Prediction.newest_step: Input should be greater than or equal to 0"),
    # -- session spec: the model
    (S, "model.A", arr(4, 3, [0.0] * 12), "SessionSpec.model.linear.A: must be square (n x n), got shape [4, 3]"),
    (S, "model.B", arr(3, 1, [0.0] * 3), "SessionSpec.model.linear.B: must have n=4 rows (A is 4x4), got shape [3, 1]"),
    (S, "model.Q", sym(3), "SessionSpec.model.linear.Q: must be 4x4 (A is 4x4), got shape [3, 3]"),
    (S, "model.Q", arr(4, 4, (-np.eye(4)).ravel()), "SessionSpec.model.linear.Q: must be positive semi-definite"),
    (S, "model.A", arr(65, 65, [0.0] * 65 * 65), "SessionSpec.model.linear.A: every array dimension must be between 1 and 64, got shape [65, 65]"),
    (S, "model.kind", "nonlinear", "SessionSpec.model: model must be a map whose 'kind' is one of: linear, unscented, imm"),
    (S, "model.kind", 3, "SessionSpec.model: model must be a map whose 'kind' is one of: linear, unscented, imm"),
    (S, "model", [1.0], "SessionSpec.model: model must be a map whose 'kind' is one of: linear, unscented, imm"),
    (S, "model.extra", 1, "SessionSpec.model.linear.extra: Extra inputs are not permitted"),
    # -- session spec: prior, sensors, timing
    (S, "x0", arr(3, [0.0] * 3), "SessionSpec.x0: must have n=4 values (model.A is 4x4), got 3"),
    (S, "P0", sym(3), "SessionSpec.P0: must be 4x4 (model.A is 4x4), got shape [3, 3]"),
    (S, "P0", arr(4, 4, (np.eye(4) + np.triu(np.ones((4, 4)), 1)).ravel()), "SessionSpec.P0: must be symmetric"),
    (S, "P0", arr(2, 2, [1.0, 2.0, 2.0, 1.0]), "SessionSpec.P0: must be 4x4"),
    (S, "sensors.0.H", arr(2, 3, [0.0] * 6), "SessionSpec.sensors.0.H: must have n=4 columns ('camera'), got shape [2, 3]"),
    (S, "sensors.1.R", sym(2), "SessionSpec.sensors.1.R: must be 1x1 (H has 1 rows), got shape [2, 2]"),
    (S, "sensors.1.R", arr(1, 1, [-0.01]), "SessionSpec.sensors.1.R: must be positive semi-definite"),
    (S, "sensors.1.name", "camera", "SessionSpec.sensors.1.name: 'camera' is used twice; names must be unique"),
    (S, "sensors.1.name", "Ranger", "SessionSpec.sensors.1.name: String should match pattern"),
    (S, "sensors", [], "SessionSpec.sensors: List should have at least 1 item after validation, not 0"),
    (S, "sensors.0.delay", -1, "SessionSpec.sensors.0.delay: Input should be greater than or equal to 0"),
    (S, "sensors.0.delay", 13, "SessionSpec.sensors.0.delay: 13 ('camera') exceeds max_delay=12: every sample would be late"),
    (S, "sensors.0.interval", 0, "SessionSpec.sensors.0.interval: Input should be greater than or equal to 1"),
    (S, "lead", -1, "SessionSpec.lead: Input should be greater than or equal to 0"),
    (S, "lead", 10_001, "SessionSpec.lead: Input should be less than or equal to 10000"),
    (S, "max_delay", 1001, "SessionSpec.max_delay: Input should be less than or equal to 1000"),
    (S, "publish_every", 0, "SessionSpec.publish_every: Input should be greater than or equal to 1"),
    (S, "command_hold", "keep", "SessionSpec.command_hold: Input should be 'hold' or 'zero'"),
    (S, "period_ns", 0, "SessionSpec.period_ns: Input should be greater than or equal to 1"),
    (S, "epoch_ns", -(2**63) - 1, "not valid msgpack"),  # msgpack itself has no such int
    # -- status and error messages
    (SessionStatus, "state", "paused", "SessionStatus.state: Input should be 'active', 'restored', 'expired' or 'removed'"),
    (SessionStatus, "latency_p99_us", -1.0, "SessionStatus.latency_p99_us: Input should be greater than or equal to 0"),
    (SessionStatus, "latency_p50_us", float("nan"), "SessionStatus.latency_p50_us: Input should be a finite number"),
    (SessionStatus, "published", True, "SessionStatus.published: Input should be a valid integer"),
    (ServiceStatus, "sessions.1", "Bad", "ServiceStatus.sessions.1: String should match pattern"),
    (ServiceStatus, "uptime_s", float("inf"), "ServiceStatus.uptime_s: Input should be a finite number"),
    (ServiceStatus, "shard", "x" * 65, "ServiceStatus.shard: String should have at most 64 characters"),
    (ErrorReport, "reason", "x" * 1025, "ErrorReport.reason: String should have at most 1024 characters"),
    (ErrorReport, "key", "k" * 513, "ErrorReport.key: String should have at most 512 characters"),
    # -- a session's lifetime: 0 (never) .. 1e9 s, finite
    (S, "expire_s", -1.0, "SessionSpec.expire_s: Input should be greater than or equal to 0"),
    (S, "expire_s", float("inf"), "SessionSpec.expire_s: Input should be a finite number"),
    (S, "expire_s", "never", "SessionSpec.expire_s: Input should be a valid number"),
]


@pytest.mark.parametrize(
    "msg_type, path, value, expected", CASES,
    ids=[f"{c[0].__name__}.{c[1]!s}={str(c[2])[:20]}" for c in CASES])
def test_rule(msg_type, path, value, expected):
    if msg_type is S and path == "epoch_ns":  # msgpack cannot even pack it
        with pytest.raises(OverflowError):
            msgpack.packb({"epoch_ns": value})
        return
    got = reason(msg_type, set_field(raw(msg_type), path, value))
    assert expected in got, got


def test_sensors_at_most_16():
    obj = raw(S)
    one = obj["sensors"][1]
    obj["sensors"] = [dict(one, name=f"r{i}") for i in range(17)]
    assert "SessionSpec.sensors: List should have at most 16 items after validation, not 17" \
        in reason(S, obj)
    obj["sensors"] = obj["sensors"][:16]
    assert len(decode(msgpack.packb(obj), S).sensors) == 16


def test_model_kind_defaults_to_linear():
    obj = raw(S)
    del obj["model"]["kind"]
    spec = decode(msgpack.packb(obj), S)
    assert spec.model.kind == "linear" and spec == paper_spec()


def test_defaults():
    spec = paper_spec()
    assert spec.publish_every == 1 and spec.command_hold == "hold" and spec.v == 1


def test_not_a_map():
    assert reason_bytes(Measurement, msgpack.packb([1, 2])) == \
        "Measurement: expected a msgpack map, got array"
    assert reason_bytes(Measurement, msgpack.packb(None)) == \
        "Measurement: expected a msgpack map, got nil"


def reason_bytes(msg_type, data: bytes) -> str:
    with pytest.raises(WireError) as info:
        decode(data, msg_type)
    return info.value.reason


def test_msgpack_level_refusals():
    good = encode(EXAMPLES[Measurement]())
    assert reason_bytes(M, good + b"\x00") == "Measurement: trailing bytes after the message"
    assert reason_bytes(M, b"\x91" * 1025 + b"\xc0") == "Measurement: msgpack nesting too deep"
    assert "not valid msgpack (Unpack failed: incomplete input)" in reason_bytes(M, good[:-1])
    assert "exceeds max_array_len" in reason_bytes(M, b"\xdd\xff\xff\xff\xff")
    assert "exceeds max_bin_len" in reason_bytes(M, msgpack.packb({"z": b"abc"}, use_bin_type=True))
    assert "exceeds max_ext_len" in reason_bytes(M, msgpack.packb({"z": msgpack.ExtType(1, b"x")}))
    assert "not allowed for map key" in reason_bytes(M, msgpack.packb({1: 2}))


def test_decode_size_limit():
    big = b"\xc0" * (MAX_MESSAGE_BYTES + 1)
    assert reason_bytes(M, big) == "Measurement: message is 65537 bytes, more than the 65536-byte limit"


def test_deep_nesting_inside_a_field():
    obj = raw(M)
    obj["z"] = "__DEEP__"
    data = msgpack.packb(obj).replace(msgpack.packb("__DEEP__"), b"\x91" * 1000 + b"\xc0")
    assert reason_bytes(M, data).startswith("Measurement.z: expected an array")


def test_encode_size_limit():
    # 16 sensors with dense 64x64 H: far over 64 KiB even in compact form
    rng = np.random.default_rng(0)
    n = 64
    sensors = [SensorSpec(name=f"s{i}", H=rng.normal(size=(n, n)), R=np.eye(n), delay=0,
                          interval=1) for i in range(16)]
    spec = SessionSpec(session="big", period_ns=1, epoch_ns=0,
                       model=LinearModelSpec(A=np.eye(n), B=np.ones((n, 1)), Q=np.eye(n)),
                       x0=np.zeros(n), P0=np.eye(n), sensors=sensors, lead=0, max_delay=0)
    with pytest.raises(WireError, match=r"SessionSpec: encoded message is \d+ bytes, more than "
                                        r"the 65536-byte limit"):
        encode(spec)


def test_large_sparse_spec_fits_in_compact_form():
    n = 64
    A = np.eye(n)
    A[0, 1] = 0.05
    spec = SessionSpec(session="big", period_ns=1, epoch_ns=0,
                       model=LinearModelSpec(A=A, B=np.eye(n, 2), Q=1e-3 * np.eye(n)),
                       x0=np.zeros(n), P0=-0.0 + np.eye(n),
                       sensors=[SensorSpec(name="all", H=np.eye(n), R=np.eye(n), delay=0,
                                           interval=1)],
                       lead=0, max_delay=0)
    # plain form: 5 matrices of 4096 float64 = 184 KB; compact form writes 0 and 1 as ints
    data = encode(spec)
    assert len(data) <= MAX_MESSAGE_BYTES
    assert decode(data, SessionSpec) == spec


def test_compact_form_keeps_negative_zero():
    from pd_service.wire.codec import _as_int

    assert type(_as_int(-0.0)) is float and type(_as_int(0.0)) is int
    assert type(_as_int(2.0**53)) is float and _as_int(-3.0) == -3


# -- covariance tolerance ---------------------------------------------------------------

def _embed(m2: np.ndarray, size: int) -> np.ndarray:
    """m2 (2x2) in the top-left corner of a size x size matrix with m2[0, 0] elsewhere on
    the diagonal: same scale, same smallest eigenvalue, exercises the n <= 2 closed form
    (size 2) and the numpy path (size 3)."""
    out = m2[0, 0] * np.eye(size)
    out[:2, :2] = m2
    return out


@pytest.mark.parametrize("size", [2, 3])
@pytest.mark.parametrize("scale", [1.0, 1e-3, 1e6])
def test_psd_tolerance_is_relative_to_max_entry(scale, size):
    s = max(1.0, scale)
    base = scale * np.eye(2)
    inside = base + np.array([[0.0, 0.5], [0.0, 0.0]]) * PSD_RTOL * s
    outside = base + np.array([[0.0, 2.0], [0.0, 0.0]]) * PSD_RTOL * s
    assert psd_problem(_embed(inside, size)) is None
    assert psd_problem(_embed(outside, size)).startswith("must be symmetric")
    near = np.diag([scale, -0.5 * PSD_RTOL * s])
    neg = np.diag([scale, -2.0 * PSD_RTOL * s])
    assert psd_problem(_embed(near, size)) is None
    assert psd_problem(_embed(neg, size)).startswith("must be positive semi-definite")


def test_psd_tolerance_1x1():
    assert psd_problem(np.array([[-0.5 * PSD_RTOL]])) is None
    assert psd_problem(np.array([[-2.0 * PSD_RTOL]])).startswith("must be positive semi-definite")
    assert psd_problem(np.array([[0.0]])) is None


@pytest.mark.parametrize("size", [1, 2, 3])
def test_psd_check_survives_huge_entries(size):
    big = np.diag([1e308] * size)
    assert psd_problem(big) is None
    ones = np.ones((size, size))
    assert psd_problem(1e308 * ones) is None  # rank 1
    assert psd_problem(-1e308 * np.eye(size)).startswith("must be positive semi-definite")
    assert psd_problem(np.zeros((size, size))) is None
    if size > 1:
        flip = 1e308 * np.eye(size)
        flip[0, 1] = -1e308
        assert psd_problem(flip).startswith("must be symmetric")


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6), min_size=4, max_size=4), st.booleans())
def test_psd_closed_form_agrees_with_numpy(v, symmetrize):
    from pd_service.wire.arrays import _psd_problem_numpy, _psd_problem_small

    m = np.array(v).reshape(2, 2)
    if symmetrize:
        m = 0.5 * (m + m.T)
    s = max(1.0, float(np.abs(m).max()))
    min_eig = float(np.linalg.eigvalsh(0.5 * (m + m.T))[0])
    assume(abs(min_eig + PSD_RTOL * s) > 1e-12 * s)  # not on the tolerance boundary
    assume(abs(abs(m[0, 1] - m[1, 0]) - PSD_RTOL * s) > 1e-12 * s)
    small, numpy = _psd_problem_small(m.ravel().tolist()), _psd_problem_numpy(m)
    assert (small is None) == (numpy is None)
    if small is not None:
        assert small.split(" (")[0] == numpy.split(" (")[0]


# -- Python construction ----------------------------------------------------------------

def test_python_construction_rules():
    good = dict(session="s1", sensor="camera", seq=0, step=0)
    with pytest.raises(ValidationError, match="expected a real numeric array, got dtype complex128"):
        Measurement(**good, z=np.array([1j]))
    with pytest.raises(ValidationError, match="expected a real numeric array, got dtype bool"):
        Measurement(**good, z=np.array([True]))
    with pytest.raises(ValidationError, match="finite numbers only"):
        Measurement(**good, z=np.array([np.nan]))
    with pytest.raises(ValidationError, match="got list"):
        Measurement(**good, z=[1.0])
    # integer arrays become float64; the caller's array is copied, the stored one read-only
    src = np.array([1, 2])
    m = Measurement(**good, z=src)
    src[0] = 99
    assert m.z.dtype == np.float64 and m.z.tolist() == [1.0, 2.0] and not m.z.flags.writeable
    with pytest.raises(ValueError):
        m.z[0] = 5.0
    with pytest.raises(ValidationError, match="frozen"):
        m.seq = 3  # type: ignore[misc]
    assert isinstance(ValidationError, type) and issubclass(ValidationError, ValueError)


def test_int_beyond_float64_in_python_wire_form():
    # msgpack cannot carry such an int, but a Python caller can pass the wire form
    with pytest.raises(ValidationError, match="holds a value that is not a finite float64"):
        Measurement(session="s1", sensor="c", seq=0, step=0,
                    z={"shape": [2], "data": [1.0, 2**1100]})


def test_messages_compare_by_value():
    a, b = EXAMPLES[Prediction](), EXAMPLES[Prediction]()
    assert a == b and hash(a) == hash(b) and a is not b
    c = EXAMPLES[Prediction](seq=12)
    assert a != c
    assert a != EXAMPLES[Command]()
    assert Command(session="s1", seq=0, step=0, u=np.array([-0.0])) == \
        Command(session="s1", seq=0, step=0, u=np.array([0.0]))


def test_sensor_lookup_follows_model_copy():
    spec = paper_spec()
    assert spec.sensor("camera").m == 2 and spec.sensor("lidar") is None
    other = spec.model_copy(update={"sensors": spec.sensors[1:]})
    assert other.sensor("camera") is None and other.sensor("ranger").m == 1
    assert spec.sensor("camera") is not None


#: Reasons about the whole message, not one field (each message type): no field path.
_WHOLE_MESSAGE = ("not valid msgpack", "expected a msgpack map", "trailing bytes", "nesting",
                  "message is", "expected bytes")


def _field_path(reason: str) -> str:
    head = reason.split(": ", 1)[0]
    assert "." in head, f"no field path in {reason!r}"
    return head.split(".", 1)[1]


@pytest.mark.parametrize(
    "msg_type, path, value, expected", CASES,
    ids=[f"{c[0].__name__}.{c[1]!s}={str(c[2])[:20]}" for c in CASES])
def test_every_rule_names_the_field_it_refuses(msg_type, path, value, expected):
    """Model-level checks too: the reason's path is the field the case broke, a field
    inside it, or the one it must agree with (e.g. exactly one of step / t_ns)."""
    if msg_type is S and path == "epoch_ns" or isinstance(path, bytes):
        return
    got = reason(msg_type, set_field(raw(msg_type), path, value))
    field = _field_path(got)
    keys = path.split(".")
    # a discriminated model's path holds its kind: SessionSpec.model.linear.A for model.A
    field_keys = [k for k in field.split(".") if k not in ("linear", "unscented", "imm")]
    partner = {"t_ns": "step", "issued_ns": "step", "x0": "P0", "model.A": "x0"}
    assert field_keys[:len(keys)] == keys or keys[:len(field_keys)] == field_keys \
        or field == partner.get(path), (path, got)


@pytest.mark.parametrize("obj, field", [
    # a per-sample R that is not PSD is a field error of R, not of the Measurement
    (lambda: set_field(raw(M), "R", arr(2, 2, [1.0, 0.0, 0.0, -1.0])), "R"),
    (lambda: set_field(raw(M), "R", arr(2, 3, [1.0] * 6)), "R"),
    (lambda: set_field(set_field(raw(M), "step", None), "t_ns", None), "step"),
])
def test_model_level_checks_of_a_measurement_name_their_field(obj, field):
    assert reason(M, obj()).startswith(f"Measurement.{field}: ")


def test_python_construction_names_the_field_too():
    with pytest.raises(ValidationError, match="R: must be positive semi-definite"):
        Measurement(session="s", sensor="a", seq=0, step=1, z=np.zeros(2),
                    R=np.array([[1.0, 0.0], [0.0, -1.0]]))
