"""Session specs and ROS messages shared by the bridge tests: a unicycle robot (odometry, IMU,
an external pose fix, Twist commands) with predicted Odometry / Pose / TF outputs."""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Point as Point
from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Pose as Pose
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__PoseWithCovariance as PoseWithCovariance,
)
from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Twist as TwistMsg
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__TwistWithCovariance as TwistWithCovariance,
)
from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3 as Vector3

from pd_service.ros2.extract import quaternion_of_yaw
from pd_service.ros2.messages import (
    Imu,
    Odometry,
    PoseWithCovarianceStamped,
    Twist,
    TwistStamped,
    header,
)
from pd_service.wire import SensorSpec, SessionSpec, UnscentedModelSpec
from pd_service.wire.pinhole import CameraMount
from pd_service.wire.ros2 import (
    CameraBinding,
    CommandBinding,
    CommandType,
    OutputBinding,
    Ros2Binding,
    StateLayout,
    TopicBinding,
)

ODOM = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF = "tf2_msgs/msg/TFMessage"
LAYOUT = StateLayout(x=0, y=1, yaw=2, vx=3, yaw_rate=4)
PERIOD_NS = 20_000_000


def unicycle_spec(name: str = "s1", *, prefix: str = "", epoch_ns: int = 1_700_000_000_000_000_000,
                  cmd_type: CommandType = "geometry_msgs/msg/Twist", lead: int = 5,
                  pose_frame: str | None = "map", tf: bool = True,
                  camera: CameraBinding | None = None) -> SessionSpec:
    """A unicycle session (state x, y, yaw, v, w) whose sensors come from ROS topics
    ``<prefix>odom`` (Odometry), ``<prefix>imu`` (Imu) and ``/<prefix>pose_fix`` (pose fix,
    frame ``pose_frame``), commands from ``<prefix>cmd_vel``; outputs on
    ``<prefix>predicted/odom`` and ``<prefix>predicted/pose`` (relative topics)."""
    return SessionSpec(
        session=name, period_ns=PERIOD_NS, epoch_ns=epoch_ns,
        model=UnscentedModelSpec(model="unicycle", params={"period_s": PERIOD_NS / 1e9}),
        x0=np.zeros(5), P0=np.diag([0.5, 0.5, 0.2, 0.1, 0.1]),
        sensors=[
            SensorSpec(name="odom", kind="model", R=np.diag([1e-4] * 5), delay=1, interval=1),
            SensorSpec(name="imu", kind="model", R=np.array([[1e-4]]), delay=1, interval=1),
            SensorSpec(name="pose", kind="model", R=np.diag([0.0025, 0.0025, 4e-4]), delay=5,
                       interval=5),
        ],
        lead=lead, max_delay=20,
        ros2=Ros2Binding(
            sensors={
                "odom": TopicBinding(topic=f"{prefix}odom", msg_type=ODOM,
                                     fields=["x", "y", "yaw", "vx", "yaw_rate"]),
                "imu": TopicBinding(topic=f"{prefix}imu", msg_type=IMU, fields=["yaw_rate"]),
                "pose": TopicBinding(topic=f"/{prefix}pose_fix", msg_type=POSE,
                                     fields=["x", "y", "yaw"], frame=pose_frame),
            },
            commands=CommandBinding(topic=f"{prefix}cmd_vel", msg_type=cmd_type),
            outputs=OutputBinding(odom_topic=f"{prefix}predicted/odom",
                                  pose_topic=f"{prefix}predicted/pose", tf=tf, layout=LAYOUT),
            camera=camera,
        ),
    )


def odometry(stamp_ns: int, x: float, y: float, yaw: float, v: float, w: float,
             pose_var: float = 1e-4, twist_var: float = 4e-4) -> Odometry:
    """Odometry with diagonal covariances (pose_var on x, y, yaw; twist_var on vx, wz; 0 means
    'unknown' in ROS, so the spec's R applies)."""
    cp = np.zeros(36)
    ct = np.zeros(36)
    for i in (0, 7, 35):
        cp[i] = pose_var
    for i in (0, 35):
        ct[i] = twist_var
    return Odometry(
        header=header(stamp_ns, "odom"), child_frame_id="base_link",
        pose=PoseWithCovariance(pose=Pose(position=Point(x=x, y=y, z=0.0),
                                          orientation=quaternion_of_yaw(yaw)), covariance=cp),
        twist=TwistWithCovariance(twist=TwistMsg(linear=Vector3(x=v, y=0.0, z=0.0),
                                                 angular=Vector3(x=0.0, y=0.0, z=w)),
                                  covariance=ct))


def imu(stamp_ns: int, w: float, var: float = 1e-4) -> Imu:
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Quaternion as Q

    cov = np.zeros(9)
    cov[8] = var
    return Imu(header=header(stamp_ns, "imu"), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
               orientation_covariance=np.array([-1.0] + [0.0] * 8),
               angular_velocity=Vector3(x=0.0, y=0.0, z=w), angular_velocity_covariance=cov,
               linear_acceleration=Vector3(x=0.0, y=0.0, z=9.81),
               linear_acceleration_covariance=np.zeros(9))


def pose_fix(stamp_ns: int, x: float, y: float, yaw: float, cov: np.ndarray | None = None,
             frame: str = "map") -> PoseWithCovarianceStamped:
    """A pose fix; ``cov`` the 6x6 covariance (None: all zeros, i.e. unknown)."""
    c = np.zeros(36) if cov is None else np.asarray(cov, dtype=float).reshape(36)
    return PoseWithCovarianceStamped(
        header=header(stamp_ns, frame),
        pose=PoseWithCovariance(pose=Pose(position=Point(x=x, y=y, z=0.0),
                                          orientation=quaternion_of_yaw(yaw)), covariance=c))


def twist(v: float, w: float) -> Twist:
    return Twist(linear=Vector3(x=v, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=w))


def twist_stamped(stamp_ns: int, v: float, w: float) -> TwistStamped:
    return TwistStamped(header=header(stamp_ns, "base_link"), twist=twist(v, w))


#: A camera 0.2 m ahead of the body origin, 0.8 m up, pitched 0.35 rad down.
MOUNT = CameraMount(x=0.2, z=0.8, pitch=0.35)
#: A 320 x 240 camera's K and plumb_bob D.
CAMERA_K = [400.0, 0.0, 161.5, 0.0, 402.0, 118.25, 0.0, 0.0, 1.0]
CAMERA_D = [-0.2, 0.05, 1e-3, -1e-3, 0.0]


def camera_binding(prefix: str = "", tolerance_ms: float = 100.0) -> CameraBinding:
    """The camera on ``<prefix>camera/...``, placed by the odometry's pose."""
    return CameraBinding(image_topic=f"{prefix}camera/image_raw/compressed",
                         info_topic=f"{prefix}camera/camera_info", pose_sensor="odom",
                         pose_tolerance_ms=tolerance_ms, mount=MOUNT)


def camera_info(stamp_ns: int, K: list[float] | None = None, model: str = "plumb_bob",
                D: list[float] | None = None, width: int = 320, height: int = 240) -> Any:
    """sensor_msgs/CameraInfo of a monocular camera (R identity, P = [K | 0])."""
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__CameraInfo as CameraInfo
    from rosbags.typesys.stores.ros2_jazzy import (
        sensor_msgs__msg__RegionOfInterest as RegionOfInterest,
    )

    K = CAMERA_K if K is None else K
    D = CAMERA_D if D is None else D
    return CameraInfo(header=header(stamp_ns, "camera_optical"), height=height, width=width,
                      distortion_model=model, d=np.array(D, dtype=np.float64),
                      k=np.array(K, dtype=np.float64), r=np.eye(3).ravel(),
                      p=np.array([*K[:3], 0.0, *K[3:6], 0.0, *K[6:], 0.0]), binning_x=0,
                      binning_y=0, roi=RegionOfInterest(x_offset=0, y_offset=0, height=0,
                                                        width=0, do_rectify=False))


def compressed_image(stamp_ns: int, data: bytes, fmt: str = "jpeg") -> Any:
    """sensor_msgs/CompressedImage of ``data``."""
    from rosbags.typesys.stores.ros2_jazzy import (
        sensor_msgs__msg__CompressedImage as CompressedImage,
    )

    return CompressedImage(header=header(stamp_ns, "camera_optical"), format=fmt,
                           data=np.frombuffer(data, dtype=np.uint8))
