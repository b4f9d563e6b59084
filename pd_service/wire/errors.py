"""The one error type the wire layer raises for bad data."""

from __future__ import annotations

#: Longest reason kept in a :class:`WireError` (characters); longer ones are clipped.
MAX_REASON_CHARS = 300


class WireError(ValueError):
    """A message that cannot be encoded, decoded or accepted.

    ``reason`` is one short line a person can read, starting with the offending field when
    there is one, e.g. ``"Measurement.z: expected 2 values for sensor 'camera', got 3"``.
    """

    def __init__(self, reason: str) -> None:
        reason = clip(str(reason))
        super().__init__(reason)
        self.reason = reason


def clip(text: str, limit: int = MAX_REASON_CHARS) -> str:
    """Return ``text`` on one line, at most ``limit`` characters (ending in '...' if cut)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."
