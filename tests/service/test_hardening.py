"""Hardening of the daemon (ServiceCore on the in-memory bus, injected clock): admission by
cost, fair config scheduling, idle sessions, numerical health, honest persistence, receive
time, explicit membership."""

from __future__ import annotations

import numpy as np

from pd_service.estimation import linear as linear_mod
from pd_service.service import ServiceCore, Settings, SpecStore
from pd_service.service.admission import Ledger, Refused, spec_cost
from pd_service.transport import InMemoryBus
from pd_service.wire import (
    LinearModelSpec,
    SensorSpec,
    SessionSpec,
    UnscentedModelSpec,
    encode,
    keys,
)

from .helpers import PERIOD_NS, Clock, Collector, paper_spec
from .test_core import at, make_core
from .test_nonlinear import omni_spec


def big_linear_spec(session: str, seed: int) -> SessionSpec:
    """The attack: n = 64, lead 10,000, max_delay 1,000 and a distinct Q each time."""
    n = 64
    rng = np.random.default_rng(seed)
    q = np.diag(1e-3 + rng.random(n) * 1e-3)
    return SessionSpec(
        session=session, period_ns=PERIOD_NS, epoch_ns=0,
        model=LinearModelSpec(A=np.eye(n), B=np.eye(n), Q=q),
        x0=np.zeros(n), P0=np.eye(n),
        sensors=[SensorSpec(name="s", R=np.eye(n), delay=0, interval=1, H=np.eye(n))],
        lead=10_000, max_delay=1_000)


def world():
    bus = InMemoryBus()
    return bus, Clock(0), Collector().attach(bus.transport()), bus.transport()


# ---------------------------------------------------------------- admission ---------------

def test_cost_model_counts_the_tables_of_the_big_spec():
    c = spec_cost(big_linear_spec("big", 0))
    C = 3 * 1000 + 10_000 + 4
    assert c.table_bytes == 8 * ((C + 1) * 2 * 64 * 64 + C * 64 * 64)
    assert c.bytes > 10**9  # the 1.2 GB the attack allocated
    small = spec_cost(paper_spec("p"))
    assert small.bytes < 2**20 and small.cpu_share < 0.01


def test_big_linear_spec_is_refused_before_anything_is_allocated(tmp_path, monkeypatch):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    built = []
    real = linear_mod.PropagationTables.build
    monkeypatch.setattr(linear_mod.PropagationTables, "build",
                        classmethod(lambda cls, m, M: built.append(M) or real(m, M)))
    for i in range(4):
        cli.put(keys.config_key(f"big{i}"), encode(big_linear_spec(f"big{i}", i)))
    core.run_once()
    assert built == []  # no table was built
    assert core.served_sessions() == []
    assert all("max_session_bytes" in col.errors[f"big{i}"][0].reason for i in range(4))
    assert core.service_status().counters["admission_refused"] == 4
    assert not list((tmp_path / "a").glob("big*"))  # nothing persisted


def test_unscented_long_lead_at_1ms_is_refused_by_the_cpu_budget(tmp_path):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    spec = omni_spec("u1").model_copy(update={"lead": 1000, "period_ns": 1_000_000})
    cli.put(keys.config_key("u1"), encode(spec))
    core.run_once()
    assert core.served_sessions() == []
    assert "max_session_cpu" in col.errors["u1"][0].reason
    # the same model at its own period and lead fits
    cli.put(keys.config_key("u2"), encode(omni_spec("u2")))
    core.run_once()
    assert core.served_sessions() == ["u2"]


def test_service_wide_budgets_and_shared_tables_counted_once():
    a = spec_cost(paper_spec("a"))
    led = Ledger(2**30, 1.0, a.bytes + a.session_bytes, 10.0)
    led.admit("a", a)
    led.admit("b", spec_cost(paper_spec("b")))  # same model: its tables are not charged again
    assert led.bytes == a.bytes + a.session_bytes
    try:
        led.admit("c", spec_cost(paper_spec("c")))
    except Refused as exc:
        assert "memory_budget_bytes" in exc.reason
    else:
        raise AssertionError("over the memory budget")
    led.admit("a", spec_cost(paper_spec("a", max_delay=12)))  # replacing itself fits
    led.release("a")
    led.release("b")
    assert (led.bytes, led.cpu) == (0, 0.0)
    cpu = Ledger(2**30, 1.0, 2**40, 2.5 * a.cpu_share)
    cpu.admit("a", a)
    cpu.admit("b", a)
    try:
        cpu.admit("c", a)
    except Refused as exc:
        assert "cpu_budget" in exc.reason
    else:
        raise AssertionError("over the CPU budget")


def test_restart_never_readmits_more_than_the_budget(tmp_path):
    bus, clock, col, cli = world()
    d = tmp_path / "a"
    store = SpecStore(d)
    for s in ("s1", "s2", "s3"):
        store.save(paper_spec(s))
    one = spec_cost(paper_spec("x")).cpu_share
    core = make_core(bus, clock, tmp_path, cpu_budget=2.5 * one)
    assert core.served_sessions() == ["s1", "s2"]
    assert (d / "s3.msgpack.refused").exists() and not (d / "s3.msgpack").exists()
    assert core.service_status().counters["admission_refused"] == 1


def test_tables_memo_is_bounded_in_bytes():
    from pd_service.estimation import LinearModel

    linear_mod.set_tables_max_bytes(200_000)
    try:
        for i in range(20):
            n = 8
            m = LinearModel(A=np.eye(n) * (1 + i * 1e-3), B=np.zeros((n, 0)), Q=np.eye(n))
            linear_mod.tables_for(m, 100)
        held = sum(linear_mod.tables_nbytes(t) for t in linear_mod._TABLES.values())
        assert 0 < held <= 200_000
    finally:
        linear_mod.set_tables_max_bytes(Settings(instance="a").tables_max_bytes)
