"""Topic bindings: which ROS 2 topic feeds a sensor or the commands, its message type, and what to
take from it. Pydantic models with JSON-Schema-friendly types (to be part of the session spec)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from pd_service.ros2.keys import check_topic_name
from pd_service.ros2.messages import CommandType, MeasurementType

#: A quantity a measurement binding can take from a message. Units: m, rad, m/s, rad/s.
#: ``x``, ``y``, ``z``: position; ``yaw``: heading from the orientation quaternion;
#: ``vx``, ``vy``: body-frame linear velocity (Odometry twist, in ``child_frame_id``);
#: ``yaw_rate``: angular velocity about z; ``range``: sensor_msgs/Range ``range``.
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


class TopicBinding(BaseModel):
    """One sensor fed by a ROS 2 topic.

    ``fields`` are taken in the order given and form the measurement vector z. ``frame``, when
    set, must equal the message's ``header.frame_id`` (else the sample is refused).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    topic: str = Field(description="ROS 2 topic name, absolute or relative to the namespace")
    msg_type: MeasurementType
    fields: tuple[FieldName, ...] = Field(min_length=1)
    frame: str | None = Field(default=None, min_length=1)

    @field_validator("topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return check_topic_name(value)

    @model_validator(mode="after")
    def _fields_of_type(self) -> TopicBinding:
        allowed = FIELDS_BY_TYPE[self.msg_type]
        bad = [f for f in self.fields if f not in allowed]
        if bad:
            raise ValueError(f"{self.msg_type} has no field(s) {bad}; it has {list(allowed)}")
        if len(set(self.fields)) != len(self.fields):
            raise ValueError(f"fields {list(self.fields)} repeat a field")
        return self


class CommandBinding(BaseModel):
    """The operator's velocity commands (``cmd_vel``): command vector u = (vx, yaw_rate)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    topic: str = "cmd_vel"
    msg_type: CommandType = "geometry_msgs/msg/Twist"

    @field_validator("topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return check_topic_name(value)
