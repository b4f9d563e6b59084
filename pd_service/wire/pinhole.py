"""A perspective (pinhole) camera's view of one frame: its intrinsics as ``sensor_msgs/CameraInfo``
gives them, its mounting on the robot (a static extrinsic, as a URDF joint to ``camera_link``)
and the robot's pose when the frame was captured; and the projection of a world point into
the frame's pixels, so that a display draws the predicted pose (the "ghost") on the frame.

Frames (REP 103, REP 105): the session frame ``w`` (x, y on the ground, z up); the robot's body
``b`` at (body_x, body_y, 0) turned by body_yaw about z; the camera's link frame ``l`` (x
forward, y left, z up) at ``mount`` in ``b``; its optical frame ``o`` (z forward, x right,
y down). With Rz, Ry, Rx the rotations about z, y, x:

    R_wb = Rz(body_yaw),                  t_wb = (body_x, body_y, 0)
    R_bl = Rz(yaw) Ry(pitch) Rx(roll),    t_bl = (mount.x, mount.y, mount.z)
    R_lo = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]       (columns: o's axes in l)
    R_wo = R_wb R_bl R_lo,                t_wo = t_wb + R_wb t_bl
    (X, Y, Z) = R_wo^T (p_w - t_wo)                  the point in the optical frame

and, for Z > 0, the pinhole with OpenCV's distortion (``plumb_bob``: D = k1 k2 p1 p2 k3;
``rational_polynomial``: D = k1 k2 p1 p2 k3 k4 k5 k6; ``""``: none), K = [[fx s cx] [0 fy cy]
[0 0 1]] (the unrectified image's K, as CameraInfo gives it):

    x' = X / Z,  y' = Y / Z,  r2 = x'^2 + y'^2
    c  = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    x" = x' c + 2 p1 x' y' + p2 (r2 + 2 x'^2)
    y" = y' c + p1 (r2 + 2 y'^2) + 2 p2 x' y'
    u  = fx x" + s y" + cx,   v = fy y" + cy       (pixels; u right, v down)

A point with Z <= 0 (beside or behind the camera) has no pixel.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from .base import WireModel, invalid

Finite = Annotated[float, Field(allow_inf_nan=False, ge=-1e9, le=1e9)]

#: Distortion models a frame may name, and their number of coefficients D.
DISTORTION_SIZES: dict[str, int] = {"": 0, "plumb_bob": 5, "rational_polynomial": 8}
DistortionModel = Literal["", "plumb_bob", "rational_polynomial"]

#: REP 103: the optical frame's axes (columns) in the camera's link frame.
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: Nearest depth (m, along the optical axis) a projected point may have.
MIN_DEPTH_M = 1e-6


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` rad about z, (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` rad about y, (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` rad about x, (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


class CameraMount(WireModel):
    """The camera's link frame in the robot's body frame: position (m) and roll, pitch, yaw
    (rad; R = Rz(yaw) Ry(pitch) Rx(roll), as a URDF joint's ``rpy``). All zero: the camera
    at the body's origin looking forward along the body's x."""

    x: Finite = Field(0.0, description="Forward of the body origin, m.")
    y: Finite = Field(0.0, description="Left of the body origin, m.")
    z: Finite = Field(0.0, description="Above the body origin, m.")
    roll: Finite = Field(0.0, description="Rotation about the link's x, rad.")
    pitch: Finite = Field(0.0, description="Rotation about y, rad (positive: looking down).")
    yaw: Finite = Field(0.0, description="Rotation about z, rad.")

    def rotation(self) -> np.ndarray:
        """R_bl, (3, 3)."""
        return rot_z(self.yaw) @ rot_y(self.pitch) @ rot_x(self.roll)


class PinholeView(WireModel):
    """The view of a frame taken by a perspective camera (module docstring): intrinsics ``K``
    (row-major 3x3, CameraInfo's ``k``), distortion ``distortion_model`` + ``D``, the camera's
    ``mount`` on the robot, and the robot's body pose on the ground at capture."""

    K: Annotated[list[Finite], Field(min_length=9, max_length=9)] = Field(
        description="Intrinsics [fx, s, cx, 0, fy, cy, 0, 0, 1], pixels.")
    distortion_model: DistortionModel = Field("", description="OpenCV / ROS distortion model.")
    D: Annotated[list[Finite], Field(max_length=8)] = Field(
        default_factory=list, description="Distortion coefficients of the model, in its order.")
    mount: CameraMount = Field(description="The camera's link frame in the body frame.")
    body_x: Finite = Field(description="The robot's x at capture, m (session frame).")
    body_y: Finite = Field(description="The robot's y at capture, m.")
    body_yaw: Finite = Field(description="The robot's heading at capture, rad.")

    @model_validator(mode="after")
    def _intrinsics(self) -> PinholeView:
        K = self.K
        if not (K[0] > 0 and K[4] > 0):
            raise invalid("K", f"fx = {K[0]} and fy = {K[4]} must be > 0")
        if (K[3], K[6], K[7], K[8]) != (0.0, 0.0, 0.0, 1.0):
            raise invalid("K", "must be [fx, s, cx, 0, fy, cy, 0, 0, 1]")
        want = DISTORTION_SIZES[self.distortion_model]
        if len(self.D) != want:
            raise invalid("D", f"{self.distortion_model or 'no distortion'} takes {want} "
                               f"coefficients, got {len(self.D)}")
        return self

    def optical_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_wo (3, 3), t_wo (3,)): the optical frame in the session frame at capture."""
        R_wb = rot_z(self.body_yaw)
        R_wo = R_wb @ self.mount.rotation() @ R_LINK_OPTICAL
        m = self.mount
        t_wo = np.array([self.body_x, self.body_y, 0.0]) + R_wb @ np.array([m.x, m.y, m.z])
        return R_wo, t_wo

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points (N, 3) (module docstring); a row of NaN for a point
        with Z <= :data:`MIN_DEPTH_M`."""
        R_wo, t_wo = self.optical_pose()
        P = (np.asarray(points, dtype=np.float64) - t_wo) @ R_wo  # rows: R_wo^T (p - t)
        Z = P[:, 2]
        ahead = Z > MIN_DEPTH_M
        Zs = np.where(ahead, Z, 1.0)
        xp, yp = P[:, 0] / Zs, P[:, 1] / Zs
        d = [*self.D, *([0.0] * (8 - len(self.D)))]
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        r2 = xp * xp + yp * yp
        c = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = xp * c + 2 * p1 * xp * yp + p2 * (r2 + 2 * xp * xp)
        yd = yp * c + p1 * (r2 + 2 * yp * yp) + 2 * p2 * xp * yp
        fx, s, cx, _, fy, cy = self.K[:6]
        uv = np.column_stack([fx * xd + s * yd + cx, fy * yd + cy])
        uv[~ahead] = np.nan
        return uv
