"""The restart and takeover of bench/faults.py, short: in the documented set-up (the SDK's
cached Robot and Operator, clients of the daemon as docs/clients.md says, default settings,
the paper run at 100 ms steps with its 1.2 s window), kill -9 and a restart 2 s later
(longer than the window), and kill -9 of the owner of two trusted instances. The first
prediction after either equals the run that never stopped (a mirror estimator fed what was
sent): the senders' caches were read back before it and what they held was taken in at
its own steps, none reset to the prior."""

from __future__ import annotations

import pytest

from tests.scripts import load_script

pytestmark = pytest.mark.integration


def _faults():
    return load_script("bench/faults.py", "bench_faults_resumed")


def _check(rows: list[dict], origin: str) -> None:
    assert rows
    for r in rows:
        assert r["origin"] == origin and r["readback"] == "answered", r
        assert r["first_ratio"] is not None and not r["reset_to_prior"], r
        # diag P of the first prediction within 10 % of the uninterrupted run's (the bar),
        # everything sent before it taken in
        assert 0.9 <= r["first_ratio_min"] and r["first_ratio"] <= 1.10, r
        assert r["first_lacks"] == (0, 0) and r["end_lacks"] == (0, 0), r


def test_a_restart_longer_than_the_window_resumes_with_everything_the_caches_kept(tmp_path):
    out = _faults().restart_run(sessions=2, down_s=2.0, max_delay=12, before_s=3.0,
                                after_s=1.0, root=tmp_path)
    _check(out["rows"], "checkpoint")
    assert out["service_counters"].get("resumed_stale", 0) == 2  # older than the window


def test_the_survivor_of_a_takeover_resumes_with_everything_the_caches_kept(tmp_path):
    out = _faults().takeover_run(sessions=4, max_delay=12, before_s=3.0, after_s=1.0,
                                 root=tmp_path)
    assert out["moved"] == len(out["rows"]) >= 1
    _check(out["rows"], "replica")
