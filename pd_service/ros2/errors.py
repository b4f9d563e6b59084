"""The error raised for ROS 2 input that cannot be used."""

from __future__ import annotations

from pd_service.wire.errors import WireError


class Ros2DecodeError(WireError):
    """A ROS 2 payload, attachment, token or message value that cannot be used: not valid CDR
    for the bound type, a bad attachment, a header stamp of zero, NaN in a pose, a covariance
    that is not positive semi-definite, ...

    It is a :class:`~pd_service.wire.errors.WireError`, so it is counted and reported like any
    native refusal. ``reason`` is one readable line naming the offending field.
    """
