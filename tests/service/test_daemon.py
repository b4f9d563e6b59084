"""The worker's pacing (pd_service.service.daemon.round_pause)."""

from __future__ import annotations

import pytest

from pd_service.service.config import Settings
from pd_service.service.daemon import BATCH_TARGET, round_pause

INTERVAL, LINGER = 1e-3, 3e-3


def test_a_full_batch_waits_the_round_interval_only():
    assert round_pause(BATCH_TARGET, INTERVAL, LINGER) == INTERVAL
    assert round_pause(10 * BATCH_TARGET, INTERVAL, LINGER) == INTERVAL


def test_a_small_batch_waits_so_that_the_next_is_about_the_target():
    # half the target in one interval: the same rate fills the target in two
    assert round_pause(BATCH_TARGET // 2, INTERVAL, LINGER) == pytest.approx(2 * INTERVAL)
    # the pause shrinks as the batch grows, never below the interval
    pauses = [round_pause(h, INTERVAL, LINGER) for h in range(1, 2 * BATCH_TARGET)]
    assert pauses == sorted(pauses, reverse=True)
    assert min(pauses) == INTERVAL


def test_a_trickle_waits_the_linger_at_most():
    assert round_pause(1, INTERVAL, LINGER) == LINGER
    # a linger no longer than the interval: the interval, whatever the batch
    assert round_pause(1, INTERVAL, INTERVAL) == INTERVAL


def test_no_round_interval_no_pause():
    assert round_pause(1, 0.0, 0.0) == 0.0


def test_the_default_linger_keeps_a_message_inside_the_latency_goal():
    # docs/service.md: p99 receipt -> prediction within 5 ms; the linger is what a message
    # may wait in its queue on top of its loop
    s = Settings()
    assert s.round_interval_us <= s.round_linger_us < 5000
