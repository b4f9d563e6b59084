"""A robot's camera frame (``robot/p<k>/<session>/camera``, bridged by pd-link to
``pd/p<k>/<session>/camera``): a JPEG image stamped with its capture time, and the view it
was taken with, so that a display can draw a predicted pose on it (the "ghost"). The daemon
never reads it. Encoded with the protocol's msgpack codec (:func:`pd_service.wire.encode`,
``decode``; the image base64-encoded, as JSON viewers and Foxglove's CompressedImage take
it, since the codec refuses msgpack bin), docs/protocol.md section 4 and
``docs/schemas/CameraFrame.json``.

The view is a top-down (orthographic) camera, north up: the world point (x, y) in the
session's frame is at pixel

    u = width / 2 + scale * (x - center_x),   v = height / 2 - scale * (y - center_y)

(u right, v down, pixel centres at half-integers), ``center`` the world point at the image's
centre when the frame was captured (a chase view follows the robot: it moves per frame).
"""

from __future__ import annotations

import base64
from typing import Annotated, Literal

from pydantic import Field, StringConstraints, field_validator

from .messages import Int64, Message, Name, NonNegInt

#: Largest image a frame carries, bytes (base64: 4/3 of it; under the codec's 64 KiB).
MAX_IMAGE_BYTES = 45_000

Finite = Annotated[float, Field(allow_inf_nan=False, ge=-1e9, le=1e9)]


class CameraFrame(Message):
    """One camera frame: ``data`` (a ``format`` image of ``width`` x ``height`` pixels) taken at
    ``t_ns``, and its top-down view (module docstring)."""

    session: Name = Field(description="Session id.")
    seq: NonNegInt = Field(description="Sender's frame counter.")
    t_ns: Int64 = Field(description="Capture time, ns on the shared clock.")
    format: Literal["jpeg"] = Field("jpeg", description="Image encoding.")
    data: Annotated[str, StringConstraints(min_length=4, max_length=MAX_IMAGE_BYTES * 4 // 3,
                                           pattern=r"^[A-Za-z0-9+/]*={0,2}$")] = Field(
        description="The encoded image, base64 (RFC 4648, padded).")
    width: Annotated[int, Field(ge=1, le=4096)] = Field(description="Image width, pixels.")
    height: Annotated[int, Field(ge=1, le=4096)] = Field(description="Image height, pixels.")
    center_x: Finite = Field(description="World x at the image centre at capture, m.")
    center_y: Finite = Field(description="World y at the image centre at capture, m.")
    scale: Annotated[float, Field(gt=0.0, le=1e6, allow_inf_nan=False)] = Field(
        description="Pixels per metre.")

    @field_validator("data")
    @classmethod
    def _base64(cls, value: str) -> str:
        if len(value) % 4:
            raise ValueError("base64: length is not a multiple of 4")
        return value

    def image(self) -> bytes:
        """The encoded image's bytes."""
        return base64.b64decode(self.data)

    def pixel(self, x: float, y: float) -> tuple[float, float]:
        """Pixel (u, v) of the world point (x, y) (module docstring)."""
        return (self.width / 2 + self.scale * (x - self.center_x),
                self.height / 2 - self.scale * (y - self.center_y))
