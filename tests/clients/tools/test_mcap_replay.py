"""MCAP recording (pd-record --mcap) and offline replay (pd-replay) against the real daemon
core on the in-memory bus: the replay with the recorded spec reproduces every published
prediction to 1e-9; with another spec it differs."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mcap")

from pd_client.tools import pd_replay  # noqa: E402
from pd_client.tools.mcap_log import McapRecorder, read_records  # noqa: E402
from pd_service.transport import InMemoryBus  # noqa: E402
from pd_service.wire import Measurement, Prediction, decode, encode, keys  # noqa: E402
from tests.service.helpers import Clock, Collector  # noqa: E402
from tests.service.test_core import PaperFeed, make_core  # noqa: E402

STEPS = 120


@pytest.fixture
def recorded(tmp_path):
    """A daemon-core run of the paper scenario (losses, duplicates, over-late copies),
    recorded to MCAP; returns (path, the daemon's predictions, the feed)."""
    bus = InMemoryBus()
    clock = Clock(0)
    col = Collector().attach(bus.transport())
    core = make_core(bus, clock, tmp_path)
    feed = PaperFeed(core, bus.transport(), clock, col, "s1", steps=STEPS)
    path = tmp_path / "run.mcap"
    rec = McapRecorder(bus.transport(), ["s1"], path, status_every=0)
    feed.configure()
    t = bus.transport()
    for k in range(STEPS):
        feed.step(k)
        if k % 10 == 5:  # camera frames after the link: recorded, ignored by the replay
            t.put(keys.camera_key("s1"), encode(_frame(k)))
    rec.close()
    core.close()
    return path, list(col.predictions["s1"]), feed


def _frame(k: int):  # type: ignore[no-untyped-def]
    """A camera frame of step k: top-down on even tens, perspective on odd ones."""
    import base64

    from pd_service.wire.camera import CameraFrame
    from pd_service.wire.pinhole import CameraMount, PinholeView

    img = base64.b64encode(b"\xff\xd8\xff\xe0 frame %d" % k + b"\x00" * (k % 3)).decode()
    view: dict = ({"center_x": 0.1 * k, "center_y": 1.0, "scale": 40.0} if k // 10 % 2 == 0
                  else {"pinhole": PinholeView(
                      K=[400.0, 0.0, 160.0, 0.0, 400.0, 120.0, 0.0, 0.0, 1.0],
                      distortion_model="plumb_bob", D=[-0.1, 0.01, 0.0, 0.0, 0.0],
                      mount=CameraMount(z=0.8, pitch=0.3), body_x=0.1 * k, body_y=1.0,
                      body_yaw=0.25)})
    return CameraFrame(session="s1", seq=k, t_ns=k * 50_000_000, data=img, width=320,
                       height=240, **view)


def test_mcap_holds_every_stream_with_schemas(recorded):
    from mcap.reader import make_reader

    path, preds, feed = recorded
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        msgs = list(reader.iter_messages())
    pred_topic = "/" + keys.prediction_key("s1")
    assert topics[pred_topic].name == "Prediction"
    assert topics[pred_topic].encoding == "jsonschema"
    assert json.loads(topics["/" + keys.config_key("s1")].data)["title"] == "SessionSpec"
    assert {"/" + k for k in (keys.sensor_key("s1", "camera"), keys.sensor_key("s1", "ranger"),
                              keys.command_key("s1"), keys.error_key("s1"))} <= set(topics)
    n_pred = sum(1 for _, ch, _ in msgs if ch.topic == pred_topic)
    assert n_pred == len(preds) >= STEPS
    # the JSON messages read back to the exact published predictions
    back = [decode(r.payload, Prediction) for r in read_records(path) if r.stream == "prediction"]
    assert [p.seq for p in back] == [p.seq for p in preds]
    for a, b in zip(back, preds, strict=True):
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    times = [m.log_time for _, _, m in msgs]
    assert all(t > 1_000_000_000_000_000_000 for t in times)  # wall clock, ns


def test_camera_frames_are_recorded_with_an_image_copy(recorded):
    """Each CameraFrame after the link is on its key's channel (exactly, both views) and as a
    foxglove.CompressedImage (JSON, data base64 per its schema) stamped with the capture time;
    read_records gives the frames back and skips the image copies."""
    import base64

    from mcap.reader import make_reader

    from pd_service.wire.camera import CameraFrame

    path, _, _ = recorded
    want = [_frame(k) for k in range(STEPS) if k % 10 == 5]
    cam_topic = "/" + keys.camera_key("s1")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schema = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in reader.iter_messages()
                if ch.topic.startswith(cam_topic)]
    assert schema[cam_topic].name == "CameraFrame"
    image_schema = schema[cam_topic + "/image"]
    assert image_schema.name == "foxglove.CompressedImage"
    assert json.loads(image_schema.data)["properties"]["data"]["contentEncoding"] == "base64"
    images = [m for topic, m in msgs if topic == cam_topic + "/image"]
    assert len(images) == len(want) == 12
    for img, f in zip(images, want, strict=True):
        assert img["timestamp"]["sec"] * 10**9 + img["timestamp"]["nsec"] == f.t_ns
        assert base64.b64decode(img["data"]) == f.image() and img["format"] == "jpeg"
    back = [decode(r.payload, CameraFrame) for r in read_records(path) if r.stream == "camera"]
    assert back == want and sum(f.pinhole is not None for f in back) == 6
    assert not [r for r in read_records(path) if r.key.endswith("/image")]


def test_replay_with_recorded_spec_equals_the_daemon(recorded):
    path, preds, feed = recorded
    recs = pd_replay.load(path)
    res = pd_replay.replay(recs["s1"])
    assert len(res.replayed) == len(preds)
    assert [q.step for q in res.replayed] == [p.step for p in preds]
    dx, dp = res.max_abs_diff()
    assert dx <= 1e-9 and dp <= 1e-9, (dx, dp)
    assert res.diverged == 0 and res.missing_inputs == 0
    # the run had refusals (duplicates, over-late copies): the replay counted them alike
    assert res.counters.get("late", 0) + res.counters.get("duplicate", 0) > 0
    assert res.counters == {k: v for k, v in preds[-1].counters.items()
                            if k in pd_replay.SENSOR_REASONS + pd_replay.COMMAND_REASONS and v}


def test_replay_with_another_spec_differs(recorded):
    path, preds, feed = recorded
    recs = pd_replay.load(path)
    spec = recs["s1"].specs[0]
    sensors = [s.model_copy(update={"R": s.R * 9.0}) for s in spec.sensors]
    res = pd_replay.replay(recs["s1"], spec.model_copy(update={"sensors": sensors}))
    dx, dp = res.max_abs_diff()
    assert dp > 1e-3


def test_cli_writes_csv_mcap_and_fails_on_a_tampered_file(recorded, tmp_path, capsys):
    path, preds, feed = recorded
    out = tmp_path / "rep" / "replay.mcap"
    assert pd_replay.main([str(path), "--out", str(out), "--no-plots"]) == 0
    text = capsys.readouterr().out
    assert "max |dx|" in text
    from mcap.reader import make_reader

    with open(out, "rb") as f:
        rep = [(ch.topic, json.loads(m.data)) for _, ch, m in make_reader(f).iter_messages()]
    assert len(rep) == len(preds) and {t for t, _ in rep} == {"/replay/s1/prediction"}
    assert [m["step"] for _, m in rep] == [p.step for p in preds]
    assert (tmp_path / "rep" / "replay.s1.csv").exists()
    # a spec file overrides: other max_delay
    spec = pd_replay.load(path)["s1"].specs[0]
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec.model_copy(update={"max_delay": 15}).model_dump(
        mode="json")))
    assert pd_replay.main([str(path), "--spec", str(spec_file), "--out",
                           str(tmp_path / "tuned.csv"), "--no-plots"]) == 0
    assert pd_replay.main([str(tmp_path / "nope.mcap")]) == 2


def test_tampered_prediction_is_detected(recorded, tmp_path):
    """A recording whose prediction was altered no longer replays within tolerance."""
    from pd_client.tools.mcap_log import McapLog

    path, preds, feed = recorded
    bad = tmp_path / "bad.mcap"
    log = McapLog(bad)
    for i, r in enumerate(read_records(path)):
        payload = r.payload
        if r.stream == "prediction" and i > 200:
            p = decode(payload, Prediction)
            payload = encode(p.model_copy(update={"x": p.x + 1e-6}))
        log.write_sample(r.key, payload, r.log_ns, r.kind)
    log.close()
    assert pd_replay.main([str(bad), "--out", str(tmp_path / "b.csv"), "--no-plots"]) == 3


def test_records_status_spec_and_raw_samples(tmp_path):
    bus = InMemoryBus()
    pub = bus.transport()
    path = tmp_path / "x.mcap"
    rec = McapRecorder(bus.transport(), ["s1"], path, status_every=0)
    pub.put(keys.sensor_key("s1", "camera"), b"\xc1junk")
    pub.put(keys.prediction_key("s2"), b"not recorded")
    rec.close()
    got = list(read_records(path))
    assert [(r.key, r.payload) for r in got] == [(keys.sensor_key("s1", "camera"), b"\xc1junk")]


def test_ros2_outputs_are_recorded_in_the_ros2_profile(tmp_path):
    """A session binding ROS 2 outputs gets cdr Odometry/Pose channels with ros2msg schemas,
    decoding to the predicted pose; the JSON prediction stays the record."""
    from mcap.reader import make_reader

    from pd_client.tools.mcap_log import McapLog
    from pd_service.ros2.extract import yaw_of
    from pd_service.ros2.messages import decode as decode_ros
    from pd_service.scenarios import get_scenario

    spec = get_scenario("diffdrive").spec("bot", 0)
    x = np.array([1.5, -2.0, 0.3, 0.4, 0.05])
    P = np.diag([0.01, 0.02, 0.003, 0.001, 0.002])
    pred = Prediction(session="bot", seq=1, step=40, t_ns=spec.time_of(40), x=x, P=P,
                      newest_step=30, made_ns=5)
    log = McapLog(tmp_path / "r.mcap")
    log.write_sample(keys.config_key("bot"), encode(spec), 1)
    log.write_sample(keys.prediction_key("bot"), encode(pred), 2)
    log.close()
    with open(tmp_path / "r.mcap", "rb") as f:
        got = {ch.topic: (sc.encoding, sc.name, ch.message_encoding, m.data)
               for sc, ch, m in make_reader(f).iter_messages()}
    prefix = "/" + keys.session_prefix("bot")
    enc, name, menc, data = got[f"{prefix}/ros2/odom"]
    assert (enc, name, menc) == ("ros2msg", "nav_msgs/msg/Odometry", "cdr")
    odom = decode_ros(data, "nav_msgs/msg/Odometry")
    p = odom.pose.pose.position
    assert (p.x, p.y) == (1.5, -2.0) and abs(yaw_of(odom.pose.pose.orientation) - 0.3) < 1e-12
    assert odom.header.stamp.sec * 10**9 + odom.header.stamp.nanosec == spec.time_of(40)
    assert got[f"{prefix}/ros2/pose"][1] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert [r.stream for r in read_records(tmp_path / "r.mcap")] == ["config", "prediction"]


def test_world_velocity_layout_without_yaw_is_recorded_in_the_ros2_profile(tmp_path, capsys):
    """Issue 45: the constant-velocity layout (world velocities, no yaw) used to give no ROS 2
    channel and no word; now converted (body = world axes), and a prediction that cannot be
    converted is counted and said once."""
    from mcap.reader import make_reader

    from pd_client.tools.mcap_log import McapLog
    from pd_service.ros2.messages import decode as decode_ros
    from pd_service.scenarios import get_scenario
    from pd_service.wire.ros2 import OutputBinding, Ros2Binding, StateLayout

    spec = get_scenario("paper").spec("cv", 0).model_copy(update={"ros2": Ros2Binding(
        outputs=OutputBinding(layout=StateLayout(x=0, vx=1, y=2, vy=3, velocity_frame="world")))})
    x = np.array([1.0, 0.5, 2.0, -0.25])
    log = McapLog(tmp_path / "cv.mcap")
    log.write_sample(keys.config_key("cv"), encode(spec), 1)
    log.write_sample(keys.prediction_key("cv"), encode(Prediction(
        session="cv", seq=1, step=4, t_ns=spec.time_of(4), x=x, P=np.eye(4), newest_step=None,
        made_ns=5)), 2)
    for seq in (2, 3):  # a state of another size: not convertible with this layout
        log.write_sample(keys.prediction_key("cv"), encode(Prediction(
            session="cv", seq=seq, step=5, t_ns=spec.time_of(5), x=np.zeros(2), P=np.eye(2),
            newest_step=None, made_ns=5)), 3)
    log.close()
    with open(tmp_path / "cv.mcap", "rb") as f:
        got = [(ch.topic, m.data) for _, ch, m in make_reader(f).iter_messages()]
    odom = [d for t, d in got if t.endswith("/ros2/odom")]
    assert len(odom) == 1
    tw = decode_ros(odom[0], "nav_msgs/msg/Odometry").twist.twist.linear
    assert (tw.x, tw.y) == (0.5, -0.25)
    assert log.ros2_errors == 2 and capsys.readouterr().err.count("not written as ROS 2") == 1


def test_log_times_never_decrease_in_the_file(tmp_path):
    """Samples written in another order than received (transport threads) and a prediction's
    ROS 2 copies: log times nondecreasing in file order, publish times the receipt times."""
    from mcap.reader import make_reader

    from pd_client.tools.mcap_log import McapLog
    from pd_service.scenarios import get_scenario

    spec = get_scenario("diffdrive").spec("bot", 0)
    pred = Prediction(session="bot", seq=1, step=40, t_ns=spec.time_of(40), x=np.ones(5),
                      P=np.eye(5), newest_step=30, made_ns=5)
    meas = Measurement(session="bot", sensor=spec.sensors[0].name, seq=1, step=30,
                       z=np.zeros(spec.sensors[0].m))
    log = McapLog(tmp_path / "t.mcap")
    log.write_sample(keys.config_key("bot"), encode(spec), 1)
    log.write_sample(keys.prediction_key("bot"), encode(pred), 50)  # + 2 ROS 2 copies
    log.write_sample(keys.sensor_key("bot", meas.sensor), encode(meas), 40)  # received before
    log.write_sample(keys.prediction_key("bot"), encode(pred), 45)
    log.close()
    with open(tmp_path / "t.mcap", "rb") as f:
        got = [(m.log_time, m.publish_time) for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert [p for _, p in got] == [1, 50, 50, 50, 40, 45, 45, 45]
    log_times = [t for t, _ in got]
    assert log_times == sorted(log_times) == [1, 50, 50, 50, 50, 50, 50, 50]


def test_logs_of_key_layout_1_and_of_another_partition_count_read_back_rekeyed(tmp_path):
    """A log without the pd-keys metadata has layout-1 topics (/pd/<s>/...); one recorded with
    another PD_PARTITIONS has other partition chunks: both read back with this process's keys."""
    from mcap.writer import Writer

    from pd_client.tools.mcap_log import McapLog, to_json

    meas = encode(Measurement(session="s1", sensor="camera", seq=1, step=3,
                              z=np.array([1.0, 2.0])))
    old = tmp_path / "layout1.mcap"
    with open(old, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="Measurement", encoding="jsonschema", data=b"{}")
        cid = w.register_channel(topic="/pd/s1/sensor/camera", message_encoding="json",
                                 schema_id=sid)
        w.add_message(channel_id=cid, log_time=5, data=to_json(meas) or b"", publish_time=5,
                      sequence=0)
        raw = w.register_channel(topic="/pd/s1/raw", message_encoding="json", schema_id=sid)
        w.add_message(channel_id=raw, log_time=6, publish_time=6, sequence=1, data=json.dumps(
            {"key": "pd/s1/cmd", "kind": "delete", "payload_b64": ""}).encode())
        w.finish()
    got = [(r.key, r.stream, r.session, r.kind) for r in read_records(old)]
    assert got == [(keys.sensor_key("s1", "camera"), "sensor", "s1", "put"),
                   (keys.command_key("s1"), "cmd", "s1", "delete")]
    assert decode(next(iter(read_records(old))).payload, Measurement) == decode(meas, Measurement)
    before = keys.partitions()
    try:
        keys.set_partitions(256)
        log = McapLog(tmp_path / "p256.mcap")
        log.write_sample(keys.sensor_key("s1", "camera"), meas, 7)
        log.close()
    finally:
        keys.set_partitions(before)
    assert [r.key for r in read_records(tmp_path / "p256.mcap")] == [keys.sensor_key("s1", "camera")]
