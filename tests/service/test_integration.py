"""The daemon as real processes over real Zenoh on loopback (free ports, events not sleeps).

Run alone with ``pytest tests/service -m integration``.
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from pd_service.estimation import ObserverPredictor
from pd_service.scenarios.paper import (
    paper_command,
    paper_model,
    paper_prior,
    paper_sensors,
    simulate_paper,
)
from pd_service.wire import Prediction, SessionSpec, encode, keys

from .helpers import Collector, cmd_bytes, cmd_now_bytes, meas_bytes, paper_spec, storm
from .procs import (
    Daemon,
    Presence,
    await_service_status,
    client,
    free_port,
    query_service_status,
    query_session_status,
    sleep_until,
)

pytestmark = pytest.mark.integration

PERIOD = 20_000_000  # 20 ms steps keep the real-time runs short
MAX_DELAY = 60  # 1.2 s of slack: on a loaded CI machine every packet is still accepted
STEPS = 150


@dataclass
class Feed:
    """The paper's run for one session, as timed publications, plus what was sent."""

    spec: SessionSpec
    schedule: list[tuple[int, str, bytes]] = field(default_factory=list)
    meas: list[tuple[str, int, np.ndarray]] = field(default_factory=list)
    cmds: list[tuple[int, float]] = field(default_factory=list)


def paper_feed(session: str, epoch: int, seed: int, loss: float = 0.1) -> Feed:
    spec = paper_spec(session, epoch_ns=epoch, period_ns=PERIOD, max_delay=MAX_DELAY)
    run = simulate_paper(STEPS, np.random.default_rng(seed), loss=loss)
    feed = Feed(spec)
    arrivals: dict[int, list] = {}
    for smp in run.samples:
        if smp.arrival is not None and smp.arrival < STEPS:
            arrivals.setdefault(smp.arrival, []).append(smp)
    seq = 0
    for k in range(STEPS):
        t = epoch + k * PERIOD + PERIOD // 10
        j = k + spec.lead
        feed.schedule.append((t, keys.command_key(session), cmd_bytes(session, j,
                                                                       paper_command(j), k)))
        feed.cmds.append((j, paper_command(j)))
        for smp in arrivals.get(k, []):
            seq += 1
            feed.schedule.append((t, keys.sensor_key(session, smp.sensor),
                                  meas_bytes(session, smp.sensor, smp.step, smp.z, seq)))
            feed.meas.append((smp.sensor, smp.step, smp.z))
    return feed


def publish(t, schedules: list[list[tuple[int, str, bytes]]]) -> None:
    for when, key, data in sorted((x for s in schedules for x in s), key=lambda x: x[0]):
        sleep_until(when)
        t.put(key, data)


def all_used(preds: list[Prediction], feed: Feed) -> bool:
    """True once a prediction has used every packet and command sent."""
    if not preds:
        return False
    c = preds[-1].counters
    return c["accepted"] == len(feed.meas) and c.get("commands_accepted") == len(feed.cmds)


def check_against_offline(preds: list[Prediction], feed: Feed) -> int:
    """Every prediction equals ObserverPredictor fed the same accepted packets (the prefix
    given by its counters: one publisher, one link, so the daemon sees them in order)."""
    x0, P0 = paper_prior()
    op = ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0,
                           lead=feed.spec.lead, max_delay=feed.spec.max_delay)
    mi = ci = 0
    for p in sorted(preds, key=lambda p: p.seq):
        now = p.step - feed.spec.lead
        c = p.counters
        assert c.get("refused", 0) == 0, c
        while ci < c.get("commands_accepted", 0):
            j, u = feed.cmds[ci]
            assert op.add_command(j, np.array([u]), now=now)
            ci += 1
        while mi < c["accepted"]:
            sensor, s, z = feed.meas[mi]
            assert op.add_measurement(sensor, s, z, now=now)
            mi += 1
        exp = op.predict(now)
        assert p.newest_step == exp.newest_step
        np.testing.assert_allclose(p.x, exp.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(p.P, exp.P, rtol=1e-9, atol=1e-12)
    assert mi == len(feed.meas) and ci == len(feed.cmds)  # everything sent was used
    return len(preds)


def _net(root):
    """The test's Zenoh peer, a collector and a presence tracker: one private network."""
    port = free_port()
    t = client(port)
    return t, Collector().attach(t), Presence(t), port, root


@pytest.fixture(scope="module")
def net(tmp_path_factory):
    """Network shared by the tests that use the module's daemon inst-a."""
    n = _net(tmp_path_factory.mktemp("svc"))
    yield n
    n[0].close()


@pytest.fixture
def own_net(tmp_path):
    """A network of the test's own (no other daemon on it)."""
    n = _net(tmp_path)
    yield n
    n[0].close()


@pytest.fixture(scope="module")
def daemon_a(net):
    t, col, pres, port, root = net
    d = Daemon("inst-a", root / "inst-a", [f"tcp/127.0.0.1:{port}"]).start()
    assert pres.wait("inst-a"), d.log()
    yield d
    assert d.stop() == 0, d.log()


def configure(t, col, spec: SessionSpec) -> None:
    before = len(col.statuses[spec.session])
    t.put(keys.config_key(spec.session), encode(spec))
    assert col.wait_for(lambda c: len(c.statuses[spec.session]) > before), "no status answer"


def test_paper_scenario_predictions_equal_offline(net, daemon_a):
    t, col, _, _, _ = net
    feed = paper_feed("paper", time.time_ns() + 300_000_000, seed=11)
    configure(t, col, feed.spec)
    assert col.statuses["paper"][-1].state == "active"
    publish(t, [feed.schedule])
    n_sent = len(feed.meas)
    assert col.wait_for(lambda c: all_used(c.predictions["paper"], feed))
    n = check_against_offline(list(col.predictions["paper"]), feed)
    st = query_session_status(t, "paper")
    # a prediction per step, or the step counted as missed (a loaded machine's worker may
    # fall a step behind: the steps it skipped are counted, never silently lost)
    assert n + st.counters.get("steps_missed", 0) >= STEPS
    assert st.counters["accepted"] == n_sent and st.latency_p99_us > 0


def test_malformed_on_one_session_leaves_another_untouched(net, daemon_a):
    t, col, _, _, _ = net
    epoch = time.time_ns() + 300_000_000
    good = paper_feed("good", epoch, seed=12)
    configure(t, col, good.spec)
    configure(t, col, paper_spec("bad", epoch_ns=epoch, period_ns=PERIOD))  # max_delay 12
    rng = np.random.default_rng(4)
    bad: list[tuple[int, str, bytes]] = []
    for k in range(20, 120, 10):  # bursts of every kind of bad input, interleaved
        msgs = storm("bad", rng)
        t_k = epoch + k * PERIOD + PERIOD // 2
        bad += [(t_k, key, data) for key, data in msgs]
        bad += [(t_k, keys.sensor_key("ghost", "ranger"), data) for _, data in msgs[:5]]
    publish(t, [good.schedule, bad])
    assert col.wait_for(lambda c: all_used(c.predictions["good"], good))
    check_against_offline(list(col.predictions["good"]), good)
    assert col.errors["good"] == []
    n_bad = sum(1 for _, key, _ in bad if key.startswith(keys.session_prefix("bad") + "/"))
    deadline = time.monotonic() + 10
    while True:  # the bad session's inbox is drained in the same rounds; poll its status
        st = query_session_status(t, "bad")
        if st.counters.get("refused", 0) == n_bad or time.monotonic() > deadline:
            break
    assert st.counters["refused"] == n_bad and st.counters.get("accepted", 0) == 0
    assert len(col.errors["bad"]) > 0
    svc = query_service_status(t, "inst-a")
    assert svc.counters["unknown_session"] > 0  # the storm's "ghost" copies were counted


def test_restart_restores_sessions(own_net, tmp_path):
    t, col, pres, port, _ = own_net
    d = Daemon("inst-r", tmp_path / "inst-r", [f"tcp/127.0.0.1:{port}"]).start()
    assert pres.wait("inst-r"), d.log()
    epoch = time.time_ns()
    names = ["r1", "r2", "r3"]
    for s in names:
        configure(t, col, paper_spec(s, epoch_ns=epoch, period_ns=PERIOD))
    d.stop(signal.SIGKILL)  # no chance to flush anything: specs were persisted on change
    assert pres.wait("inst-r", alive=False)
    counts = {s: len(col.predictions[s]) for s in names}
    d2 = Daemon("inst-r", tmp_path / "inst-r", [f"tcp/127.0.0.1:{port}"]).start()
    try:
        assert pres.wait("inst-r"), d2.log()
        # a restored session nobody has sent to yet is idle: one prediction at restart...
        assert col.wait_for(lambda c: all(len(c.predictions[s]) > counts[s]
                                          for s in names)), "no prediction at restart"
        for s in names:
            st = query_session_status(t, s)
            assert st.state == "restored" and st.instance == "inst-r"
            assert col.predictions[s][counts[s]].seq == 0  # a new estimator and sequence
        # ...and one every step again from its first message on
        for s in names:
            t.put(keys.command_key(s), cmd_now_bytes(s, time.time_ns()))
        assert col.wait_for(lambda c: all(len(c.predictions[s]) > counts[s] + 3
                                          for s in names)), "publishing did not resume"
        assert "event=session_restored" in d2.log()
    finally:
        assert d2.stop() == 0, d2.log()
    assert "event=stopped" in d2.log()


def test_two_instances_split_sessions_and_take_over(own_net, tmp_path):
    t, col, pres, port, _ = own_net
    peer = f"tcp/127.0.0.1:{port}"
    a = Daemon("inst-x", tmp_path / "inst-x", [peer], ["--peer", "inst-y"]).start()
    assert pres.wait("inst-x"), a.log()
    b = Daemon("inst-y", tmp_path / "inst-y", [peer, a.endpoint], ["--peer", "inst-x"]).start()
    try:
        assert pres.wait("inst-y"), b.log()
        # inst-x has seen inst-y too (the test may see its token first: a config put
        # meanwhile would be answered by both, the first name's owner differing)
        st = await_service_status(t, "inst-x", lambda st: st.counters["members"] == 2)
        assert st is not None and st.counters["members"] == 2, a.log()
        epoch = time.time_ns()
        names = [f"split{i:02d}" for i in range(20)]
        for s in names:
            configure(t, col, paper_spec(s, epoch_ns=epoch, period_ns=PERIOD))
        owners = {s: col.statuses[s][-1].instance for s in names}
        by_x = {s for s, o in owners.items() if o == "inst-x"}
        by_y = {s for s, o in owners.items() if o == "inst-y"}
        assert by_x and by_y and by_x | by_y == set(names)
        # each instance knows every spec (the owner answered; the other may apply it later)
        sx, sy = (await_service_status(t, inst, lambda st: st.counters["sessions_known"]
                                       == len(names)) for inst in ("inst-x", "inst-y"))
        assert set(sx.sessions) == by_x and set(sy.sessions) == by_y
        assert sx.counters["sessions_known"] == sy.counters["sessions_known"] == len(names)
        # inst-y stops: inst-x takes its sessions over and says so on their status keys
        assert b.stop() == 0, b.log()
        assert col.wait_for(lambda c: all(c.statuses[s][-1].instance == "inst-x"
                                          and "taken over" in c.statuses[s][-1].detail
                                          for s in by_y)), a.log()
        # a taken-over session is idle until its next message: from it on, every step
        for s in by_y:
            t.put(keys.command_key(s), cmd_now_bytes(s, time.time_ns()))
        counts = {s: len(col.predictions[s]) for s in by_y}
        assert col.wait_for(lambda c: all(len(c.predictions[s]) > counts[s] + 3 for s in by_y)), (
            f"{ {s: (counts[s], len(col.predictions[s])) for s in by_y} }\n"
            f"{ {s: [e.reason for e in col.errors[s]] for s in by_y} }\n{a.log()}")
        assert set(query_service_status(t, "inst-x").sessions) == set(names)
    finally:
        b.stop()
        assert a.stop() == 0, a.log()


def test_a_stop_during_a_takeover_read_back_exits_cleanly(own_net, tmp_path):
    """SIGTERM while a takeover's read-back waits on senders' caches that never answer (a
    stalled sender: its tokens stand, its queries time out after recover_timeout_s): the
    instance stops with status 0. Its read-back threads end with the transport and it waits
    for them: a process that exited under them sometimes crashed in Zenoh's native code
    (SIGSEGV or SIGABRT in 2 of 8 stops with bench/takeover.py's stalled caches; this test
    saw none in 5 runs of that build, so it guards the exit more than it reproduces it)."""
    t, col, pres, port, _ = own_net
    peer = f"tcp/127.0.0.1:{port}"
    a = Daemon("inst-x", tmp_path / "inst-x", [peer], ["--peer", "inst-y"]).start()
    assert pres.wait("inst-x"), a.log()
    b = Daemon("inst-y", tmp_path / "inst-y", [peer, a.endpoint], ["--peer", "inst-x"]).start()
    held: list = []  # the caches' queryables and tokens
    asked: list = []  # their queries, never answered
    queried = threading.Condition()

    def on_query(q) -> None:
        with queried:
            asked.append(q)
            queried.notify_all()

    try:
        assert pres.wait("inst-y"), b.log()
        names = [f"rb{i:02d}" for i in range(40)]
        for s in names:
            configure(t, col, paper_spec(s, epoch_ns=time.time_ns(), period_ns=PERIOD))
        by_y = [s for s in names if col.statuses[s][-1].instance == "inst-y"]
        assert by_y
        zid = t.session.info.zid()
        for i, key in enumerate(k for s in by_y for k in (keys.command_key(s),
                                                           keys.sensor_key(s, "ranger"))):
            at = f"{key}/@adv/pub/{zid}/{i}/_"
            held += [t.session.declare_queryable(at, on_query),
                     t.session.liveliness().declare_token(at)]
        caches = len(held) // 2
        with queried:  # the tokens reached both: each instance asked each cache once
            assert queried.wait_for(lambda: len(asked) >= 2 * caches, 60), (a.log(), b.log())
        assert b.stop(signal.SIGKILL) == -signal.SIGKILL
        assert col.wait_for(lambda c: all(c.statuses[s][-1].instance == "inst-x"
                                          for s in by_y)), a.log()
        assert a.stop() == 0, a.log()  # the read-back still waits on the caches
        assert "event=stopped" in a.log()
    finally:
        b.stop()
        a.stop()
        held.clear()
        asked.clear()
