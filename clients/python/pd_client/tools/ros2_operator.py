"""The scripted operator's ROS 2 face (``pd-operator --ros2``): a node ``operator`` that
publishes the scenario's commands as ``geometry_msgs/Twist`` (or ``TwistStamped``) on the
session's bound command topic (``cmd_vel``), in rmw_zenoh's format (``pd_service.ros2``).

On the wire, as ``rmw_zenoh_cpp`` (ROS 2 Jazzy) does it:

* data key ``<domain>/<topic>/<dds type>/<RIHS01 hash>`` (the plain key: pd-ros2 reads it, and
  pd-link's ``deploy/link-ros2.toml`` carries it to the robot as ``robot/<key>`` with the uplink
  delay);
* payload: CDR from the rosbags Jazzy typestore; u = (v m/s, yaw rate rad/s) goes to
  ``linear.x`` and ``angular.z``, every other component 0. A TwistStamped's ``header.stamp`` is
  the publication time (ns since the epoch), frame_id ``base_link``;
* attachment: sequence number 1, 2, ..., source timestamp (wall clock, ns), the publisher's GID,
  ``positional`` layout (Jazzy >= 0.2.4);
* liveliness tokens: the node (``NN``) and one ``MP`` for the command topic.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3 as Vector3

from pd_service.ros2.attachment import Attachment, encode_attachment
from pd_service.ros2.keys import NodeIdentity, TopicEndpoint
from pd_service.ros2.messages import Twist, TwistStamped, encode, header, type_hash
from pd_service.transport import Transport
from pd_service.transport.base import Handle, Publisher
from pd_service.wire.ros2 import CommandBinding

from .ros2_robot import Ros2Options, close_quietly, session_id_of

NODE_NAME = "operator"


def twist_message(u: Sequence[float] | np.ndarray, msg_type: str,
                  stamp_ns: int) -> Twist | TwistStamped:
    """The Twist (or TwistStamped stamped ``stamp_ns``) of u = (v, yaw_rate) (2,)."""
    v, w = (float(c) for c in np.asarray(u, dtype=np.float64).reshape(2))
    tw = Twist(linear=Vector3(x=v, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=w))
    if msg_type == "geometry_msgs/msg/TwistStamped":
        return TwistStamped(header=header(stamp_ns, "base_link"), twist=tw)
    return tw


class Ros2OperatorNode:
    """The node ``operator``: one publisher on the command binding's topic and its tokens.
    ``clock``: wall clock (ns) of the attachment's source timestamp and a TwistStamped's stamp.
    The key has no prefix (``options.prefix`` is ignored): the operator is on the service's
    side of the link."""

    def __init__(self, transport: Transport, binding: CommandBinding, *,
                 options: Ros2Options | None = None, session_id: str | None = None,
                 clock: Callable[[], int] = time.time_ns) -> None:
        options = options or Ros2Options()
        self.node = NodeIdentity(domain_id=options.domain_id,
                                 session_id=session_id or session_id_of(transport),
                                 node_id=0, name=NODE_NAME, namespace=options.namespace)
        self.binding = binding
        self.endpoint = TopicEndpoint(node=self.node, entity_id=1, kind="MP",
                                      topic=self.node.resolve(binding.topic),
                                      ros_type=binding.msg_type,
                                      type_hash=type_hash(binding.msg_type))
        self._clock = clock
        self.sent = 0
        self._handles: list[Handle] = []
        self._publisher: Publisher | None = None
        try:
            self._handles.append(transport.declare_token(self.node.token()))
            self._publisher = transport.publisher(self.key)
            self._handles.append(transport.declare_token(self.endpoint.token()))
        except BaseException:
            self.close()
            raise

    @property
    def key(self) -> str:
        """The rmw_zenoh data key the commands are published on."""
        return self.endpoint.keyexpr()

    def send(self, u: Sequence[float] | np.ndarray) -> None:
        """Publish u = (v, yaw_rate) now."""
        assert self._publisher is not None
        now = self._clock()
        payload = encode(twist_message(u, self.binding.msg_type, now), self.binding.msg_type)
        self.sent += 1
        att = Attachment(sequence_number=self.sent, source_timestamp_ns=now,
                         gid=self.endpoint.gid())
        self._publisher.put(payload, attachment=encode_attachment(att))

    def close(self) -> None:
        close_quietly(reversed(self._handles))
        self._handles.clear()
        if self._publisher is not None:
            close_quietly([self._publisher])
            self._publisher = None
