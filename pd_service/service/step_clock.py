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
- ``|err| > bound``: the host clock stepped. Counted (:attr:`steps`), handed to ``on_step``
  (the daemon logs it and counts ``clock_steps``), remembered (:meth:`stepped_near`) so that
  the refusals it causes are counted under their own reason (``clock_step``); then, forward
  or more than :data:`BACK_SLEW_MAX_NS` back, the mapping is re-anchored to the wall clock
  at once, deliberately (forward the sessions' steps jump; back each holds its step until
  the clock is at it again); a smaller backward step is caught up at half speed
  (:data:`BACK_SLEW`: the steps go on, at half their rate, for twice the step), so that
  the sessions keep predicting through an NTP correction of a second.

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
#: How long after a step (ns, beyond the time it takes to follow it) refusals are blamed
#: on it.
STEP_SETTLE_NS: Final = 1_000_000_000
#: Largest backward step (ns) caught up by running slow rather than re-anchored.
BACK_SLEW_MAX_NS: Final = 2_000_000_000
#: The rate at which such a step is caught up (ns of correction per ns): half speed.
BACK_SLEW: Final = 0.5
#: How often (ns of monotonic time) a read compares with the wall clock; reads in between
#: extend the mapping alone (every sample is stamped: the comparison is the costly part).
CHECK_NS: Final = 1_000_000


class StepClock:
    """Wall-clock ns advanced by a monotonic clock (module docstring). Call it for ``now``."""

    def __init__(self, wall_ns: Callable[[], int] = time.time_ns,
                 mono_ns: Callable[[], int] = time.monotonic_ns,
                 bound_ns: int = STEP_BOUND_NS,
                 on_step: Callable[[int, int], None] | None = None,
                 check_ns: int = CHECK_NS) -> None:
        """``check_ns``: how often (ns of monotonic time) a read compares with the wall
        clock (0: at every read)."""
        self._wall, self._mono = wall_ns, mono_ns
        self.bound_ns = bound_ns
        self.check_ns = check_ns
        #: Called (outside the clock's lock) with (step ns, new now ns) at each re-anchor.
        self.on_step = on_step
        self._lock = threading.Lock()
        self._anchor_mono = mono_ns()
        self._anchor_wall = wall_ns()
        self._last_mono = self._anchor_mono
        self._last = self._anchor_wall
        #: Steps followed so far, and their sum (ns; how far the mapping moved).
        self.steps = 0
        self.stepped_ns = 0
        #: The last step: (now right after it, how long following it takes) in ns; (0, -1)
        #: before any.
        self._step_at, self._step_size = 0, -1
        #: A small backward step is being caught up at half speed.
        self._catching = False
        #: (anchor wall, anchor mono, mono of the last comparison): one tuple, replaced
        #: whole, so a read between comparisons needs no lock.
        self._fast = (self._anchor_wall, self._anchor_mono, self._anchor_mono)

    def __call__(self) -> int:
        mono = self._mono()
        wall0, mono0, checked = self._fast
        if 0 <= mono - checked < self.check_ns:
            now = wall0 + (mono - mono0)
            last = self._last
            if now < last:
                return last
            self._last = now
            return now
        return self._compared(mono)

    def _compared(self, mono: int) -> int:
        """A read that compares with the wall clock (module docstring)."""
        wall = self._wall()
        step = 0
        with self._lock:
            now = self._anchor_wall + (mono - self._anchor_mono)
            err = wall - now
            # while a small backward step is being caught up, only a further one beyond the
            # catch-up's own reach is a new step
            back = self.bound_ns + (BACK_SLEW_MAX_NS if self._catching else 0)
            if err > self.bound_ns or err < -back:
                # a step of the host clock: counted and said so, once
                self.steps += 1
                self.stepped_ns += err
                step = err
                if -BACK_SLEW_MAX_NS <= err < 0:  # caught up at half speed, below
                    self._catching = True
                    self._step_at, self._step_size = now, -2 * err
                else:  # re-anchored here
                    self._catching = False
                    self._anchor_wall, self._anchor_mono = wall, mono
                    self._step_at, self._step_size = wall, abs(err)
                    now, err = wall, 0
            if err:
                # drift or a slew: followed at a bounded rate (never a leap, never backwards)
                rate = BACK_SLEW if self._catching else MAX_SLEW
                room = int((mono - self._last_mono) * rate)
                corr = max(-room, min(room, err))
                if corr:
                    self._anchor_wall += corr
                    now += corr
            if self._catching and now <= wall:
                self._catching = False  # caught up
            if now < self._last and not (step and err == 0):  # a reader saw a later instant
                now = self._last
            self._last, self._last_mono = now, max(mono, self._last_mono)
            self._fast = (self._anchor_wall, self._anchor_mono, mono)
        if step and self.on_step is not None:
            self.on_step(step, now)
        return now

    def stepped_near(self, now_ns: int) -> bool:
        """A step happened recently enough to explain a stamp refused at ``now_ns``: within
        the time following it takes (a re-anchored step: its size; one caught up: twice
        its size) plus :data:`STEP_SETTLE_NS` after it (the clocks of senders and daemon
        then disagree by the step)."""
        at, size = self._step_at, self._step_size
        return size >= 0 and at <= now_ns <= at + size + STEP_SETTLE_NS
