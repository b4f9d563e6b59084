"""The router restart of bench/faults.py, short: one daemon and the SDK's cached senders,
clients of a Python router on loopback that is killed (SIGKILL) and started again on the
same port. Zenoh 1.10's clients reconnect by themselves and declare again what they had
declared (subscribers, queryables, liveliness tokens, the senders' caches); this checks that
the daemon and the SDK come back whole: every session predicting again, no reset to the
prior, no prediction twice, every declaration back."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.scenarios.paper import paper_prior
from tests.scripts import load_script


def _faults():
    return load_script("bench/faults.py", "bench_faults")


@pytest.mark.parametrize("link", [False, True], ids=["direct", "through-pd-link"])
def test_everything_comes_back_after_a_router_restart(tmp_path, link):
    """``link``: the robots' samples go through a pd-link process (itself a client of the
    router, its publishers cached)."""
    out = _faults().router_restart(sessions=3, down_s=1.0, before_s=1.5, after_s=1.5,
                                   root=tmp_path, link=link)
    prior = float(np.trace(paper_prior()[1]))
    for row in out["rows"]:
        assert row["gap_s"] is not None, row  # predicting again
        assert row["data_back_s"] is not None, row  # and accepting measurements
        assert not row["reset_to_prior"] and row["first_trace_P"] < prior, row
        assert row["duplicates"] == 0, row
        assert row["display_received_after"] > 0, row  # the SDK's Display shows them again
    assert out["declarations_before"]["subscriber"] > 0
    # the daemon's token, and per session at least the ranger's cache and the command's
    assert out["declarations_before"]["token"] >= 1 + 2 * 3
    assert out["declarations_missing"] == {"subscriber": [], "queryable": [], "token": []}
    assert out["send_errors"] == 0
