"""pd-viz read by Foxglove's own WebSocket protocol client (@foxglove/ws-protocol's
FoxgloveClient, in node: viewers/foxglove_ws_protocol_client.js), not by the tests' Python
client: the omni robot on the daemon core, its predicted path, camera frames 12 steps late in
both views (top-down and a perspective camera mounted on the robot), and the numeric series.
Each message the node client received is checked against the daemon's output: the path
(JSON and SceneUpdate) against the daemon's PredictedPath, the image and its calibration
against the frame, the ghost against the daemon's prediction projected by OpenCV
(``cv2.projectPoints``: another implementation of the pinhole camera) or the top-down view's
formula, the ``ros2/*`` series (decoded by rosbags from the advertised definition) against
the daemon's Prediction; and PlotJuggler's channel filter, applied to what the node client was
advertised, keeps exactly the numeric series."""

from __future__ import annotations

import base64
import json
import math
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("google.protobuf")

from pd_client.tools.camera_view import outline  # noqa: E402
from pd_service.wire import encode, keys  # noqa: E402
from pd_service.wire.camera import CameraFrame  # noqa: E402
from pd_service.wire.pinhole import CameraMount, PinholeView  # noqa: E402

from .foxglove_ws import protobuf_message_class  # noqa: E402
from .omni_drive import VIDEO_DELAY, drive, pose  # noqa: E402
from .test_viz import omni_viz, plotjuggler_lists  # noqa: E402

VIEWERS = Path(__file__).parent / "viewers"
CLIENT = VIEWERS / "foxglove_ws_protocol_client.js"
TOPICS = ["/omni/path", "/omni/path_band", "/omni/camera", "/omni/camera_info", "/omni/ghost",
          "/omni/ros2/prediction"]
#: The perspective camera: 1.2 m behind the body origin, 1 m up, pitched 0.35 rad down.
MOUNT = CameraMount(x=-1.2, z=1.0, pitch=0.35)
K = [300.0, 0.0, 160.5, 0.0, 310.0, 119.5, 0.0, 0.0, 1.0]
D = [-0.15, 0.04, 5e-4, -8e-4, 0.0]


def _node_client_or_skip() -> None:
    if shutil.which("node") is None:
        pytest.skip("needs node (20+)")
    if not (VIEWERS / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.skip("@foxglove/ws-protocol not installed: make node-deps (npm ci in "
                    f"{VIEWERS})")


class NodeClient:
    """The node process and what it printed, read on a thread."""

    def __init__(self, url: str, topics: list[str]) -> None:
        self.p = subprocess.Popen(["node", "--experimental-websocket", str(CLIENT), url, *topics],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        self.events: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            with self._cond:
                self.events.append(json.loads(line))
                self._cond.notify_all()

    def wait(self, what: str, topics: list[str], timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        with self._cond:
            while not set(topics) <= {e.get("topic") for e in self.events if e["op"] == what}:
                left = end - time.monotonic()
                assert left > 0, f"{what} not seen for {topics}: {self.events[-5:]}"
                self._cond.wait(left)

    def close(self) -> None:
        assert self.p.stdin is not None
        self.p.stdin.close()
        try:
            self.p.wait(30)
        except subprocess.TimeoutExpired:
            self.p.kill()
        assert self.p.stderr is not None
        self.stderr = self.p.stderr.read()

    def channels(self) -> dict[str, dict[str, Any]]:
        return {e["channel"]["topic"]: e["channel"] for e in self.events if e["op"] == "advertise"}

    def messages(self, topic: str) -> list[bytes]:
        return [base64.b64decode(e["data"]) for e in self.events
                if e["op"] == "message" and e["topic"] == topic]

    def protobuf_class(self, topic: str) -> Any:
        return protobuf_message_class(self.channels()[topic])


def _pinhole_frame(k: int, t_ns: int) -> CameraFrame:
    x, y, yaw = pose(k)
    return CameraFrame(session="omni", seq=10_000 + k, t_ns=t_ns, format="png",
                       data=base64.b64encode(b"\x89PNG frame %d" % k + b"\x00" * (k % 3)).decode(),
                       width=320, height=240, pinhole=PinholeView(
                           K=K, distortion_model="plumb_bob", D=D, mount=MOUNT, body_x=x,
                           body_y=y, body_yaw=yaw))


def _cv2_pixels(view: PinholeView, xy: np.ndarray) -> np.ndarray:
    """Ground points' pixels by OpenCV, from the camera's pose at capture."""
    cv2 = pytest.importorskip("cv2")
    R_wo, t_wo = view.optical_pose()
    pts = np.column_stack([xy, np.zeros(len(xy))])
    rvec, _ = cv2.Rodrigues(R_wo.T)
    uv, _ = cv2.projectPoints(pts, rvec, -R_wo.T @ t_wo, np.array(K).reshape(3, 3),
                              np.array(D))
    return uv.reshape(-1, 2)


def _top_down_pixels(f: CameraFrame, xy: np.ndarray) -> np.ndarray:
    """u = w/2 + scale (x - cx), v = h/2 - scale (y - cy) (docs/protocol.md, CameraFrame)."""
    assert f.scale is not None and f.center_x is not None and f.center_y is not None
    return np.column_stack([f.width / 2 + f.scale * (xy[:, 0] - f.center_x),
                            f.height / 2 - f.scale * (xy[:, 1] - f.center_y)])


def test_foxglove_ws_protocol_client_reads_path_image_ghost_and_series(tmp_path) -> None:
    _node_client_or_skip()
    rosbags = pytest.importorskip("rosbags.typesys")
    with omni_viz(tmp_path) as (t, spec, got, server, run_core):
        node = NodeClient(server.url, TOPICS)
        try:
            node.wait("subscribed", TOPICS)  # every channel is advertised on connecting
            time.sleep(0.5)  # the server has taken the subscriptions

            def run(k: int) -> None:
                run_core(k)
                if k >= VIDEO_DELAY and k % 3 == 1:  # the perspective camera's frame
                    f = _pinhole_frame(k - VIDEO_DELAY, spec.time_of(k - VIDEO_DELAY))
                    t.put(keys.camera_key("omni"), encode(f))
                    got.on_frame(f)

            drive(t, spec, run, 36, 3, got.on_frame)
            time.sleep(1.0)
        finally:
            node.close()
    preds, paths, frames = got.preds, got.paths, got.frames
    assert not [e for e in node.events if e["op"] in ("error", "status")], node.events
    assert node.events[0] == {"op": "open", "protocol": "foxglove.sdk.v1"}, node.stderr
    by_seq = {p.seq: p for p in preds}

    # the path, as JSON and as a SceneUpdate line strip, equals the daemon's PredictedPath
    jpaths = [json.loads(d) for d in node.messages("/omni/path")]
    assert len(jpaths) >= 20
    for m in jpaths:
        p = paths[m["seq"]]
        assert m["steps"] == list(p.steps) and m["x"] == p.X[:, 0].tolist()
        assert m["y"] == p.X[:, 1].tolist()
        assert m["sd_x"] == [math.sqrt(p.covariance(r)[0, 0]) for r in range(len(p.steps))]
    Scene = node.protobuf_class("/omni/path_band")
    bands = [Scene.FromString(d) for d in node.messages("/omni/path_band")]
    assert len(bands) == len(jpaths)
    for b, m in zip(bands, jpaths, strict=True):
        strip = b.entities[0].lines[0]
        assert [(q.x, q.y) for q in strip.points] == list(zip(m["x"], m["y"], strict=True))

    # every frame: its image, its calibration, the ghost where the daemon's prediction is
    Image = node.protobuf_class("/omni/camera")
    Calib = node.protobuf_class("/omni/camera_info")
    Ann = node.protobuf_class("/omni/ghost")
    images = [Image.FromString(d) for d in node.messages("/omni/camera")]
    calibs = [Calib.FromString(d) for d in node.messages("/omni/camera_info")]
    anns = [Ann.FromString(d) for d in node.messages("/omni/ghost")]
    assert len(images) == len(calibs) == len(anns) == len(frames) == 16
    perspective = 0
    for (f, seq), img, cal, ann in zip(frames, images, calibs, anns, strict=True):
        assert img.timestamp.seconds * 10**9 + img.timestamp.nanos == f.t_ns
        assert img.data == f.image() and img.format == f.format
        p = by_seq[seq]
        ghost_xy = outline(float(p.x[0]), float(p.x[1]), float(p.x[2]))
        path = paths[seq]
        if f.pinhole is not None:
            perspective += 1
            assert list(cal.K) == K and list(cal.D) == D and cal.distortion_model == "plumb_bob"
            want_ghost = _cv2_pixels(f.pinhole, ghost_xy)
            want_path = _cv2_pixels(f.pinhole, path.X[:, :2])
        else:
            assert cal.K[0] == cal.K[4] == f.scale * 10.0  # type: ignore[operator]
            want_ghost = _top_down_pixels(f, ghost_xy)
            want_path = _top_down_pixels(f, path.X[:, :2])
        ghost, ellipse, path_line = ann.points
        np.testing.assert_allclose([(q.x, q.y) for q in ghost.points], want_ghost, rtol=0,
                                   atol=1e-6)
        np.testing.assert_allclose([(q.x, q.y) for q in path_line.points], want_path, rtol=0,
                                   atol=1e-6)
        assert len(ellipse.points) == 48
    assert perspective == 8

    # PlotJuggler's filter on what this client was advertised: the numeric series only
    channels = node.channels()
    assert sorted(t for t, ch in channels.items() if plotjuggler_lists(ch)) == [
        "/omni/ros2/error", "/omni/ros2/prediction", "/omni/ros2/status"]
    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    ch = channels["/omni/ros2/prediction"]
    ts.register(rosbags.get_types_from_msg(ch["schema"].split("\n" + "=" * 80)[0],
                                           ch["schemaName"]))
    series = [ts.deserialize_cdr(d, ch["schemaName"])
              for d in node.messages("/omni/ros2/prediction")]
    assert len(series) >= 30
    by_step = {p.step: p for p in preds}
    for m in series:
        p = by_step[m.step]
        assert m.stamp.sec * 10**9 + m.stamp.nanosec == p.t_ns
        assert [m.x_0, m.x_1, m.x_2] == p.x[:3].tolist()
        assert m.sd_0 == math.sqrt(p.P[0, 0])
