"""Small accounting helpers of the daemon: latency windows and their percentiles."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable


def percentiles(values: Iterable[float]) -> tuple[float, float]:
    """(p50, p99) of ``values`` (µs), clipped at 0; (0, 0) when empty.

    Linear interpolation between order statistics, as numpy's default: with the sorted
    values x_0..x_{n-1} and h = (n - 1) q, p_q = x_i + (h - i)(x_{i+1} - x_i), i = floor(h).
    Plain Python (a sort of at most a few thousand floats): no first-call cost, nothing to
    warm up.
    """
    xs = sorted(values)
    if not xs:
        return 0.0, 0.0

    def at(q: float) -> float:
        h = (len(xs) - 1) * q
        i = math.floor(h)
        j = min(i + 1, len(xs) - 1)
        return max(xs[i] + (h - i) * (xs[j] - xs[i]), 0.0)

    return at(0.50), at(0.99)


class LatencyWindow:
    """The last ``size`` latencies in µs; percentiles over that sliding window."""

    __slots__ = ("_buf",)

    def __init__(self, size: int) -> None:
        self._buf: deque[float] = deque(maxlen=size)

    def add(self, us: float) -> None:
        self._buf.append(us)

    def __len__(self) -> int:
        return len(self._buf)

    def values(self) -> list[float]:
        """A copy of the window (µs), e.g. taken under a lock and reduced outside it."""
        return list(self._buf)

    def percentiles(self) -> tuple[float, float]:
        """(p50, p99) in µs; (0, 0) when empty."""
        return percentiles(self._buf)
