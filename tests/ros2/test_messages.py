"""CDR round trips through the rosbags typestore (ROS 2 Jazzy) for every bound type, RIHS01
hashes from the library, and refusal of payloads that are not CDR of the bound type."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.ros2.errors import Ros2DecodeError
from pd_service.ros2.extract import (
    odometry_from_state,
    path_from_points,
    pose_from_state,
    tf_from_state,
)
from pd_service.ros2.messages import (
    MESSAGE_TYPES,
    Imu,
    PointStamped,
    PoseStamped,
    Range,
    RosMessage,
    Twist,
    TwistStamped,
    decode,
    encode,
    header,
    type_hash,
    typestore,
)
from pd_service.wire.ros2 import StateLayout
from tests.ros2.specs import camera_info, compressed_image

STAMP = 1_700_000_000_250_000_000


def _vec(x: float, y: float, z: float):  # type: ignore[no-untyped-def]
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3 as V

    return V(x=x, y=y, z=z)


def samples() -> dict[str, RosMessage]:
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Point as Point
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Pose as Pose
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Quaternion as Q

    x = np.array([1.0, -2.0, 0.3, 0.5, 0.1])
    P = np.diag([0.1, 0.2, 0.01, 0.05, 0.02])
    layout = StateLayout(x=0, y=1, yaw=2, vx=3, yaw_rate=4)
    cov9 = np.zeros(9)
    cov9[8] = 0.004
    return {
        "nav_msgs/msg/Odometry": odometry_from_state(x, P, layout, STAMP, "odom"),
        "geometry_msgs/msg/PoseWithCovarianceStamped": pose_from_state(x, P, layout, STAMP, "map"),
        "geometry_msgs/msg/PoseStamped": PoseStamped(
            header=header(STAMP, "map"),
            pose=Pose(position=Point(x=1.0, y=2.0, z=0.0), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)),
        ),
        "geometry_msgs/msg/PointStamped": PointStamped(
            header=header(STAMP, "map"), point=Point(x=1.5, y=-0.5, z=2.0)
        ),
        "sensor_msgs/msg/Range": Range(
            header=header(STAMP, "sonar"),
            radiation_type=0,
            field_of_view=0.5,
            min_range=0.1,
            max_range=4.0,
            range=1.25,
            variance=0.0,
        ),
        "sensor_msgs/msg/Imu": Imu(
            header=header(STAMP, "imu"),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8),
            angular_velocity=_vec(0.0, 0.0, 0.3),
            angular_velocity_covariance=cov9,
            linear_acceleration=_vec(0.1, 0.0, 9.8),
            linear_acceleration_covariance=np.zeros(9),
        ),
        "geometry_msgs/msg/Twist": Twist(linear=_vec(0.5, 0.0, 0.0), angular=_vec(0.0, 0.0, -0.2)),
        "geometry_msgs/msg/TwistStamped": TwistStamped(
            header=header(STAMP, "base_link"),
            twist=Twist(linear=_vec(0.5, 0.0, 0.0), angular=_vec(0.0, 0.0, -0.2)),
        ),
        "tf2_msgs/msg/TFMessage": tf_from_state(x, layout, STAMP, "odom"),
        "nav_msgs/msg/Path": path_from_points([STAMP, STAMP + 50_000_000],
                                              np.array([[1.0, -2.0, 0.3], [1.1, -2.1, 0.35]]),
                                              [0, 1, 2], layout, "odom"),
        "sensor_msgs/msg/CompressedImage": compressed_image(STAMP, b"\xff\xd8\xff\xe0 a jpeg"),
        "sensor_msgs/msg/CameraInfo": camera_info(STAMP),
    }


def _assert_same(a: object, b: object) -> None:
    if isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, np.asarray(b))
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b)
        for u, v in zip(a, b, strict=True):
            _assert_same(u, v)
    elif hasattr(a, "__dataclass_fields__"):
        assert type(a) is type(b)
        for name in a.__dataclass_fields__:
            _assert_same(getattr(a, name), getattr(b, name))
    elif isinstance(a, float):
        assert a == pytest.approx(b, rel=1e-6)  # Range is float32 on the wire
    else:
        assert a == b


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES)
def test_round_trip(msg_type: str) -> None:
    msg = samples()[msg_type]
    raw = encode(msg, msg_type)
    assert raw[:4] == b"\x00\x01\x00\x00"  # little-endian CDR encapsulation
    back = decode(raw, msg_type)
    _assert_same(msg, back)
    assert encode(back, msg_type) == raw
    # the typestore's own serializer agrees (no hand-written path)
    assert bytes(typestore().serialize_cdr(msg, msg_type)) == raw


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES)
def test_big_endian_payload_decodes(msg_type: str) -> None:
    msg = samples()[msg_type]
    raw = bytes(typestore().serialize_cdr(msg, msg_type, little_endian=False))
    assert raw[:2] == b"\x00\x00"
    assert encode(decode(raw, msg_type), msg_type) == encode(msg, msg_type)


def test_type_hashes_come_from_the_typestore() -> None:
    for t in MESSAGE_TYPES:
        h = type_hash(t)
        assert h.startswith("RIHS01_") and len(h) == 7 + 64
        assert h == typestore().hash_rihs01(t)
    assert len({type_hash(t) for t in MESSAGE_TYPES}) == len(MESSAGE_TYPES)
    # also printed by other rmw_zenoh users for tf2_msgs/msg/TFMessage (cross-check)
    assert type_hash("tf2_msgs/msg/TFMessage") == (
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    )


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES)
def test_invalid_payloads_refused(msg_type: str) -> None:
    raw = encode(samples()[msg_type], msg_type)
    for bad in (b"", b"\x00\x01", b"\x07\x01\x00\x00" + raw[4:], raw[: len(raw) // 2], raw + b"\x00" * 8):
        with pytest.raises(Ros2DecodeError) as info:
            decode(bad, msg_type)
        assert msg_type in info.value.reason


def test_payload_of_another_type_refused() -> None:
    raw = encode(samples()["nav_msgs/msg/Odometry"], "nav_msgs/msg/Odometry")
    with pytest.raises(Ros2DecodeError):
        decode(raw, "geometry_msgs/msg/Twist")


def test_unsupported_type_and_wrong_class() -> None:
    with pytest.raises(ValueError):
        type_hash("std_msgs/msg/String")
    with pytest.raises(TypeError):
        encode(samples()["geometry_msgs/msg/Twist"], "nav_msgs/msg/Odometry")
