"""StepClock: the daemon's wall-clock time for steps, advanced by a monotonic clock.

Sessions map time to steps through the wall clock (``step = (t - epoch_ns) // period_ns``,
the senders' stamps are wall-clock times), so the daemon needs wall time; but the host's
wall clock may step (an NTP correction of a second, +1 h after a dead RTC), and a step read
straight from it makes every session's ``now`` leap by accident. The StepClock reads

    now = anchor_wall + (mono - anchor_mono) + slew      (ns)

anchored to the wall clock once. At each read it compares with the wall clock,
``err = wall - now``:

- ``|err| <= bound``: the difference is drift or an NTP slew; the mapping follows it by at
  most ``max_slew`` ns per ns of monotonic time (500 ppm, ntpd's own limit), so ``now``
  never goes backwards and never leaps;
- ``|err| > bound``: the host clock stepped; the mapping is re-anchored to the wall clock
  at once, deliberately: counted (:attr:`steps`), handed to ``on_step`` (the daemon logs
  it and counts ``clock_steps``), remembered (:meth:`stepped_near`) so that the refusals it
  causes are counted under their own reason (``clock_step``).

Thread-safe (the transport threads stamp arrivals with it, the worker reads it each loop).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Final

#: Default largest difference (ns) from the wall clock followed by slewing.
STEP_BOUND_NS: Final = 500_000_000
#: Largest slew rate (ns of correction per ns of monotonic time).
MAX_SLEW: Final = 5e-4
#: How long after a step (ns, beyond the step's own size) refusals are blamed on it.
STEP_SETTLE_NS: Final = 1_000_000_000


class StepClock:
    """Wall-clock ns advanced by a monotonic clock (module docstring). Call it for ``now``."""

    def __init__(self, wall_ns: Callable[[], int] = time.time_ns,
                 mono_ns: Callable[[], int] = time.monotonic_ns,
                 bound_ns: int = STEP_BOUND_NS,
                 on_step: Callable[[int, int], None] | None = None) -> None:
        self._wall, self._mono = wall_ns, mono_ns
        self.bound_ns = bound_ns
        #: Called (outside the clock's lock) with (step ns, new now ns) at each re-anchor.
        self.on_step = on_step
        self._lock = threading.Lock()
        self._anchor_mono = mono_ns()
        self._anchor_wall = wall_ns()
        self._last_mono = self._anchor_mono
        self._last = self._anchor_wall
        #: Re-anchors so far, and the sum of their steps (ns; how far the mapping moved).
        self.steps = 0
        self.stepped_ns = 0
        #: The last step: (now right after it, |step|) in ns; (0, -1) before any.
        self._step_at, self._step_size = 0, -1

    def __call__(self) -> int:
        mono, wall = self._mono(), self._wall()
        step = 0
        with self._lock:
            now = self._anchor_wall + (mono - self._anchor_mono)
            err = wall - now
            if abs(err) > self.bound_ns:
                # a step of the host clock: re-anchored here, once, and said so
                self._anchor_wall, self._anchor_mono = wall, mono
                self.steps += 1
                self.stepped_ns += err
                self._step_at, self._step_size = wall, abs(err)
                now, step = wall, err
            elif err:
                # drift or a slew: followed at a bounded rate (never a leap, never backwards)
                room = int((mono - self._last_mono) * MAX_SLEW)
                corr = max(-room, min(room, err))
                if corr:
                    self._anchor_wall += corr
                    now += corr
            if not step and now < self._last:  # a concurrent reader saw a later instant
                now = self._last
            self._last, self._last_mono = now, max(mono, self._last_mono)
        if step and self.on_step is not None:
            self.on_step(step, now)
        return now

    def stepped_near(self, now_ns: int) -> bool:
        """A step happened recently enough to explain a stamp refused at ``now_ns``: within
        its own size plus :data:`STEP_SETTLE_NS` after it (the clocks of senders and daemon
        then disagree by the step)."""
        at, size = self._step_at, self._step_size
        return size >= 0 and at <= now_ns <= at + size + STEP_SETTLE_NS
