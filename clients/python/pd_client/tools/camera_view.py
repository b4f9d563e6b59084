"""A synthetic camera for the simulated robot: a top-down chase view rendered with Pillow.

Each frame looks straight down on the session's plane, north up, centred on the robot's true
position at capture, ``scale`` pixels per metre (the view of :class:`pd_service.wire.camera.
CameraFrame`): a grid line every metre (fixed to the world, so motion shows), and the robot's
outline (:data:`FOOTPRINT`, turned by its heading) filled. JPEG-encoded; deterministic for
the same inputs. Pillow is in the client's ``viz`` extra.
"""

from __future__ import annotations

import base64
import io
import math

import numpy as np

from pd_service.wire.camera import MAX_IMAGE_BYTES, CameraFrame

#: The robot's outline in its body frame (m): a 0.6 x 0.4 m body with a nose, x forward.
FOOTPRINT = np.array([[-0.3, -0.2], [0.2, -0.2], [0.35, 0.0], [0.2, 0.2], [-0.3, 0.2]])

WIDTH, HEIGHT, SCALE = 320, 240, 40.0


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
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=quality)
    data = buf.getvalue()
    if len(data) > MAX_IMAGE_BYTES:
        raise ValueError(f"frame of {len(data)} bytes exceeds {MAX_IMAGE_BYTES}: lower the "
                         "size or the quality")
    return CameraFrame(session=session, seq=seq, t_ns=t_ns,
                       data=base64.b64encode(data).decode(), width=width, height=height,
                       center_x=float(x), center_y=float(y), scale=scale)
