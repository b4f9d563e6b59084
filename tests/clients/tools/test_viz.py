"""pd-viz: a Foxglove WebSocket client (foxglove.websocket.v1, named foxglove.sdk.v1 by the
SDK's server) connected to the server while
the daemon core runs the paper scenario on the in-memory bus; the decoded predicted pose
equals the daemon's Prediction for the same step."""

from __future__ import annotations

import json
from contextlib import contextmanager

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
pytest.importorskip("google.protobuf")

from pd_client.tools.pd_viz import VizServer, ellipse_points, position_indices  # noqa: E402
from pd_service.transport import InMemoryBus  # noqa: E402
from pd_service.wire import Prediction, decode, encode, keys  # noqa: E402
from pd_service.wire.messages import PathSpec  # noqa: E402
from pd_service.wire.path import PredictedPath  # noqa: E402
from tests.service.helpers import Clock, Collector  # noqa: E402
from tests.service.test_core import PaperFeed, make_core  # noqa: E402

from .foxglove_ws import FoxgloveClient  # noqa: E402

TOPICS = ["/s1/pose", "/s1/ellipse", "/s1/prediction", "/s1/measurement", "/s1/command",
          "/s1/status", "/s1/log"]


@contextmanager
def viz_on_paper(tmp_path, path: PathSpec | None = None, paths: list | None = None):
    """The daemon core running the paper scenario (session s1, 60 steps) on the in-memory
    bus, pd-viz serving it, and a Foxglove client connected: (feed, collector, client).
    ``path``: the session's path setting; the daemon's paths are appended to ``paths``."""
    bus = InMemoryBus()
    clock = Clock(0)
    col = Collector().attach(bus.transport())
    if paths is not None:
        bus.transport().subscribe(keys.ALL_PATHS, lambda s: paths.append(
            decode(bytes(s.payload), PredictedPath)))
    core = make_core(bus, clock, tmp_path)
    feed = PaperFeed(core, bus.transport(), clock, col, "s1", steps=60, check=False)
    feed.spec = feed.spec.model_copy(update={"path": path})
    feed.configure()
    server = VizServer(bus.transport(), ["s1"], port=0, xy=(0, 2), status_every=0)
    client = FoxgloveClient(server.url)
    try:
        yield feed, col, client
    finally:
        client.close()
        server.close()
        core.close()


@contextmanager
def omni_viz(tmp_path):
    """The daemon core serving the omni session (path on; tests/clients/tools/omni_drive.py)
    on the in-memory bus and pd-viz serving it: (transport, spec, the daemon's outputs, the
    server, ``run(k)``: the core's step k at mid-step)."""
    from .omni_drive import OmniOutputs, omni_spec

    bus = InMemoryBus()
    t = bus.transport()
    spec = omni_spec()
    got = OmniOutputs(t)
    clock = Clock(-1)
    core = make_core(bus, clock, tmp_path)
    t.put(keys.config_key("omni"), encode(spec))
    core.run_once()
    server = VizServer(bus.transport(), ["omni"], port=0, status_every=0)

    def run(k: int) -> None:
        clock.t = spec.time_of(k) + spec.period_ns // 2
        core.run_once()

    try:
        yield t, spec, got, server, run
    finally:
        server.close()
        core.close()


def test_pose_equals_the_daemons_prediction(tmp_path):
    with viz_on_paper(tmp_path) as (feed, col, client):
        client.wait_channels(TOPICS)
        assert client.server_info is not None
        assert client.subprotocol == "foxglove.sdk.v1"
        client.subscribe(TOPICS)
        client.pump(0.5)  # the server takes the subscription
        for k in range(60):
            feed.step(k)
        client.pump(1.0)
    preds = {p.t_ns: p for p in col.predictions["s1"]}
    Pose = client.protobuf_class("/s1/pose")
    poses = [Pose.FromString(data) for _, data in client.messages.get("/s1/pose", [])]
    assert len(poses) >= 50, len(poses)
    for pose in poses:
        t_ns = pose.timestamp.seconds * 1_000_000_000 + pose.timestamp.nanos
        p = preds[t_ns]  # the prediction of the same target step
        assert pose.frame_id == "world"
        assert pose.pose.position.x == p.x[0] and pose.pose.position.y == p.x[2]
    js = [json.loads(d) for _, d in client.messages["/s1/prediction"]]
    by_step = {p.step: p for p in col.predictions["s1"]}
    for m in js:
        p = by_step[m["step"]]
        assert list(m["x"].values()) == p.x.tolist()
        assert list(m["var"].values()) == np.diag(p.P).tolist()
    # the measurements as they arrive, with their age
    meas = [json.loads(d) for _, d in client.messages["/s1/measurement"]]
    assert meas and {m["sensor"] for m in meas} <= {s.name for s in feed.spec.sensors}
    # (ages here are against the wall clock: the core runs on a test clock from epoch 0)
    assert all("age_steps" in m and "age_ms" in m and "step" in m for m in meas)
    assert any(json.loads(d)["late"] > 0 or json.loads(d)["accepted"] > 0
               for _, d in client.messages["/s1/status"])
    Scene = client.protobuf_class("/s1/ellipse")
    scene = Scene.FromString(client.messages["/s1/ellipse"][-1][1])
    assert len(scene.entities[0].lines[0].points) == 48
    # the refused duplicates / over-late copies show up as Log messages
    assert client.messages.get("/s1/log")


def test_path_channels_equal_the_daemons_path(tmp_path):
    """A session whose spec asks for the path: ``/s1/path`` (JSON) carries the daemon's path
    of the (x, y) components point for point, ``/s1/path_band`` (SceneUpdate) its means as a
    line and a 2-sigma ellipse per point."""
    paths: list[PredictedPath] = []
    topics = ["/s1/path", "/s1/path_band", "/s1/pose"]
    with viz_on_paper(tmp_path, PathSpec(indices=[0, 2], stride=2), paths) as (feed, col, client):
        client.wait_channels(topics)
        client.subscribe(topics)
        client.pump(0.5)
        for k in range(40):
            feed.step(k)
        client.pump(1.0)
    by_seq = {p.seq: p for p in paths}
    preds = {p.seq: p for p in col.predictions["s1"]}
    js = [json.loads(d) for _, d in client.messages["/s1/path"]]
    assert len(js) >= 30 and len(paths) >= len(js)
    for m in js:
        path = by_seq[m["seq"]]
        assert m["steps"] == path.steps and m["x"] == path.X[:, 0].tolist()
        assert m["y"] == path.X[:, 1].tolist()
        assert m["t_ns"][-1] == preds[m["seq"]].t_ns and m["x"][-1] == preds[m["seq"]].x[0]
        sd = np.sqrt([np.diag(path.covariance(i)) for i in range(len(path.steps))])
        np.testing.assert_allclose(np.array([m["sd_x"], m["sd_y"]]).T, sd, rtol=1e-12)
    Scene = client.protobuf_class("/s1/path_band")
    scenes = [Scene.FromString(d) for _, d in client.messages["/s1/path_band"]]
    assert len(scenes) == len(js)
    for scene, m in zip(scenes, js, strict=True):
        [ent] = scene.entities
        assert ent.frame_id == "world"
        assert ent.timestamp.seconds * 10**9 + ent.timestamp.nanos == m["t_ns"][-1]
        mean, *loops = ent.lines
        assert [(p.x, p.y) for p in mean.points] == list(zip(m["x"], m["y"], strict=True))
        assert len(loops) == len(m["steps"])
        for loop, x, y, sx, sy in zip(loops, m["x"], m["y"], m["sd_x"], m["sd_y"], strict=True):
            pts = np.array([(p.x, p.y) for p in loop.points])
            assert len(pts) == 24  # every point of a 2-sigma ellipse lies within its box
            assert np.all(np.abs(pts - [x, y]) <= 2 * np.array([sx, sy]) * (1 + 1e-9) + 1e-12)


def test_position_and_ellipse_helpers():
    assert position_indices(4, ["p1", "v1", "p2", "v2"]) == (0, 2)
    assert position_indices(5, ["x", "y", "theta", "v", "w"]) == (0, 1)
    assert position_indices(1, None) == (0, None)
    assert position_indices(4, None, (1, 3)) == (1, 3)
    pts = np.array(ellipse_points((1.0, 2.0), np.diag([4.0, 1.0]), k=2.0, segments=4))
    assert np.allclose(pts, [[5.0, 2.0], [1.0, 4.0], [-3.0, 2.0], [1.0, 0.0]]) or np.allclose(
        np.sort(pts, axis=0), np.sort(np.array([[5.0, 2.0], [1.0, 4.0], [-3.0, 2.0],
                                                [1.0, 0.0]]), axis=0))


def plotjuggler_lists(channel: dict) -> bool:
    """PlotJuggler 3.16+'s Foxglove client keeps a channel only if this holds
    (plotjuggler_plugins/DataStreamFoxgloveBridge/foxglove_client.cpp, canUseChannel)."""
    return (channel.get("encoding") == "cdr" and channel.get("schemaEncoding") == "ros2msg"
            and bool(channel.get("schema")) and bool(channel.get("schemaName"))
            and bool(channel.get("topic")))


def test_plotjuggler_lists_the_numeric_series_and_they_decode(tmp_path):
    """The ros2/* channels pass PlotJuggler's filter (the others do not: it lists nothing
    else), and rosbags (an independent ROS 2 message and CDR implementation) reads their
    messages, from the advertised definition alone, as the daemon's predictions."""
    rosbags = pytest.importorskip("rosbags.typesys")

    series = ["/s1/ros2/prediction", "/s1/ros2/status"]
    with viz_on_paper(tmp_path) as (feed, col, client):
        client.wait_channels(TOPICS + series)
        pred = client.channels["/s1/prediction"]  # JSON: a real schema with a stable name
        assert (pred["schemaName"], pred["schemaEncoding"]) == ("pd_viz.Prediction", "jsonschema")
        assert json.loads(pred["schema"])["properties"]["step"] == {"type": "integer"}
        listed = sorted(t for t, ch in client.channels.items() if plotjuggler_lists(ch))
        assert listed == ["/s1/ros2/error", *series]
        client.subscribe(series)
        client.pump(0.5)
        for k in range(60):
            feed.step(k)
        client.pump(1.0)
    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    for t in series:
        ch = client.channels[t]
        own = ch["schema"].split("\n" + "=" * 80)[0]  # the message; its dependency is Jazzy's
        ts.register(rosbags.get_types_from_msg(own, ch["schemaName"]))
    by_step = {p.step: p for p in col.predictions["s1"]}
    ch = client.channels["/s1/ros2/prediction"]
    assert ch["schemaName"] == "pd_viz_msgs/msg/S1Prediction"
    msgs = [ts.deserialize_cdr(d, ch["schemaName"]) for _, d in client.messages[series[0]]]
    assert len(msgs) >= 40
    for m in msgs:
        p = by_step[m.step]
        assert m.stamp.sec * 10**9 + m.stamp.nanosec == p.t_ns
        assert m.newest_step == (-1 if p.newest_step is None else p.newest_step)
        assert [m.x_0, m.x_1, m.x_2, m.x_3] == p.x.tolist()
        assert m.sd_2 == np.sqrt(p.P[2, 2]) and m.latency_ms >= 0
    st = [ts.deserialize_cdr(d, client.channels[series[1]]["schemaName"])
          for _, d in client.messages[series[1]]]
    assert st[-1].accepted == col.predictions["s1"][-1].counters["accepted"]


def test_a_viewer_connected_before_the_first_prediction_gets_every_channel_at_once(tmp_path):
    """Every channel, the ros2/* series too, is in the advertisement a viewer gets on
    connecting, before the session's first prediction; none is advertised, replaced or
    withdrawn later, and a subscription taken then receives the series of every prediction.
    (foxglove-sdk 0.30 sends a channel's advertisement before it registers the channel for
    the connected viewer's subscribe: one made while a viewer is connected can be refused
    as "Unknown channel ID", which lost test_viz_ws_protocol its ros2/prediction series.)"""
    series = ["/s1/ros2/prediction", "/s1/ros2/error", "/s1/ros2/status"]
    with viz_on_paper(tmp_path) as (feed, col, client):
        client.wait_channels(TOPICS + series, timeout=5.0)
        client.pump(0.5)
        at_connect = list(client.advertised)
        client.subscribe(series)
        client.pump(0.5)  # the server takes the subscription
        assert not col.predictions.get("s1")  # no prediction yet
        for k in range(60):
            feed.step(k)
        client.pump(1.0)
    assert client.advertised == at_connect and not client.unadvertised
    assert len({ch["topic"] for ch in at_connect}) == len(at_connect)
    steps = [p.step for p in col.predictions["s1"]]
    got = client.messages["/s1/ros2/prediction"]
    assert len(got) == len(steps) and len(client.messages["/s1/ros2/status"]) == len(steps)
    # the step (int64 at offset 8 after the 4-byte CDR header) of each message, in order
    assert [int.from_bytes(d[12:20], "little", signed=True) for _, d in got] == steps


def test_a_session_unknown_at_start_gets_its_series_at_its_first_prediction():
    """No daemon serves the session when pd-viz starts (its spec unknown): its ros2/status
    channel exists at once, ros2/prediction and ros2/error come with its first prediction
    (fields for that state size); a prediction of another size is counted, not sent."""
    bus = InMemoryBus()
    t = bus.transport()
    server = VizServer(bus.transport(), ["late"], port=0, status_every=0)
    client = FoxgloveClient(server.url)

    def put(seq: int, n: int) -> None:
        t.put(keys.prediction_key("late"), encode(Prediction(
            session="late", seq=seq, step=10 + seq, t_ns=(10 + seq) * 1000,
            x=np.arange(n, dtype=float), P=np.eye(n), made_ns=0)))

    try:
        client.wait_channels(["/late/ros2/status"])
        assert "/late/ros2/prediction" not in client.channels
        put(0, 3)
        client.wait_channels(["/late/ros2/prediction", "/late/ros2/error"])
        schema = client.channels["/late/ros2/prediction"]["schema"]
        assert "float64 x_2\n" in schema and "x_3" not in schema
        view = server.views["late"]
        assert view.counts["series_unshown"] == 0
        put(1, 5)
        assert view.counts["predictions"] == 2 and view.counts["series_unshown"] == 1
    finally:
        client.close()
        server.close()


def test_camera_calibration_and_ghost_channels_equal_the_daemons_output(tmp_path):
    """An omni session (the daemon core in-process, path on) and camera frames 12 steps late:
    ``/omni/camera`` carries each frame's JPEG at its capture stamp, ``/omni/camera_info`` its
    view as a pinhole, ``/omni/ghost`` the outline at the daemon's newest prediction (and the
    path of the same seq) in that frame's pixels."""
    from pd_client.tools.camera_view import outline_px

    from .omni_drive import drive

    topics = ["/omni/camera", "/omni/camera_info", "/omni/ghost"]
    with omni_viz(tmp_path) as (t, spec, got, server, run):
        client = FoxgloveClient(server.url)
        try:
            client.wait_channels(topics)
            client.subscribe(topics)
            client.pump(0.5)
            drive(t, spec, run, 30, 3, got.on_frame)
            client.pump(1.0)
        finally:
            client.close()
    preds, paths, frames = got.preds, got.paths, got.frames
    by_seq = {p.seq: p for p in preds}
    Image = client.protobuf_class("/omni/camera")
    Calib = client.protobuf_class("/omni/camera_info")
    Ann = client.protobuf_class("/omni/ghost")
    images = [Image.FromString(d) for _, d in client.messages["/omni/camera"]]
    calibs = [Calib.FromString(d) for _, d in client.messages["/omni/camera_info"]]
    anns = [Ann.FromString(d) for _, d in client.messages["/omni/ghost"]]
    assert len(images) == len(calibs) == len(anns) == len(frames) == 6
    for (f, seq), img, cal, ann in zip(frames, images, calibs, anns, strict=True):
        stamp = img.timestamp.seconds * 10**9 + img.timestamp.nanos
        assert stamp == f.t_ns and img.format == "jpeg" and img.data == f.image()
        assert (cal.width, cal.height) == (320, 240) and list(cal.K)[2::3][:2] == [160.0, 120.0]
        assert cal.K[0] == cal.K[4] == f.scale * 10.0
        p = by_seq[seq]
        ghost, ellipse, path_line = ann.points
        np.testing.assert_allclose([(q.x, q.y) for q in ghost.points],
                                   outline_px(f, p.x[0], p.x[1], p.x[2]), rtol=0, atol=1e-9)
        assert len(ellipse.points) == 48
        np.testing.assert_allclose([(q.x, q.y) for q in path_line.points],
                                   f.project(paths[seq].X[:, :2]), rtol=0, atol=1e-9)
