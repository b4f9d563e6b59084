"""Measurement / command extraction from ROS messages and the predicted-state outputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from pd_service.ros2.errors import Ros2DecodeError
from pd_service.ros2.extract import (
    UNOBSERVED_VARIANCE,
    decode_measurement,
    extract_command,
    extract_measurement,
    odometry_from_state,
    pose_from_state,
    quaternion_of_yaw,
    tf_from_state,
    yaw_of,
)
from pd_service.ros2.messages import decode, encode, time_msg
from pd_service.wire.ros2 import CommandBinding, StateLayout, TopicBinding
from tests.ros2.test_messages import STAMP, samples

X = np.array([1.0, -2.0, 0.3, 0.5, 0.1])
P = np.array(
    [
        [0.1, 0.02, 0.0, 0.0, 0.0],
        [0.02, 0.2, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.01, 0.0, 0.003],
        [0.0, 0.0, 0.0, 0.05, 0.0],
        [0.0, 0.0, 0.003, 0.0, 0.02],
    ]
)
LAYOUT = StateLayout(x=0, y=1, yaw=2, vx=3, yaw_rate=4)


def test_odometry_round_trip_through_cdr_and_extraction() -> None:
    odom = odometry_from_state(X, P, LAYOUT, STAMP, "odom")
    binding = TopicBinding(
        topic="/odom",
        msg_type="nav_msgs/msg/Odometry",
        fields=["x", "y", "yaw", "vx", "yaw_rate"],
        frame="odom",
    )
    s = decode_measurement(binding, encode(odom, "nav_msgs/msg/Odometry"))
    np.testing.assert_allclose(s.z, X, atol=1e-12)
    assert s.R is not None and s.stamp_ns == STAMP and s.frame_id == "odom"
    # pose block and twist block from P; the yaw / yaw-rate cross term is not representable
    expected = P.copy()
    expected[2, 4] = expected[4, 2] = 0.0
    np.testing.assert_allclose(s.R, expected, atol=1e-15)


def test_unobserved_axes_are_marked() -> None:
    odom = odometry_from_state(X, P, LAYOUT, STAMP, "odom")
    cp = np.asarray(odom.pose.covariance).reshape(6, 6)
    ct = np.asarray(odom.twist.covariance).reshape(6, 6)
    for i in (2, 3, 4):
        assert cp[i, i] == UNOBSERVED_VARIANCE and not np.any(np.delete(cp[i], i))
    for i in (1, 2, 3, 4):  # vy absent from the layout, vz, wx, wy
        assert ct[i, i] == UNOBSERVED_VARIANCE
    assert cp[0, 1] == 0.02 and cp[5, 5] == 0.01 and ct[0, 0] == 0.05 and ct[5, 5] == 0.02
    assert odom.child_frame_id == "base_link_predicted"
    assert yaw_of(odom.pose.pose.orientation) == pytest.approx(0.3)


def test_world_velocities_rotated_into_body_frame() -> None:
    x = np.array([0.0, 0.0, math.pi / 2, 1.0, 0.0])  # heading north, moving east in the world
    layout = StateLayout(x=0, y=1, yaw=2, vx=3, vy=4, velocity_frame="world")
    P = np.diag([1.0, 1.0, 0.04, 0.01, 0.01])
    odom = odometry_from_state(x, P, layout, STAMP, "map")
    assert odom.twist.twist.linear.x == pytest.approx(0.0, abs=1e-12)
    assert odom.twist.twist.linear.y == pytest.approx(-1.0)
    ct = np.asarray(odom.twist.covariance).reshape(6, 6)
    # var(vy_b) = var(vx_w) s^2 + var(vy_w) c^2 + vx_b^2 var(yaw)... d vy_b/d yaw = -vx_b = 0 here
    assert ct[1, 1] == pytest.approx(0.01)
    # d vx_b / d yaw = vy_b = -1: var(vx_b) = 0.01 + 1 * 0.04
    assert ct[0, 0] == pytest.approx(0.05)


def test_world_velocities_without_a_yaw_are_published_as_they_are() -> None:
    """The constant-velocity layout (StateLayout's docstring): no yaw, so the orientation is
    identity and the body frame is the world's; v and its covariance pass unchanged."""
    layout = StateLayout(x=0, vx=1, y=2, vy=3, velocity_frame="world")
    x = np.array([1.0, 0.5, 2.0, -0.25])
    P = np.array([[1.0, 0.1, 0.0, 0.0], [0.1, 0.04, 0.0, 0.01],
                  [0.0, 0.0, 2.0, 0.0], [0.0, 0.01, 0.0, 0.09]])
    odom = odometry_from_state(x, P, layout, STAMP, "map")
    assert (odom.twist.twist.linear.x, odom.twist.twist.linear.y) == (0.5, -0.25)
    assert yaw_of(odom.pose.pose.orientation) == 0.0
    ct = np.asarray(odom.twist.covariance).reshape(6, 6)
    assert ct[:2, :2].tolist() == [[0.04, 0.01], [0.01, 0.09]]
    only_vx = odometry_from_state(x[:2], P[:2, :2], StateLayout(x=0, vx=1, velocity_frame="world"),
                                  STAMP, "map")
    ct = np.asarray(only_vx.twist.covariance).reshape(6, 6)
    assert only_vx.twist.twist.linear.x == 0.5 and ct[0, 0] == 0.04
    assert ct[1, 1] == UNOBSERVED_VARIANCE  # no vy, no yaw: vy_b is unknown, not a certain 0


def test_pose_and_tf_outputs() -> None:
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    assert pose.header.frame_id == "map" and pose.header.stamp == time_msg(STAMP)
    tf = tf_from_state(X, LAYOUT, STAMP, "odom", "base_link_predicted")
    (t,) = tf.transforms
    assert (t.header.frame_id, t.child_frame_id) == ("odom", "base_link_predicted")
    assert (t.transform.translation.x, t.transform.translation.y) == (1.0, -2.0)
    assert yaw_of(t.transform.rotation) == pytest.approx(0.3)
    with pytest.raises(ValueError):
        odometry_from_state(X, P[:3, :3], LAYOUT, STAMP, "odom")
    with pytest.raises(ValueError):
        odometry_from_state(np.array([np.nan, 0, 0, 0, 0]), P, LAYOUT, STAMP, "odom")


def test_unknown_covariance_rule() -> None:
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    pose.pose.covariance[:] = 0.0
    assert extract_measurement(pose, ("x", "y", "yaw")).R is None
    pose.pose.covariance[0] = -1.0
    assert extract_measurement(pose, ("x", "y", "yaw")).R is None
    imu = samples()["sensor_msgs/msg/Imu"]
    s = extract_measurement(imu, ("yaw_rate",))
    assert s.z.tolist() == [0.3] and s.R is not None and s.R[0, 0] == 0.004
    imu.angular_velocity_covariance[0] = -1.0
    assert extract_measurement(imu, ("yaw_rate",)).R is None
    # Odometry: an unknown twist covariance makes the whole R unknown when twist fields are taken
    odom = odometry_from_state(X, P, LAYOUT, STAMP, "odom")
    odom.twist.covariance[:] = 0.0
    assert extract_measurement(odom, ("x", "vx")).R is None
    assert extract_measurement(odom, ("x", "y")).R is not None


def test_messages_without_covariance() -> None:
    m = samples()
    assert extract_measurement(m["geometry_msgs/msg/PointStamped"], ("x", "y", "z")).z.tolist() == [
        1.5,
        -0.5,
        2.0,
    ]
    r = extract_measurement(m["sensor_msgs/msg/Range"], ("range",))
    assert r.z.tolist() == [1.25] and r.R is None and r.stamp_ns == STAMP
    p = extract_measurement(m["geometry_msgs/msg/PoseStamped"], ("yaw", "x"))
    assert p.z.tolist() == [0.0, 1.0] and p.R is None


def test_bad_values_refused() -> None:
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    pose.header.stamp = time_msg(0)
    with pytest.raises(Ros2DecodeError, match="stamp"):
        extract_measurement(pose, ("x",))
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    pose.pose.pose.position.x = float("nan")
    with pytest.raises(Ros2DecodeError, match="x"):
        extract_measurement(pose, ("x", "y"))
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    pose.pose.covariance[0] = -4.0  # negative variance: not PSD
    with pytest.raises(Ros2DecodeError, match="positive semi-definite"):
        extract_measurement(pose, ("x", "y"))
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    pose.pose.covariance[1] = 5.0  # asymmetric
    with pytest.raises(Ros2DecodeError, match="symmetric"):
        extract_measurement(pose, ("x", "y"))
    pose = pose_from_state(X, P, LAYOUT, STAMP, "map")
    pose.pose.pose.orientation.w = 0.0
    pose.pose.pose.orientation.z = 0.0
    with pytest.raises(Ros2DecodeError, match="quaternion"):
        extract_measurement(pose, ("yaw",))
    with pytest.raises(Ros2DecodeError):
        extract_measurement(samples()["geometry_msgs/msg/Twist"], ("x",))


def test_frame_mismatch_refused() -> None:
    b = TopicBinding(
        topic="pose", msg_type="geometry_msgs/msg/PoseWithCovarianceStamped", fields=["x", "y"], frame="map"
    )
    raw = encode(pose_from_state(X, P, LAYOUT, STAMP, "odom"), b.msg_type)
    with pytest.raises(Ros2DecodeError, match="frame_id"):
        decode_measurement(b, raw)


def test_commands() -> None:
    m = samples()
    c = extract_command(
        decode(encode(m["geometry_msgs/msg/Twist"], "geometry_msgs/msg/Twist"), "geometry_msgs/msg/Twist")
    )
    assert c.u.tolist() == [0.5, -0.2] and c.stamp_ns is None
    c = extract_command(m["geometry_msgs/msg/TwistStamped"])
    assert c.u.tolist() == [0.5, -0.2] and c.stamp_ns == STAMP
    ts = m["geometry_msgs/msg/TwistStamped"]
    ts.header.stamp = time_msg(0)
    with pytest.raises(Ros2DecodeError):
        extract_command(ts)
    with pytest.raises(Ros2DecodeError):
        extract_command(m["sensor_msgs/msg/Range"])


def test_yaw_quaternion_round_trip() -> None:
    for yaw in np.linspace(-3.1, 3.1, 13):
        assert yaw_of(quaternion_of_yaw(float(yaw))) == pytest.approx(yaw)


def test_bindings_validate_and_have_a_schema() -> None:
    with pytest.raises(ValidationError):
        TopicBinding(topic="/imu", msg_type="sensor_msgs/msg/Imu", fields=["x",])
    with pytest.raises(ValidationError):
        TopicBinding(topic="/a//b", msg_type="sensor_msgs/msg/Range", fields=["range",])
    with pytest.raises(ValidationError):
        TopicBinding(topic="/odom", msg_type="nav_msgs/msg/Odometry", fields=["x", "x"])
    with pytest.raises(ValidationError):
        TopicBinding(topic="/odom", msg_type="nav_msgs/msg/Odometry", fields=[])
    b = TopicBinding.model_validate(
        {"topic": "odom", "msg_type": "nav_msgs/msg/Odometry", "fields": ["x", "y", "yaw"]}
    )
    assert TopicBinding.model_validate_json(b.model_dump_json()) == b
    schema = TopicBinding.model_json_schema()
    assert "nav_msgs/msg/Odometry" in schema["properties"]["msg_type"]["enum"]
    assert CommandBinding().topic == "cmd_vel"
    CommandBinding.model_json_schema()
