"""The one error type the wire layer raises for bad data."""

from __future__ import annotations

from typing import Literal

#: Longest reason kept in a :class:`WireError` (characters); longer ones are clipped.
MAX_REASON_CHARS = 300


#: What is wrong with a message, for counters (never derived from the reason's text):
#: ``malformed`` bytes or structure, ``non_finite`` NaN or infinity in a value.
ErrorKind = Literal["malformed", "non_finite"]


class WireError(ValueError):
    """A message that cannot be encoded, decoded or accepted.

    ``reason`` is one short line a person can read, starting with the offending field when
    there is one, e.g. ``"Measurement.z: expected 2 values for sensor 'camera', got 3"``.
    ``kind`` classifies it for counters; ``seq`` is the message's ``seq`` when it could be
    read even though the message as a whole could not (echoed in the ErrorReport).
    """

    def __init__(self, reason: str, kind: ErrorKind = "malformed", seq: int | None = None) -> None:
        reason = clip(str(reason))
        super().__init__(reason)
        self.reason = reason
        self.kind: ErrorKind = kind
        self.seq = seq


def clip(text: str, limit: int = MAX_REASON_CHARS) -> str:
    """Return ``text`` on one line, at most ``limit`` characters (ending in '...' if cut)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."
