"""ROS 2 topic bindings of a session (``SessionSpec.ros2``): which ROS 2 topic feeds each
sensor and the commands, what to take from each message, and what pd-service publishes back.

Only the description lives here (the wire layer builds nothing); ``pd_service.ros2`` turns it
into rmw_zenoh keys, CDR decoding and messages, and the ``pd-ros2`` bridge serves it.
Units: m, rad, m/s, rad/s. Topic names follow ROS 2: absolute ``/a/b`` or relative ``a/b``
(resolved under the bridge's namespace).
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

from pydantic import (
    Field,
    SerializerFunctionWrapHandler,
    StringConstraints,
    field_validator,
    model_serializer,
    model_validator,
)

from .base import WireModel, invalid
from .pinhole import CameraMount

#: Sensor message types a measurement binding may name.
MeasurementType = Literal[
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PointStamped",
    "sensor_msgs/msg/Range",
    "sensor_msgs/msg/Imu",
]
#: Command message types (the operator's ``cmd_vel``).
CommandType = Literal["geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped"]

#: A quantity a measurement binding can take from a message. ``x``, ``y``, ``z``: position;
#: ``yaw``: heading from the orientation quaternion; ``vx``, ``vy``: body-frame linear velocity
#: (Odometry twist, in ``child_frame_id``); ``yaw_rate``: angular velocity about z;
#: ``range``: sensor_msgs/Range ``range``.
FieldName = Literal["x", "y", "z", "yaw", "vx", "vy", "yaw_rate", "range"]

#: The fields each measurement type carries.
FIELDS_BY_TYPE: dict[str, tuple[FieldName, ...]] = {
    "nav_msgs/msg/Odometry": ("x", "y", "yaw", "vx", "vy", "yaw_rate"),
    "geometry_msgs/msg/PoseWithCovarianceStamped": ("x", "y", "yaw"),
    "geometry_msgs/msg/PoseStamped": ("x", "y", "yaw"),
    "geometry_msgs/msg/PointStamped": ("x", "y", "z"),
    "sensor_msgs/msg/Range": ("range",),
    "sensor_msgs/msg/Imu": ("yaw_rate",),
}

_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_TOPIC = re.compile(rf"^/?{_TOKEN}(/{_TOKEN})*$")
_FRAME = r"^[A-Za-z0-9_][A-Za-z0-9_/.-]{0,127}$"
Frame = Annotated[str, StringConstraints(pattern=_FRAME)]
StateIndex = Annotated[int, Field(ge=0, lt=64)]


def check_topic_name(name: str) -> str:
    """Return ``name`` if it is a ROS 2 topic name pd-service accepts (absolute ``/a/b`` or
    relative ``a/b``; no ``~``, no substitutions, no ``//``, no trailing ``/``), else raise
    ValueError naming the problem."""
    if not _TOPIC.match(name):
        raise ValueError(
            f"{name!r} is not a ROS 2 topic name (tokens of letters, digits and '_', not starting "
            "with a digit, separated by single '/')"
        )
    return name


class _Topic(WireModel):
    topic: Annotated[str, StringConstraints(max_length=256)]

    @field_validator("topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return check_topic_name(value)


class TopicBinding(_Topic):
    """One sensor fed by a ROS 2 topic. ``fields`` are taken in the order given and form the
    measurement vector z (so their number is the sensor's dimension). ``frame``, when set, must
    equal the message's ``header.frame_id`` (else the sample is refused)."""

    topic: Annotated[str, StringConstraints(max_length=256)] = Field(
        description="ROS 2 topic name, absolute or relative to the bridge's namespace.")
    msg_type: MeasurementType = Field(description="ROS 2 message type.")
    fields: Annotated[list[FieldName], Field(min_length=1, max_length=6)] = Field(
        description="Quantities taken from each message, in the order of z.")
    frame: Frame | None = Field(None, description="Required header.frame_id, if any.")

    @model_validator(mode="after")
    def _fields_of_type(self) -> TopicBinding:
        allowed = FIELDS_BY_TYPE[self.msg_type]
        bad = [f for f in self.fields if f not in allowed]
        if bad:
            raise invalid("fields", f"{self.msg_type} has no field(s) {bad}; it has {list(allowed)}")
        if len(set(self.fields)) != len(self.fields):
            raise invalid("fields", f"{list(self.fields)} repeat a field")
        return self


class CommandBinding(_Topic):
    """The operator's velocity commands: command vector u = (linear.x, angular.z). A Twist
    applies at the step the bridge receives it (plus the session's lead, like every command);
    a TwistStamped at the step of its ``header.stamp`` plus the lead."""

    topic: Annotated[str, StringConstraints(max_length=256)] = Field(
        "cmd_vel", description="ROS 2 topic of the velocity commands.")
    msg_type: CommandType = Field("geometry_msgs/msg/Twist", description="Twist or TwistStamped.")


class StateLayout(WireModel):
    """Where the planar quantities sit in the state vector (None: not in the state).
    ``velocity_frame``: ``body`` when (vx, vy) are along / across the heading (a unicycle's v
    is vx), ``world`` when they are in the session frame (a constant-velocity model). World
    velocities are published in the body frame, turned by the state's yaw; without a yaw the
    orientation is written as identity, so they are published as they are."""

    x: StateIndex | None = None
    y: StateIndex | None = None
    yaw: StateIndex | None = None
    vx: StateIndex | None = None
    vy: StateIndex | None = None
    yaw_rate: StateIndex | None = None
    velocity_frame: Literal["body", "world"] = "body"

    def indices(self) -> dict[str, int]:
        """Quantity name -> state index, for the quantities the state holds."""
        names = ("x", "y", "yaw", "vx", "vy", "yaw_rate")
        return {n: i for n in names if (i := getattr(self, n)) is not None}


#: OutputBinding.path_topic's default.
DEFAULT_PATH_TOPIC = "predicted/path"


class OutputBinding(WireModel):
    """What pd-service publishes per prediction: nav_msgs/Odometry on ``odom_topic``,
    geometry_msgs/PoseWithCovarianceStamped on ``pose_topic`` (None: not published) and, with
    ``tf``, a tf2_msgs/TFMessage on ``/tf`` from ``frame_id`` to ``child_frame_id``; stamped
    with the time of the predicted step. With the spec's ``path``, each PredictedPath as a
    nav_msgs/Path on ``path_topic`` (its covariances are not carried: no standard message
    holds a path's; the target's is on ``pose_topic``)."""

    odom_topic: Annotated[str, StringConstraints(max_length=256)] | None = Field(
        "predicted/odom", description="Odometry of the predicted state (None: off).")
    pose_topic: Annotated[str, StringConstraints(max_length=256)] | None = Field(
        "predicted/pose", description="PoseWithCovarianceStamped of the prediction (None: off).")
    path_topic: Annotated[str, StringConstraints(max_length=256)] | None = Field(
        DEFAULT_PATH_TOPIC, description="nav_msgs/Path of the predicted path, published when "
                                      "the spec has ``path`` (None: off).")
    tf: bool = Field(True, description="Publish the predicted pose on /tf.")
    frame_id: Frame = Field("odom", description="The session's (world) frame.")
    child_frame_id: Frame = Field("base_link_predicted", description="The predicted body frame.")
    layout: StateLayout = Field(description="Where x, y, yaw, velocities sit in the state.")

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out = handler(self)
        if self.path_topic == DEFAULT_PATH_TOPIC:  # the default: the bytes stay as before
            out.pop("path_topic", None)
        return dict(out)

    @field_validator("odom_topic", "pose_topic", "path_topic")
    @classmethod
    def _topic(cls, value: str | None) -> str | None:
        return None if value is None else check_topic_name(value)


class CameraBinding(WireModel):
    """The robot's camera, for the displays' ghost (the daemon never reads it): a
    ``sensor_msgs/CompressedImage`` topic (JPEG or PNG) and the ``sensor_msgs/CameraInfo`` of
    that camera (its K, distortion model and D). Each image becomes a CameraFrame with a
    pinhole view (:mod:`pd_service.wire.pinhole`): the camera's ``mount`` on the robot (a
    static extrinsic, as in the robot's URDF) and the robot's pose at the image's
    ``header.stamp``, taken from ``pose_sensor`` (a bound sensor with fields x, y and yaw):
    its sample stamped nearest the image, within ``pose_tolerance_ms``, else the image is
    refused."""

    image_topic: Annotated[str, StringConstraints(max_length=256)] = Field(
        "camera/image_raw/compressed", description="sensor_msgs/CompressedImage topic.")
    info_topic: Annotated[str, StringConstraints(max_length=256)] = Field(
        "camera/camera_info", description="sensor_msgs/CameraInfo topic.")
    pose_sensor: Annotated[str, StringConstraints(max_length=64)] = Field(
        description="The bound sensor giving the robot's x, y, yaw at capture.")
    pose_tolerance_ms: Annotated[float, Field(gt=0.0, le=10_000.0)] = Field(
        100.0, description="Largest |pose stamp - image stamp|, ms.")
    mount: CameraMount = Field(description="The camera's link frame in the robot's body frame.")

    @field_validator("image_topic", "info_topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return check_topic_name(value)


class Ros2Binding(WireModel):
    """A session's ROS 2 topics: ``sensors`` maps a sensor name of the spec to its topic;
    ``camera`` (optional) the robot's camera for the displays."""

    sensors: Annotated[dict[Annotated[str, StringConstraints(max_length=64)], TopicBinding],
                       Field(max_length=16)] = Field(
        default_factory=dict, description="Sensor name -> topic binding.")
    commands: CommandBinding | None = Field(None, description="Velocity commands, if bound.")
    outputs: OutputBinding | None = Field(None, description="Predicted pose outputs, if any.")
    camera: CameraBinding | None = Field(None, description="The robot's camera, if bound.")

    @model_validator(mode="after")
    def _camera_pose(self) -> Ros2Binding:
        cam = self.camera
        if cam is not None:
            pose = self.sensors.get(cam.pose_sensor)
            if pose is None or not {"x", "y", "yaw"} <= set(pose.fields):
                raise invalid("camera.pose_sensor", f"{cam.pose_sensor!r} is not a bound sensor "
                                                    "with fields x, y and yaw")
        return self

    @model_serializer(mode="wrap")
    def _serialize(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        out = handler(self)
        if self.camera is None:  # no camera: the bytes stay as before
            out.pop("camera", None)
        return dict(out)
