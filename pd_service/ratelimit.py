"""A token-bucket rate limiter (stdlib only): the daemon's and the ROS 2 bridge's limit on
error replies and configuration changes."""

from __future__ import annotations


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

    def refund(self) -> None:
        """Give back the token :meth:`allow` just took (another limit refused the event)."""
        self.tokens = min(self.burst, self.tokens + 1.0)
