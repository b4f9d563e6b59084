"""Small accounting helpers of the daemon: latency windows and their percentiles."""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence

import numpy as np


def percentiles(values: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """(p50, p99) of ``values`` (µs), clipped at 0; (0, 0) when empty.

    Linear interpolation between order statistics, as numpy's default: with the sorted
    values x_0..x_{n-1} and h = (n - 1) q, p_q = x_i + (h - i)(x_{i+1} - x_i), i = floor(h).
    The sort is numpy's, which runs without the GIL: a status query's thread never stops
    the worker while it sorts.
    """
    xs = np.sort(np.asarray(values, dtype=np.float64))
    n = int(xs.shape[0])
    if n == 0:
        return 0.0, 0.0

    def at(q: float) -> float:
        h = (n - 1) * q
        i = math.floor(h)
        j = min(i + 1, n - 1)
        lo, hi = float(xs[i]), float(xs[j])
        return max(lo + (h - i) * (hi - lo), 0.0)

    return at(0.50), at(0.99)


class LatencyWindow:
    """The last ``size`` latencies in µs (a ring of doubles); percentiles over that sliding
    window."""

    __slots__ = ("_buf", "_next", "_n", "_size")

    def __init__(self, size: int) -> None:
        self._buf = array("d", bytes(8 * size))
        self._size = size
        self._next = 0  # where the next value goes
        self._n = 0  # values held (<= size)

    def add(self, us: float) -> None:
        i = self._next
        self._buf[i] = us
        i += 1
        self._next = 0 if i == self._size else i
        if self._n < self._size:
            self._n += 1

    def __len__(self) -> int:
        return self._n

    def values(self) -> np.ndarray:
        """A copy of the window (µs, oldest first), e.g. taken under a lock and reduced
        outside it (one copy of the ring)."""
        ring = np.frombuffer(self._buf, dtype=np.float64)
        if self._n < self._size:
            return ring[: self._n].copy()
        return np.concatenate((ring[self._next :], ring[: self._next]))

    def percentiles(self) -> tuple[float, float]:
        """(p50, p99) in µs; (0, 0) when empty."""
        return percentiles(self.values())
