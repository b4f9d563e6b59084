"""The ROS 2 message types pd-service binds, their CDR encoding and RIHS01 type hashes, all from
the ``rosbags`` typestore of ROS 2 Jazzy (no hand-written serializers).

A payload on the wire is CDR with its 4-byte encapsulation header (``00 01 00 00`` for
little-endian CDR, ``00 00 00 00`` big-endian), exactly what rmw_zenoh_cpp and
zenoh-bridge-ros2dds carry.
"""

from __future__ import annotations

from functools import cache
from typing import Literal, TypeAlias, get_args

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore
from rosbags.typesys.stores.ros2_jazzy import (
    builtin_interfaces__msg__Time as Time,
)
from rosbags.typesys.stores.ros2_jazzy import (
    diagnostic_msgs__msg__DiagnosticArray as DiagnosticArray,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__PointStamped as PointStamped,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__PoseStamped as PoseStamped,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__PoseWithCovarianceStamped as PoseWithCovarianceStamped,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Twist as Twist,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__TwistStamped as TwistStamped,
)
from rosbags.typesys.stores.ros2_jazzy import (
    nav_msgs__msg__Odometry as Odometry,
)
from rosbags.typesys.stores.ros2_jazzy import (
    nav_msgs__msg__Path as Path,
)
from rosbags.typesys.stores.ros2_jazzy import (
    sensor_msgs__msg__CameraInfo as CameraInfo,
)
from rosbags.typesys.stores.ros2_jazzy import (
    sensor_msgs__msg__CompressedImage as CompressedImage,
)
from rosbags.typesys.stores.ros2_jazzy import (
    sensor_msgs__msg__Imu as Imu,
)
from rosbags.typesys.stores.ros2_jazzy import (
    sensor_msgs__msg__Range as Range,
)
from rosbags.typesys.stores.ros2_jazzy import (
    std_msgs__msg__Header as Header,
)
from rosbags.typesys.stores.ros2_jazzy import (
    tf2_msgs__msg__TFMessage as TFMessage,
)

from pd_service.ros2.errors import Ros2DecodeError
from pd_service.wire.ros2 import CommandType, MeasurementType

#: Output message types pd-service publishes.
OutputType = Literal[
    "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseWithCovarianceStamped", "tf2_msgs/msg/TFMessage",
    "nav_msgs/msg/Path",
]
#: The camera's message types (CameraBinding): images and their calibration.
CameraType = Literal["sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"]
MessageType = Literal[MeasurementType, CommandType, OutputType, CameraType]

#: Every message type of this module.
MESSAGE_TYPES: tuple[str, ...] = tuple(dict.fromkeys(
    get_args(MeasurementType) + get_args(CommandType) + get_args(OutputType)
    + get_args(CameraType)))

RosMessage: TypeAlias = (
    Odometry
    | PoseWithCovarianceStamped
    | PoseStamped
    | PointStamped
    | Range
    | Imu
    | Twist
    | TwistStamped
    | TFMessage
    | Path
    | CompressedImage
    | CameraInfo
)

_CLASSES: dict[str, type] = {
    "nav_msgs/msg/Odometry": Odometry,
    "geometry_msgs/msg/PoseWithCovarianceStamped": PoseWithCovarianceStamped,
    "geometry_msgs/msg/PoseStamped": PoseStamped,
    "geometry_msgs/msg/PointStamped": PointStamped,
    "sensor_msgs/msg/Range": Range,
    "sensor_msgs/msg/Imu": Imu,
    "geometry_msgs/msg/Twist": Twist,
    "geometry_msgs/msg/TwistStamped": TwistStamped,
    "tf2_msgs/msg/TFMessage": TFMessage,
    "nav_msgs/msg/Path": Path,
    "sensor_msgs/msg/CompressedImage": CompressedImage,
    "sensor_msgs/msg/CameraInfo": CameraInfo,
    # published by pd-ros2 itself on /diagnostics (pd_service.ros2.diagnostics)
    "diagnostic_msgs/msg/DiagnosticArray": DiagnosticArray,
}

_ROS_MESSAGE_CLASSES = (
    Odometry,
    PoseWithCovarianceStamped,
    PoseStamped,
    PointStamped,
    Range,
    Imu,
    Twist,
    TwistStamped,
    TFMessage,
    Path,
    CompressedImage,
    CameraInfo,
)

#: CDR encapsulation headers (representation id, options): plain CDR little / big endian.
CDR_LE = b"\x00\x01\x00\x00"
CDR_BE = b"\x00\x00\x00\x00"


@cache
def typestore() -> Typestore:
    """The rosbags typestore of ROS 2 Jazzy message definitions (built once)."""
    return get_typestore(Stores.ROS2_JAZZY)


def _check_type(msg_type: str) -> None:
    if msg_type not in _CLASSES:
        raise ValueError(f"{msg_type!r} is not a message type pd-service binds ({', '.join(_CLASSES)})")


@cache
def type_hash(msg_type: str) -> str:
    """The RIHS01 type hash (``RIHS01_<64 hex>``, REP-2016) of ``msg_type`` in Jazzy, computed by
    the typestore from the type description; rmw_zenoh puts it in keys and tokens."""
    _check_type(msg_type)
    return typestore().hash_rihs01(msg_type)


def encode(msg: RosMessage, msg_type: str) -> bytes:
    """CDR bytes (little-endian, with encapsulation header) of ``msg``, which must be an instance
    of ``msg_type``'s class."""
    _check_type(msg_type)
    if not isinstance(msg, _CLASSES[msg_type]):
        raise TypeError(f"expected a {msg_type} message, got {type(msg).__name__}")
    return bytes(typestore().serialize_cdr(msg, msg_type))


def decode(payload: bytes | bytearray | memoryview, msg_type: str) -> RosMessage:
    """Parse CDR ``payload`` as ``msg_type``. Raises Ros2DecodeError when the payload is not
    valid CDR for the type: a missing or unknown encapsulation header, too few bytes, a string
    that is not UTF-8, an array length past the end, or bytes left over beyond CDR's final
    alignment padding (at most 3; the typestore checks the size)."""
    _check_type(msg_type)
    raw = bytes(payload)
    if len(raw) < 4:
        raise Ros2DecodeError(f"{msg_type}: payload of {len(raw)} bytes has no CDR header")
    if raw[:2] not in (CDR_LE[:2], CDR_BE[:2]):
        raise Ros2DecodeError(f"{msg_type}: unknown CDR encapsulation {raw[:4].hex()}")
    try:
        msg = typestore().deserialize_cdr(raw, msg_type)
    except (SerdeError, UnicodeDecodeError, ValueError, IndexError) as exc:
        raise Ros2DecodeError(f"{msg_type}: not valid CDR ({exc})") from None
    if not isinstance(msg, _ROS_MESSAGE_CLASSES) or not isinstance(msg, _CLASSES[msg_type]):
        raise Ros2DecodeError(f"{msg_type}: typestore returned {type(msg).__name__}")  # pragma: no cover
    return msg


def time_msg(stamp_ns: int) -> Time:
    """``builtin_interfaces/Time`` of a stamp in ns since the epoch (sec, nanosec >= 0)."""
    if stamp_ns < 0:
        raise ValueError(f"stamp {stamp_ns} ns is negative")
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if sec >= 2**31:
        raise ValueError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 s)")
    return Time(sec=sec, nanosec=nanosec)


def stamp_ns(stamp: Time) -> int:
    """ns since the epoch of a ``builtin_interfaces/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header(stamp: int, frame_id: str) -> Header:
    """``std_msgs/Header`` with ``stamp`` in ns since the epoch."""
    return Header(stamp=time_msg(stamp), frame_id=frame_id)
