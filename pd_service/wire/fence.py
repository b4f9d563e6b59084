"""The readers' side of ownership terms (``Prediction.term``): drop output of an older term.

During a partition between instances two owners may publish one session's predictions on the
same key; each publishes with its ownership term, and the newer owner's term is larger
(docs/service.md, "Partition between instances"). A reader keeps the newest term seen per
session and drops a prediction of an older one (counted): it shows one owner's predictions,
never two interleaved. Used by the SDK's Display, pd-web, pd-viz and pd-ros2.
"""

from __future__ import annotations

#: Sessions whose newest term a fence remembers (the oldest seen forgotten first).
MAX_FENCED_SESSIONS = 100_000


class TermFence:
    """Newest ownership term seen per session; :meth:`admit` says whether a prediction of
    ``term`` is shown. ``dropped``: predictions refused as of an older term; ``changes``:
    how often a session's term grew (a takeover, a hand-over, a restart). Not thread-safe:
    its owner calls it under its own lock."""

    def __init__(self) -> None:
        self.newest: dict[str, int] = {}
        self.dropped = 0
        self.changes = 0

    def admit(self, session: str, term: int) -> bool:
        """True if a prediction of ``session`` published with ``term`` is shown: its term is
        the newest seen for the session or newer (then the newest from now on)."""
        seen = self.newest.get(session)
        if seen is None:
            if len(self.newest) >= MAX_FENCED_SESSIONS:
                self.newest.pop(next(iter(self.newest)))
            self.newest[session] = term
            return True
        if term == seen:
            return True
        if term > seen:
            self.newest[session] = term
            self.changes += 1
            return True
        self.dropped += 1
        return False
