"""SessionSpec.ros2: topic bindings are checked against the spec's sensors and state."""

from __future__ import annotations

import msgpack
import pytest

from pd_service.wire import SessionSpec, WireError, decode, encode
from pd_service.wire.ros2 import OutputBinding, Ros2Binding, StateLayout, TopicBinding
from tests.wire.factories import paper_spec

POINT = "geometry_msgs/msg/PointStamped"


def with_ros2(binding: Ros2Binding) -> bytes:
    """The paper spec's wire bytes with a ``ros2`` entry added."""
    raw = msgpack.unpackb(encode(paper_spec()))
    raw["ros2"] = binding.model_dump()
    return msgpack.packb(raw)


@pytest.mark.parametrize("binding, reason", [
    (Ros2Binding(sensors={"lidar": TopicBinding(topic="p", msg_type=POINT, fields=["x"])}),
     "ros2.sensors.lidar: no sensor of that name"),
    (Ros2Binding(sensors={"camera": TopicBinding(topic="p", msg_type=POINT, fields=["x"])}),
     "ros2.sensors.camera.fields: has 1 values but sensor 'camera' measures m=2"),
    (Ros2Binding(outputs=OutputBinding(layout=StateLayout(x=0, y=4))),
     "ros2.outputs.layout.y: 4 must be < n=4"),
])
def test_bindings_must_fit_the_spec(binding: Ros2Binding, reason: str) -> None:
    with pytest.raises(WireError, match=reason.replace("[", r"\[").replace("]", r"\]")):
        decode(with_ros2(binding), SessionSpec)


@pytest.mark.parametrize("topic", ["/a//b", "1abc", "a/", "~/x", ""])
def test_topic_names_are_ros2_names(topic: str) -> None:
    with pytest.raises(ValueError, match="not a ROS 2 topic name|string"):
        TopicBinding(topic=topic, msg_type=POINT, fields=["x"])


def test_a_fitting_binding_is_accepted() -> None:
    binding = Ros2Binding(
        sensors={"camera": TopicBinding(topic="/cam", msg_type=POINT, fields=["x", "y"]),
                 "ranger": TopicBinding(topic="range", msg_type="sensor_msgs/msg/Range",
                                        fields=["range"])},
        outputs=OutputBinding(layout=StateLayout(x=0, vx=1, y=2, vy=3, velocity_frame="world")))
    spec = decode(with_ros2(binding), SessionSpec)
    assert spec.ros2 == binding
