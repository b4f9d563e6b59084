"""Hardening of the daemon (ServiceCore on the in-memory bus, injected clock): admission by
cost, fair config scheduling, idle sessions, numerical health, honest persistence, receive
time, explicit membership."""

from __future__ import annotations

import zlib

import numpy as np

from pd_service.backends import Cost, command_dim, spec_cost
from pd_service.estimation import linear as linear_mod
from pd_service.service import Settings, SpecStore
from pd_service.service.admission import Ledger, OverBudget
from pd_service.transport import InMemoryBus
from pd_service.wire import (
    LinearModelSpec,
    SensorSpec,
    SessionSpec,
    encode,
    keys,
)

from .helpers import PERIOD_NS, Clock, Collector, paper_spec
from .test_core import at, make_core
from .test_nonlinear import omni_spec


def price(spec: SessionSpec) -> Cost:
    """The spec's cost, as ``backends.build`` hands it to ``admit`` (nothing allocated)."""
    return spec_cost(spec, command_dim(spec))


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
    c = price(big_linear_spec("big", 0))
    C = 3 * 1000 + 10_000 + 4
    assert c.table_bytes == 8 * ((C + 1) * 2 * 64 * 64 + C * 64 * 64)
    assert c.bytes > 10**9  # the 1.2 GB the attack allocated
    small = price(paper_spec("p"))
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
    while core.has_work():  # run_once may stop early after its time budget (under load)
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
    a = price(paper_spec("a"))
    led = Ledger(2**30, 1.0, a.bytes + a.session_bytes, 10.0)
    led.admit("a", a)
    led.admit("b", price(paper_spec("b")))  # same model: its tables are not charged again
    assert led.bytes == a.bytes + a.session_bytes
    try:
        led.admit("c", price(paper_spec("c")))
    except OverBudget as exc:
        assert "memory_budget_bytes" in exc.reason
    else:
        raise AssertionError("over the memory budget")
    led.admit("a", price(paper_spec("a", max_delay=12)))  # replacing itself fits
    led.release("a")
    led.release("b")
    assert (led.bytes, led.cpu) == (0, 0.0)
    cpu = Ledger(2**30, 1.0, 2**40, 2.5 * a.cpu_share)
    cpu.admit("a", a)
    cpu.admit("b", a)
    try:
        cpu.admit("c", a)
    except OverBudget as exc:
        assert "cpu_budget" in exc.reason
    else:
        raise AssertionError("over the CPU budget")


def test_restart_never_readmits_more_than_the_budget(tmp_path):
    bus, clock, col, cli = world()
    d = tmp_path / "a"
    store = SpecStore(d)
    for s in ("s1", "s2", "s3"):
        store.save(paper_spec(s))
    one = price(paper_spec("x")).cpu_share
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


# ---------------------------------------------------------------- fair config scheduling --

def test_config_flood_does_not_delay_another_sessions_predictions(tmp_path):
    from .helpers import meas_bytes

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("calm"), encode(paper_spec("calm")))
    cli.put(keys.config_key("evil"), encode(paper_spec("evil")))
    core.run_once()
    per_step = 50  # 1,000 replacements per second at 50 ms steps
    steps = range(5, 45)
    for k in steps:
        clock.t = at(k + 0.1)
        for i in range(per_step):
            cli.put(keys.config_key("evil"),
                    encode(paper_spec("evil", max_delay=12 + (k * per_step + i) % 50)))
        cli.put(keys.sensor_key("calm", "ranger"), meas_bytes("calm", "ranger", k, [1.0], k))
        start = len(col.order)
        core.run_once()
        got = col.order[start:]
        # the calm session's prediction went out after at most one slice of configs
        first = got.index(("calm", "prediction"))
        assert sum(1 for s, kind in got[:first] if s == "evil" and kind == "status") <= \
            core.settings.config_slice
        clock.t = at(k + 0.6)
        core.run_once()
    lead = paper_spec("calm").lead
    steps_with_pred = {p.step - lead for p in col.predictions["calm"]}
    assert set(steps) <= steps_with_pred  # one prediction per step at least
    c = core.service_status().counters
    total = per_step * len(steps)
    allowed = len(col.statuses["evil"]) - 1  # each allowed change is answered
    assert c["config_rate_limited"] == total - allowed
    elapsed_s = (at(44.6) - at(5.1)) / 1e9
    assert 1 <= allowed <= 5 + 2.0 * elapsed_s + 1  # config_burst + config_rate * time


# ---------------------------------------------------------------- idle sessions -----------

def test_idle_sessions_tick_rarely_and_wake_on_traffic(tmp_path):
    """"once" sent one command at its start: every step until idle_after_s (1 s = 20 steps)
    without traffic, then a prediction every idle_publish_s; traffic wakes it again."""
    from .helpers import cmd_bytes, meas_bytes

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path, idle_after_s=1.0, idle_publish_s=1.0)
    for s in ("busy", "once"):
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    lead = paper_spec("x").lead
    cli.put(keys.command_key("once"), cmd_bytes("once", lead, [0.0]))
    core.run_once()
    for k in range(0, 100):  # 5 s at 50 ms
        clock.t = at(k + 0.1)
        cli.put(keys.sensor_key("busy", "ranger"), meas_bytes("busy", "ranger", k, [1.0], k))
        core.run_once()
        clock.t = at(k + 0.6)
        core.run_once()
    busy = {p.step - lead for p in col.predictions["busy"]}
    once = [p.step - lead for p in col.predictions["once"]]
    assert set(range(100)) <= busy
    assert set(range(21)) <= set(once)  # every step until idle (1 s = 20 steps)
    late = [k for k in once if k > 21]
    assert 3 <= len(late) <= 5 and all(b - a >= 20 for a, b in zip(late, late[1:], strict=False))
    # traffic wakes it: every step again
    for k in range(100, 110):
        clock.t = at(k + 0.1)
        cli.put(keys.sensor_key("once", "ranger"), meas_bytes("once", "ranger", k, [1.0], k))
        core.run_once()
        clock.t = at(k + 0.6)
        core.run_once()
    assert set(range(100, 110)) <= {p.step - lead for p in col.predictions["once"]}


def test_a_new_session_is_idle_until_its_first_message(tmp_path):
    """Created and never sent to: one prediction at its first tick (the prior, at once),
    then one per idle_publish_s, never one per step; its first measurement is published at
    once and it ticks every step from then on; a first command alone wakes the ticks; bytes
    that do not decode are no traffic."""
    from .helpers import cmd_bytes, meas_bytes

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path, idle_publish_s=1.0)  # idle_after_s: default 5 s
    names = ("by_meas", "by_cmd", "garbage", "never")
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while core.has_work():
        core.run_once()
    lead = paper_spec("x").lead

    def steps(s):
        return [p.step - lead for p in col.predictions[s]]

    def tick(k):
        clock.t = at(k + 0.6)
        core.run_once()

    assert all(steps(s) == [] for s in names)  # not before the first tick...
    tick(0)
    x0 = paper_spec("x").x0
    for s in names:  # ...then at once: the prior, nothing measured yet
        assert steps(s) == [0] and col.predictions[s][0].newest_step is None
        assert np.allclose(col.predictions[s][0].x, x0)
    for k in range(1, 30):
        tick(k)
    for s in names:  # idle from the start: then only at its phase, once per 20 steps
        phase = zlib.crc32(s.encode()) % 20
        assert steps(s) == [0] + [k for k in range(1, 30) if k % 20 == phase], (s, steps(s))
    assert core.service_status().counters["published"] <= 3 * len(names)
    n = {s: len(steps(s)) for s in names}
    clock.t = at(30.1)
    cli.put(keys.sensor_key("by_meas", "ranger"), meas_bytes("by_meas", "ranger", 29, [1.0]))
    cli.put(keys.command_key("by_cmd"), cmd_bytes("by_cmd", 30 + lead, [0.0]))
    cli.put(keys.sensor_key("garbage", "ranger"), b"\x00not msgpack")
    core.run_once()
    assert steps("by_meas")[n["by_meas"]:] == [30]  # published at once
    assert col.predictions["by_meas"][-1].newest_step == 29
    assert len(steps("by_cmd")) == n["by_cmd"]  # a command alone publishes at the tick
    for k in range(30, 45):
        tick(k)
    for s in ("by_meas", "by_cmd"):  # awake: every step
        assert set(range(30, 45)) <= set(steps(s)), (s, steps(s))
    # a refused undecodable message is no traffic: the session stays idle
    assert len([k for k in steps("garbage") if 31 <= k < 45]) <= 1
    assert len([k for k in steps("never") if 30 <= k < 45]) <= 1
    assert core.session_status("garbage").counters["malformed"] == 1


def test_a_message_that_arrived_before_its_session_wakes_it(tmp_path):
    """A measurement that waited in the unknown inbox while the config was applied is the
    session's first message: published, and every step from then on."""
    from .helpers import meas_bytes

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path, idle_publish_s=1.0)
    lead = paper_spec("x").lead
    # the measurement's callback runs before the config is applied (both in one run_once)
    clock.t = at(3.1)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 2, [1.0]))
    core.run_once()
    assert core.session_status("s1").counters["accepted"] == 1
    for k in range(3, 10):
        clock.t = at(k + 0.6)
        core.run_once()
    assert set(range(3, 10)) <= {p.step - lead for p in col.predictions["s1"]}


def test_a_restored_session_is_idle_until_traffic(tmp_path):
    """Restart: a session restored from the state directory (its estimate from its
    checkpoint) gives one prediction at once, then is idle until its first message."""
    from .helpers import cmd_bytes, meas_bytes

    bus, clock, col, cli = world()
    lead = paper_spec("x").lead
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=0.3)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    a.run_once()
    for k in range(20):
        clock.t = at(k + 0.1)
        cli.put(keys.command_key("s1"), cmd_bytes("s1", k + lead, [0.1], k))
        cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", k, [1.0], k))
        a.run_once()
        clock.t = at(k + 0.6)
        a.run_once()
    assert a.counters["checkpoints"] >= 1
    a.t.close()  # a crash
    clock.t = at(21.1)  # no sender cache to wait for (the wait: handover/test_keeper.py)
    b = make_core(bus, clock, tmp_path, idle_publish_s=1.0, recover_samples=0)
    st = b.session_status("s1")
    assert st.state == "restored" and st.origin == "checkpoint"
    n = len(col.predictions["s1"])
    for k in range(21, 35):
        clock.t = at(k + 0.6)
        b.run_once()
    got = [p.step - lead for p in col.predictions["s1"][n:]]
    phase = zlib.crc32(b"s1") % 20  # one at once, then at its phase (idle_publish_s = 20 steps)
    assert got == [21] + [k for k in range(22, 35) if k % 20 == phase]
    assert col.predictions["s1"][n].newest_step is not None  # from the checkpoint
    clock.t = at(35.1)
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 34, [1.0], 99))
    b.run_once()
    for k in range(35, 45):
        clock.t = at(k + 0.6)
        b.run_once()
    assert set(range(35, 45)) <= {p.step - lead for p in col.predictions["s1"][n:]}


def test_idle_sessions_spread_their_ticks(tmp_path):
    """Idle sessions sharing an epoch predict at phases of their own, not all in one tick."""
    from collections import Counter

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path, idle_after_s=1.0, idle_publish_s=1.0)
    names = [f"i{i:02d}" for i in range(40)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while core.has_work():
        core.run_once()
    lead = paper_spec("x").lead
    for k in range(0, 120):  # 6 s at 50 ms, idle from 1 s on
        clock.t = at(k + 0.6)
        core.run_once()
    late = Counter(p.step - lead for s in names for p in col.predictions[s] if p.step - lead > 25)
    assert sum(late.values()) >= 40  # every idle session still predicts now and then
    assert max(late.values()) <= 10, late  # not all 40 in the same step


# ---------------------------------------------------------------- receive time ------------

def test_a_packet_is_judged_at_its_arrival_not_at_the_loops_clock_read(tmp_path):
    from .helpers import meas_bytes

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    clock.t = at(20.5)
    core.run_once()
    clock.t = at(21.1)  # the packet of step 21 arrives in step 21 ...
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 21, [1.0]))
    clock.t = at(20.9)  # ... while the worker's loop read the clock a little before
    core.run_once()
    c = core.session_status("s1").counters
    assert c["accepted"] == 1 and c.get("future", 0) == 0
    clock.t = at(21.2)
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 23, [1.0]))
    core.run_once()
    assert core.session_status("s1").counters["future"] == 1  # really in the future


# ---------------------------------------------------------------- membership -------------

def test_standalone_ignores_stray_service_tokens(tmp_path, caplog):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    names = [f"s{i:02d}" for i in range(20)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    core.run_once()
    fake = [cli.declare_token(keys.service_token_key(f"fake{i}")) for i in range(10)]
    core.run_once()
    assert core.served_sessions() == names  # nobody handed over to a forged token
    assert core.ownership.members == {"a"}
    assert core.service_status().counters["untrusted_peer"] == 10
    for f in fake:
        f.close()
    core.run_once()
    fake2 = cli.declare_token(keys.service_token_key("fake0"))  # seen before: warned once
    core.run_once()
    assert core.service_status().counters["untrusted_peer"] == 10
    fake2.close()


def test_configured_peers_share_sessions_and_strangers_do_not(tmp_path):
    bus, clock, col, cli = world()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=["inst-b"])
    b = make_core(bus, clock, tmp_path, "inst-b", peers=["inst-a"])
    c = make_core(bus, clock, tmp_path, "inst-c")  # standalone, not in their lists
    names = [f"s{i:02d}" for i in range(12)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    for core in (a, b, c):
        while core.has_work():  # run_once may stop early after its time budget (under load)
            core.run_once()
    assert a.ownership.members == b.ownership.members == {"inst-a", "inst-b"}
    assert sorted(a.served_sessions() + b.served_sessions()) == names
    assert c.served_sessions() == names


# ---------------------------------------------------------------- persistence -------------

def test_fifo_and_symlink_named_like_state_files_are_set_aside(tmp_path):
    import os

    d = tmp_path / "a"
    d.mkdir()
    os.mkfifo(d / "s1.msgpack")
    (d / "s2.msgpack").symlink_to("/dev/zero")
    os.mkfifo(d / "s3.ckpt")  # a checkpoint file of an earlier version: not read
    os.mkfifo(d / "checkpoints.log")
    SpecStore(d).save(paper_spec("s3"))
    (d / "s4.msgpack").write_bytes(b"\x00" * (2 << 20))  # too big
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)  # returns: nothing blocked
    assert core.served_sessions() == ["s3"]
    for name in ("s1", "s2", "s4"):
        assert os.path.lexists(d / f"{name}.msgpack.bad"), name
    assert os.path.lexists(d / "checkpoints.log.bad")


def test_unpersisted_changes_are_answered_as_such(tmp_path):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)

    def fail(*a, **k):
        raise OSError(30, "Read-only file system")

    core.store._write = fail
    real_remove = core.store.remove
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    st = col.statuses["s1"][-1]
    assert st.detail.startswith("created; NOT persisted")
    c = core.service_status().counters
    assert c["persist_failed"] == 1 and c["state_dir_unhealthy"] == 1
    core.store.remove = fail
    cli.delete(keys.config_key("s1"))
    core.run_once()
    st = col.statuses["s1"][-1]
    assert st.state == "removed" and "could NOT be removed" in st.detail
    core.store.remove = real_remove
    del core.store._write  # writable again
    cli.put(keys.config_key("s2"), encode(paper_spec("s2")))
    core.run_once()
    assert col.statuses["s2"][-1].detail == "created"
    assert core.service_status().counters.get("state_dir_unhealthy", 0) == 0


# ---------------------------------------------------------------- numerical health --------

def test_huge_finite_inputs_are_refused_and_the_session_keeps_publishing(tmp_path):
    from .helpers import cmd_bytes, meas_bytes

    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    clock.t = at(20.1)
    core.run_once()
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 20, [1e308]))
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 30, [1e308]))
    core.run_once()
    c = core.session_status("s1").counters
    assert c["out_of_range"] == 1 and c["commands_out_of_range"] == 1
    assert "max_abs_input" in col.errors["s1"][0].reason
    n = len(col.predictions["s1"])
    for k in range(21, 25):
        clock.t = at(k + 0.6)
        core.run_once()
    assert len(col.predictions["s1"]) >= n + 4
    assert all(np.all(np.isfinite(p.x)) and np.abs(p.x).max() < 1e6
               for p in col.predictions["s1"])
