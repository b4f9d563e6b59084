"""Restart from a checkpoint and takeover from a replica, on the in-memory bus: the resumed
session's predictions equal an offline estimator that saw what the checkpoint / replica held
plus what the new instance accepted (a stale one propagated forward); future, corrupt,
other-spec and other-version states are refused (counted, reported) and the session starts
from its prior."""

from __future__ import annotations

import copy
import threading
import time

import numpy as np
import pytest

from pd_service.backends import build
from pd_service.service import ServiceCore, Settings, SpecStore
from pd_service.service.handover.checkpoint_log import LOG_NAME, MAGIC
from pd_service.service.handover.keeper import checkpoint_key, replica_key
from pd_service.service.session import READ_BACK_COPIES
from pd_service.transport import InMemoryBus, Sample
from pd_service.transport.keyexpr import check_keyexpr
from pd_service.wire import SessionState, SessionStatus, decode, encode, keys

from ..helpers import PERIOD_NS, Clock, Collector, cmd_bytes, meas_bytes, paper_spec
from ..test_core import PAIR, make_core, settle


class Driver:
    """Step k: command for k + lead, a ranger sample of step k - 2 and a camera sample of
    k - 5; mirrored on an offline estimator; ``snap`` holds a copy of it as of each
    checkpoint / replica the core took."""

    def __init__(self, cli, clock, col, session="s1", max_delay: int = 12):
        self.cli, self.clock, self.col, self.s = cli, clock, col, session
        self.spec = paper_spec(session, max_delay=max_delay)
        self.off = build(self.spec).est
        self.snap = None
        self.rng = np.random.default_rng(3)

    def step(self, cores, k, taken=lambda: 0, mirror=True):
        self.clock.t = int((k + 0.1) * PERIOD_NS)
        u = self.rng.standard_normal(1)
        z1, z2 = self.rng.standard_normal(1) + 5, self.rng.standard_normal(2)
        self.cli.put(keys.command_key(self.s), cmd_bytes(self.s, k + self.spec.lead, u))
        if k >= 2:
            self.cli.put(keys.sensor_key(self.s, "ranger"),
                         meas_bytes(self.s, "ranger", k - 2, z1))
        if k >= 5:
            self.cli.put(keys.sensor_key(self.s, "camera"), meas_bytes(self.s, "camera", k - 5, z2))
        if mirror:
            self.off.add_command(k + self.spec.lead, u, now=k)
            if k >= 2:
                self.off.add_measurement("ranger", k - 2, z1, now=k)
            if k >= 5:
                self.off.add_measurement("camera", k - 5, z2, now=k)
        for phase in (0.1, 0.6):  # inputs, then the tick (a state may be taken at both)
            self.clock.t = int((k + phase) * PERIOD_NS)
            before = taken()
            for c in cores:
                c.run_once()
            if taken() != before:
                self.snap = copy.deepcopy(self.off)

    def check(self, k, ref):
        pred = self.col.predictions[self.s][-1]
        want = ref.predict(k)
        assert pred.step == want.step
        np.testing.assert_allclose(pred.x, want.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(pred.P, want.P, rtol=1e-9, atol=1e-9)


def status(cli, s):
    return decode(cli.get(keys.status_key(s))[0].payload, SessionStatus)



def two_instances(bus, clock, tmp_path, cli, sessions: int = 12, peers=PAIR,
                  max_delay: int = 12, **kw):
    """inst-a and inst-b (explicit ``peers``, settings ``kw``) sharing ``sessions`` paper
    sessions s00, s01, ... (window ``max_delay``); returns (a, b, names) once both have
    applied every config."""
    a = make_core(bus, clock, tmp_path, "inst-a", peers=peers, **kw)
    b = make_core(bus, clock, tmp_path, "inst-b", peers=peers, **kw)
    names = [f"s{i:02d}" for i in range(sessions)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s, max_delay=max_delay)))
    settle(a, b)
    return a, b, names

@pytest.mark.parametrize("gap", [3, 40])
def test_restart_resumes_from_the_checkpoint_exactly(tmp_path, gap):
    """Restarted ``gap`` steps after the crash: within the window (3) or long after it (40
    steps, more than 3 windows): the stale checkpoint is propagated forward, not dropped."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=0.3)
    d = Driver(cli, clock, col)
    cli.put(keys.config_key("s1"), encode(d.spec))
    a.run_once()
    for k in range(40):
        d.step([a], k, lambda: a.counters["checkpoints"])
    assert a.counters["checkpoints"] >= 5 and d.snap is not None
    a.t.close()  # a crash: nothing flushed, nothing said
    ref = d.snap  # what the newest checkpoint held; the steps after it are lost
    clock.t = int((40 + gap) * PERIOD_NS)  # the restart (no sender cache to wait for)
    b = make_core(bus, clock, tmp_path, recover_samples=0)
    d.off = ref
    for k in range(40 + gap, 70 + gap):  # max_delay is 12 steps
        d.step([b], k)
        d.check(k, ref)
    st = status(cli, "s1")
    assert st.origin == "checkpoint" and st.origin_step is not None and 30 <= st.origin_step < 40
    assert b.counters["resumed_from_checkpoint"] == 1
    assert b.counters["resumed_stale"] == (gap > d.spec.max_delay)
    assert b.counters["restore_refused"] == 0
    # the run from the prior would be far off: P(p2) back near the prior's 100
    fresh = build(d.spec).est
    assert float(col.predictions["s1"][-1].P[1, 1]) < 0.1 * float(
        fresh.predict(40 + gap).P[1, 1])


def _checkpointed(tmp_path, steps=20):
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=0.3)
    d = Driver(cli, clock, col)
    cli.put(keys.config_key("s1"), encode(d.spec))
    a.run_once()
    for k in range(steps):
        d.step([a], k)
    a.t.close()
    return bus, clock, col, cli, d


def _tamper(store, **update):
    msg = decode(store.load_state("s1"), SessionState)
    store.save_state("s1", encode(msg.model_copy(update=update)))


@pytest.mark.parametrize("how, reason", [
    ("future", "future"),
    ("corrupt", "corrupt"),
    ("spec", "spec"),
    ("version", "version"),
    ("misfit", "corrupt"),
])
def test_a_bad_checkpoint_is_refused_and_the_session_starts_from_its_prior(tmp_path, how,
                                                                           reason):
    bus, clock, col, cli, d = _checkpointed(tmp_path)
    store = SpecStore(tmp_path / "a")  # the checkpoint log the daemon wrote
    data = store.load_state("s1")
    assert data is not None
    restart_step = 19
    if how == "future":
        _tamper(store, now_step=restart_step + 5)
    elif how == "corrupt":
        store.save_state("s1", data[:-7])
    elif how == "spec":
        _tamper(store, spec_fingerprint="0" * 64)
    elif how == "version":
        _tamper(store, state_version=2)
    elif how == "misfit":
        _tamper(store, kind="ImmObserverPredictor")
    clock.t = int((restart_step + 0.1) * PERIOD_NS)
    b = make_core(bus, clock, tmp_path, recover_samples=0)
    assert b.counters["restore_refused"] == 1
    assert b.counters[f"restore_refused_{reason}"] == 1
    st = status(cli, "s1")
    assert st.origin == "prior" and st.origin_step is None
    assert st.counters.get("restore_refused") == 1
    b.run_once()  # the ErrorReport leaves with the first flush
    (rep,) = [e for e in col.errors["s1"] if f"({reason})" in e.reason]
    assert rep.key == checkpoint_key(b.instance, "s1") == f"pd/@service/{b.instance}/checkpoint/s1"
    check_keyexpr(rep.key)
    clock.t = int((restart_step + 0.6) * PERIOD_NS)
    b.run_once()  # the tick: a prediction from the prior
    prior = build(d.spec).est.predict(restart_step)
    assert col.predictions["s1"][-1].step == prior.step
    np.testing.assert_allclose(col.predictions["s1"][-1].P, prior.P, rtol=1e-9)


def test_a_damaged_checkpoint_log_is_counted_and_reported(tmp_path):
    bus, clock, col, cli, d = _checkpointed(tmp_path)
    path = tmp_path / "a" / LOG_NAME
    buf = bytearray(path.read_bytes())
    buf[len(MAGIC) + 12] ^= 0xFF  # inside the first record: its CRC fails, nothing read
    path.write_bytes(bytes(buf))
    clock.t = int(19.1 * PERIOD_NS)
    b = make_core(bus, clock, tmp_path, recover_samples=0)
    assert b.counters["checkpoint_log_damaged"] == 1
    assert b.counters["restore_refused_damaged"] == 1 and b.counters["restore_refused"] == 1
    b.run_once()
    (rep,) = [e for e in col.errors["s1"] if "(damaged)" in e.reason]
    assert "fails its CRC" in rep.reason and rep.key == checkpoint_key(b.instance, "s1")
    assert status(cli, "s1").origin == "prior"


@pytest.mark.parametrize("gap", [1, 30])
def test_takeover_resumes_from_the_replica_exactly(tmp_path, gap):
    """Taken over ``gap`` steps after the owner died: a replica older than the window (30
    steps, max_delay 12) is propagated forward, exact to its reference as well."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a, b, names = two_instances(bus, clock, tmp_path, cli, replica_interval_s=0.3,
                                recover_samples=0)  # no sender cache to wait for
    owner_of = {s: ("inst-a" if s in a.served_sessions() else "inst-b") for s in names}
    s = next(n for n in names if owner_of[n] == "inst-a")  # a serves it, b is its successor
    assert a.ownership.successor(s) == "inst-b"
    d = Driver(cli, clock, col, s)
    for k in range(40):
        d.step([a, b], k, lambda: b.keeper.replicas.get(s, (None,))[0] or 0)
    assert d.snap is not None and b.counters["replicas_received"] > 0
    held = decode(b.keeper.replicas[s][1], SessionState)
    assert held.session == s and held.instance == "inst-a"
    a.t.close()  # a dies; b learns it through liveliness (the bus drops a's token)
    clock.t = int((40 + gap) * PERIOD_NS)
    b.dispatch.on_liveliness(keys.service_token_key("inst-a"), False)
    b.run_once()  # takes the session over (inputs sent before that reach nobody)
    ref = d.snap
    d.off = ref
    for k in range(40 + gap, 60 + gap):
        d.step([b], k)
        d.check(k, ref)
    st = status(cli, s)
    assert st.instance == "inst-b" and st.origin == "replica"
    assert b.counters["resumed_from_replica"] >= 1
    assert b.counters["resumed_stale"] == (gap > d.spec.max_delay)


def test_a_replica_for_another_spec_is_refused(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    a.run_once()
    other = build(paper_spec("s1", max_delay=20)).est
    from pd_service.service.handover.checkpoint import to_message
    from pd_service.wire.session_state import spec_fingerprint
    msg = to_message(other.export_state(), session="s1", instance="inst-x",
                     fingerprint=spec_fingerprint(paper_spec("s1", max_delay=20)), made_ns=0)
    cli.put(replica_key("inst-a", "s1"), encode(msg))
    assert "s1" in a.keeper.replicas
    a.keeper.resume(a.dispatch.routes["s1"].sess, "replica", 0)
    assert a.counters["restore_refused_spec"] == 1
    assert a.dispatch.routes["s1"].sess.origin == "prior"


def test_a_replica_is_only_unpacked_on_arrival_and_validated_at_the_takeover(tmp_path):
    """On arrival a replica is kept if it is a msgpack map naming its key's session with a
    valid now_step (else counted as ``replica_malformed``), the newest by now_step; the whole
    SessionState is validated only when a takeover resumes from it."""
    import msgpack

    from pd_service.service.handover.checkpoint import to_message
    from pd_service.wire.session_state import spec_fingerprint

    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    a.run_once()
    est = build(paper_spec("s1")).est
    good = to_message(est.export_state(), session="s1", instance="inst-x",
                      fingerprint=spec_fingerprint(paper_spec("s1")), made_ns=0)
    obj = msgpack.unpackb(encode(good))
    key = replica_key("inst-a", "s1")
    for bad in (b"\xc1", msgpack.packb([1, 2]), msgpack.packb({**obj, "session": "s2"}),
                msgpack.packb({**obj, "now_step": -1}), msgpack.packb({**obj, "now_step": 1.5}),
                msgpack.packb({**obj, "now_step": True})):
        cli.put(key, bad)
    assert a.counters["replica_malformed"] == 6 and "s1" not in a.keeper.replicas
    cli.put(key, msgpack.packb({**obj, "now_step": 7}))
    cli.put(key, msgpack.packb({**obj, "now_step": 5}))  # older: the newest is kept
    assert a.keeper.replicas["s1"][0] == 7 and a.counters["replicas_received"] == 2
    # unpackable but no SessionState (P not a matrix): refused when resumed, not before
    cli.put(key, msgpack.packb({**obj, "now_step": 9, "P": "not a matrix"}))
    assert a.keeper.replicas["s1"][0] == 9
    a.keeper.resume(a.dispatch.routes["s1"].sess, "replica", 0)
    assert a.counters["restore_refused_corrupt"] == 1
    assert a.dispatch.routes["s1"].sess.origin == "prior"


def test_checkpoints_are_bounded_in_rate(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=1.0)
    d = Driver(cli, clock, col)
    cli.put(keys.config_key("s1"), encode(d.spec))
    a.run_once()
    for k in range(100):  # 5 s of 50 ms steps
        d.step([a], k)
    assert 4 <= a.counters["checkpoints"] <= 6
    assert isinstance(a, ServiceCore)


def test_a_graceful_stop_hands_the_newest_state_over(tmp_path):
    """SIGTERM path: the owner's close() sends every served session's state to its
    successor before withdrawing its presence, so nothing it accepted is lost."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    # replicas every 100 s (and a window of 20 s, half of which would bound the interval):
    # only the handover can carry the newest state
    a, b, names = two_instances(bus, clock, tmp_path, cli, replica_interval_s=100.0,
                                max_delay=400, recover_samples=0)  # no cache to wait for
    s = next(n for n in names if n in a.served_sessions())
    d = Driver(cli, clock, col, s, max_delay=400)
    for k in range(40):
        d.step([a, b], k)
    periodic = b.keeper.replicas[s][0]  # the one periodic replica, taken early on
    a.close()
    # s only: the others never accepted anything (their successor's prior is their state)
    assert len(a.served_sessions()) > 1 and a.counters["replicas_handover"] == 1
    held = decode(b.keeper.replicas[s][1], SessionState)
    assert held.now_step == 39 > periodic
    b.dispatch.on_liveliness(keys.service_token_key("inst-a"), False)
    b.run_once()
    for k in range(40, 60):  # d.off saw everything: the takeover lost nothing
        d.step([b], k)
        d.check(k, d.off)
    st = status(cli, s)
    assert st.instance == "inst-b" and st.origin == "replica" and st.origin_step == 39


class DropsReplicas:
    """A transport that loses ``n`` replica puts (a congested link drops them); ``n`` is 0
    until set."""

    def __init__(self, t):
        self._t, self.n, self.dropped = t, 0, 0

    def __getattr__(self, name):
        return getattr(self._t, name)

    def put(self, key, payload):
        if "/replica/" in key and self.dropped < self.n:
            self.dropped += 1
            return
        self._t.put(key, payload)


def test_a_graceful_stop_puts_a_lost_final_state_again_until_the_successor_holds_it(tmp_path):
    """The successor's answer, not the put, ends the hand-over: a final state lost on the
    way is put again, and the owner withdraws only once the successor holds it."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    lossy = DropsReplicas(bus.transport())
    a = ServiceCore(lossy, Settings(instance="inst-a", peers=PAIR, replica_interval_s=100.0),
                    store=SpecStore(tmp_path / "inst-a"), now_ns=clock, spawn=lambda fn: fn())
    a.start()
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR, replica_interval_s=100.0)
    for n in ("s00", "s01", "s02", "s03"):  # a window of 20 s: no replica within the test
        cli.put(keys.config_key(n), encode(paper_spec(n, max_delay=400)))
    settle(a, b)
    s = a.served_sessions()[0]  # owned by the lossy one
    d = Driver(cli, clock, col, s, max_delay=400)
    for k in range(30):
        d.step([a, b], k)
    periodic = b.keeper.replicas[s][0]
    lossy.n = 1  # the next replica put, the final state's, is lost
    a.close()
    assert lossy.dropped == 1 and a.counters["replicas_handover"] == 1
    assert a.counters["replicas_handover_unconfirmed"] == 0
    assert a.counters["replicas_handover_resent"] == 1
    held = decode(b.keeper.replicas[s][1], SessionState)
    assert held.now_step == 29 > periodic


def test_a_successor_that_does_not_answer_is_waited_for_a_bounded_time(tmp_path):
    """No answer (the successor is gone or its link is down): the wait ends after the
    timeout, the unconfirmed states are counted and named."""
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a, b, names = two_instances(bus, clock, tmp_path, cli, sessions=2)
    b.t.close()
    missing = a.keeper.confirm_handover("inst-b", {"s00": b"x", "s01": b"y"}, 0.2)
    assert missing == ["s00", "s01"]
    assert a.counters["replicas_handover_unconfirmed"] == 2


def test_a_session_in_its_first_window_is_checkpointed(tmp_path):
    """Nothing commits before max_delay steps; accepted packets alone make a checkpoint."""
    bus, clock, col, cli, d = _checkpointed(tmp_path, steps=8)  # max_delay 12
    msg = decode(SpecStore(tmp_path / "a").load_state("s1"), SessionState)
    assert msg.committed_step == 0 and msg.packets
    b = make_core(bus, clock, tmp_path)
    assert b.counters["resumed_from_checkpoint"] == 1
    assert status(cli, "s1").origin == "checkpoint"


def test_state_writer_writes_newest_and_removes(tmp_path):
    """The daemon's checkpoint thread: the newest submitted state of a session is on disk
    after flush, a removal deletes it even with a write pending, failures are reported."""
    from pd_service.service.handover.checkpoint_writer import CheckpointWriter
    from pd_service.service.spec_store import SpecStore

    store = SpecStore(tmp_path)
    w = CheckpointWriter(store)
    try:
        for i in range(50):
            w.submit("alpha", b"state-%d" % i)
        w.submit("beta", b"b")
        w.flush()
        assert store.load_state("alpha") == b"state-49"
        assert store.load_state("beta") == b"b"
        assert all(err is None for _, _, err in w.done)
        w.submit("beta", b"b2")
        w.remove("beta")
        w.flush()
        assert store.load_state("beta") is None
    finally:
        w.close()


def test_store_keeps_the_newest_checkpoint_in_one_log(tmp_path):
    """Rewrites and removals are records appended to one file; a new store reads the
    newest checkpoint of each session back; a shorter state after longer ones leaves
    nothing of them behind."""
    from pd_service.service.spec_store import SpecStore

    store = SpecStore(tmp_path)
    for i in range(5):
        store.save_state("gamma", b"v%d" % i)
        assert store.load_state("gamma") == b"v%d" % i
    for data in (b"x" * 5000, b"y" * 4000, b"short", b"z" * 6000):
        store.save_state("gamma", data)
        assert store.load_state("gamma") == data
    store.save_states([("delta", b"d1"), ("gamma", None), ("delta", b"d2")])
    assert SpecStore(tmp_path).load_state("delta") == b"d2"
    assert SpecStore(tmp_path).load_state("gamma") is None
    store.remove_state("delta")
    store.close()
    assert SpecStore(tmp_path).states.sessions() == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoints.log"]


def test_states_due_together_are_spread_over_rounds(tmp_path):
    """Sessions that fall due for a checkpoint in the same round are encoded at most
    STATES_PER_ROUND per round (a burst stalled the worker); the others stay due and are
    all taken by the following rounds and sweeps, none starved (a session written first
    may be due again meanwhile, at its own phase: it takes a share of the budget)."""
    from pd_service.service.handover.keeper import STATES_PER_ROUND

    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=1.0)
    names = [f"s{i:02d}" for i in range(3 * STATES_PER_ROUND + 1)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while a.has_work():  # one run_once returns after ~50 ms of (fsynced) configs
        a.run_once()
    clock.t = int(0.1 * PERIOD_NS)
    for s in names:
        cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 0, [5.0]))
    a.run_once()  # one round touches every session: all due at once
    assert a.counters["checkpoints"] == STATES_PER_ROUND
    for j in range(1, 4):  # sweeps every 250 ms take the rest, a budget each
        clock.t = int(0.1 * PERIOD_NS) + j * 260_000_000
        before = a.counters["checkpoints"]
        a.run_once()
        assert 0 < a.counters["checkpoints"] - before <= STATES_PER_ROUND
    assert all(a.store.load_state(s) is not None for s in names)


def test_a_disk_that_refuses_checkpoints_is_counted_and_logged_sparingly(tmp_path, caplog):
    """Every refused checkpoint counts (checkpoint_failed); the log gets one line per
    FAILED_LOG_EVERY_S, not one per session and second."""
    import logging

    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=0.2)

    def refuse(items):
        raise OSError(28, "No space left on device")

    a.store.states.append = refuse
    names = [f"f{i}" for i in range(5)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while a.has_work():
        a.run_once()
    with caplog.at_level(logging.ERROR):
        for k in range(20):  # 1 s: each session due 5 times
            clock.t = int((k + 0.1) * PERIOD_NS)
            for s in names:
                cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", k, [5.0]))
            a.run_once()
    assert a.counters["checkpoint_failed"] >= 4 * len(names)
    assert a.counters["checkpoints"] == 0
    assert caplog.text.count("checkpoint_failed") == 1


def test_sessions_started_together_spread_their_checkpoints_and_snapshots(tmp_path):
    """Sessions with one epoch, configured in one burst, each fed every step: after their
    first checkpoints and snapshots (at once), each falls due at its own phase of the
    interval (Session.spread), not all in the same few rounds every interval (they were: at
    500 sessions a worker loop of ~50 ms once per second, p99 latency 30-40 ms)."""
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=1.0)
    names = [f"s{i:02d}" for i in range(40)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while a.has_work():
        a.run_once()
    written = []  # checkpoints written in each step
    for k in range(60):  # 3 s
        clock.t = int((k + 0.1) * PERIOD_NS)
        for s in names:
            cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", k, [5.0]))
        before = a.counters["checkpoints"]
        a.run_once()
        written.append(a.counters["checkpoints"] - before)
    second_two = written[20:40]
    assert sum(second_two) >= len(names) * 0.8  # about one each per second ...
    assert sum(1 for w in second_two if w) >= 12  # ... in most of the second's 20 steps
    sessions = [a.dispatch.routes[s].sess for s in names]
    assert all(x.snapshot is not None for x in sessions)
    snap_every = sessions[0].snap_every
    assert len({x.next_snapshot_step % snap_every for x in sessions}) >= 12


def test_a_session_nobody_sent_to_writes_no_state_and_a_replace_drops_the_old_one(tmp_path):
    """A session whose estimate is its prior alone gives no checkpoint and no replica
    (resuming from the prior gives the same), however its committed step moves; a replaced
    spec's checkpoint is deleted (it could only be refused at restart)."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR, checkpoint_interval_s=0.3,
                  replica_interval_s=0.3, idle_publish_s=0.5)
    make_core(bus, clock, tmp_path, "inst-b", peers=PAIR)
    names = [f"q{i:02d}" for i in range(6)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while a.has_work():
        a.run_once()
    mine = a.served_sessions()
    assert mine
    for k in range(60):  # 3 s: ticks at creation and every idle_publish_s commit steps
        clock.t = int((k + 0.6) * PERIOD_NS)
        a.run_once()
    assert all(len(col.predictions[s]) >= 2 for s in mine)
    assert a.counters["checkpoints"] == 0 and a.counters["replicas_sent"] == 0
    assert a.store.states.sessions() == []
    # nor an in-memory health snapshot (recovery to the prior gives the same)
    assert all(a._routes[s].sess.snapshot is None for s in mine)
    # traffic: now there is something to keep
    s = mine[0]
    d = Driver(cli, clock, col, s)
    for k in range(60, 70):
        d.step([a], k)
    assert a.store.load_state(s) is not None and a.counters["replicas_sent"] >= 1
    assert a._routes[s].sess.snapshot is not None
    cli.put(keys.config_key(s), encode(paper_spec(s, max_delay=20)))  # replaced
    a.run_once()
    assert "replaced" in status(cli, s).detail
    assert a.store.load_state(s) is None


class CachedSender:
    """A sender that keeps its last ``cache`` samples per key (``publisher(key, cache=N)``),
    like the SDK's Robot and Operator: ``put`` as on a transport."""

    def __init__(self, t, cache):
        self.t, self.cache, self.pubs = t, cache, {}

    def put(self, key, payload):
        if key not in self.pubs:
            self.pubs[key] = self.t.publisher(key, cache=self.cache)
        self.pubs[key].put(payload)


def _crashed_with_caches(tmp_path, cache: int, back: int):
    """One daemon fed 40 steps through senders keeping ``cache`` samples per key, killed
    (nothing flushed), the feed going on until step ``back`` with no daemon (only the
    caches keep it); the clock at the restart's moment. Returns (bus, clock, col, d)."""
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    snd = CachedSender(bus.transport(), cache)
    a = make_core(bus, clock, tmp_path, checkpoint_interval_s=0.3)
    d = Driver(snd, clock, col)
    bus.transport().put(keys.config_key("s1"), encode(d.spec))
    a.run_once()
    for k in range(40):
        d.step([a], k, lambda: a.counters["checkpoints"])
    a.t.close()  # a crash: nothing flushed, nothing said
    for k in range(40, back):  # sent while no daemon runs: only the senders' caches keep them
        d.step([], k)
    clock.t = int((back + 0.05) * PERIOD_NS)
    return bus, clock, col, d


@pytest.mark.parametrize("cache", [64, 2])
def test_restart_recovers_what_the_senders_kept(tmp_path, cache):
    """Kill (no flush), 3 steps with no daemon, restart: the restarted daemon reads back the
    senders' caches. cache=64 reaches past the checkpoint and past the window: every packet
    since the checkpoint comes back (all still inside the window), so it continues *exactly*
    as the run that never stopped, from its first prediction on; the repeats of checkpointed
    packets and the samples older than the window are refused quietly (counted as
    recovered_*, no ErrorReport). cache=2 keeps only the last 2 steps of the outage: the
    steps before them are lost (as without caches)."""
    bus, clock, col, d = _crashed_with_caches(tmp_path, cache, 43)
    errors_before = len(col.errors["s1"])
    n0 = len(col.predictions["s1"])
    b = make_core(bus, clock, tmp_path)
    for k in range(43, 70):
        d.step([b], k)
        if cache == 64:  # every prediction equals the run that never stopped
            d.check(k, d.off)
    c = b.counters
    assert len(col.errors["s1"]) == errors_before  # recovered repeats are not reported
    assert c["refused"] == 0 and c["recovered_accepted"] > 0
    assert c["recovered_commands_accepted"] > 0
    assert status(bus.transport(), "s1").origin == "checkpoint"
    first = col.predictions["s1"][n0]
    want = d.off.predict(69)
    got = col.predictions["s1"][-1]
    if cache == 64:
        # the first prediction after the restart (made by the start, before step 43's
        # packets) already has the outage's packets: the ranger sample of step 40, sent at
        # step 42, is the newest
        assert c["recovered_duplicate"] > 0 and c["recovered_late"] > 0
        assert c["recovered_commands_duplicate"] > 0
        assert first.newest_step == 40 and first.step == 43 + d.spec.lead
    else:
        # what was sent from the checkpoint to step 40 fell out of the caches: lost, so the
        # estimate is less certain than the uninterrupted run's
        assert c["recovered_accepted"] + c["recovered_duplicate"] == 4
        assert float(np.trace(got.P)) > float(np.trace(want.P)) * (1 + 1e-6)


def test_a_restart_longer_than_the_window_takes_in_what_the_senders_kept(tmp_path):
    """An outage of 30 steps against a window of 12: at the restart the checkpoint is older
    than the window, and the senders' caches (64 per key) hold every sample since it. The
    restarted session takes them in at their own stamps' steps, from the checkpoint's step
    on (``Dispatch.catch_up``), before its first prediction: it continues *exactly* as the
    run that never stopped, instead of propagating the checkpoint over the gap."""
    bus, clock, col, d = _crashed_with_caches(tmp_path, 64, 70)
    n0 = len(col.predictions["s1"])
    b = make_core(bus, clock, tmp_path)
    d.check(70, d.off)  # the first prediction, made by the start (before step 70's inputs)
    assert len(col.predictions["s1"]) == n0 + 1
    for k in range(70, 90):
        d.step([b], k)
        d.check(k, d.off)
    c, st = b.counters, status(bus.transport(), "s1")
    assert st.origin == "checkpoint" and st.origin_step is not None \
        and st.origin_step < 70 - d.spec.max_delay
    assert c["resumed_stale"] == 1 and st.readback == "answered"
    # the outage's 30 steps at least: 2 samples and a command each
    assert c["recovered_accepted"] >= 2 * 30 and c["recovered_commands_accepted"] >= 30
    assert c["refused"] == 0


def test_inputs_kept_during_the_wait_are_judged_at_their_stamps_not_at_their_arrival(
        tmp_path):
    """The catch-up judges each kept input at its own stamp's step, also one that arrived
    after the worker's loop read its clock (its arrival time is later than the loop's):
    judged at that arrival, it would take the estimator to the current step and every
    older stamp after it would be refused (late, or "now went backwards")."""
    bus, clock, col, cli, d = _checkpointed(tmp_path, 40)
    clock.t = int(70.05 * PERIOD_NS)
    b = make_core(bus, clock, tmp_path)  # no sender cache: it waits 2 x recover_timeout_s
    sess = b.dispatch.routes["s1"].sess
    assert sess.readback == "waiting" and sess.origin_step is not None
    # samples of the steps after the checkpoint, arriving after the wait's end ...
    clock.t = sess.hold_until_ns + 5 * PERIOD_NS
    for j in range(sess.origin_step + 1, sess.origin_step + 6):
        cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", j, [5.0]))
    clock.t = sess.hold_until_ns + PERIOD_NS // 2  # ... read by a loop that began before
    accepted = sess.counters["accepted"]
    b.run_once()
    assert sess.readback == "timeout"
    assert sess.counters["accepted"] == accepted + 5 and b.counters["refused"] == 0


def test_a_command_to_a_session_taken_over_at_its_prior_is_taken_in_after_the_wait(tmp_path):
    """A session nobody sent to is taken over at its prior (no replica) and waits for its
    senders' caches like any other; a command it gets meanwhile is judged at its own step
    from the wait's start when the wait ends, not at the end of the wait (where its apply
    step would be long final)."""
    from ..helpers import cmd_now_bytes

    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a, b, names = two_instances(bus, clock, tmp_path, cli)
    s = next(n for n in names if n in a.served_sessions())
    a.t.close()
    clock.t = 5 * PERIOD_NS
    b.dispatch.on_liveliness(keys.service_token_key("inst-a"), False)
    b.run_once()
    sess = b.dispatch.routes[s].sess
    assert sess.origin == "prior" and sess.readback == "waiting"
    cli.put(keys.command_key(s), cmd_now_bytes(s, clock.t))
    b.run_once()
    clock.t = sess.hold_until_ns + PERIOD_NS  # no cache answers: the bound (4 s, 80 steps)
    b.run_once()
    assert sess.readback == "timeout"
    assert sess.counters["commands_accepted"] == 1 and b.counters["refused"] == 0
    # and it is awake: a prediction every step from then on (not one per idle_publish_s)
    published = sess.published
    k0 = sess.step_now(clock.t)
    for k in range(k0 + 1, k0 + 6):
        clock.t = int((k + 0.6) * PERIOD_NS)
        b.run_once()
    assert sess.published >= published + 5


def test_takeover_reads_back_what_the_senders_kept(tmp_path):
    """The owner dies; what it accepted after its last replica and what was sent until the
    survivor took over come back from the senders' caches: the survivor continues exactly
    as the run that never stopped, quietly refusing the repeats."""
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    a, b, names = two_instances(bus, clock, tmp_path, cli, replica_interval_s=0.3)
    s = next(n for n in names if n in a.served_sessions())
    d = Driver(CachedSender(bus.transport(), 64), clock, col, s)
    for k in range(40):
        d.step([a, b], k)
    a.t.close()  # a dies: nothing more replicated
    d.step([b], 40)  # b does not serve s yet: it drops these (its caches keep them)
    errors_before = len(col.errors[s])
    b.dispatch.on_liveliness(keys.service_token_key("inst-a"), False)
    b.run_once()  # takes s over, reads the caches back
    for k in range(41, 60):
        d.step([b], k)
        d.check(k, d.off)  # as if it never stopped
    c = b.counters
    assert status(cli, s).origin == "replica" and status(cli, s).readback == "answered"
    assert c["recovered_accepted"] > 0 and c["recovered_duplicate"] > 0
    assert c["refused"] == 0 and len(col.errors[s]) == errors_before


def test_a_message_during_the_read_back_wakes_the_taken_over_session(tmp_path):
    """A taken-over session is idle until its next message. A message that arrives while
    its senders' caches are still being read back is held, handled when the read-back ends,
    and wakes the session like any other: from then on it publishes every step, with no
    further traffic (the read-back slow, as on a loaded machine)."""
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    later: list = []
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    b = ServiceCore(bus.transport(), Settings(instance="inst-b", peers=PAIR),
                    store=SpecStore(tmp_path / "inst-b"), now_ns=clock, spawn=later.append)
    b.start()
    names = [f"s{i:02d}" for i in range(12)]
    for n in names:
        cli.put(keys.config_key(n), encode(paper_spec(n)))
    settle(a, b)
    while later:
        later.pop(0)()
    settle(a, b)
    s = next(n for n in names if n in a.served_sessions())
    d = Driver(CachedSender(bus.transport(), 64), clock, col, s)
    for k in range(10):
        d.step([a, b], k)
    a.t.close()
    b.dispatch.on_liveliness(keys.service_token_key("inst-a"), False)
    b.run_once()  # takes s over; its read-back is pending
    assert later and s in b.served_sessions()
    d.step([b], 10, mirror=False)  # held in the parked inbox
    while later:  # the read-back ends
        later.pop(0)()
    count = len(col.predictions[s])
    for k in range(11, 16):  # no traffic: the message above woke the session
        for phase in (0.1, 0.6):
            clock.t = int((k + phase) * PERIOD_NS)
            b.run_once()
    assert len(col.predictions[s]) >= count + 5
    assert col.predictions[s][-1].step == 15 + d.spec.lead


class SlowReadBack:
    """A transport whose read-back of one session's keys waits for ``gate`` (a sender
    across a slow link, or one that never answers before the timeout)."""

    def __init__(self, t, session):
        self._t, self.session, self.gate = t, session, threading.Event()

    def __getattr__(self, name):
        return getattr(self._t, name)

    def read_back(self, keyexpr, callback, **kw):
        if keys.session_of(keyexpr) == self.session:
            assert self.gate.wait(10)
        return self._t.read_back(keyexpr, callback, **kw)


def test_a_slow_read_back_holds_only_its_own_session(tmp_path):
    """Sessions taken over together are read back concurrently, and each rejoins the
    rounds when its own read-back ends: while one sender's cache is slow to answer, the
    other taken-over sessions already take their messages (the slow one holds its own)."""
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    later: list = []
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    names = [f"s{i:02d}" for i in range(12)]
    for n in names:
        cli.put(keys.config_key(n), encode(paper_spec(n)))
    settle(a)
    taken = a.served_sessions()
    slow = SlowReadBack(bus.transport(), taken[0])
    b = ServiceCore(slow, Settings(instance="inst-b", peers=PAIR),
                    store=SpecStore(tmp_path / "inst-b"), now_ns=clock, spawn=later.append)
    b.start()
    settle(a, b)
    while later:
        later.pop(0)()
    a.t.close()
    b.dispatch.on_liveliness(keys.service_token_key("inst-a"), False)
    b.run_once()  # takes them over; the read-back is spawned
    assert len(later) == 1 and set(taken) <= set(b.served_sessions())
    reader = threading.Thread(target=later.pop())
    reader.start()
    clock.t = int(0.1 * PERIOD_NS)
    for n in taken:
        cli.put(keys.command_key(n), cmd_bytes(n, 3, [1.0]))

    def taken_in(n):
        """Its message served from its inbox: accepted, or kept for the session's catch-up
        (no sender cache here answers: each waits for its bound before it takes them in)."""
        return b.dispatch.routes[n].sess.counters["commands_accepted"] + \
            len(b.dispatch.held_inputs.get(n, ()))

    deadline = time.monotonic() + 10
    while not all(taken_in(n) for n in taken[1:]) and time.monotonic() < deadline:
        b.run_once()
        time.sleep(0.001)
    assert all(taken_in(n) == 1 for n in taken[1:])
    assert taken_in(taken[0]) == 0  # still parked: its read-back has not ended
    slow.gate.set()
    reader.join(10)
    b.run_once()
    assert taken_in(taken[0]) == 1


def test_a_live_copy_after_its_read_back_is_dropped_quietly(tmp_path):
    """A sender that appears is read back; its cache's reply can overtake the live sample of
    the same message. The live copy is then the message already accepted: dropped quietly
    (``live_copy_of_recovered``), neither refused nor reported. A real duplicate (other
    bytes, same step) is still refused and reported, and a copy is remembered only for the
    window."""
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    clock.t = 3 * PERIOD_NS
    d = core.dispatch
    cmd, meas = cmd_bytes("s1", 5, [0.5]), meas_bytes("s1", "ranger", 2, [1.0])

    def sample(key: str, payload: bytes, recovered: bool = False) -> Sample:
        # recv_mono_ns on the transport's monotonic clock, as a transport sets it
        return Sample(key, payload, "put", clock.t, time.monotonic_ns(), recovered=recovered)

    d.on_read_back_command(sample(keys.command_key("s1"), cmd, True))
    d.on_read_back_sensor(sample(keys.sensor_key("s1", "ranger"), meas, True))
    core.run_once()
    d.on_command_sample(sample(keys.command_key("s1"), cmd))
    d.on_sensor_sample(sample(keys.sensor_key("s1", "ranger"), meas))
    core.run_once()
    c = core.counters
    assert c["recovered_accepted"] == 1 and c["recovered_commands_accepted"] == 1
    assert c["live_copy_of_recovered"] == 2
    assert c["refused"] == 0 and col.errors["s1"] == []
    # the same step with other bytes is a duplicate, refused as always
    d.on_command_sample(sample(keys.command_key("s1"), cmd_bytes("s1", 5, [0.7])))
    core.run_once()
    assert c["commands_duplicate"] == 1 and c["refused"] == 1 and len(col.errors["s1"]) == 1
    # a copy is expected only within the window: later, a repeat is a duplicate again
    d.on_read_back_sensor(sample(keys.sensor_key("s1", "ranger"),
                                 meas_bytes("s1", "ranger", 3, [1.0]), True))
    core.run_once()
    clock.t = (3 + paper_spec("s1").max_delay + 2) * PERIOD_NS
    d.on_sensor_sample(sample(keys.sensor_key("s1", "ranger"),
                              meas_bytes("s1", "ranger", 3, [1.0])))
    core.run_once()
    assert c["live_copy_of_recovered"] == 2 and c["refused"] == 2
    # bounded: at most READ_BACK_COPIES remembered (hashes, oldest dropped first); those
    # kept before now - max_delay - 1 are past their window and go at the next look-up
    sess = d.routes["s1"].sess
    now_step = sess.step_now(clock.t)
    for i in range(READ_BACK_COPIES + 100):
        sess.keep_read_back_copy(b"m%d" % i, now_step - 20 + i // 100)  # steps now-20 .. now-9
    assert len(sess.read_back_copies) == READ_BACK_COPIES
    assert not sess.take_read_back_copy(b"m0", now_step)  # the oldest went first
    assert len(sess.read_back_copies) < READ_BACK_COPIES  # expired ones purged
    assert sess.take_read_back_copy(b"m%d" % (READ_BACK_COPIES + 99), now_step)


def test_a_restored_session_waits_for_its_senders_caches_or_the_bound(tmp_path):
    """After a restart a restored session publishes nothing until the cache of every one of
    its data keys (each sensor's, the command's) was read back, as a sender that reconnects
    later is; one whose senders never come publishes once 2 x recover_timeout_s passed.
    Its status says which."""
    bus, clock, col, cli, d = _checkpointed(tmp_path)
    SpecStore(tmp_path / "a").save(paper_spec("s2"))  # a second session, never sent to
    clock.t = int(30.1 * PERIOD_NS)
    b = make_core(bus, clock, tmp_path)  # default settings: recover_timeout_s 2
    assert sorted(b.served_sessions()) == ["s1", "s2"]
    assert status(cli, "s1").readback == "waiting" and status(cli, "s1").origin == "checkpoint"
    published = len(col.predictions["s1"])
    sender = bus.transport()
    want = [keys.sensor_key("s1", "ranger"), keys.sensor_key("s1", "camera"),
            keys.command_key("s1")]
    for i, key in enumerate(want):
        clock.t = int((31 + i + 0.6) * PERIOD_NS)
        b.run_once()  # its ticks: nothing published yet
        assert len(col.predictions["s1"]) == published
        sender.publisher(key, cache=16)  # a sender that (re)connects: its cache is read
    b.run_once()
    assert len(col.predictions["s1"]) == published + 1  # at once, the last cache read
    st = status(cli, "s1")
    assert st.readback == "answered" and st.origin == "checkpoint"
    assert b.counters["readback_answered"] == 1
    assert not col.predictions.get("s2") and status(cli, "s2").readback == "waiting"
    clock.t = int(30.1 * PERIOD_NS) + 4_000_000_000  # 2 x recover_timeout_s after the start
    b.run_once()
    assert col.predictions["s2"] and status(cli, "s2").readback == "timeout"
    assert b.counters["readback_timeout"] == 1
