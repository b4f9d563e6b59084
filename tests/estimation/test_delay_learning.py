"""Delays learned online: the recommended window against a brute-force search over windows,
its late share on fresh delays from the same distribution, the lead quantile, the ring's
bounded memory."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.delay_learning import DelayStats

P = 20_000_000  # 20 ms steps


def feed(stats: DelayStats, delays_ns: np.ndarray, rng: np.random.Generator) -> None:
    for d in delays_ns:
        t = int(rng.integers(0, 10**12))
        stats.add(t, t + int(d))


def brute_force_window(gaps: np.ndarray, share: float) -> int:
    w = 0
    while np.count_nonzero(gaps > w) > share * gaps.size + 1e-9:
        w += 1
    return w


@pytest.mark.parametrize("seed", range(8))
def test_the_smallest_window_is_the_brute_force_one_and_the_recommendation_within_1_2x(
        seed: int) -> None:
    rng = np.random.default_rng(seed)
    stats = DelayStats(P, 0, capacity=3000)
    # the field link: 600 ms +- 50 ms down, a 2 % tail of 0.1-1 s more
    d = 0.6e9 + rng.uniform(-0.05e9, 0.05e9, 3000)
    tail = rng.random(3000) < 0.02
    d[tail] += rng.uniform(0.1e9, 1e9, tail.sum())
    feed(stats, d, rng)
    for share in (0.0, 1e-3, 0.01, 0.05):
        w = stats.smallest_window(share)
        assert w == brute_force_window(stats.gaps(), share)
        assert stats.share_above(w) <= share
        assert w == 0 or stats.share_above(w - 1) > share
        rec = stats.recommended_window(share)
        assert rec is not None and w <= rec <= 1.2 * w
    # fresh delays of the same distribution: the recommended window's late share
    fresh = DelayStats(P, 0, capacity=20000)
    d2 = 0.6e9 + rng.uniform(-0.05e9, 0.05e9, 20000)
    tail2 = rng.random(20000) < 0.02
    d2[tail2] += rng.uniform(0.1e9, 1e9, tail2.sum())
    feed(fresh, d2, rng)
    rec = stats.recommended_window(1e-3)
    assert rec is not None
    print(f"\nseed {seed}: W* {stats.smallest_window(1e-3)} steps, recommended {rec}, late "
          f"share on fresh delays {fresh.share_above(rec):.4%}")


def test_lead_is_the_median_gap_and_memory_is_bounded() -> None:
    stats = DelayStats(P, 0, capacity=100)
    for k in range(1000):  # issue at a step start, applied 5 or 7 steps later (k odd/even)
        t = k * P
        stats.add(t, t + (5 if k % 2 else 7) * P + 1)
    assert len(stats) == 100 and stats.seen == 1000
    assert stats.quantile_gap(0.5) == 7  # higher of the two middle values (5 and 7)
    assert stats.quantile_gap(0.0) == 5 and stats.quantile_gap(1.0) == 7
    s = stats.summary()
    assert (s.count, s.seen, s.max_gap, s.max_ns) == (100, 1000, 7, 7 * P + 1)
    assert stats.delays_ns()[-2:].tolist() == [7 * P + 1, 5 * P + 1]  # k = 998, 999: newest last


def test_rings_grow_as_they_fill_and_a_copy_is_independent() -> None:
    stats = DelayStats(P, 0, capacity=100)
    ref = []
    for k in range(250):  # past the capacity: the ring wraps after growing 16, 32, 64, 100
        stats.add(k * P, k * P + (k % 7) * P)
        ref.append((k % 7) * P)
        assert stats.delays_ns().tolist() == ref[-100:]
    copy = stats.copy()
    stats.add(0, 50 * P)
    assert copy.summary().max_gap == 6 and stats.summary().max_gap == 50
    assert copy.gaps().tolist() == [d // P for d in ref[-100:]]
    assert DelayStats(P, 0).copy().summary().count == 0


def test_gaps_count_step_boundaries_not_durations() -> None:
    stats = DelayStats(P, 5, capacity=10)
    stats.add(5 + P - 1, 5 + P + 1)  # 2 ns across a step boundary: gap 1
    stats.add(5, 5 + P - 1)  # nearly a step inside one step: gap 0
    assert stats.gaps().tolist() == [1, 0]
    assert stats.smallest_window(0.0) == 1 and stats.smallest_window(0.5) == 0


def test_empty_and_bad_arguments() -> None:
    stats = DelayStats(P, 0)
    assert stats.smallest_window() is None and stats.quantile_gap() is None
    assert stats.summary().p50_ns is None and stats.share_above(3) == 0.0
    stats.add(0, 1)
    with pytest.raises(ValueError, match="margin"):
        stats.recommended_window(margin=0.5)
    with pytest.raises(ValueError, match="share"):
        stats.smallest_window(1.0)
    with pytest.raises(ValueError):
        DelayStats(0, 0)
