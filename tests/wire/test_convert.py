"""Wire <-> estimation conversion (pd_service.wire.convert)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from pd_service.backends import build
from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.checks import PSD_RTOL as ESTIMATION_PSD_RTOL
from pd_service.wire import PSD_RTOL, Prediction, SessionSpec, WireError, decode, encode, keys
from pd_service.wire.convert import (
    PredictionEncoder,
    check_command,
    check_key,
    check_measurement,
    command_step,
    command_time,
    measurement_step,
    measurement_time,
    prediction_from,
)
from tests.wire.factories import (
    PERIOD_NS,
    command,
    measurement,
    paper_continuous_spec,
    paper_spec,
)

EPOCH = 1_700_000_000_000_000_000


def test_same_tolerance_as_the_estimator():
    assert PSD_RTOL == ESTIMATION_PSD_RTOL


@pytest.mark.parametrize("hold", ["hold", "zero"])
def test_build_matches_direct_construction(hold):
    spec = paper_spec().model_copy(update={"command_hold": hold})
    op = build(spec).est
    direct = ObserverPredictor(
        LinearModel(A=spec.model.A, B=spec.model.B, Q=spec.model.Q),
        [Sensor(name=s.name, H=s.H, R=s.R) for s in spec.sensors],
        x0=spec.x0, P0=spec.P0, lead=spec.lead, max_delay=spec.max_delay, command_hold=hold)
    assert isinstance(op, ObserverPredictor)
    for k in range(60):
        for est in (op, direct):
            if k % 7 == 0:
                est.add_command(step=k + 10, u=np.array([0.5 if k < 40 else 0.0]))
            if k >= 10 and k % 2 == 0:
                est.add_measurement("camera", step=k - 10, z=np.array([0.1, 5.0]), now=k)
            if k >= 12:
                est.add_measurement("ranger", step=k - 12, z=np.array([4.9]), now=k)
        a, b = op.predict(now=k), direct.predict(now=k)
        assert a.step == b.step == k + spec.lead
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.P, b.P)
    assert op.counters == direct.counters


def test_measurement_step_from_step_or_time():
    spec = paper_spec(epoch_ns=EPOCH).model_copy(update={"stamp_rounding": "floor"})
    assert measurement_step(measurement(step=42), spec) == 42
    for k in [0, 1, 17, 10**9]:
        t = EPOCH + k * PERIOD_NS
        assert measurement_step(measurement(step=None, t_ns=t), spec) == k
        assert measurement_step(measurement(step=None, t_ns=t + PERIOD_NS - 1), spec) == k
        assert measurement_step(measurement(step=None, t_ns=t - 1), spec) == k - 1  # floor
    assert measurement_step(measurement(step=None, t_ns=EPOCH - PERIOD_NS), spec) == -1


def test_a_discrete_spec_rounds_stamps_to_the_nearest_step_by_default():
    spec = paper_spec(epoch_ns=EPOCH)
    assert spec.stamp_rounding == "nearest" and not spec.continuous_time
    half = PERIOD_NS // 2
    for k in [0, 1, 17, 10**9]:
        t = EPOCH + k * PERIOD_NS
        assert measurement_time(measurement(step=None, t_ns=t), spec) == (k, 0.0)
        assert measurement_time(measurement(step=None, t_ns=t + half - 1), spec) == (k, 0.0)
        assert measurement_time(measurement(step=None, t_ns=t + half), spec) == (k + 1, 0.0)
        assert measurement_time(measurement(step=None, t_ns=t - 1), spec) == (k, 0.0)
    # commands stay on the grid: floor + lead
    issued = EPOCH + 25 * PERIOD_NS + PERIOD_NS - 1
    assert command_time(command(step=None, issued_ns=issued), spec) == (25 + spec.lead, 0.0)
    # the default is not written: a spec's bytes (and fingerprint) stay as they were
    assert "stamp_rounding" not in spec.model_dump()
    assert spec.model_copy(update={"stamp_rounding": "floor"}).model_dump()[
        "stamp_rounding"] == "floor"


def test_a_continuous_spec_keeps_each_stamps_offset_into_its_step():
    spec = paper_continuous_spec(epoch_ns=EPOCH)
    assert spec.continuous_time and spec.model.continuous and spec.n == 4
    for k in [0, 1, 17, 10**9]:
        t = EPOCH + k * PERIOD_NS
        assert measurement_time(measurement(step=None, t_ns=t), spec) == (k, 0.0)
        assert measurement_time(measurement(step=None, t_ns=t + 1), spec) == (k, 1e-9)
        s, off = measurement_time(measurement(step=None, t_ns=t + PERIOD_NS - 1), spec)
        assert s == k and off == (PERIOD_NS - 1) / 1e9
        s, off = measurement_time(measurement(step=None, t_ns=t - 7), spec)
        assert s == k - 1 and off == (PERIOD_NS - 7) / 1e9
    assert measurement_time(measurement(step=17), spec) == (17, 0.0)  # a step: its start
    issued = EPOCH + 25 * PERIOD_NS + 123_456
    assert command_time(command(step=None, issued_ns=issued), spec) == (25 + spec.lead,
                                                                        123_456 / 1e9)
    # the model is the exact discretisation of F, G, Qc; A, B, Q are not on the wire
    est = build(spec).est
    assert isinstance(est, ObserverPredictor) and est.model.continuous_time
    np.testing.assert_allclose(est.model.A, paper_spec().model.A, atol=1e-15)
    assert set(spec.model.model_dump()) == {"kind", "F", "G", "Qc"}


@pytest.mark.parametrize("model, field", [
    ({"kind": "linear", "A": np.eye(2), "B": np.ones((2, 1)), "Q": np.eye(2),
      "F": np.eye(2)}, "A"),
    ({"kind": "linear", "F": np.eye(2), "G": np.ones((2, 1))}, "A"),
    ({"kind": "linear", "F": np.eye(2), "G": np.ones((3, 1)), "Qc": np.eye(2)}, "G"),
    ({"kind": "linear", "F": np.eye(2), "G": np.ones((2, 1)), "Qc": -np.eye(2)}, "Qc"),
])
def test_a_linear_model_is_one_complete_triple(model, field):
    with pytest.raises(ValidationError, match=rf"model\.linear\s+{field}:"):
        SessionSpec.model_validate({**paper_spec().model_dump(), "model": model,
                                    "x0": np.zeros(2), "P0": np.eye(2)})


def test_step_arithmetic_is_exact_for_large_int64():
    spec = paper_spec(epoch_ns=-(2**62))
    t = 2**62 + 3  # float64 could not hold the difference exactly
    assert measurement_step(measurement(step=None, t_ns=t), spec) == (t + 2**62) // PERIOD_NS
    assert spec.time_of(spec.step_of(t)) <= t < spec.time_of(spec.step_of(t) + 1)


def test_command_step_adds_lead_to_issue_time():
    spec = paper_spec(epoch_ns=EPOCH)
    assert command_step(command(step=33), spec) == 33
    issued = EPOCH + 25 * PERIOD_NS + 7
    assert command_step(command(step=None, issued_ns=issued), spec) == 25 + spec.lead


def test_check_measurement():
    spec = paper_spec(epoch_ns=EPOCH)
    check_measurement(measurement(step=3), spec)
    check_measurement(measurement(sensor="ranger", z=np.array([1.0]), R=np.eye(1)), spec)
    cases = [
        (measurement(session="s2"), "Measurement.session: 's2' is not session 's1'"),
        (measurement(sensor="lidar"),
         "Measurement.sensor: unknown sensor 'lidar' (session 's1' has: camera, ranger)"),
        (measurement(z=np.array([1.0])), "Measurement.z: expected 2 values for sensor 'camera', got 1"),
        (measurement(sensor="ranger", z=np.array([1.0, 2.0]), R=np.eye(2)),
         "Measurement.z: expected 1 values for sensor 'ranger', got 2"),
        (measurement(step=None, t_ns=EPOCH - 1),
         f"Measurement.t_ns: {EPOCH - 1} is before the session epoch {EPOCH} (step < 0)"),
    ]
    for msg, text in cases:
        with pytest.raises(WireError) as info:
            check_measurement(msg, spec)
        assert info.value.reason == text


def test_check_command():
    spec = paper_spec(epoch_ns=EPOCH)
    check_command(command(), spec, spec.model.r)
    # issued before the epoch, but lead moves the apply step to >= 0: fine
    check_command(command(step=None, issued_ns=EPOCH - 3 * PERIOD_NS), spec, spec.model.r)
    cases = [
        (command(session="s9"), "Command.session: 's9' is not session 's1'"),
        (command(u=np.array([1.0, 2.0])),
         "Command.u: expected 1 values (model.B has 1 columns), got 2"),
        (command(step=None, issued_ns=EPOCH - 11 * PERIOD_NS),
         f"Command.issued_ns: {EPOCH - 11 * PERIOD_NS} gives apply step -1 < 0"),
    ]
    for msg, text in cases:
        with pytest.raises(WireError) as info:
            check_command(msg, spec, spec.model.r)
        assert info.value.reason == text


def _estimate():
    spec = paper_spec(epoch_ns=EPOCH)
    op = build(spec).est
    op.add_command(step=0, u=np.array([0.5]))
    op.add_measurement("camera", step=0, z=np.array([0.0, 5.0]), now=10)
    return spec, op, op.predict(now=10)


def _encoded(pred, spec, session, seq, made_ns, counters) -> bytes:
    """The daemon's fast path: x and P packed as msgpack arrays (as its health check does),
    then the session's PredictionEncoder."""
    return PredictionEncoder(spec, session).encode_packed(
        pred, msgpack.packb(np.asarray(pred.x).tolist()),
        msgpack.packb(np.asarray(pred.P).ravel().tolist()), seq, made_ns, counters)


def test_prediction_from():
    spec, op, pred = _estimate()
    msg = prediction_from(pred, spec, "s1", seq=4, made_ns=EPOCH + 999, counters=op.counters)
    assert isinstance(msg, Prediction)
    assert msg.step == 20 and msg.t_ns == EPOCH + 20 * PERIOD_NS
    assert msg.newest_step == 0 and msg.seq == 4 and msg.made_ns == EPOCH + 999
    assert msg.counters == op.counters and msg.counters["accepted"] == 1
    np.testing.assert_array_equal(msg.x, pred.x)
    np.testing.assert_array_equal(msg.P, pred.P)
    # the fast path builds the same message full validation would, and it decodes
    full = Prediction(session="s1", seq=4, step=20, t_ns=EPOCH + 20 * PERIOD_NS, x=pred.x,
                      P=pred.P, newest_step=0, made_ns=EPOCH + 999, counters=op.counters)
    assert msg == full
    assert encode(msg) == encode(full)
    assert decode(encode(msg), Prediction) == msg
    # the direct-to-bytes path gives the very same bytes
    fast = _encoded(pred, spec, "s1", seq=4, made_ns=EPOCH + 999, counters=op.counters)
    assert fast == encode(full)


@pytest.mark.parametrize("session", ["s1", "a-session-name-longer-than-31-bytes_" + "x" * 26])
def test_one_encoder_gives_the_models_bytes_for_every_message(session):
    """The daemon's per-session PredictionEncoder, reused: every field that varies (seq,
    step, newest_step None or not, made_ns, counters, values) across the msgpack size
    classes of ints and strings, byte for byte equal to the validated model's encoding."""
    spec = paper_spec(epoch_ns=EPOCH).model_copy(update={"session": session})
    enc = PredictionEncoder(spec, session)
    rng = np.random.default_rng(7)
    for i in range(300):
        x = rng.normal(size=4) * 10.0 ** rng.integers(-20, 20)
        A = rng.normal(size=(4, 4))
        P = A @ A.T * 10.0 ** rng.integers(-20, 20)
        step = int(rng.choice([0, 1, 127, 128, 255, 65_535, 2**31, 2**32 + 1]))
        newest = None if i % 3 == 0 else int(rng.integers(0, step + 1))
        counters = {f"c{j}": int(rng.choice([0, 1, 200, 70_000, 2**33])) for j in range(i % 20)}
        fake = type("P", (), {"step": step, "x": x, "P": P, "newest_step": newest})()
        seq, made = int(rng.choice([0, 5, 300, 2**35])), EPOCH + int(rng.integers(0, 10**9))
        # ownership terms: 0 (unfenced), small, and next_term's form (ms << 16 | tag)
        term = int(rng.choice([0, 1, 200, 70_000, (1_800_000_000_000 << 16) | 0xBEEF]))
        want = encode(Prediction(session=session, seq=seq, step=step,
                                 t_ns=EPOCH + step * PERIOD_NS, x=x, P=P, newest_step=newest,
                                 made_ns=made, counters=counters, term=term))
        assert encode(prediction_from(fake, spec, session, seq, made, counters, term)) == want
        # x and P packed as msgpack arrays (the daemon's health check, service/_moments.c)
        assert enc.encode_packed(fake, msgpack.packb(x.tolist()),
                                 msgpack.packb(P.ravel().tolist()), seq, made, counters,
                                 term) == want
    with pytest.raises(WireError, match=r"expected x \(4,\) and P \(4, 4\) packed in 37 and "
                                        r"147 bytes, got 28 and 147"):
        enc.encode_packed(fake, msgpack.packb(x.tolist()[:3]), msgpack.packb(P.ravel().tolist()),
                          0, 0, {})


def test_prediction_from_copies_and_freezes():
    spec, op, pred = _estimate()
    x_src = np.array(pred.x)
    counters = {"accepted": 1}
    fake = type("P", (), {"step": np.int64(20), "x": x_src, "P": np.array(pred.P),
                          "newest_step": np.int64(3)})()
    msg = prediction_from(fake, spec, "s1", 0, 0, counters)
    x_src[0] = 123.0
    counters["accepted"] = 99
    assert msg.x[0] != 123.0 and msg.counters == {"accepted": 1}
    assert not msg.x.flags.writeable and not msg.P.flags.writeable
    assert type(msg.step) is int and type(msg.newest_step) is int
    assert decode(encode(msg), Prediction) == msg


def test_prediction_from_refuses_bad_estimates():
    spec, op, pred = _estimate()
    bad_x = np.array(pred.x)
    bad_x[1] = np.nan
    fake = type("P", (), {"step": 1, "x": bad_x, "P": pred.P, "newest_step": None})()
    with pytest.raises(WireError, match="not finite"):
        prediction_from(fake, spec, "s1", 0, 0, {})
    big = type("P", (), {"step": 1, "x": np.full(4, 1e308), "P": np.diag(np.full(4, 1e308)),
                         "newest_step": None})()  # large, finite values
    assert decode(_encoded(big, spec, "s1", 0, 0, {}), Prediction) == \
        prediction_from(big, spec, "s1", 0, 0, {})
    fake = type("P", (), {"step": 1, "x": pred.x[:3], "P": pred.P, "newest_step": None})()
    with pytest.raises(WireError, match=r"expected x \(4,\) and P \(4, 4\)"):
        prediction_from(fake, spec, "s1", 0, 0, {})


def test_check_key():
    assert check_key(measurement(), keys.sensor_key("s1", "camera")).sensor == "camera"
    assert check_key(measurement(), keys.robot_sensor_key("s1", "camera")).side == "robot"
    assert check_key(command(), keys.command_key("s1")).kind == "cmd"
    ranger1, camera2 = keys.sensor_key("s1", "ranger"), keys.sensor_key("s2", "camera")
    bogus = f"{keys.session_prefix('s1')}/bogus"
    cases = [
        (measurement(), ranger1,
         f"Measurement.sensor: 'camera' does not match the key '{ranger1}'"),
        (measurement(), camera2,
         f"Measurement.session: 's1' does not match the key '{camera2}'"),
        (command(), keys.command_key("s2"),
         f"Command.session: 's1' does not match the key '{keys.command_key('s2')}'"),
        (command(), bogus,
         f"Command: key '{bogus}': unknown stream 'bogus' for the operator side"),
    ]
    for msg, key, text in cases:
        with pytest.raises(WireError) as info:
            check_key(msg, key)
        assert info.value.reason == text
