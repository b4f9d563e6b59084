"""pd-ros2's camera binding on the in-memory bus: sensor_msgs/CompressedImage + CameraInfo
(CDR from the rosbags typestore, as a ROS 2 camera driver publishes them) become CameraFrames
with a pinhole view: the CameraInfo's K and D, the spec's mount, the robot's pose from the
odometry sample stamped nearest the image; and every way a camera input is refused."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from pydantic import ValidationError

from pd_service.ros2.messages import encode
from pd_service.wire import SessionSpec, keys
from pd_service.wire import decode as wire_decode
from pd_service.wire import encode as wire_encode
from pd_service.wire.camera import MAX_IMAGE_BYTES, CameraFrame
from pd_service.wire.ros2 import CameraBinding, Ros2Binding
from tests.ros2.specs import (
    CAMERA_D,
    CAMERA_K,
    MOUNT,
    ODOM,
    camera_binding,
    camera_info,
    compressed_image,
    odometry,
    unicycle_spec,
)
from tests.ros2.test_bridge import NOW, STAMP, Rig, make_rig, rmw_key

IMAGE = "sensor_msgs/msg/CompressedImage"
INFO = "sensor_msgs/msg/CameraInfo"
MS = 1_000_000


def _jpeg() -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (320, 240), (40, 90, 160)).save(buf, format="JPEG", quality=60)
    return buf.getvalue()


@pytest.fixture
def cam() -> Rig:
    r = make_rig(specs=(unicycle_spec("s1", camera=camera_binding()),
                        unicycle_spec("s2", prefix="b/")))
    yield r
    r.bridge.close()


def _frames(rig: Rig, session: str = "s1") -> list[CameraFrame]:
    return [wire_decode(s.payload, CameraFrame) for s in rig.on(keys.camera_key(session))]


def test_an_image_becomes_a_frame_placed_by_the_nearest_odometry(cam: Rig) -> None:
    cam.ros_put(rmw_key("/camera/camera_info", INFO), camera_info(STAMP), INFO)
    for i, (x, yaw) in enumerate(((1.0, 0.1), (1.2, 0.2), (1.4, 0.3))):  # 40 ms apart
        cam.ros_put(rmw_key("/odom", ODOM), odometry(STAMP + 40 * MS * i, x, -2.0, yaw, 0.5, 0.1),
                    ODOM)
    jpeg = _jpeg()
    cam.ros_put(rmw_key("/camera/image_raw/compressed", IMAGE),
                compressed_image(STAMP + 50 * MS, jpeg, "bgr8; jpeg compressed bgr8"), IMAGE)
    (f,) = _frames(cam)
    assert f.session == "s1" and f.t_ns == STAMP + 50 * MS and f.image() == jpeg
    assert (f.format, f.width, f.height, f.seq) == ("jpeg", 320, 240, 1)
    assert f.center_x is None and f.pinhole is not None
    v = f.pinhole
    assert v.K == CAMERA_K and v.D == CAMERA_D and v.distortion_model == "plumb_bob"
    assert v.mount == MOUNT
    assert (v.body_x, v.body_y, v.body_yaw) == pytest.approx((1.2, -2.0, 0.2), abs=1e-15)
    c = cam.counters("s1")
    assert c["camera_info_applied"] == 1 and c["camera_frames_forwarded"] == 1
    assert c.get("refused", 0) == 0
    # a png, placed by the newest sample (stamp +80 ms, image +85 ms)
    cam.ros_put(rmw_key("/camera/image_raw/compressed", IMAGE),
                compressed_image(STAMP + 85 * MS, b"\x89PNG\r\n\x1a\n....", "png"), IMAGE)
    assert _frames(cam)[-1].format == "png" and _frames(cam)[-1].pinhole.body_x == 1.4
    assert not _frames(cam, "s2")  # the other session has no camera


def test_the_ghost_projects_through_the_ros_cameras_view(cam: Rig) -> None:
    """The robot at the origin heading +y at capture; the camera 0.2 m ahead, 0.8 m up, pitched
    p = 0.35 rad down: at (0, 0.2, 0.8). The ground point (0, 3) is straight ahead: d = (0, 2.8,
    -0.8), X = 0, Y = -2.8 sin p + 0.8 cos p, Z = 2.8 cos p + 0.8 sin p; with y' = Y / Z,
    r2 = y'^2 the plumb_bob terms give x" = p2 r2, y" = y' (1 + k1 r2 + k2 r2^2) + 3 p1 y'^2."""
    cam.ros_put(rmw_key("/camera/camera_info", INFO), camera_info(STAMP), INFO)
    cam.ros_put(rmw_key("/odom", ODOM), odometry(STAMP, 0.0, 0.0, math.pi / 2, 0.0, 0.0), ODOM)
    cam.ros_put(rmw_key("/camera/image_raw/compressed", IMAGE),
                compressed_image(STAMP, _jpeg()), IMAGE)
    (f,) = _frames(cam)
    ((u, v),) = f.project(np.array([[0.0, 3.0]]))
    p = MOUNT.pitch
    y1 = (-2.8 * math.sin(p) + 0.8 * math.cos(p)) / (2.8 * math.cos(p) + 0.8 * math.sin(p))
    k1, k2, p1, p2, _ = CAMERA_D
    r2 = y1 * y1
    fx, _, cx, _, fy, cy = CAMERA_K[:6]
    assert u == pytest.approx(cx + fx * p2 * r2, abs=1e-9)
    assert v == pytest.approx(cy + fy * (y1 * (1 + k1 * r2 + k2 * r2 * r2) + 3 * p1 * r2),
                              abs=1e-9)
    assert f.project(np.array([[0.0, -3.0]])) is None  # behind the robot: no ghost


def _bad_camera_inputs() -> dict[str, list[tuple[str, object, str, str]]]:
    """reason -> the inputs to put, in order (topic, message, type), and the last input's
    refusal text."""
    odom = ("/odom", odometry(STAMP, 1.0, 2.0, 0.0, 0.0, 0.0), ODOM)
    info = ("/camera/camera_info", camera_info(STAMP), INFO)
    img = "/camera/image_raw/compressed"
    return {
        "camera_info": [odom, (img, compressed_image(STAMP, b"\xff\xd8\xff\xe0jpeg"), IMAGE),
                        "no CameraInfo yet"],
        "camera_info ": [("/camera/camera_info", camera_info(STAMP, K=[0.0] * 9), INFO),
                         "uncalibrated"],
        "camera_info  ": [("/camera/camera_info", camera_info(STAMP, model="equidistant",
                                                               D=[0.1, 0, 0, 0]), INFO),
                          "not plumb_bob (5) or rational_polynomial (8)"],
        "camera_info   ": [("/camera/camera_info", camera_info(STAMP, width=0), INFO),
                           "outside 1..4096"],
        "pose": [info, (img, compressed_image(STAMP, b"\xff\xd8\xff\xe0jpeg"), IMAGE),
                 "no odom sample within 100 ms"],
        "pose ": [info, ("/odom", odometry(STAMP - 150 * MS, 1.0, 2.0, 0.0, 0.0, 0.0), ODOM),
                  (img, compressed_image(STAMP, b"\xff\xd8\xff\xe0jpeg"), IMAGE),
                  "no odom sample within 100 ms"],
        "image": [info, odom, (img, compressed_image(STAMP, b"\x00" * 64, "rgb8"), IMAGE),
                  "format 'rgb8' is not JPEG or PNG"],
        "image ": [info, odom, (img, compressed_image(STAMP, b"\xff" * (MAX_IMAGE_BYTES + 1)),
                                IMAGE), f"not within 4..{MAX_IMAGE_BYTES}"],
        "stamp": [info, odom, (img, compressed_image(0, b"\xff\xd8\xff\xe0jpeg"), IMAGE),
                  "header.stamp is 0"],
    }


@pytest.mark.parametrize("case", list(_bad_camera_inputs()))
def test_bad_camera_input_is_refused_counted_and_reported(cam: Rig, case: str) -> None:
    *inputs, text = _bad_camera_inputs()[case]
    reason = case.strip()
    for topic, msg, msg_type in inputs:  # type: ignore[misc]
        cam.ros_put(rmw_key(topic, msg_type), msg, msg_type)
    c = cam.counters("s1")
    assert c["refused"] == 1 and c[f"refused_{reason}"] == 1, c
    (err,) = cam.errors("s1")
    assert err.reason.startswith(f"ros2 {reason}:") and text in err.reason, err.reason
    assert err.t_ns == NOW and not _frames(cam)


def test_a_refused_camera_info_keeps_the_previous_calibration(cam: Rig) -> None:
    cam.ros_put(rmw_key("/camera/camera_info", INFO), camera_info(STAMP), INFO)
    cam.ros_put(rmw_key("/camera/camera_info", INFO), camera_info(STAMP, K=[0.0] * 9), INFO)
    cam.ros_put(rmw_key("/odom", ODOM), odometry(STAMP, 1.0, 2.0, 0.0, 0.0, 0.0), ODOM)
    cam.ros_put(rmw_key("/camera/image_raw/compressed", IMAGE),
                compressed_image(STAMP, _jpeg()), IMAGE)
    (f,) = _frames(cam)
    assert f.pinhole is not None and f.pinhole.K == CAMERA_K
    assert cam.counters("s1")["refused_camera_info"] == 1


def test_camera_topics_are_announced_and_listed() -> None:
    rig = make_rig(specs=(unicycle_spec("s1", camera=camera_binding()),))
    tokens = rig.bridge.tokens()
    assert any("%camera%image_raw%compressed/sensor_msgs::msg::dds_::CompressedImage_/" in t
               for t in tokens)
    assert any("%camera%camera_info/sensor_msgs::msg::dds_::CameraInfo_/" in t for t in tokens)
    inputs = rig.bridge.status()["sessions"]["s1"]["inputs"]
    assert inputs["camera"]["type"] == IMAGE and inputs["camera_info"]["type"] == INFO
    rig.bridge.close()


def test_a_camera_needs_a_bound_pose_sensor_with_x_y_yaw() -> None:
    spec = unicycle_spec("s1")
    assert spec.ros2 is not None
    sensors = spec.ros2.sensors
    for pose_sensor in ("lidar", "imu"):  # not bound; bound without x, y, yaw
        with pytest.raises(ValidationError, match="with fields x, y and yaw"):
            Ros2Binding(sensors=sensors, camera=CameraBinding(pose_sensor=pose_sensor,
                                                              mount=MOUNT))
    # a spec without a camera encodes as before (no "camera" key); with one, it round-trips
    assert b"camera" not in wire_encode(spec)
    with_cam = unicycle_spec("s1", camera=camera_binding())
    assert wire_decode(wire_encode(with_cam), SessionSpec) == with_cam


def test_camera_messages_round_trip_through_cdr() -> None:
    """The typestore's CDR of both camera types decodes back (what pd-ros2 reads)."""
    from pd_service.ros2.messages import decode

    info = camera_info(NOW)
    back = decode(encode(info, INFO), INFO)
    assert list(back.k) == CAMERA_K and back.distortion_model == "plumb_bob"  # type: ignore[union-attr]
    img = compressed_image(NOW, b"abcd")
    assert bytes(decode(encode(img, IMAGE), IMAGE).data) == b"abcd"  # type: ignore[union-attr]
