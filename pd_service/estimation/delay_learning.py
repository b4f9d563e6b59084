"""Delays learned online: per stream the observed delays, the window that would have taken
them, and the lead at which commands take effect.

A :class:`DelayStats` keeps the newest ``capacity`` delays of one stream (a ring: bounded
memory), each as ns and as a step gap ``g = step(later) - step(earlier)`` with
``step(t) = floor((t - epoch_ns) / period_ns)``, both times on one timeline (the daemon's;
robot stamps mapped with the clock-offset estimate first). Two uses:

- **measurements** (sample stamp -> receipt): the daemon accepts a sample iff its gap is
  ``<= max_delay``, so the smallest window refusing at most a share q as late is
  ``W* = min { W : #{g_i > W} <= q n }``, the ``ceil((1 - q) n)``-th smallest gap;
  :meth:`DelayStats.recommended_window` adds ``floor(margin W*)`` (margin <= 0.2: the
  recommendation stays within 1.2 W*) for the delays the window has not seen yet.
- **commands** (issued -> applied, from the robot's echoes): the recommended ``lead`` is a
  quantile of the gaps, the median by default (:data:`LEAD_QUANTILE`: the apply step of a
  command sent now is then as often earlier as later than predicted; a higher quantile
  predicts further ahead).

Pure numpy; time is passed in.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass
from typing import Final

import numpy as np

#: The quantile of issue -> applied gaps recommended as ``lead`` (the median).
LEAD_QUANTILE: Final = 0.5
#: The share refused as late that the recommended window allows by default (0.1 %).
LATE_SHARE: Final = 1e-3


@dataclass(frozen=True)
class DelaySummary:
    """The observed delays of one stream (ns; None when none yet): how many are kept
    (``count``, of ``seen`` in all), p50 / p90 / p99 / max, and the step gaps' maximum."""

    seen: int
    count: int
    p50_ns: int | None
    p90_ns: int | None
    p99_ns: int | None
    max_ns: int | None
    max_gap: int | None


class DelayStats:
    """The newest ``capacity`` delays of one stream (see the module docstring)."""

    def __init__(self, period_ns: int, epoch_ns: int, capacity: int = 4096) -> None:
        if period_ns <= 0 or capacity < 1:
            raise ValueError("delay stats: period_ns and capacity must be positive")
        self.period_ns = period_ns
        self.epoch_ns = epoch_ns
        self.capacity = capacity
        # int64 rings (array.array): a sample costs two element writes of plain ints (a
        # numpy element write converts a scalar: several times dearer), a read views them as
        # numpy arrays without a copy; grown by doubling while they fill, so a stream that
        # never sends costs no memory
        self._ns = array("q")
        self._gap = array("q")
        self._size = 0  # allocated
        self._n = 0  # kept
        self._next = 0  # ring position
        self.seen = 0

    def add(self, earlier_ns: int, later_ns: int) -> None:
        """One delay: from ``earlier_ns`` (sample stamp / command issued) to ``later_ns``
        (receipt / applied), ns on one timeline. Negative delays are kept as they are (a
        clock-offset estimate off by more than the delay shows up in them)."""
        p, e = self.period_ns, self.epoch_ns
        i = self._next
        if i == self._size:  # filling: full rings wrap before this
            self._grow()
        self._ns[i] = later_ns - earlier_ns
        self._gap[i] = (later_ns - e) // p - (earlier_ns - e) // p
        i += 1
        self._next = 0 if i == self.capacity else i
        if self._n < self.capacity:
            self._n += 1
        self.seen += 1

    def _grow(self) -> None:
        """Double the rings (16 at first; at most ``capacity``), keeping what they hold."""
        size = min(self.capacity, max(16, 2 * self._size))
        more = array("q", bytes(8 * (size - self._size)))
        self._ns, self._gap = self._ns + more, self._gap + more
        self._size = size

    def copy(self) -> DelayStats:
        """An independent copy of what is kept (the same statistics; later adds reach only
        one of them): taken under a lock, read after it is released."""
        out = DelayStats(self.period_ns, self.epoch_ns, self.capacity)
        out._ns, out._gap = array("q", self._ns), array("q", self._gap)
        out._size, out._n, out._next, out.seen = self._size, self._n, self._next, self.seen
        return out

    def _kept(self, ring: array[int]) -> np.ndarray:
        """The kept values of ``ring`` (n,), in ring order: a view, no copy."""
        return np.frombuffer(ring, dtype=np.int64, count=self._n)

    def __len__(self) -> int:
        return self._n

    def _oldest_first(self, ring: array[int]) -> np.ndarray:
        kept = self._kept(ring)
        if self._n < self.capacity:
            return kept.copy()
        return np.concatenate((kept[self._next:], kept[: self._next]))

    def gaps(self) -> np.ndarray:
        """The kept step gaps (n,), oldest first."""
        return self._oldest_first(self._gap)

    def delays_ns(self) -> np.ndarray:
        """The kept delays (n,), ns, oldest first."""
        return self._oldest_first(self._ns)

    def summary(self) -> DelaySummary:
        """p50 / p90 / p99 / max of the kept delays (the higher order statistic: an
        observed value)."""
        if not self._n:
            return DelaySummary(self.seen, 0, None, None, None, None, None)
        n = self._n
        d = np.sort(self._kept(self._ns))
        # numpy's quantile with method "higher": the sorted value at ceil(q (n - 1))
        q = [int(d[math.ceil(f * (n - 1))]) for f in (0.5, 0.9, 0.99)]
        return DelaySummary(self.seen, n, q[0], q[1], q[2], int(d[-1]),
                            int(self._kept(self._gap).max()))

    def share_above(self, window: int) -> float:
        """The share of kept gaps above ``window`` steps (those a window of that size would
        have refused as late); 0.0 when none is kept."""
        if not self._n:
            return 0.0
        return float(np.count_nonzero(self._kept(self._gap) > window)) / self._n

    def smallest_window(self, share: float = LATE_SHARE) -> int | None:
        """``W* = min { W >= 0 : #{g_i > W} <= share n }`` (steps); None when none is kept."""
        n = self._n
        if not n:
            return None
        if not 0.0 <= share < 1.0:
            raise ValueError(f"share: must be in [0, 1), got {share!r}")
        allowed = math.floor(share * n + 1e-9)  # gaps that may stay above the window
        g = np.sort(self._kept(self._gap))
        return max(0, int(g[n - 1 - allowed]))

    def recommended_window(self, share: float = LATE_SHARE, margin: float = 0.1) -> int | None:
        """``W* + floor(margin W*)`` (steps; ``0 <= margin <= 0.2``: at most 1.2 W*)."""
        if not 0.0 <= margin <= 0.2:
            raise ValueError(f"margin: must be in [0, 0.2], got {margin!r}")
        w = self.smallest_window(share)
        return None if w is None else w + math.floor(margin * w)

    def quantile_gap(self, q: float = LEAD_QUANTILE) -> int | None:
        """The q-quantile of the kept gaps (steps, an observed value: the higher one), e.g.
        the recommended lead of issue -> applied gaps; None when none is kept."""
        if not self._n:
            return None
        if not 0.0 <= q <= 1.0:
            raise ValueError(f"q: must be in [0, 1], got {q!r}")
        n = self._n
        return int(np.sort(self._kept(self._gap))[math.ceil(q * (n - 1))])  # numpy's "higher"
