"""Admission with the default settings admits the fleet the README promises: 1,000 paper
sessions on one instance, created by one client that respects the config rate (in-process:
ServiceCore on the in-memory bus, the clock injected; no wall time)."""

from __future__ import annotations

from pd_service.backends import command_dim, spec_cost
from pd_service.service import ServiceCore, Settings
from pd_service.service.admission import Ledger
from pd_service.transport import InMemoryBus
from pd_service.wire import CONFIG_RATE_LIMITED, encode, keys

from .helpers import Clock, Collector, paper_spec

FLEET = 1_000


def test_the_default_budgets_admit_a_thousand_paper_sessions():
    s = Settings(instance="a")
    led = Ledger(s.max_session_bytes, s.max_session_cpu, s.memory_budget_bytes, s.cpu_budget)
    for i in range(FLEET):
        spec = paper_spec(f"s{i}")
        led.admit(spec.session, spec_cost(spec, command_dim(spec)))
    assert led.cpu <= s.cpu_budget and led.bytes <= s.memory_budget_bytes


def test_a_fleet_created_at_once_is_admitted_at_the_config_rate():
    """One client puts 1,000 specs as fast as the service lets it: what the rate limits
    refuse comes back with a reason starting ``config_rate_limited`` and is put again later
    (as the SDK's Admin does); in the end every session runs, none refused by admission."""
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    core = ServiceCore(bus.transport(), Settings(instance="a"), store=None, now_ns=clock,
                       run_clock_ns=lambda: 0, spawn=lambda fn: fn())
    core.start()
    cli = bus.transport()
    waiting = [paper_spec(f"s{i}") for i in range(FLEET)]
    rounds = 0
    while waiting and rounds < 1_000:
        rounds += 1
        for spec in waiting:
            cli.put(keys.config_key(spec.session), encode(spec))
        while core.has_work():
            core.run_once()
        running = set(core.service_status().sessions)
        waiting = [s for s in waiting if s.session not in running]
        clock.t += 1_000_000_000  # a second later: the rate limits' tokens are back
        assert all(e.reason.startswith(CONFIG_RATE_LIMITED)
                   for errs in col.errors.values() for e in errs), "a refusal not by rate"
    st = core.service_status()
    assert len(st.sessions) == FLEET
    assert "admission_refused" not in st.counters
    assert st.counters["config_rate_limited"] > 0  # the rate did limit the burst


def test_a_change_the_service_wide_rate_refused_keeps_the_sessions_share():
    """The service's bucket refuses s2's put: s2's own bucket (burst 1, nearly no refill)
    is not spent, so its put once the service's bucket refilled is admitted."""
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    core = ServiceCore(bus.transport(), Settings(
        instance="a", config_rate=0.001, config_burst=1, config_rate_total=1.0,
        config_burst_total=1), store=None, now_ns=clock, run_clock_ns=lambda: 0,
        spawn=lambda fn: fn())
    core.start()
    cli = bus.transport()
    for name in ("s1", "s2"):
        cli.put(keys.config_key(name), encode(paper_spec(name)))
    core.run_once()
    assert core.service_status().sessions == ["s1"]
    assert col.errors["s2"][-1].reason.startswith(CONFIG_RATE_LIMITED)
    clock.t += 1_000_000_000  # the service's bucket has a token again, s2's would not
    cli.put(keys.config_key("s2"), encode(paper_spec("s2")))
    core.run_once()
    assert core.service_status().sessions == ["s1", "s2"]
