"""The fast cases of the attack suite (bench/attack.py) on the in-memory core with an injected
clock: each attack runs beside an innocent paper session, which must keep one prediction per
step (counted by step, not by wall time); the daemon must not raise and must count what it
refused."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.transport import InMemoryBus
from pd_service.wire import encode, keys
from tests.service.helpers import Clock, Collector, cmd_bytes, meas_bytes, paper_spec, storm
from tests.service.test_core import at, make_core
from tests.service.test_hardening import big_linear_spec
from tests.service.test_nonlinear import omni_spec

LEAD = paper_spec("x").lead
STEPS = range(5, 45)


class _Q:
    """A status query as the queryable sees it (replies dropped)."""

    def __init__(self, key: str) -> None:
        self.key = key

    def reply(self, key: str, payload: bytes) -> None:
        pass

    def reply_err(self, payload: bytes) -> None:
        pass


def _big(cli, core, k, rng):
    if k == 5:
        for i in range(4):
            cli.put(keys.config_key(f"big{i}"), encode(big_linear_spec(f"big{i}", i)))
        return 4
    return 0


def _spec_flood(cli, core, k, rng):
    for i in range(40):
        cli.put(keys.config_key("evil"), encode(paper_spec("evil", max_delay=12 + (k + i) % 50)))
    return 40


def _unscented(cli, core, k, rng):
    if k == 5:
        spec = omni_spec("ukf").model_copy(update={"lead": 1000, "period_ns": 1_000_000})
        cli.put(keys.config_key("ukf"), encode(spec))
        return 1
    return 0


def _huge(cli, core, k, rng):
    cli.put(keys.sensor_key("evil", "ranger"), meas_bytes("evil", "ranger", k, [1e308]))
    cli.put(keys.command_key("evil"), cmd_bytes("evil", k + 5, [1e308]))
    return 2


def _hostile(cli, core, k, rng):
    batch = storm("evil", rng) + storm("ghost", rng)
    for key, data in batch:
        cli.put(key, data)
    return len(batch)


def _status_storm(cli, core, k, rng):
    q = core.queries
    for _ in range(50):
        q.on_status_query(_Q(keys.ALL_STATUS))  # type: ignore[arg-type]
        q.on_status_query(_Q(keys.status_key("innocent")))  # type: ignore[arg-type]
        q.on_service_query(_Q(keys.service_status_key("a")))  # type: ignore[arg-type]
    return 150


def _fake_tokens(cli, core, k, rng):
    if k == 5:
        _fake_tokens.held = [cli.declare_token(keys.service_token_key(f"fake{i}"))
                             for i in range(10)]
        return 10
    return 0


ATTACKS = {  # name -> (attack per step, counter that must count its refusals, at least)
    "big_spec": (_big, "admission_refused", 4),
    "spec_flood": (_spec_flood, "config_rate_limited", 1000),
    "unscented_1ms": (_unscented, "admission_refused", 1),
    "huge_values": (_huge, "out_of_range", 40),
    "hostile_bytes": (_hostile, "malformed", 40),
    "status_storm": (_status_storm, None, 0),
    "fake_tokens": (_fake_tokens, "untrusted_peer", 10),
}


@pytest.mark.parametrize("name", list(ATTACKS))
def test_innocent_keeps_one_prediction_per_step(tmp_path, name):
    attack, counter, least = ATTACKS[name]
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("innocent"), encode(paper_spec("innocent")))
    cli.put(keys.config_key("evil"), encode(paper_spec("evil")))
    core.run_once()
    rng = np.random.default_rng(3)
    sent = 0
    for k in STEPS:
        clock.t = at(k + 0.1)
        cli.put(keys.sensor_key("innocent", "ranger"),
                meas_bytes("innocent", "ranger", k, [1.0], k))
        sent += attack(cli, core, k, rng)
        core.run_once()
        clock.t = at(k + 0.6)
        core.run_once()
    assert sent > 0
    steps = [p.step - LEAD for p in col.predictions["innocent"]]
    assert set(STEPS) <= set(steps)  # at least one prediction for every step
    assert all(np.isfinite(p.x).all() for p in col.predictions["innocent"])
    c = core.session_status("innocent").counters
    assert c["accepted"] == len(STEPS) and c.get("refused", 0) == 0
    if counter is not None:
        assert core.service_status().counters.get(counter, 0) >= least, \
            core.service_status().counters
    assert "innocent" in core.served_sessions()
