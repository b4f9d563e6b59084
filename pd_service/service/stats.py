"""Small accounting helpers of the daemon: latency windows and a token-bucket rate limiter."""

from __future__ import annotations

from collections import deque

import numpy as np


class LatencyWindow:
    """The last ``size`` latencies in µs; percentiles over that sliding window."""

    __slots__ = ("_buf",)

    def __init__(self, size: int) -> None:
        self._buf: deque[float] = deque(maxlen=size)

    def add(self, us: float) -> None:
        self._buf.append(us)

    def __len__(self) -> int:
        return len(self._buf)

    def percentiles(self) -> tuple[float, float]:
        """(p50, p99) in µs; (0, 0) when empty."""
        if not self._buf:
            return 0.0, 0.0
        arr = np.fromiter(self._buf, dtype=np.float64, count=len(self._buf))
        p50, p99 = np.percentile(arr, [50.0, 99.0])
        return float(max(p50, 0.0)), float(max(p99, 0.0))


class TokenBucket:
    """At most ``rate`` events per second on average, bursts of ``burst``.

    ``allow(now_ns)``: tokens = min(burst, tokens + rate * dt); take one if >= 1.
    """

    __slots__ = ("rate", "burst", "tokens", "t_ns")

    def __init__(self, rate: float, burst: int, now_ns: int) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self.tokens = float(burst)
        self.t_ns = now_ns

    def allow(self, now_ns: int) -> bool:
        dt = max(0, now_ns - self.t_ns) * 1e-9
        self.t_ns = max(self.t_ns, now_ns)
        self.tokens = min(self.burst, self.tokens + self.rate * dt)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False
