"""A synthetic camera for the simulated robot, rendered with Pillow, in either view of
:class:`pd_service.wire.camera.CameraFrame`:

- ``top`` (:func:`render`): straight down on the session's plane, north up, centred on the
  robot's true position at capture, ``scale`` pixels per metre;
- ``chase`` (:func:`render_chase`): a perspective camera mounted on the robot
  (:data:`CHASE_MOUNT`: behind and above it, looking forward and down; intrinsics
  :data:`CHASE_K`, mild barrel distortion :data:`CHASE_D`), as a teleoperated robot's own
  camera sees the ground ahead; each ground point drawn through the frame's pinhole view.

Both draw a grid line every metre (fixed to the world, so motion shows) and the robot's
outline (:data:`FOOTPRINT`, turned by its heading) filled. JPEG-encoded; deterministic for
the same inputs. Pillow is in the client's ``viz`` extra.
"""

from __future__ import annotations

import base64
import io
import math

import numpy as np

from pd_service.wire.camera import MAX_IMAGE_BYTES, CameraFrame
from pd_service.wire.pinhole import CameraMount, PinholeView

#: The robot's outline in its body frame (m): a 0.6 x 0.4 m body with a nose, x forward.
FOOTPRINT = np.array([[-0.3, -0.2], [0.2, -0.2], [0.35, 0.0], [0.2, 0.2], [-0.3, 0.2]])

WIDTH, HEIGHT, SCALE = 320, 240, 40.0
#: The chase camera: 1.6 m behind the body origin, 1.4 m up, pitched 0.5 rad down; a 320 x 240
#: image with a 90 degree horizontal field of view and a little barrel distortion.
CHASE_MOUNT = CameraMount(x=-1.6, z=1.4, pitch=0.5)
CHASE_K = [160.0, 0.0, 160.0, 0.0, 160.0, 120.0, 0.0, 0.0, 1.0]
CHASE_D = [-0.05, 0.004, 0.0, 0.0, 0.0]
#: Views :func:`render_view` draws.
VIEWS = ("top", "chase")


def outline(x: float, y: float, yaw: float) -> np.ndarray:
    """The footprint at pose (x, y, yaw) in the world frame, (5, 2) m:
    p = (x, y) + R(yaw) f."""
    c, s = math.cos(yaw), math.sin(yaw)
    return FOOTPRINT @ np.array([[c, s], [-s, c]]) + [x, y]


def ellipse_points(mean: tuple[float, float], cov: np.ndarray, k: float = 2.0,
                   segments: int = 48) -> list[tuple[float, float]]:
    """The k-sigma ellipse {m + k L (cos t, sin t)} of a 2x2 covariance (L: its Cholesky-like
    square root from the eigendecomposition, negative eigenvalues clipped to 0)."""
    w, v = np.linalg.eigh((cov + cov.T) / 2.0)
    L = v @ np.diag(np.sqrt(np.maximum(w, 0.0)))
    t = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    pts = np.asarray(mean)[:, None] + k * L @ np.vstack([np.cos(t), np.sin(t)])
    return [(float(a), float(b)) for a, b in pts.T]


def outline_px(frame: CameraFrame, x: float, y: float, yaw: float) -> list[list[float]] | None:
    """The footprint at (x, y, yaw) in ``frame``'s pixels (its capture-time view): the ghost;
    None when a corner has no pixel (behind a perspective camera)."""
    return frame.project(outline(x, y, yaw))


def render(session: str, seq: int, t_ns: int, x: float, y: float, yaw: float, *,
           width: int = WIDTH, height: int = HEIGHT, scale: float = SCALE,
           quality: int = 70) -> CameraFrame:
    """The frame of the robot at (x, y, yaw) captured at ``t_ns``."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (width, height), (24, 30, 38))
    d = ImageDraw.Draw(img)
    half_w, half_h = width / 2 / scale, height / 2 / scale
    for gx in range(math.floor(x - half_w), math.ceil(x + half_w) + 1):
        u = width / 2 + scale * (gx - x)
        d.line([(u, 0), (u, height)], fill=(52, 64, 80), width=1)
    for gy in range(math.floor(y - half_h), math.ceil(y + half_h) + 1):
        v = height / 2 - scale * (gy - y)
        d.line([(0, v), (width, v)], fill=(52, 64, 80), width=1)
    pts = [(width / 2 + scale * (px - x), height / 2 - scale * (py - y))
           for px, py in outline(x, y, yaw)]
    d.polygon(pts, fill=(232, 232, 232), outline=(255, 176, 32))
    return CameraFrame(session=session, seq=seq, t_ns=t_ns, data=_jpeg(img, quality),
                       width=width, height=height, center_x=float(x), center_y=float(y),
                       scale=scale)


def _jpeg(img: object, quality: int) -> str:
    """Base64 of the JPEG of ``img`` (a PIL image), at most MAX_IMAGE_BYTES."""
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=quality)  # type: ignore[attr-defined]
    data = buf.getvalue()
    if len(data) > MAX_IMAGE_BYTES:
        raise ValueError(f"frame of {len(data)} bytes exceeds {MAX_IMAGE_BYTES}: lower the "
                         "size or the quality")
    return base64.b64encode(data).decode()


def render_chase(session: str, seq: int, t_ns: int, x: float, y: float, yaw: float, *,
                 quality: int = 70, reach_m: float = 12.0) -> CameraFrame:
    """The chase camera's frame (module docstring) of the robot at (x, y, yaw) captured at
    ``t_ns``: the ground grid within ``reach_m`` of the robot, each line drawn through the
    frame's own projection (points behind the camera left out), and the robot."""
    from PIL import Image, ImageDraw

    frame = CameraFrame(session=session, seq=seq, t_ns=t_ns, data="AAAA", width=WIDTH,
                        height=HEIGHT, pinhole=PinholeView(
                            K=CHASE_K, distortion_model="plumb_bob", D=CHASE_D,
                            mount=CHASE_MOUNT, body_x=x, body_y=y, body_yaw=yaw))
    assert frame.pinhole is not None
    img = Image.new("RGB", (WIDTH, HEIGHT), (36, 44, 40))
    d = ImageDraw.Draw(img)
    d.rectangle([0, 0, WIDTH, HEIGHT * 0.22], fill=(58, 74, 96))  # sky beyond the reach
    t = np.linspace(-reach_m, reach_m, 97)
    for g in range(-math.ceil(reach_m), math.ceil(reach_m) + 1):
        for pts in (np.column_stack([np.full_like(t, math.floor(x) + g), y + t]),
                    np.column_stack([x + t, np.full_like(t, math.floor(y) + g)])):
            uv = frame.pinhole.project(np.column_stack([pts, np.zeros(len(t))]))
            ok = ~np.isnan(uv[:, 0]) & (np.abs(uv).max(axis=1) < 4 * WIDTH)
            for a, b in zip(uv[:-1][ok[:-1] & ok[1:]], uv[1:][ok[:-1] & ok[1:]], strict=True):
                d.line([tuple(a), tuple(b)], fill=(78, 96, 84), width=1)
    body = frame.project(outline(x, y, yaw))
    if body is not None:
        d.polygon([tuple(p) for p in body], fill=(232, 232, 232), outline=(255, 176, 32))
    return frame.model_copy(update={"data": _jpeg(img, quality)})


def render_view(view: str, session: str, seq: int, t_ns: int, x: float, y: float,
                yaw: float) -> CameraFrame:
    """The frame of ``view`` (one of :data:`VIEWS`)."""
    if view == "chase":
        return render_chase(session, seq, t_ns, x, y, yaw)
    return render(session, seq, t_ns, x, y, yaw)

