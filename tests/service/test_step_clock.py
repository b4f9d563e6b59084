"""StepClock: wall-clock time advanced by a monotonic clock; drift followed by a bounded
slew (never a leap, never backwards), a step beyond the bound re-anchored once and counted."""

from __future__ import annotations

from pd_service.service.step_clock import (
    BACK_SLEW,
    BACK_SLEW_MAX_NS,
    CHECK_NS,
    MAX_SLEW,
    STEP_BOUND_NS,
    STEP_SETTLE_NS,
    StepClock,
)


class _Host:
    def __init__(self) -> None:
        self.wall, self.mono = 1_000_000_000_000, 5_000

    def tick(self, ns: int, drift: float = 0.0) -> None:
        self.mono += ns
        self.wall += ns + int(ns * drift)


def test_steady_clocks_read_the_wall_clock():
    h = _Host()
    c = StepClock(lambda: h.wall, lambda: h.mono, check_ns=0)
    for _ in range(10):
        h.tick(7_000_000)
        assert c() == h.wall
    assert (c.steps, c.stepped_ns) == (0, 0)


def test_drift_is_slewed_at_a_bounded_rate_and_never_backwards():
    h = _Host()
    c = StepClock(lambda: h.wall, lambda: h.mono, check_ns=0)
    last = c()
    for _ in range(2000):
        h.tick(10_000_000, drift=-1e-3)  # the wall clock runs slow by 1000 ppm
        now = c()
        assert now > last  # never backwards
        assert now - last >= int(10_000_000 * (1 - MAX_SLEW))  # never faster than the slew
        last = now
    assert c.steps == 0
    assert abs(c() - h.wall) <= 10_000_000 * 2000 * (1e-3 - MAX_SLEW) + 10


def test_a_step_beyond_the_bound_is_re_anchored_once_and_reported():
    h = _Host()
    seen: list[tuple[int, int]] = []
    c = StepClock(lambda: h.wall, lambda: h.mono, check_ns=0, on_step=lambda s, n: seen.append((s, n)))
    c()
    h.tick(1_000_000)
    h.wall -= STEP_BOUND_NS // 2  # within the bound: slewed, not a step
    c()
    assert c.steps == 0
    h.wall += STEP_BOUND_NS // 2 + 3_600_000_000_000  # +1 h
    now = c()
    assert now == h.wall and c.steps == 1 and seen == [(c.stepped_ns, now)]
    size = abs(c.stepped_ns)  # the hour and what was not yet slewed of the half bound
    assert size > 3_600_000_000_000
    assert c.stepped_near(now + size + STEP_SETTLE_NS)
    assert not c.stepped_near(now + size + STEP_SETTLE_NS + 1)
    assert not c.stepped_near(now - 1)
    h.tick(1_000_000)
    assert c() == h.wall and c.steps == 1  # exact again, once


def test_a_small_step_back_is_caught_up_at_half_speed():
    """1 s back: counted once; the clock runs at half speed (never back, never stopped)
    until it meets the wall clock (2 s), then follows it exactly."""
    h = _Host()
    c = StepClock(lambda: h.wall, lambda: h.mono, check_ns=0)
    c()
    h.wall -= 1_000_000_000
    start = c()
    assert c.steps == 1 and c.stepped_ns == -1_000_000_000
    last = start
    for _ in range(19):
        h.tick(100_000_000)
        now = c()
        assert now - last == int(100_000_000 * (1 - BACK_SLEW))  # half speed
        last = now
    assert c.steps == 1 and c() > h.wall
    h.tick(100_000_000)
    assert c() == h.wall  # caught up after 2 s
    h.tick(100_000_000)
    assert c() == h.wall and c.steps == 1
    assert c.stepped_near(start + 2_000_000_000 + STEP_SETTLE_NS)


def test_a_large_step_back_is_re_anchored():
    h = _Host()
    c = StepClock(lambda: h.wall, lambda: h.mono, check_ns=0)
    before = c()
    h.wall -= BACK_SLEW_MAX_NS + 1
    assert c() == h.wall < before  # steps hold in the sessions (Session.step_now)
    assert c.steps == 1


def test_reads_between_comparisons_extend_the_mapping_and_a_step_is_seen_within_check_ns():
    """(The other tests compare at every read, ``check_ns=0``.) By default a read compares
    with the wall clock once per CHECK_NS of monotonic time: in between it extends the
    mapping (never backwards), and a step of the wall clock is seen at the next comparison."""
    h = _Host()
    c = StepClock(lambda: h.wall, lambda: h.mono)
    start = c()
    h.wall += 3_600_000_000_000  # +1 h, seen only at the next comparison
    h.mono += CHECK_NS // 2
    assert c() == start + CHECK_NS // 2 and c.steps == 0
    h.mono += CHECK_NS
    assert c() == h.wall and c.steps == 1
