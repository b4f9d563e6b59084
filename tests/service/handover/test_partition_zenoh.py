"""A partition between two daemon processes over real Zenoh on loopback, then its heal
(bench/partition.py's set-up: two Python routers, the router-to-router link cut through a
relay, pd-a on router-a and pd-b on router-b, half the senders on each side, an SDK Display
per session on each router).

During the partition both instances serve every session; no Display shows an older term
after a newer one (raw subscribers may, where the two owners' outputs overlap at the heal). After the
heal one instance serves each session, and the predictions stay within 2x the diag P of the
uninterrupted run (every sample fed, in order, to one offline estimator). Bounds here are
generous for a loaded machine; bench/partition.py prints the figures.
Run alone with ``pytest tests/service/handover/test_partition_zenoh.py -m integration -s``.
"""

from __future__ import annotations

import argparse

import pytest

from tests.scripts import load_script

pytestmark = pytest.mark.integration


def load_bench():
    return load_script("bench/partition.py", "bench_partition")


def test_a_partition_and_its_heal_show_one_owner_per_session_and_keep_the_estimate():
    bench = load_bench()
    args = argparse.Namespace(sessions=6, warm=3.0, partition=3.0, after=5.0, seed=3)
    r = bench.one_run(args)
    print(r)
    assert r["taken_over"] == 6, r  # each side took the other's sessions over
    # two owners' outputs may overlap on a key at the heal (raw subscribers see both terms
    # interleaved when they do); a Display never shows an older term after a newer one
    assert r["display_interleaved"] == 0, r
    assert r["stale_dropped"] >= 1 or r["two_owner_keys"] == 0, r
    assert r["one_owner_s"] is not None, r  # one owner per session before the run ended
    assert r["yielded"] + r["kept"] >= 6, r  # every doubly served session settled
    assert r["diagP_after"] is not None and r["diagP_after"] <= 2.0, r


def test_interleaved_terms_are_told_apart():
    bench = load_bench()
    assert bench.interleaved([5, 5, 9, 5]) and not bench.interleaved([5, 5, 9, 9, 12])
