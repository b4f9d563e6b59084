"""The simulated robot's ROS 2 face (``pd-robot-sim --ros2``): a node ``robot_sim`` that
publishes its sensors as ROS 2 messages and obeys Twist commands, in rmw_zenoh's format.

For each sensor bound in the session's ``ros2`` bindings the node has a publisher on the
bound topic and message type; for the bound command topic (``cmd_vel``) a subscription. On
the wire, as ``rmw_zenoh_cpp`` (ROS 2 Jazzy) does it (``pd_service.ros2``):

* data key ``<prefix>/<domain>/<topic>/<dds type>/<RIHS01 hash>``: the rmw_zenoh key under
  ``prefix`` (default ``robot``), so that pd-link, which maps ``robot/...`` to the plain key,
  carries the samples with the emulated delay and loss; no prefix with ``--direct``;
* payload: CDR (little-endian, with encapsulation header) from the rosbags Jazzy typestore;
* attachment: sequence number (1, 2, ... per publisher), source timestamp (the wall clock at
  publication, ns) and the publisher's GID, in the ``positional`` layout (Jazzy >= 0.2.4);
* liveliness tokens: the node's (``NN``), one ``MP`` per publisher and one ``MS`` for the
  command subscription, declared on the robot's own Zenoh session (not through the link),
  advertising the plain keys that pd-link publishes on.

Each message's ``header.stamp`` is the time of the sample (the step time on the session's
clock). Message contents (units m, rad, m/s, rad/s; covariances row-major as ROS has them):

* ``nav_msgs/Odometry``: the bound fields (pose x, y, yaw; twist vx, vy, yaw_rate) with R on
  their diagonal entries; other axes of a block that carries a bound field get variance
  :data:`UNKNOWN_VARIANCE`; a block without bound fields is zero with an all-zero covariance
  (ROS' "unknown"). header.frame_id ``odom``, child_frame_id ``base_link``.
* ``sensor_msgs/Imu``: angular_velocity.z = the yaw rate, angular_velocity_covariance
  diag(UNKNOWN, UNKNOWN, R); orientation and linear acceleration absent (covariance[0] = -1,
  REP-145). frame_id ``base_link``.
* ``geometry_msgs/PoseWithCovarianceStamped`` / ``PoseStamped``: x, y, yaw (z = roll = pitch
  = 0), R on the x, y, yaw entries. frame_id ``odom``.

A binding's ``frame``, when set, is the frame_id written instead.

With a camera bound (``ros2.camera``), :meth:`Ros2RobotNode.publish_frame` publishes each
frame of the simulated camera as a camera driver does: ``sensor_msgs/CompressedImage``
(``format`` ``jpeg``, the JPEG bytes) on the image topic and its ``sensor_msgs/CameraInfo``
(K, distortion model and D of the frame's pinhole view, R identity, P = [K | 0]) on the info
topic, both stamped with the capture time, frame_id ``camera_optical``.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Point as Point,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Pose as Pose,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__PoseWithCovariance as PoseWithCovariance,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Twist as Twist,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__TwistWithCovariance as TwistWithCovariance,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Vector3 as Vector3,
)

from pd_service.ros2.attachment import Attachment, decode_attachment, encode_attachment
from pd_service.ros2.errors import Ros2DecodeError
from pd_service.ros2.extract import extract_command, quaternion_of_yaw
from pd_service.ros2.keys import NodeIdentity, TopicEndpoint
from pd_service.ros2.messages import (
    Imu,
    Odometry,
    PoseStamped,
    PoseWithCovarianceStamped,
    RosMessage,
    decode,
    encode,
    header,
    type_hash,
)
from pd_service.transport import Transport
from pd_service.transport.base import Handle, Publisher, Sample
from pd_service.wire.camera import CameraFrame
from pd_service.wire.ros2 import Ros2Binding, TopicBinding

log = logging.getLogger(__name__)

#: Variance written for an axis the simulated sensor does not measure.
UNKNOWN_VARIANCE = 1e6
NODE_NAME = "robot_sim"
IMAGE_TYPE, INFO_TYPE = "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
DEFAULT_FRAMES: dict[str, str] = {
    "nav_msgs/msg/Odometry": "odom",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "odom",
    "geometry_msgs/msg/PoseStamped": "odom",
    "sensor_msgs/msg/Imu": "base_link",
}
_POSE_INDEX = {"x": 0, "y": 1, "yaw": 5}
_TWIST_INDEX = {"vx": 0, "vy": 1, "yaw_rate": 5}


def close_quietly(closables: Iterable[Handle | Publisher]) -> None:
    """Close each of ``closables``, ignoring errors (the transport may already be closed)."""
    for c in closables:
        try:
            c.close()
        except Exception:
            pass


@dataclass(frozen=True)
class Ros2Options:
    """Where the node lives: ROS domain id, namespace (absolute), the key prefix the link
    strips (None: publish on the plain rmw_zenoh keys, no link in between)."""

    domain_id: int = 0
    namespace: str = "/"
    prefix: str | None = "robot"


def _block_cov(size: int, index: Mapping[str, int], values: Mapping[str, float]) -> np.ndarray:
    """Row-major size x size covariance: ``values`` (field -> variance) on their diagonal
    entries, UNKNOWN_VARIANCE on the others; all zeros (unknown) when ``values`` is empty."""
    cov = np.zeros((size, size))
    if values:
        np.fill_diagonal(cov, UNKNOWN_VARIANCE)
        for field, var in values.items():
            cov[index[field], index[field]] = var
    return cov.reshape(size * size)


def sensor_message(binding: TopicBinding, z: np.ndarray, R: np.ndarray,
                   stamp_ns: int) -> RosMessage:
    """The ROS message of one sample z (m,) with noise covariance R (m, m), in the binding's
    field order (see the module docstring). ValueError for a message type the robot does not
    publish."""
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if z.shape != (len(binding.fields),):
        raise ValueError(f"{binding.topic}: z has {z.size} values, fields {binding.fields}")
    value: dict[str, float] = dict(zip(binding.fields, (float(v) for v in z), strict=True))
    var: dict[str, float] = dict(zip(binding.fields, (float(R[i, i]) for i in range(len(z))),
                                     strict=True))
    frame = binding.frame or DEFAULT_FRAMES.get(binding.msg_type, "odom")
    hdr = header(stamp_ns, frame)

    def pose() -> Pose:
        return Pose(position=Point(x=value.get("x", 0.0), y=value.get("y", 0.0), z=0.0),
                    orientation=quaternion_of_yaw(value.get("yaw", 0.0)))

    pose_var = {f: v for f, v in var.items() if f in _POSE_INDEX}
    twist_var = {f: v for f, v in var.items() if f in _TWIST_INDEX}
    if binding.msg_type == "nav_msgs/msg/Odometry":
        twist = Twist(linear=Vector3(x=value.get("vx", 0.0), y=value.get("vy", 0.0), z=0.0),
                      angular=Vector3(x=0.0, y=0.0, z=value.get("yaw_rate", 0.0)))
        return Odometry(
            header=hdr, child_frame_id="base_link",
            pose=PoseWithCovariance(pose=pose(), covariance=_block_cov(6, _POSE_INDEX, pose_var)),
            twist=TwistWithCovariance(twist=twist,
                                      covariance=_block_cov(6, _TWIST_INDEX, twist_var)))
    if binding.msg_type == "geometry_msgs/msg/PoseWithCovarianceStamped":
        return PoseWithCovarianceStamped(
            header=hdr,
            pose=PoseWithCovariance(pose=pose(), covariance=_block_cov(6, _POSE_INDEX, pose_var)))
    if binding.msg_type == "geometry_msgs/msg/PoseStamped":
        return PoseStamped(header=hdr, pose=pose())
    if binding.msg_type == "sensor_msgs/msg/Imu":
        absent = np.zeros(9)
        absent[0] = -1.0  # REP-145: this field is not provided
        return Imu(header=hdr, orientation=quaternion_of_yaw(0.0),
                   orientation_covariance=absent.copy(),
                   angular_velocity=Vector3(x=0.0, y=0.0, z=value["yaw_rate"]),
                   angular_velocity_covariance=_block_cov(3, {"yaw_rate": 2}, twist_var),
                   linear_acceleration=Vector3(x=0.0, y=0.0, z=0.0),
                   linear_acceleration_covariance=absent.copy())
    raise ValueError(f"{binding.topic}: the simulated robot does not publish {binding.msg_type}")


def session_id_of(transport: Transport) -> str:
    """The Zenoh session id (lowercase hex) for the liveliness tokens: the transport's own when
    it has a Zenoh session, else a random 128-bit id (the in-memory bus has none)."""
    session = getattr(transport, "session", None)
    info = getattr(session, "info", None)
    if info is not None:
        return str(info.zid())
    return os.urandom(16).hex().lstrip("0") or "1"


def _attachment_seq(attachment: bytes | None) -> int | None:
    """The rmw_zenoh attachment's sequence number; None when absent, unreadable or negative."""
    if attachment is None:
        return None
    try:
        seq = decode_attachment(attachment).sequence_number
    except Ros2DecodeError:
        return None
    return seq if seq >= 0 else None


class Ros2RobotNode:
    """The node ``robot_sim``: publishers of the bound sensors, the command subscription and
    their liveliness tokens (see the module docstring).

    ``on_command(u, seq)`` gets u = (linear.x, angular.z) (2,) of every valid Twist/TwistStamped
    and its rmw_zenoh attachment's sequence number (None without a readable one: what pd-ros2
    names the Command and its echo), on the transport's callback thread; an invalid one is
    counted (``commands_invalid``) and logged. ``clock``: wall clock of the attachment's
    source timestamp (ns).
    """

    def __init__(self, transport: Transport, binding: Ros2Binding,
                 sensor_R: Mapping[str, np.ndarray], *, options: Ros2Options = Ros2Options(),
                 on_command: Callable[[np.ndarray, int | None], None] | None = None,
                 session_id: str | None = None,
                 clock: Callable[[], int] = time.time_ns) -> None:
        missing = sorted(set(binding.sensors) - set(sensor_R))
        if missing:
            raise ValueError(f"ROS 2 bindings name sensors {missing} the robot does not have")
        self.node = NodeIdentity(domain_id=options.domain_id,
                                 session_id=session_id or session_id_of(transport),
                                 node_id=0, name=NODE_NAME, namespace=options.namespace)
        self._transport = transport
        self._binding = binding
        self._R = {name: np.asarray(R, dtype=np.float64) for name, R in sensor_R.items()}
        self._prefix = options.prefix
        self._clock = clock
        self._on_command = on_command
        self._lock = threading.Lock()
        self.endpoints: dict[str, TopicEndpoint] = {}
        self._publishers: dict[str, Publisher] = {}
        self._seq: dict[str, int] = {}
        self._handles: list[Handle] = []
        #: The camera's publishers: "camera" / "camera_info" -> (endpoint, type, publisher).
        self._camera: dict[str, tuple[TopicEndpoint, str, Publisher]] = {}
        self.published = 0
        self.commands_received = 0
        self.commands_invalid = 0
        try:
            self._declare()
        except BaseException:
            self.close()
            raise

    def _key(self, endpoint: TopicEndpoint) -> str:
        key = endpoint.keyexpr()
        return key if self._prefix is None else f"{self._prefix}/{key}"

    def _declare(self) -> None:
        t, node = self._transport, self.node
        self._handles.append(t.declare_token(node.token()))
        entity = 1
        for name, b in self._binding.sensors.items():
            if b.msg_type not in DEFAULT_FRAMES:
                raise ValueError(f"sensor {name!r}: the simulated robot does not publish "
                                 f"{b.msg_type}")
            ep = TopicEndpoint(node=node, entity_id=entity, kind="MP", topic=node.resolve(b.topic),
                               ros_type=b.msg_type, type_hash=type_hash(b.msg_type))
            entity += 1
            self.endpoints[name] = ep
            self._publishers[name] = t.publisher(self._key(ep))
            self._seq[name] = 0
            self._handles.append(t.declare_token(ep.token()))
        cmd = self._binding.commands
        if cmd is not None:
            ep = TopicEndpoint(node=node, entity_id=entity, kind="MS",
                               topic=node.resolve(cmd.topic), ros_type=cmd.msg_type,
                               type_hash=type_hash(cmd.msg_type))
            self.command_endpoint: TopicEndpoint | None = ep
            self._handles.append(t.subscribe(self._key(ep), self._on_sample))
            self._handles.append(t.declare_token(ep.token()))
            entity += 1
        else:
            self.command_endpoint = None
        self._declare_camera(entity)

    def _declare_camera(self, entity: int) -> None:
        cam = self._binding.camera
        if cam is None:
            return
        for name, topic, msg_type in (("camera", cam.image_topic, IMAGE_TYPE),
                                      ("camera_info", cam.info_topic, INFO_TYPE)):
            ep = TopicEndpoint(node=self.node, entity_id=entity, kind="MP",
                               topic=self.node.resolve(topic), ros_type=msg_type,
                               type_hash=type_hash(msg_type))
            entity += 1
            self._camera[name] = (ep, msg_type, self._transport.publisher(self._key(ep)))
            self._handles.append(self._transport.declare_token(ep.token()))

    @property
    def films(self) -> bool:
        """Whether a camera is bound (frames go out as CompressedImage + CameraInfo)."""
        return bool(self._camera)

    def publish_frame(self, frame: CameraFrame) -> None:
        """Publish a perspective ``frame`` as its CompressedImage and CameraInfo (module
        docstring)."""
        from rosbags.typesys.stores.ros2_jazzy import (
            sensor_msgs__msg__CameraInfo as CameraInfo,
        )
        from rosbags.typesys.stores.ros2_jazzy import (
            sensor_msgs__msg__CompressedImage as CompressedImage,
        )
        from rosbags.typesys.stores.ros2_jazzy import (
            sensor_msgs__msg__RegionOfInterest as RegionOfInterest,
        )

        view = frame.pinhole
        if view is None:
            raise ValueError("a ROS 2 camera frame needs a perspective (pinhole) view")
        K = view.K
        hdr = header(frame.t_ns, "camera_optical")
        msgs: dict[str, RosMessage] = {"camera": CompressedImage(header=hdr, format="jpeg",
                                          data=np.frombuffer(frame.image(), dtype=np.uint8)),
                "camera_info": CameraInfo(
                    header=hdr, height=frame.height, width=frame.width,
                    distortion_model=view.distortion_model, d=np.array(view.D, dtype=np.float64),
                    k=np.array(K, dtype=np.float64), r=np.eye(3).reshape(9),
                    p=np.array([*K[:3], 0.0, *K[3:6], 0.0, *K[6:], 0.0]), binning_x=0,
                    binning_y=0, roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0,
                                                      do_rectify=False))}
        for name in ("camera_info", "camera"):  # the calibration first, as drivers do
            ep, msg_type, pub = self._camera[name]
            with self._lock:
                self._seq[name] = self._seq.get(name, 0) + 1
                seq = self._seq[name]
            att = Attachment(sequence_number=seq, source_timestamp_ns=self._clock(), gid=ep.gid())
            pub.put(encode(msgs[name], msg_type), attachment=encode_attachment(att))
            self.published += 1

    def key_of(self, sensor: str) -> str:
        """The key the samples of ``sensor`` are published on."""
        return self._key(self.endpoints[sensor])

    @property
    def command_key(self) -> str | None:
        """The key the commands are read from (None: no command binding)."""
        ep = self.command_endpoint
        return None if ep is None else self._key(ep)

    def binds(self, sensor: str) -> bool:
        return sensor in self.endpoints

    def publish(self, sensor: str, z: Sequence[float] | np.ndarray, stamp_ns: int) -> None:
        """Publish the sample z of ``sensor`` taken at ``stamp_ns`` (ns since the epoch)."""
        msg = sensor_message(self._binding.sensors[sensor], np.asarray(z), self._R[sensor],
                             stamp_ns)
        payload = encode(msg, self._binding.sensors[sensor].msg_type)
        with self._lock:
            self._seq[sensor] += 1
            seq = self._seq[sensor]
        att = Attachment(sequence_number=seq, source_timestamp_ns=self._clock(),
                         gid=self.endpoints[sensor].gid())
        self._publishers[sensor].put(payload, attachment=encode_attachment(att))
        self.published += 1

    def _on_sample(self, sample: Sample) -> None:
        cmd = self._binding.commands
        assert cmd is not None
        self.commands_received += 1
        try:
            u = extract_command(decode(sample.payload, cmd.msg_type)).u
        except Ros2DecodeError as exc:
            self.commands_invalid += 1
            log.warning("ignoring %s sample: %s", cmd.topic, exc.reason)
            return
        if self._on_command is not None and all(math.isfinite(v) for v in u):
            self._on_command(u, _attachment_seq(sample.attachment))

    def close(self) -> None:
        close_quietly(reversed(self._handles))
        self._handles.clear()
        close_quietly([*self._publishers.values(), *(p for _, _, p in self._camera.values())])
        self._publishers.clear()
        self._camera.clear()
