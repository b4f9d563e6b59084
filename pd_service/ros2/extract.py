"""Conversions between ROS 2 messages and pd-service vectors.

Inputs: a bound sensor message -> :class:`Sample` (z, R or None, stamp); a Twist/TwistStamped
-> :class:`Command` (u = (vx, yaw_rate), stamp or None). Outputs: a predicted state (x, P) ->
Odometry, PoseWithCovarianceStamped and TFMessage.

Covariance rule (inputs). ROS 6x6 covariances are row-major over (x, y, z, roll, pitch, yaw) for
poses and (vx, vy, vz, wx, wy, wz) for twists; Imu's 3x3 over (wx, wy, wz). A covariance is
*unknown* when it is all zeros or its first element is -1 (REP-145 / sensor_msgs convention).
R is the sub-matrix of the chosen fields' rows and columns when every covariance those fields
come from is known; otherwise R is None and the spec's R applies. Odometry fields taken from both
the pose and the twist get a block-diagonal R (the message carries no pose-twist cross term).
A known sub-matrix must be finite, symmetric (to 1e-9 relative) and positive semi-definite
(smallest eigenvalue >= -1e-9 times the largest), else the sample is refused. Messages without a
covariance (PoseStamped, PointStamped, Range) give R = None.

Unobserved axes (outputs). A pose or twist axis the state does not hold (z, roll, pitch, vz, wx,
wy, and any of x, y, yaw, vx, vy, yaw rate absent from the layout) is written as value 0 with
variance :data:`UNOBSERVED_VARIANCE` and zero cross-covariances, so RViz/Foxglove and
robot_localization-style consumers treat it as unknown rather than as certain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, cast

import numpy as np
from numpy.typing import NDArray
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
    geometry_msgs__msg__Quaternion as Quaternion,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Transform as Transform,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__TransformStamped as TransformStamped,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Twist as TwistMsg,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__TwistWithCovariance as TwistWithCovariance,
)
from rosbags.typesys.stores.ros2_jazzy import (
    geometry_msgs__msg__Vector3 as Vector3,
)

from pd_service.ros2.errors import Ros2DecodeError
from pd_service.ros2.messages import (
    CameraInfo,
    CompressedImage,
    Imu,
    Odometry,
    Path,
    PointStamped,
    PoseStamped,
    PoseWithCovarianceStamped,
    Range,
    RosMessage,
    TFMessage,
    Time,
    Twist,
    TwistStamped,
    decode,
    header,
    stamp_ns,
)
from pd_service.wire.camera import MAX_IMAGE_BYTES
from pd_service.wire.pinhole import DISTORTION_SIZES, DistortionModel
from pd_service.wire.ros2 import FieldName, StateLayout, TopicBinding

FloatArray = NDArray[np.float64]

#: Variance written for an axis the predicted state does not hold (m^2, rad^2, (m/s)^2,
#: (rad/s)^2): 1e6, i.e. a standard deviation of 1000, far beyond any real uncertainty.
UNOBSERVED_VARIANCE = 1e6

# Index of each field in the ROS 6x6 pose / twist covariance.
_POSE_INDEX: dict[str, int] = {"x": 0, "y": 1, "yaw": 5}
_TWIST_INDEX: dict[str, int] = {"vx": 0, "vy": 1, "yaw_rate": 5}
_PSD_TOL = 1e-9


@dataclass(frozen=True)
class Sample:
    """One measurement from a ROS message: ``z`` (m,) in the binding's field order, ``R`` (m, m)
    from the message's covariance or None (use the spec's R), ``stamp_ns`` = header.stamp in
    ns since the epoch, ``frame_id`` = header.frame_id."""

    z: FloatArray
    R: FloatArray | None
    stamp_ns: int
    frame_id: str


@dataclass(frozen=True)
class Command:
    """A velocity command: ``u`` = (vx [m/s], yaw_rate [rad/s]); ``stamp_ns`` = header.stamp for
    TwistStamped, None for a bare Twist (then the arrival time applies)."""

    u: FloatArray
    stamp_ns: int | None


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def yaw_of(q: Quaternion) -> float:
    """Heading (rad, in (-pi, pi]) of a quaternion: atan2(2(wz + xy), w^2 + x^2 - y^2 - z^2),
    valid for any non-zero scale of q. Raises Ros2DecodeError for a zero or non-finite q."""
    w, x, y, z = float(q.w), float(q.x), float(q.y), float(q.z)
    norm2 = w * w + x * x + y * y + z * z
    if not math.isfinite(norm2) or norm2 < 1e-18:
        raise Ros2DecodeError(f"orientation quaternion {(x, y, z, w)} is zero or not finite")
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def quaternion_of_yaw(yaw: float) -> Quaternion:
    """Unit quaternion of a rotation by ``yaw`` (rad) about z: (0, 0, sin(yaw/2), cos(yaw/2))."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _stamp(stamp: Time, what: str) -> int:
    ns = stamp_ns(stamp)
    if ns <= 0:
        raise Ros2DecodeError(f"{what}: header.stamp is {ns} ns (zero or before the epoch)")
    return ns


def _known(cov: FloatArray) -> bool:
    """False for the 'unknown' covariance conventions: all zeros, or -1 as first element."""
    return not (cov[0] == -1.0 or not np.any(cov))


def _check_psd(R: FloatArray, what: str) -> FloatArray:
    if not np.all(np.isfinite(R)):
        raise Ros2DecodeError(f"{what}: covariance has NaN or inf")
    scale = max(float(np.max(np.abs(R))), 1e-300)
    if not np.allclose(R, R.T, rtol=0.0, atol=_PSD_TOL * scale):
        raise Ros2DecodeError(f"{what}: covariance is not symmetric")
    R = 0.5 * (R + R.T)
    eig = np.linalg.eigvalsh(R)
    if eig[0] < -_PSD_TOL * scale:
        raise Ros2DecodeError(f"{what}: covariance is not positive semi-definite (eigenvalue {eig[0]:.3g})")
    return R


def _finite(values: list[float], fields: Sequence[FieldName], what: str) -> FloatArray:
    z = np.asarray(values, dtype=np.float64)
    bad = [f for f, v in zip(fields, z, strict=True) if not math.isfinite(v)]
    if bad:
        raise Ros2DecodeError(f"{what}: {', '.join(bad)} not finite")
    return z


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------


def _pose_values(pose: Pose, fields: Sequence[FieldName]) -> list[float]:
    out: list[float] = []
    for f in fields:
        if f == "x":
            out.append(float(pose.position.x))
        elif f == "y":
            out.append(float(pose.position.y))
        elif f == "yaw":
            out.append(yaw_of(pose.orientation))
    return out


def _twist_values(twist: TwistMsg, fields: Sequence[FieldName]) -> list[float]:
    values = {"vx": twist.linear.x, "vy": twist.linear.y, "yaw_rate": twist.angular.z}
    return [float(values[f]) for f in fields]


def _sub(cov: FloatArray, size: int, idx: list[int]) -> FloatArray:
    full = np.asarray(cov, dtype=np.float64).reshape(size, size)
    return full[np.ix_(idx, idx)]


def extract_measurement(msg: RosMessage, fields: Sequence[FieldName]) -> Sample:
    """The measurement ``fields`` of a decoded sensor message (see the module docstring for R).
    Raises Ros2DecodeError for a zero stamp, a non-finite value, a zero quaternion, a bad
    covariance or a field the message type does not carry."""
    what = getattr(msg, "__msgtype__", type(msg).__name__)
    R: FloatArray | None
    if isinstance(msg, Odometry):
        stamp, frame = _stamp(msg.header.stamp, what), msg.header.frame_id
        pose_f = tuple(f for f in fields if f in _POSE_INDEX)
        twist_f = tuple(f for f in fields if f in _TWIST_INDEX)
        if len(pose_f) + len(twist_f) != len(fields):
            raise Ros2DecodeError(f"{what}: fields {list(fields)} not all in Odometry")
        pose_vals = _pose_values(msg.pose.pose, pose_f)
        twist_vals = _twist_values(msg.twist.twist, twist_f)
        values = {f: v for f, v in zip(pose_f + twist_f, pose_vals + twist_vals, strict=True)}
        z = _finite([values[f] for f in fields], fields, what)
        pose_cov = np.asarray(msg.pose.covariance, dtype=np.float64)
        twist_cov = np.asarray(msg.twist.covariance, dtype=np.float64)
        known = (not pose_f or _known(pose_cov)) and (not twist_f or _known(twist_cov))
        if known:
            full = np.zeros((len(fields), len(fields)))
            pos = {f: i for i, f in enumerate(fields)}
            for sub_f, cov, index in ((pose_f, pose_cov, _POSE_INDEX), (twist_f, twist_cov, _TWIST_INDEX)):
                if sub_f:
                    block = _sub(cov, 6, [index[f] for f in sub_f])
                    rows = [pos[f] for f in sub_f]
                    full[np.ix_(rows, rows)] = block
            R = _check_psd(full, what)
        else:
            R = None
        return Sample(z=z, R=R, stamp_ns=stamp, frame_id=frame)
    if isinstance(msg, PoseWithCovarianceStamped):
        _only(fields, ("x", "y", "yaw"), what)
        z = _finite(_pose_values(msg.pose.pose, fields), fields, what)
        cov = np.asarray(msg.pose.covariance, dtype=np.float64)
        R = _check_psd(_sub(cov, 6, [_POSE_INDEX[f] for f in fields]), what) if _known(cov) else None
        return Sample(z=z, R=R, stamp_ns=_stamp(msg.header.stamp, what), frame_id=msg.header.frame_id)
    if isinstance(msg, PoseStamped):
        _only(fields, ("x", "y", "yaw"), what)
        z = _finite(_pose_values(msg.pose, fields), fields, what)
        return Sample(z=z, R=None, stamp_ns=_stamp(msg.header.stamp, what), frame_id=msg.header.frame_id)
    if isinstance(msg, PointStamped):
        _only(fields, ("x", "y", "z"), what)
        p: Point = msg.point
        values = {"x": p.x, "y": p.y, "z": p.z}
        z = _finite([float(values[f]) for f in fields], fields, what)
        return Sample(z=z, R=None, stamp_ns=_stamp(msg.header.stamp, what), frame_id=msg.header.frame_id)
    if isinstance(msg, Range):
        _only(fields, ("range",), what)
        z = _finite([float(msg.range)], fields, what)
        return Sample(z=z, R=None, stamp_ns=_stamp(msg.header.stamp, what), frame_id=msg.header.frame_id)
    if isinstance(msg, Imu):
        _only(fields, ("yaw_rate",), what)
        z = _finite([float(msg.angular_velocity.z)], fields, what)
        cov = np.asarray(msg.angular_velocity_covariance, dtype=np.float64)
        R = _check_psd(_sub(cov, 3, [2]), what) if _known(cov) else None
        return Sample(z=z, R=R, stamp_ns=_stamp(msg.header.stamp, what), frame_id=msg.header.frame_id)
    raise Ros2DecodeError(f"{what} is not a measurement message type")


def _only(fields: Sequence[FieldName], allowed: tuple[str, ...], what: str) -> None:
    bad = [f for f in fields if f not in allowed]
    if bad:
        raise Ros2DecodeError(f"{what}: no field(s) {bad}")


def decode_measurement(binding: TopicBinding, payload: bytes | bytearray | memoryview) -> Sample:
    """Decode a CDR payload of ``binding.msg_type`` and take its fields; the header's frame
    must equal ``binding.frame`` when that is set. Raises Ros2DecodeError."""
    sample = extract_measurement(decode(payload, binding.msg_type), binding.fields)
    if binding.frame is not None and sample.frame_id != binding.frame:
        raise Ros2DecodeError(
            f"{binding.topic}: frame_id {sample.frame_id!r}, binding expects {binding.frame!r}"
        )
    return sample


def extract_command(msg: RosMessage) -> Command:
    """u = (linear.x, angular.z) of a Twist or TwistStamped. Raises Ros2DecodeError for a
    non-finite value or (TwistStamped) a zero stamp."""
    if isinstance(msg, TwistStamped):
        twist, stamp = msg.twist, _stamp(msg.header.stamp, "geometry_msgs/msg/TwistStamped")
    elif isinstance(msg, Twist):
        twist, stamp = msg, None
    else:
        raise Ros2DecodeError(f"{type(msg).__name__} is not a Twist or TwistStamped")
    u = _finite([float(twist.linear.x), float(twist.angular.z)], ("vx", "yaw_rate"), "command")
    return Command(u=u, stamp_ns=stamp)


# ---------------------------------------------------------------------------------------------
# camera
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """A camera's calibration from its CameraInfo: ``K`` (9, row-major), ``distortion_model``
    (``""`` when D is empty: none), ``D``, image ``width`` x ``height`` (pixels)."""

    K: list[float]
    distortion_model: DistortionModel
    D: list[float]
    width: int
    height: int


@dataclass(frozen=True)
class Image:
    """A compressed image: its bytes, ``format`` ``jpeg`` or ``png``, capture ``stamp_ns``."""

    data: bytes
    format: Literal["jpeg", "png"]
    stamp_ns: int


def extract_calibration(msg: CameraInfo) -> Calibration:
    """The calibration in a CameraInfo (the unrectified image's K and D, what a raw image is
    projected with). Raises Ros2DecodeError for a size outside 1..4096, a K that is not
    finite or not calibrated (fx or fy <= 0: an uncalibrated driver publishes zeros), or a
    distortion model other than plumb_bob / rational_polynomial with its 5 / 8 coefficients
    (an empty D: no distortion)."""
    w, h = int(msg.width), int(msg.height)
    if not (1 <= w <= 4096 and 1 <= h <= 4096):
        raise Ros2DecodeError(f"camera_info: size {w} x {h} is outside 1..4096")
    K = [float(v) for v in msg.k]
    D = [float(v) for v in msg.d]
    if not all(math.isfinite(v) for v in K + D):
        raise Ros2DecodeError("camera_info: K or D not finite")
    if not (K[0] > 0 and K[4] > 0):
        raise Ros2DecodeError(f"camera_info: uncalibrated (fx = {K[0]}, fy = {K[4]})")
    model = str(msg.distortion_model) if D else ""
    want = DISTORTION_SIZES.get(model)
    if want is None or len(D) != want:
        raise Ros2DecodeError(f"camera_info: distortion model {model[:40]!r} with {len(D)} "
                              "coefficients is not plumb_bob (5) or rational_polynomial (8)")
    return Calibration(K, cast(DistortionModel, model), D, w, h)


def extract_image(msg: CompressedImage) -> Image:
    """The image in a CompressedImage: ``format`` naming JPEG (``jpeg``, ``jpg``, image_transport's
    ``bgr8; jpeg compressed bgr8``) or PNG. Raises Ros2DecodeError for a zero stamp, another
    format, no data or more than :data:`~pd_service.wire.camera.MAX_IMAGE_BYTES`."""
    stamp = _stamp(msg.header.stamp, "sensor_msgs/msg/CompressedImage")
    fmt = str(msg.format).lower()
    kind: Literal["jpeg", "png"]
    if "jpeg" in fmt or "jpg" in fmt:
        kind = "jpeg"
    elif "png" in fmt:
        kind = "png"
    else:
        raise Ros2DecodeError(f"image: format {fmt[:40]!r} is not JPEG or PNG")
    data = bytes(msg.data)
    if not 4 <= len(data) <= MAX_IMAGE_BYTES:
        raise Ros2DecodeError(f"image: {len(data)} bytes, not within 4..{MAX_IMAGE_BYTES}")
    return Image(data, kind, stamp)


# ---------------------------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------------------------


def _moments(
    x: FloatArray, P: FloatArray, layout: StateLayout
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Pose (6,) and twist (6,) values and their 6x6 covariances from (x, P).

    With o = f(x) the 12 outputs (pose x, y, z, roll, pitch, yaw; twist vx, vy, vz, wx, wy, wz)
    and J = df/dx, cov(o) = J P J^T; rows of unobserved outputs are zero in J, then their
    variance is set to UNOBSERVED_VARIANCE.
    """
    n = x.shape[0]
    if x.shape != (n,) or P.shape != (n, n):
        raise ValueError(f"x must be (n,) and P (n, n); got {x.shape} and {P.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        raise ValueError("predicted state or covariance is not finite")
    idx = layout.indices()
    if any(i >= n or i < 0 for i in idx.values()):
        raise ValueError(f"layout {idx} does not fit a state of size {n}")
    o = np.zeros(12)
    J = np.zeros((12, n))
    observed = np.zeros(12, dtype=bool)
    for name, row in (("x", 0), ("y", 1), ("yaw", 5), ("yaw_rate", 11)):
        if name in idx:
            o[row], J[row, idx[name]], observed[row] = x[idx[name]], 1.0, True
    if layout.velocity_frame == "body":
        for name, row in (("vx", 6), ("vy", 7)):
            if name in idx:
                o[row], J[row, idx[name]], observed[row] = x[idx[name]], 1.0, True
    elif "vx" in idx or "vy" in idx:
        # v_body = R(yaw)^T v_world with the yaw the pose carries: the state's, or 0 when it
        # holds none (the orientation is written as identity, so body = world axes); an absent
        # velocity component is 0. vx_b = c vx + s vy, vy_b = -s vx + c vy;
        # d/dyaw: vx_b' = vy_b, vy_b' = -vx_b.
        yaw = x[idx["yaw"]] if "yaw" in idx else 0.0
        c, s = math.cos(yaw), math.sin(yaw)
        vxw = x[idx["vx"]] if "vx" in idx else 0.0
        vyw = x[idx["vy"]] if "vy" in idx else 0.0
        vxb, vyb = c * vxw + s * vyw, -s * vxw + c * vyw
        o[6], o[7] = vxb, vyb
        if "vx" in idx:
            J[6, idx["vx"]], J[7, idx["vx"]] = c, -s
        if "vy" in idx:
            J[6, idx["vy"]], J[7, idx["vy"]] = s, c
        if "yaw" in idx:
            J[6, idx["yaw"]], J[7, idx["yaw"]] = vyb, -vxb
        turned = "yaw" in idx or ("vx" in idx and "vy" in idx)
        observed[6] = turned or "vx" in idx
        observed[7] = turned or "vy" in idx
    C = J @ P @ J.T
    C = 0.5 * (C + C.T)
    C[~observed, :] = 0.0
    C[:, ~observed] = 0.0
    C[~observed, ~observed] = UNOBSERVED_VARIANCE
    return o[:6], o[6:], C[:6, :6], C[6:, 6:]


def _pose_msg(pose: FloatArray) -> Pose:
    return Pose(
        position=Point(x=float(pose[0]), y=float(pose[1]), z=0.0),
        orientation=quaternion_of_yaw(float(pose[5])),
    )


def odometry_from_state(
    x: FloatArray,
    P: FloatArray,
    layout: StateLayout,
    stamp: int,
    frame_id: str,
    child_frame_id: str = "base_link_predicted",
) -> Odometry:
    """nav_msgs/Odometry of the predicted state at ``stamp`` (ns): pose in ``frame_id``, twist in
    ``child_frame_id``, covariances from P (pose-twist cross terms are not representable and are
    dropped)."""
    pose, twist, cov_p, cov_t = _moments(x, P, layout)
    return Odometry(
        header=header(stamp, frame_id),
        child_frame_id=child_frame_id,
        pose=PoseWithCovariance(pose=_pose_msg(pose), covariance=cov_p.reshape(36).copy()),
        twist=TwistWithCovariance(
            twist=TwistMsg(
                linear=Vector3(x=float(twist[0]), y=float(twist[1]), z=0.0),
                angular=Vector3(x=0.0, y=0.0, z=float(twist[5])),
            ),
            covariance=cov_t.reshape(36).copy(),
        ),
    )


def pose_from_state(
    x: FloatArray, P: FloatArray, layout: StateLayout, stamp: int, frame_id: str
) -> PoseWithCovarianceStamped:
    """geometry_msgs/PoseWithCovarianceStamped of the predicted pose at ``stamp`` (ns)."""
    pose, _, cov_p, _ = _moments(x, P, layout)
    return PoseWithCovarianceStamped(
        header=header(stamp, frame_id),
        pose=PoseWithCovariance(pose=_pose_msg(pose), covariance=cov_p.reshape(36).copy()),
    )


def tf_from_state(
    x: FloatArray,
    layout: StateLayout,
    stamp: int,
    frame_id: str,
    child_frame_id: str = "base_link_predicted",
) -> TFMessage:
    """tf2_msgs/TFMessage with one transform ``frame_id`` -> ``child_frame_id`` at the predicted
    pose (z = 0; an absent x, y or yaw is 0)."""
    idx = layout.indices()
    if x.ndim != 1 or any(i >= x.shape[0] for i in idx.values()):
        raise ValueError(f"layout {idx} does not fit a state of shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("predicted state is not finite")

    def get(name: str) -> float:
        return float(x[idx[name]]) if name in idx else 0.0

    transform = TransformStamped(
        header=header(stamp, frame_id),
        child_frame_id=child_frame_id,
        transform=Transform(
            translation=Vector3(x=get("x"), y=get("y"), z=0.0), rotation=quaternion_of_yaw(get("yaw"))
        ),
    )
    return TFMessage(transforms=[transform])


def path_from_points(
    stamps: Sequence[int], X: FloatArray, indices: Sequence[int], layout: StateLayout,
    frame_id: str,
) -> Path:
    """nav_msgs/Path of a predicted path: one PoseStamped per point (k), stamped with its
    step's time (ns), position from the layout's x, y and orientation from its yaw when the
    path carries them (columns of X (k, d) are the state components ``indices``; an absent
    yaw is identity). The covariances are not carried: a Path has none."""
    idx = layout.indices()
    col = {name: list(indices).index(i) for name, i in idx.items() if i in indices}
    if "x" not in col or "y" not in col:
        raise ValueError(f"the path carries components {list(indices)}, not the layout's x "
                         f"and y ({idx.get('x')}, {idx.get('y')})")
    if X.ndim != 2 or X.shape != (len(stamps), len(indices)) or not np.all(np.isfinite(X)):
        raise ValueError(f"path means must be finite, {len(stamps)} x {len(indices)}")
    poses = []
    for t, row in zip(stamps, X, strict=True):
        yaw = float(row[col["yaw"]]) if "yaw" in col else 0.0
        poses.append(PoseStamped(header=header(int(t), frame_id), pose=Pose(
            position=Point(x=float(row[col["x"]]), y=float(row[col["y"]]), z=0.0),
            orientation=quaternion_of_yaw(yaw))))
    return Path(header=header(int(stamps[-1]), frame_id), poses=poses)
