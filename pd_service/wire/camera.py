"""A robot's camera frame (``robot/p<k>/<session>/camera``, bridged by pd-link to
``pd/p<k>/<session>/camera``): a JPEG image stamped with its capture time, and the view it
was taken with, so that a display can draw a predicted pose on it (the "ghost"). The daemon
never reads it. Encoded with the protocol's msgpack codec (:func:`pd_service.wire.encode`,
``decode``; the image base64-encoded, as JSON viewers and Foxglove's CompressedImage take
it, since the codec refuses msgpack bin), docs/protocol.md section 4 and
``docs/schemas/CameraFrame.json``.

The view is one of two:

- top-down (orthographic), north up (``center_x``, ``center_y``, ``scale``): the world point
  (x, y) in the session's frame is at pixel

      u = width / 2 + scale * (x - center_x),   v = height / 2 - scale * (y - center_y)

  (u right, v down, pixel centres at half-integers), ``center`` the world point at the
  image's centre when the frame was captured (a chase view follows the robot: it moves);
- perspective (``pinhole``, :class:`~pd_service.wire.pinhole.PinholeView`): a real camera's
  intrinsics and distortion (from ``sensor_msgs/CameraInfo``), its mounting on the robot and
  the robot's pose at capture; a ground point projects by the pinhole equations there.
"""

from __future__ import annotations

import base64
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, StringConstraints, field_validator, model_validator

from .base import invalid
from .messages import Int64, Message, Name, NonNegInt
from .pinhole import PinholeView

#: Largest image a frame carries, bytes (base64: 4/3 of it; under the codec's 64 KiB).
MAX_IMAGE_BYTES = 45_000

Finite = Annotated[float, Field(allow_inf_nan=False, ge=-1e9, le=1e9)]


class CameraFrame(Message):
    """One camera frame: ``data`` (a ``format`` image of ``width`` x ``height`` pixels) taken at
    ``t_ns``, and its view (module docstring): the top-down fields ``center_x``, ``center_y``,
    ``scale``, or ``pinhole``; exactly one of the two."""

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="Sender's frame counter.")
    t_ns: Int64 = Field(description="Capture time, ns on the shared clock.")
    format: Literal["jpeg", "png"] = Field("jpeg", description="Image encoding.")
    data: Annotated[str, StringConstraints(min_length=4, max_length=MAX_IMAGE_BYTES * 4 // 3,
                                           pattern=r"^[A-Za-z0-9+/]*={0,2}$")] = Field(
        description="The encoded image, base64 (RFC 4648, padded).")
    width: Annotated[int, Field(ge=1, le=4096)] = Field(description="Image width, pixels.")
    height: Annotated[int, Field(ge=1, le=4096)] = Field(description="Image height, pixels.")
    center_x: Finite | None = Field(
        None, description="Top-down view: world x at the image centre at capture, m.")
    center_y: Finite | None = Field(
        None, description="Top-down view: world y at the image centre at capture, m.")
    scale: Annotated[float, Field(gt=0.0, le=1e6, allow_inf_nan=False)] | None = Field(
        None, description="Top-down view: pixels per metre.")
    pinhole: PinholeView | None = Field(None, description="Perspective view.")

    @model_validator(mode="after")
    def _one_view(self) -> CameraFrame:
        top = (self.center_x, self.center_y, self.scale)
        if self.pinhole is None and None in top:
            raise invalid("center_x", "a frame needs center_x, center_y and scale (top-down "
                                      "view) or pinhole")
        if self.pinhole is not None and top != (None, None, None):
            raise invalid("pinhole", "a frame has one view: pinhole or center_x, center_y, "
                                     "scale, not both")
        return self

    @field_validator("data")
    @classmethod
    def _base64(cls, value: str) -> str:
        if len(value) % 4:
            raise ValueError("base64: length is not a multiple of 4")
        return value

    def image(self) -> bytes:
        """The encoded image's bytes."""
        return base64.b64decode(self.data)

    def project(self, xy: np.ndarray) -> list[list[float]] | None:
        """Pixels [[u, v], ...] of ground points ``xy`` (N, 2) m in the session frame, in this
        frame's view (module docstring); None when one of them has no pixel (behind a
        perspective camera)."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.pinhole is not None:
            uv = self.pinhole.project(np.column_stack([pts, np.zeros(len(pts))]))
            return None if np.isnan(uv).any() else uv.tolist()
        assert self.center_x is not None and self.center_y is not None and self.scale
        return [[self.width / 2 + self.scale * (float(x) - self.center_x),
                 self.height / 2 - self.scale * (float(y) - self.center_y)] for x, y in pts]
