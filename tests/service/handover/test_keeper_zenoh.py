"""Restart and takeover with the estimate, as real processes over real Zenoh on loopback.

(1) The only daemon is killed (SIGKILL) mid-run, kept down 2 s more and restarted within one
    window: it resumes every session from its checkpoint file and reads back from the
    senders' caches (cached publishers, as the SDK's) what it missed; (2) two instances
    serve 20 sessions, the owner of about half of them is killed: the survivor resumes
    those from the replicas it received (plain puts: what was sent before the takeover is
    lost); (3) two instances, one stopped by SIGTERM: the survivor resumes from the final
    replica sent at the stop, and from the caches.

Each session is fed the paper scenario by a publisher thread that keeps going while a
daemon is down. Checks, per resumed session:

- where the estimate came from: ``SessionStatus.origin`` / ``origin_step`` name the state
  written before the kill / at the stop (read back from the checkpoint file, or caught on
  the replica key);
- exactness: every prediction of the new daemon equals, to 1e-9, an offline estimator
  restored from that state and fed what the new daemon accepted, live or read back (a
  suffix of what was sent: the prediction counters say how much of it);
- with caches, nothing lost and the bar of the issue: every diagonal entry of P within
  10 % of an offline run of the same feed that never stopped (the reference), from the
  first prediction after the restart on; without caches (2), no reset to the prior.

Without caches, packets accepted after the last replica and those sent while nobody served
the session are lost, so right after a takeover the covariance is larger than the
reference's (each lost step of the paper's ranger and camera adds a few %). How many steps
are lost depends on the replica interval against the step (here 0.1 s replicas for 100 ms
steps; with 0.25 s replicas a loaded machine once lost enough steps for a ratio of 2.09,
and a fresh CI run with 0.1 s replicas 2.14): the tests print the ratios and assert only that
no prediction's covariance is the prior's.

No wall-time asserts; everything waits on events (liveliness, predictions) with generous
timeouts. Run alone with ``pytest tests/service/handover/test_keeper_zenoh.py -m integration -s``.
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zenoh

from pd_service.backends import build
from pd_service.scenarios.paper import paper_command, simulate_paper
from pd_service.service import SpecStore
from pd_service.service.handover.checkpoint import from_message
from pd_service.transport import DEFAULT_SENDER_CACHE, Sample
from pd_service.wire import Prediction, SessionSpec, SessionState, decode, encode, keys

from ..helpers import Collector, cmd_bytes, meas_bytes, paper_spec
from ..procs import Daemon, Presence, client, free_port, query_session_status, sleep_until

pytestmark = pytest.mark.integration

PERIOD = 100_000_000  # 100 ms steps: a restart costs a few steps, not tens
WAIT_S = 60.0  # every wait on an event; only reached when something is broken


@dataclass
class Feed:
    """One session's paper run: what is put at each step, in order, and what it carries."""

    spec: SessionSpec
    steps: int
    schedule: list[tuple[int, str, bytes]] = field(default_factory=list)
    meas: list[tuple[str, int, np.ndarray]] = field(default_factory=list)
    cmds: list[tuple[int, np.ndarray]] = field(default_factory=list)
    #: step k -> how many of meas / cmds were put up to and including step k
    sent_by: list[tuple[int, int]] = field(default_factory=list)

    @property
    def last_step(self) -> int:
        """Sample step of the final measurement: the newest of all, put last."""
        return self.meas[-1][1]


def make_feed(session: str, epoch: int, seed: int, steps: int, max_delay: int) -> Feed:
    """Step k: the command for k + lead, then the samples arriving at k (10 % lost). The
    last put is a camera sample of the last step: a prediction whose newest_step is that
    step has used everything this feed put before it (one publisher, one session inbox)."""
    spec = paper_spec(session, epoch_ns=epoch, period_ns=PERIOD, max_delay=max_delay)
    run = simulate_paper(steps, np.random.default_rng(seed), loss=0.1)
    arrivals: dict[int, list] = {}
    for smp in run.samples:
        if smp.arrival is not None and smp.arrival < steps:
            arrivals.setdefault(smp.arrival, []).append((smp.sensor, smp.step, smp.z))
    k_last = steps - 1
    z_last = run.truth[k_last][[0, 2]] + np.random.default_rng(seed + 1).normal(0, 0.5, 2)
    arrivals.setdefault(k_last, []).append(("camera", k_last, z_last))
    feed = Feed(spec, steps)
    seq = 0
    for k in range(steps):
        t = epoch + k * PERIOD + PERIOD // 10
        j = k + spec.lead
        u = np.array([paper_command(j)])
        feed.schedule.append((t, keys.command_key(session), cmd_bytes(session, j, u, k)))
        feed.cmds.append((j, u))
        for sensor, s, z in arrivals.get(k, []):
            seq += 1
            feed.schedule.append((t, keys.sensor_key(session, sensor),
                                  meas_bytes(session, sensor, s, z, seq)))
            feed.meas.append((sensor, s, z))
        feed.sent_by.append((len(feed.meas), len(feed.cmds)))
    return feed


class FeedSender(threading.Thread):
    """Puts every feed's schedule on time, whoever is listening. ``cache`` 0: plain puts (a
    dead daemon loses them); > 0: one publisher per key keeping its last ``cache`` samples,
    as the SDK's Robot and Operator do (a restarted daemon reads them back)."""

    def __init__(self, t, feeds: list[Feed], cache: int = 0) -> None:
        super().__init__(daemon=True, name="feed")
        self.t = t
        self.items = sorted((x for f in feeds for x in f.schedule), key=lambda x: x[0])
        self.done = threading.Event()
        self.pubs = {}
        if cache > 0:  # declared before the run, like a robot's sensors
            for _, key, _ in self.items:
                if key not in self.pubs:
                    self.pubs[key] = t.publisher(key, cache=cache)

    def run(self) -> None:
        try:
            for when, key, data in self.items:
                sleep_until(when)
                pub = self.pubs.get(key)
                if pub is not None:
                    pub.put(data)
                else:
                    self.t.put(key, data)
        except zenoh.ZError:  # the test ended early and closed its session
            return
        self.done.set()


def reference(feed: Feed) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The run that never stopped: for each step k, diag P of predict(k) having been fed
    everything put up to step k (``full``) and up to step k - 1 (``prev``)."""
    est = build(feed.spec).est
    full, prev = [], []
    mi = ci = 0
    for k in range(feed.steps):
        prev.append(np.diag(est.predict(k).P).copy())
        n_meas, n_cmds = feed.sent_by[k]
        for j, u in feed.cmds[ci:n_cmds]:
            assert est.add_command(j, u, now=k)
        for sensor, s, z in feed.meas[mi:n_meas]:
            assert est.add_measurement(sensor, s, z, now=k)
        mi, ci = n_meas, n_cmds
        full.append(np.diag(est.predict(k).P).copy())
    return full, prev


def check_resumed(preds: list[Prediction], feed: Feed, state: SessionState | None
                  ) -> tuple[int, int]:
    """Every prediction in ``preds`` (one daemon's, after it resumed from ``state``; None:
    from the prior) equals an offline estimator restored from ``state`` and fed the packets
    the daemon accepted since (live or read back from the senders' caches): the last
    ``accepted - accepted(state)`` measurements put (likewise commands), in the order the
    prediction counters reveal them. Returns the number of predictions and of packets
    (measurements + commands) put after the state that the daemon never accepted (lost)."""
    spec = feed.spec
    est = build(spec).est  # ObserverPredictor, as the daemon's
    base: dict[str, int] = {}
    if state is not None:
        assert state.kind == "ObserverPredictor"
        est.restore_state(from_message(state, est.n))
        base = dict(state.session_counters)
    n0, c0 = base.get("accepted", 0), base.get("commands_accepted", 0)
    preds = sorted(preds, key=lambda p: p.seq)
    last = preds[-1].counters
    assert preds[-1].newest_step == feed.last_step  # everything put was seen
    m0 = len(feed.meas) - (last["accepted"] - n0)
    k0 = len(feed.cmds) - (last.get("commands_accepted", 0) - c0)
    assert n0 <= m0 and c0 <= k0, "accepted more than was put after the state"
    if state is None:
        assert m0 == k0 == 0  # nothing lost
    mi, ci = m0, k0
    assert preds[0].seq == (state.seq if state is not None else 0)  # the sequence goes on
    for p in preds:
        now = p.step - spec.lead
        c = p.counters
        assert c.get("refused", 0) == base.get("refused", 0), c
        while ci < k0 + c.get("commands_accepted", 0) - c0:
            j, u = feed.cmds[ci]
            assert est.add_command(j, u, now=now)
            ci += 1
        while mi < m0 + c["accepted"] - n0:
            sensor, s, z = feed.meas[mi]
            assert est.add_measurement(sensor, s, z, now=now)
            mi += 1
        exp = est.predict(now)
        assert p.newest_step == exp.newest_step
        np.testing.assert_allclose(p.x, exp.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(p.P, exp.P, rtol=1e-9, atol=1e-12)
    assert mi == len(feed.meas) and ci == len(feed.cmds)
    return len(preds), (m0 - n0) + (k0 - c0)


def ratios(preds: list[Prediction], feed: Feed, ref: list[np.ndarray]) -> np.ndarray:
    """Largest diag(P) / diag(P_ref) of each prediction (ref indexed by the step 'now')."""
    out = []
    for p in sorted(preds, key=lambda p: p.seq):
        now = p.step - feed.spec.lead
        out.append(float(np.max(np.diag(p.P) / ref[min(now, feed.steps - 1)])))
    return np.array(out)


def write_config(path: Path) -> Path:
    path.write_text("checkpoint_interval_s = 0.2\nreplica_interval_s = 0.1\n")
    return path


def after(col: Collector, session: str, t_ns: int) -> list[Prediction]:
    with col.cond:
        return [p for p in col.predictions[session] if p.made_ns > t_ns]


def used_all(feed: Feed):
    """Condition: a prediction made after ``t_ns`` has used the feed's final sample."""
    def check(col: Collector, t_ns: int) -> bool:
        return any(p.made_ns > t_ns and p.newest_step == feed.last_step
                   for p in col.predictions[feed.spec.session])
    return check


def got_all(feed: Feed):
    """Condition: a prediction made after ``t_ns`` has accepted every packet the feed put
    (its counters count those accepted before the state and after it, live or recovered)."""
    def check(col: Collector, t_ns: int) -> bool:
        return any(p.made_ns > t_ns and p.newest_step == feed.last_step
                   and p.counters.get("accepted", 0) == len(feed.meas)
                   and p.counters.get("commands_accepted", 0) == len(feed.cmds)
                   for p in col.predictions[feed.spec.session])
    return check


@pytest.fixture
def world(tmp_path):
    port = free_port()
    t = client(port)
    col = Collector().attach(t)
    pres = Presence(t)
    yield t, col, pres, f"tcp/127.0.0.1:{port}", tmp_path
    t.close()


def test_kill_and_restart_resumes_from_the_checkpoint_and_the_senders_caches(world):
    """The issue's bar: kill -9 the only daemon mid-run, restart it within one window, while
    the feed keeps publishing through cached publishers (as the SDK's Robot and Operator
    do). The restarted daemon resumes from its checkpoint and reads back from the senders'
    caches what it accepted after the checkpoint and what was sent while it was down: no
    packet put is lost, every prediction equals to 1e-9 an offline filter restored from the
    checkpoint and fed what the new daemon accepted (recovered packets included), and every
    diagonal entry of every P after the restart (the first ones included) is within 10 % of
    the run that never stopped. The recovered repeats of checkpointed packets are refused
    quietly: no ErrorReport."""
    t, col, pres, peer, root = world
    max_delay = 100  # 10 s: the restart must fit in one window
    conf = write_config(root / "svc.toml")
    d = Daemon("inst-r", root / "inst-r", [peer], ["--config", str(conf)]).start()
    assert pres.wait("inst-r", timeout=WAIT_S), d.log()
    epoch = time.time_ns() + 2_000_000_000
    kill_at, steps = 60, 220
    feed = make_feed("ck", epoch, seed=21, steps=steps, max_delay=max_delay)
    t.put(keys.config_key("ck"), encode(feed.spec))
    assert col.wait_for(lambda c: c.statuses["ck"], WAIT_S), d.log()
    pub = FeedSender(t, [feed], cache=DEFAULT_SENDER_CACHE)
    pub.start()
    assert col.wait_for(lambda c: any(p.step - feed.spec.lead >= kill_at
                                      for p in c.predictions["ck"]), WAIT_S), d.log()
    t_kill = time.time_ns()
    d.stop(signal.SIGKILL)
    assert pres.wait("inst-r", alive=False, timeout=WAIT_S)
    state = decode(SpecStore(root / "inst-r").load_state("ck"), SessionState)
    # down for 2 s more (20 steps, a fifth of the window): the feed goes on, nobody hears it
    sleep_until(t_kill + 2_000_000_000)
    d2 = Daemon("inst-r", root / "inst-r", [peer], ["--config", str(conf)]).start()
    try:
        assert pres.wait("inst-r", timeout=WAIT_S), d2.log()
        # every packet put is accepted in the end (a lost one: this times out)
        assert col.wait_for(lambda c: got_all(feed)(c, t_kill), WAIT_S + steps * PERIOD / 1e9), \
            (d2.log(), after(col, "ck", t_kill)[-1].counters)
        st = query_session_status(t, "ck")
        assert st is not None and st.state == "restored", d2.log()
        assert st.origin == "checkpoint" and st.origin_step == state.now_step, st
        resumed = sorted(after(col, "ck", t_kill), key=lambda p: p.seq)
        first = resumed[0]
        first_now = first.step - feed.spec.lead
        assert first_now - state.now_step <= max_delay  # the restart fit in one window
        n, lost = check_resumed(resumed, feed, state)
        assert n > max_delay  # predictions for more than a window after the restart
        assert lost == 0  # every packet put after the checkpoint was accepted
        # the first prediction already has what the caches gave back: the packets accepted
        # after the checkpoint and those put while no daemon ran (lost without the caches)
        assert first.counters.get("recovered_accepted", 0) > 0, first.counters
        assert first.counters.get("refused", 0) == state.session_counters.get("refused", 0)
        with col.cond:
            reports = [e for e in col.errors["ck"] if e.t_ns > t_kill]
        assert reports == []  # recovered repeats (recovered_duplicate) are not reported

        full, prev = reference(feed)
        r_prev = ratios(resumed, feed, prev)
        r_full = ratios(resumed, feed, full)
        prior = np.diag(build(feed.spec).est.predict(first_now).P)
        c = first.counters
        print(f"\nrestart: checkpoint of step {state.now_step}, first prediction at step "
              f"{first_now}; recovered at the start: {c.get('recovered_accepted', 0)} "
              f"measurements + {c.get('recovered_commands_accepted', 0)} commands accepted, "
              f"{c.get('recovered_refused', 0)} refused quietly "
              f"({c.get('recovered_duplicate', 0)} + {c.get('recovered_commands_duplicate', 0)}"
              f" repeats, {c.get('recovered_late', 0)} + {c.get('recovered_commands_late', 0)}"
              f" older than the window); largest diag P / reference (fed up to step now - 1): "
              f"first {r_prev[0]:.4f}, max {r_prev.max():.4f}; diag P / reference (fed up to "
              f"now): min {r_full.min():.4f}; prior / reference "
              f"{np.max(prior / full[first_now]):.0f}")
        # not the prior's, and within 10 % of the run that never stopped, from the first on
        assert np.all(np.diag(first.P) < 0.1 * prior)
        assert np.all(r_prev <= 1.10) and np.all(r_full >= 0.90)
        assert "event=session_resumed" in d2.log()
    finally:
        pub.join(timeout=WAIT_S)
        assert d2.stop() == 0, d2.log()


#: The two instances trust each other (explicit membership: standalone otherwise).
PEERS = ["--peer", "inst-x", "--peer", "inst-y"]


class Replicas:
    """Every replica put on the service's replica keys, by session and then by now_step."""

    def __init__(self, t) -> None:
        self.lock = threading.Lock()
        self.by_session: dict[str, dict[int, SessionState]] = {}
        t.subscribe(f"{keys.OPERATOR_ROOT}/{keys.SERVICE_CHUNK}/*/replica/*", self._on)

    def _on(self, sample: Sample) -> None:
        st = decode(sample.payload, SessionState)
        with self.lock:
            self.by_session.setdefault(st.session, {})[st.now_step or 0] = st

    def steps(self, session: str) -> list[int]:
        with self.lock:
            return list(self.by_session.get(session, {}))

    def at(self, session: str, step: int) -> SessionState:
        with self.lock:
            return self.by_session[session][step]


def start_pair(root: Path, peer: str, conf: Path, pres: Presence) -> tuple[Daemon, Daemon]:
    """inst-x, then inst-y (connected to the test's peer and to inst-x), both present."""
    args = ["--config", str(conf), *PEERS]
    x = Daemon("inst-x", root / "inst-x", [peer], args).start()
    assert pres.wait("inst-x", timeout=WAIT_S), x.log()
    y = Daemon("inst-y", root / "inst-y", [peer, x.endpoint], args).start()
    if not pres.wait("inst-y", timeout=WAIT_S):
        log = y.log()
        y.stop()
        x.stop()
        raise AssertionError(log)
    return x, y


def open_feeds(t, col, prefix: str, n: int, seed: int, steps: int,
               max_delay: int) -> tuple[dict[str, Feed], dict[str, str]]:
    """n sessions ``<prefix>00``... configured; their feeds and owner instances."""
    names = [f"{prefix}{i:02d}" for i in range(n)]
    epoch = time.time_ns() + 3_000_000_000
    feeds = {s: make_feed(s, epoch, seed=seed + i, steps=steps, max_delay=max_delay)
             for i, s in enumerate(names)}
    for s in names:
        t.put(keys.config_key(s), encode(feeds[s].spec))
    assert col.wait_for(lambda c: all(c.statuses[s] for s in names), WAIT_S)
    return feeds, {s: col.statuses[s][-1].instance for s in names}


def test_owner_killed_survivor_resumes_from_its_replicas(world):
    t, col, pres, peer, root = world
    max_delay = 60
    conf = write_config(root / "svc.toml")
    replicas = Replicas(t)
    x, y = start_pair(root, peer, conf, pres)
    try:
        kill_at, steps = 50, 150
        feeds, owners = open_feeds(t, col, "fo", 20, 100, steps, max_delay)
        names = list(feeds)
        lost = [s for s in names if owners[s] == "inst-y"]
        kept = [s for s in names if owners[s] == "inst-x"]
        assert lost and kept, owners
        pub = FeedSender(t, list(feeds.values()))
        pub.start()
        # kill once every session of inst-y has been replicated past kill_at
        assert col.wait_for(lambda c: all(any(k >= kill_at for k in replicas.steps(s))
                                          for s in lost), WAIT_S), y.log()
        t_kill = time.time_ns()
        y.stop(signal.SIGKILL)
        assert pres.wait("inst-y", alive=False, timeout=WAIT_S)
        # the taken sessions lost what was put while nobody served them: their last
        # measurement used is the end; the survivor's own lost nothing: every packet
        # accepted (the last command may be put after the last measurement)
        assert col.wait_for(lambda c: all(used_all(feeds[s])(c, t_kill) for s in lost)
                            and all(got_all(feeds[s])(c, t_kill) for s in kept),
                            WAIT_S + steps * PERIOD / 1e9), x.log()
        worst = []
        for s in lost:
            feed = feeds[s]
            st = query_session_status(t, s)
            assert st is not None and st.instance == "inst-x", st
            assert st.origin == "replica" and st.origin_step is not None, st
            state = replicas.at(s, st.origin_step)
            assert state.instance == "inst-y"
            mine = after(col, s, t_kill)
            check_resumed(mine, feed, state)
            # no reset to the prior at the takeover: every prediction's covariance after it
            # far below the prior's at its step (how far above the reference it
            # is depends on the steps lost while nobody served the session: on the
            # machine's speed, so it is printed, not asserted)
            full, _ = reference(feed)
            r = ratios(list(col.predictions[s]), feed, full)
            worst.append(float(r.max()))
            fresh = build(feed.spec).est
            for p in mine:  # those made after the kill
                prior = np.diag(fresh.predict(p.step - feed.spec.lead).P)
                assert np.all(np.diag(p.P) < 0.1 * prior), (s, p.step, r.max())
        for s in kept:  # the survivor's own sessions never noticed
            st = query_session_status(t, s)
            assert st.instance == "inst-x" and st.origin == "prior"
            check_resumed(list(col.predictions[s]), feeds[s], None)
        print(f"\ntakeover: {len(lost)} sessions resumed from replicas; largest "
              f"diag P / reference {max(worst):.3f}")
        pub.join(timeout=WAIT_S)
    finally:
        y.stop()
        assert x.stop() == 0, x.log()


def test_sigterm_hands_the_final_state_to_the_successor(world):
    """A graceful stop (SIGTERM) of the owner of about half of 10 sessions: before it
    withdraws its presence it sends every served session's newest state to its successor
    (the final replica); the survivor resumes from exactly that state (origin "replica",
    origin_step = the newest replica it got), and from the senders' caches what was sent
    until it took over. Every prediction after the takeover equals, to 1e-9, an offline
    filter restored from the final replica and fed what the survivor accepted; no packet
    put is lost; the covariance is not reset: each diagonal entry within 10 % of the run
    that never stopped."""
    t, col, pres, peer, root = world
    max_delay = 60
    # replicas rarely (10 s): the only replica that can be recent is the final one
    conf = root / "svc.toml"
    conf.write_text("checkpoint_interval_s = 0.2\nreplica_interval_s = 10.0\n")
    replicas = Replicas(t)
    x, y = start_pair(root, peer, conf, pres)
    try:
        stop_at, steps = 50, 130
        feeds, owners = open_feeds(t, col, "gt", 10, 300, steps, max_delay)
        names = list(feeds)
        moved = [s for s in names if owners[s] == "inst-y"]
        assert moved and len(moved) < len(names), owners
        pub = FeedSender(t, list(feeds.values()), cache=DEFAULT_SENDER_CACHE)
        pub.start()
        assert col.wait_for(lambda c: all(any(p.step - feeds[s].spec.lead >= stop_at
                                              for p in c.predictions[s]) for s in moved),
                            WAIT_S), y.log()
        t_stop = time.time_ns()
        assert y.stop(signal.SIGTERM) == 0, y.log()
        assert pres.wait("inst-y", alive=False, timeout=WAIT_S)
        assert col.wait_for(lambda c: all(got_all(feeds[s])(c, t_stop) for s in moved),
                            WAIT_S + steps * PERIOD / 1e9), x.log()
        worst_first, worst = 0.0, 0.0
        for s in moved:
            feed = feeds[s]
            st = query_session_status(t, s)
            assert st is not None and st.instance == "inst-x" and st.origin == "replica", st
            final = replicas.at(s, max(replicas.steps(s)))
            assert final.instance == "inst-y" and final.made_ns >= t_stop  # sent at the stop
            assert st.origin_step == final.now_step, (st, final.now_step, y.log(), x.log())
            mine = sorted(after(col, s, t_stop), key=lambda p: p.seq)
            mine = [p for p in mine if p.seq >= final.seq]  # the survivor's, not y's last
            n, lost = check_resumed(mine, feed, final)
            assert lost == 0  # what y accepted is in the final replica, the rest came back
            full, prev = reference(feed)
            r_prev, r_full = ratios(mine, feed, prev), ratios(mine, feed, full)
            assert np.all(r_prev <= 1.10) and np.all(r_full >= 0.90), (s, r_prev.max())
            worst_first = max(worst_first, float(r_prev[0]))
            worst = max(worst, float(r_prev.max()))
        print(f"\nSIGTERM hand-over: {len(moved)} sessions resumed from the final replica; "
              f"largest diag P / reference (fed up to now - 1): first prediction "
              f"{worst_first:.4f}, any {worst:.4f}")
        pub.join(timeout=WAIT_S)
    finally:
        y.stop()
        assert x.stop() == 0, x.log()
