"""ServiceCore on the in-memory bus with an injected clock: deterministic, no network."""

from __future__ import annotations

import threading

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
from pd_service.service import ServiceCore, Settings, SpecStore, dispatch
from pd_service.transport import InMemoryBus
from pd_service.wire import (
    Command,
    ErrorReport,
    Measurement,
    Prediction,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
    decode,
    encode,
    keys,
)

from .helpers import PERIOD_NS, Clock, Collector, cmd_bytes, meas_bytes, paper_spec, storm

#: Two instances that share sessions must list each other (the ``peers`` setting).
PAIR = ["inst-a", "inst-b"]


def make_core(bus, clock, tmp_path, instance="a", **kw) -> ServiceCore:
    """A started core on ``bus``; its run_once budget's clock is frozen (one call does all
    the work there is, on a slow machine as on a fast one)."""
    settings = Settings(instance=instance, **kw)
    store = SpecStore(tmp_path / instance)
    core = ServiceCore(bus.transport(), settings, store=store, now_ns=clock,
                       run_clock_ns=lambda: 0, spawn=lambda fn: fn())
    core.start()
    return core


def settle(*cores: ServiceCore) -> None:
    """Run each core until it has no work left (one run_once returns after ~50 ms of work,
    e.g. of fsynced configs under load)."""
    for c in cores:
        c.run_once()
    while any(c.has_work() for c in cores):
        for c in cores:
            c.run_once()


@pytest.fixture
def world(tmp_path):
    bus = InMemoryBus()
    clock = Clock(0)
    col = Collector().attach(bus.transport())
    return bus, clock, col, bus.transport()


def at(step: float, period: int = PERIOD_NS, epoch: int = 0) -> int:
    return epoch + int(round(step * period))


# ---------------------------------------------------------------- paper scenario driver --

class PaperFeed:
    """Feeds the paper's run to the daemon step by step and mirrors every call on an
    offline ObserverPredictor built straight from pd_service.estimation (not via the wire).

    At step k (clock at 10 % of the step): the operator's command for apply step k + lead,
    then every sample arriving at k (plus injected duplicates and over-late copies);
    run_once; then the clock moves to 60 % of the step (past the tick) and run_once again.
    After each run_once the new predictions must equal the offline predict(k).
    """

    def __init__(self, core, cli, clock, col, session, seed=1, loss=0.1, steps=200,
                 extra_late=True, epoch=0, max_delay=12, check=True):
        self.core, self.cli, self.clock, self.col = core, cli, clock, col
        self.s = session
        self.spec = paper_spec(session, epoch_ns=epoch, max_delay=max_delay)
        self.epoch = epoch
        self.steps = steps
        self.check = check
        rng = np.random.default_rng(seed)
        run = simulate_paper(steps, rng, loss=loss)
        self.arrivals: dict[int, list] = {}
        for smp in run.samples:
            if smp.arrival is not None:
                self.arrivals.setdefault(smp.arrival, []).append((smp.sensor, smp.step, smp.z))
        if extra_late:  # a duplicate and an over-late copy now and then: both refused
            for smp in run.samples[5::37]:
                if smp.arrival is not None:
                    self.arrivals.setdefault(smp.arrival + 1, []).append(
                        (smp.sensor, smp.step, smp.z))
                    self.arrivals.setdefault(smp.step + max_delay + 3, []).append(
                        (smp.sensor, smp.step, smp.z))
        x0, P0 = paper_prior()
        self.offline = ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0,
                                         lead=self.spec.lead, max_delay=max_delay)
        self.accepted = 0
        self.compared = 0
        self.seq = 0

    def configure(self):
        self.clock.t = at(0, epoch=self.epoch) - 1
        self.cli.put(keys.config_key(self.s), encode(self.spec))
        self.core.run_once()

    def step(self, k: int):
        s, lead = self.s, self.spec.lead
        self.clock.t = at(k + 0.1, epoch=self.epoch)
        u = paper_command(k + lead)
        self.cli.put(keys.command_key(s), cmd_bytes(s, k + lead, u, seq=k))
        assert self.offline.add_command(k + lead, np.array([u]), now=k)
        for sensor, stamp, z in self.arrivals.get(k, []):
            self.seq += 1
            self.cli.put(keys.sensor_key(s, sensor), meas_bytes(s, sensor, stamp, z, self.seq))
            self.accepted += self.offline.add_measurement(sensor, stamp, z, now=k)
        self._run(k)
        self.clock.t = at(k + 0.6, epoch=self.epoch)
        self._run(k)

    def _run(self, k):
        before = len(self.col.predictions[self.s])
        self.core.run_once()
        new = self.col.predictions[self.s][before:]
        if not self.check:
            return
        for p in new:
            exp = self.offline.predict(k)
            assert p.step == exp.step == k + self.spec.lead
            assert p.newest_step == exp.newest_step
            np.testing.assert_allclose(p.x, exp.x, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(p.P, exp.P, rtol=1e-9, atol=1e-12)
            assert p.counters["accepted"] == self.accepted
            self.compared += 1

    def run(self, steps=None):
        for k in range(self.steps if steps is None else steps):
            self.step(k)


# ---------------------------------------------------------------- lifecycle ---------------

def test_session_lifecycle_answers_every_change(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    spec = paper_spec("s1")
    cli.put(keys.config_key("s1"), encode(spec))
    core.run_once()
    st = col.statuses["s1"][-1]
    assert (st.state, st.instance, st.detail) == ("active", "a", "created")
    assert (tmp_path / "a" / "s1.msgpack").exists()

    # the status queryable answers for the session
    [rep] = cli.get(keys.status_key("s1"))
    assert rep.ok and decode(rep.payload, SessionStatus).state == "active"
    # the same spec again: answered, estimator kept
    est = core._routes["s1"].sess.est
    cli.put(keys.config_key("s1"), encode(spec))
    core.run_once()
    assert col.statuses["s1"][-1].detail.startswith("unchanged")
    assert core._routes["s1"].sess.est is est
    # a different spec replaces it
    cli.put(keys.config_key("s1"), encode(paper_spec("s1", max_delay=20)))
    core.run_once()
    assert col.statuses["s1"][-1].detail.startswith("replaced")
    assert core._routes["s1"].sess.est is not est
    assert decode((tmp_path / "a" / "s1.msgpack").read_bytes(), SessionSpec).max_delay == 20
    # delete removes it, from memory and disk; the status query now says unknown
    cli.delete(keys.config_key("s1"))
    core.run_once()
    assert col.statuses["s1"][-1].state == "removed"
    assert not (tmp_path / "a" / "s1.msgpack").exists()
    [rep] = cli.get(keys.status_key("s1"))
    assert not rep.ok and "unknown session" in decode(rep.payload, ErrorReport).reason
    # deleting an unknown session is answered too
    cli.delete(keys.config_key("nope"))
    core.run_once()
    assert col.statuses["nope"][-1].state == "removed"
    assert col.statuses["nope"][-1].detail == "no such session"


def test_bad_config_is_refused_with_an_error_report(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), b"\x81\xa1v\x01")  # a map, but not a SessionSpec
    cli.put(keys.config_key("s2"), encode(paper_spec("s3")))  # session != key
    cli.put(keys.config_key("s4"), encode(paper_spec("s4", period_ns=1)))  # would spin
    core.run_once()
    assert core.served_sessions() == []
    assert "SessionSpec" in col.errors["s1"][0].reason
    assert "does not match the key" in col.errors["s2"][0].reason
    assert "period_ns" in col.errors["s4"][0].reason
    assert core.service_status().counters["config_refused"] == 3


def test_session_limit(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, max_sessions=2)
    for s in ("s1", "s2", "s3"):
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    cli.put(keys.config_key("s1"), encode(paper_spec("s1", max_delay=20)))  # replace: fine
    core.run_once()
    assert core.served_sessions() == ["s1", "s2"]
    assert "max_sessions" in col.errors["s3"][0].reason
    assert col.statuses["s1"][-1].detail.startswith("replaced")


def test_ticks_publish_every_step_and_measurements_publish_at_once(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()  # created at t=0: first tick is due at 0.5 period
    # traffic first (a session nobody has sent to is idle): a command does not publish
    # by itself, but from it on the session ticks every step
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 10, [0.0]))
    core.run_once()
    assert col.predictions["s1"] == []
    for k in range(5):
        clock.t = at(k + 0.6)
        core.run_once()
    assert [p.step for p in col.predictions["s1"]] == [10, 11, 12, 13, 14]
    # a measurement at 0.1 of step 5 publishes at once; the tick of step 5 then stays quiet
    clock.t = at(5.1)
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 2, [5.0]))
    core.run_once()
    assert col.predictions["s1"][-1].newest_step == 2
    clock.t = at(5.7)
    core.run_once()
    assert len(col.predictions["s1"]) == 6
    clock.t = at(6.7)
    core.run_once()
    assert len(col.predictions["s1"]) == 7
    seqs = [p.seq for p in col.predictions["s1"]]
    assert seqs == list(range(7))
    # the clock jumps 3 steps: one late tick, counted as an overrun, publishes once
    clock.t = at(10.7)
    core.run_once()
    assert len(col.predictions["s1"]) == 8
    assert core.service_status().counters["tick_overruns"] >= 1


def test_a_message_sent_before_its_config_wakes_the_session(world, tmp_path):
    """A command that arrives before its session's config waits among the unknown ones and
    is handed over (accepted, not refused as unknown) once the config is applied; from it
    on the session ticks every step with no further traffic."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 10, [0.0]))
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    c = core.service_status().counters
    assert c.get("commands_accepted") == 1 and c.get("unknown_session", 0) == 0
    for k in range(5):
        clock.t = at(k + 0.6)
        core.run_once()
    assert [p.step for p in col.predictions["s1"]] == [10, 11, 12, 13, 14]


def test_data_driven_session_publishes_once_per_step(world, tmp_path):
    """Data every step after tick_phase: one prediction per step (on data), not the tick's
    and then the data's; when the data stop, the late tick still publishes that step."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 10, [0.0]))  # traffic: not idle
    core.run_once()
    clock.t = at(0.6)
    core.run_once()  # tick of step 0
    n0 = len(col.predictions["s1"])
    for k in range(1, 8):
        clock.t = at(k + 0.55)  # the regular tick phase (0.5) has passed, no data yet
        core.run_once()
        clock.t = at(k + 0.7)
        cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", k, [5.0]))
        core.run_once()
    got = col.predictions["s1"][n0:]
    # step 1 (no data in step 0): its tick, then the data; from step 2 on the tick waits
    # and the data give the step's only prediction
    assert [p.step - 10 for p in got] == [1, 1, 2, 3, 4, 5, 6, 7]
    assert all(p.newest_step == p.step - 10 for p in got[1:])
    clock.t = at(8.7)  # no data in step 8: nothing yet, the late tick publishes at 0.95
    core.run_once()
    assert len(col.predictions["s1"]) == n0 + 8
    clock.t = at(8.96)
    core.run_once()
    assert len(col.predictions["s1"]) == n0 + 9
    assert col.predictions["s1"][-1].step == 18
    assert core.service_status().counters.get("steps_missed", 0) == 0


def test_publish_every_and_epoch_in_the_future(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    epoch = at(10)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1", epoch_ns=epoch, publish_every=3)))
    core.run_once()
    clock.t = at(5)  # before the epoch: no prediction, measurements refused as future
    cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 0, [5.0]))
    core.run_once()
    assert col.predictions["s1"] == []
    assert col.errors["s1"][-1].reason.startswith("Measurement.step")
    for k in range(8):
        clock.t = epoch + at(k + 0.6)
        core.run_once()
    assert [p.step - 10 for p in col.predictions["s1"]] == [0, 3, 6]


# ---------------------------------------------------------------- exactness ---------------

def test_predictions_equal_offline_observer_predictor(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    feed = PaperFeed(core, cli, clock, col, "s1", seed=3, loss=0.1)
    feed.configure()
    feed.run()
    assert feed.compared >= feed.steps  # at least one prediction per step, all compared
    st = decode(cli.get(keys.status_key("s1"))[0].payload, SessionStatus)
    off = feed.offline.counters
    for name in ("accepted", "late", "duplicate", "commands_accepted"):
        assert st.counters.get(name, 0) == off[name], name
    assert off["late"] > 0 and off["duplicate"] > 0  # the refusals were exercised
    # every refusal produced a counter, and an ErrorReport (within the rate limit)
    reasons = [e.reason for e in col.errors["s1"]]
    assert len(reasons) == off["late"] + off["duplicate"]
    assert all(r.startswith("Measurement") for r in reasons)


def test_commands_by_issue_time_and_refusals(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    clock.t = at(20.2)
    from pd_service.wire import Command
    msg = Command(session="s1", seq=1, issued_ns=at(20.1), u=np.array([0.5]))
    cli.put(keys.command_key("s1"), encode(msg))
    cli.put(keys.command_key("s1"), encode(msg))  # duplicate
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 2, 0.1))  # final already (late)
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 10**9, 0.1))  # far future
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 25, [0.1, 0.2]))  # wrong dims
    core.run_once()
    c = core.session_status("s1").counters
    assert c["commands_accepted"] == 1
    assert (c["commands_duplicate"], c["commands_late"], c["commands_future"],
            c["commands_wrong_dims"]) == (1, 1, 1, 1)
    assert core._routes["s1"].sess.est._inputs.has_command(30)  # issued step 20 + lead 10


# ---------------------------------------------------------------- isolation ---------------

def test_malformed_storm_leaves_other_session_byte_identical(tmp_path):
    def run(with_storm: bool):
        bus = InMemoryBus()
        clock = Clock(0)
        col = Collector().attach(bus.transport())
        cli = bus.transport()
        core = make_core(bus, clock, tmp_path / str(with_storm), error_burst=1000,
                         error_rate_total=10_000.0)
        good = PaperFeed(core, cli, clock, col, "good", seed=5, steps=120, check=False)
        cli.put(keys.config_key("bad"), encode(paper_spec("bad")))
        good.configure()
        rng = np.random.default_rng(9)
        sent = 0
        for k in range(good.steps):
            if with_storm and 30 <= k < 40:
                msgs = storm("bad", rng)
                for key, data in msgs:
                    cli.put(key, data)
                    cli.put(keys.sensor_key("ghost", "ranger"), data)  # unknown session
                sent += len(msgs)
            good.step(k)
        return col, core, sent

    col0, _, _ = run(False)
    col1, core1, sent = run(True)
    assert col1.raw["good/prediction"] == col0.raw["good/prediction"]  # byte-identical
    assert len(col1.raw["good/prediction"]) >= 120
    assert col1.errors["good"] == col0.errors["good"]
    bad = core1.session_status("bad").counters
    assert bad["refused"] == sent  # every storm message refused and counted
    assert bad.get("accepted", 0) == 0
    for reason in ("malformed", "non_finite", "wrong_dims", "unknown_sensor", "key_mismatch",
                   "future", "late", "commands_malformed", "commands_future",
                   "commands_late", "commands_wrong_dims", "commands_non_finite"):
        assert bad.get(reason, 0) > 0, reason
    assert len(col1.errors["bad"]) == sent  # burst raised: one report per refusal
    svc = core1.service_status().counters
    assert svc["unknown_session"] == sent
    assert len(col1.errors["ghost"]) > 0  # reported, rate-limited


def test_error_reports_are_rate_limited(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, error_rate=20.0, error_burst=20)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    clock.t = at(3)
    for _ in range(100):
        cli.put(keys.sensor_key("s1", "ranger"), b"junk")
    core.run_once()
    assert len(col.errors["s1"]) == 20
    c = core.session_status("s1").counters
    assert c["malformed"] == 100 and c["errors_suppressed"] == 80
    clock.t += 1_000_000_000  # one second later: 20 more allowed
    for _ in range(100):
        cli.put(keys.sensor_key("s1", "ranger"), b"junk")
    core.run_once()
    assert len(col.errors["s1"]) == 40


def test_flooding_session_cannot_starve_another(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, inbox_size=256, batch_budget=16)
    for s in ("flood", "calm"):
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    core.run_once()
    clock.t = at(20.1)
    for i in range(5000):
        cli.put(keys.sensor_key("flood", "ranger"), meas_bytes("flood", "ranger", 20, [1.0], i))
    cli.put(keys.sensor_key("calm", "ranger"), meas_bytes("calm", "ranger", 19, [1.0]))
    start = len(col.order)
    core.run_once()
    preds = [s for s, kind in col.order[start:] if kind == "prediction"]
    # the calm session's packet went in the first round, so its prediction is among the
    # first two published, not behind the flood's 256 queued messages
    assert "calm" in preds[:2]
    fl = core.session_status("flood").counters
    assert fl["flood"] == 5000 - 256
    assert fl["accepted"] == 1 and fl["duplicate"] == 255
    assert core.session_status("calm").counters["accepted"] == 1


def serve_many(world, tmp_path, prefix: str, n: int) -> tuple[ServiceCore, list[str]]:
    """A core serving ``n`` paper sessions ``<prefix>000`` ... (limits raised to take them
    all at once), configured and settled."""
    bus, clock, _col, cli = world
    core = make_core(bus, clock, tmp_path, max_sessions=1000, config_rate_total=1e6,
                     config_burst_total=10**6, cpu_budget=1000)
    names = [f"{prefix}{i:03d}" for i in range(n)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(core)
    return core, names


def test_a_backlog_is_served_in_rounds_each_published_before_the_next(world, tmp_path):
    """150 sessions ready at once: one run_once serves them all in arrival order,
    ROUND_SESSIONS at a time, and predicts each round's sessions before the next round
    handles its messages (a session's message and its prediction close together); each
    round's predictions are put before the next round is handled (the first round's
    displays do not wait for the rest of a long pass)."""
    bus, clock, col, cli = world
    core, names = serve_many(world, tmp_path, "r", 150)
    assert core.served_sessions() == names
    sessions = [core._routes[s].sess for s in names]
    start = len(col.order)
    accepted_at_predict: list[int] = []
    put_at_predict: list[int] = []  # predictions on the bus when each session predicts
    for sess in sessions:  # wrap each estimator's predict (the session looks it up per call)
        def predict(now, _real=sess.est.predict):
            accepted_at_predict.append(sum(x.counters.get("accepted", 0) for x in sessions))
            put_at_predict.append(sum(1 for _, kind in col.order[start:] if kind == "prediction"))
            return _real(now)
        sess.est.predict = predict
    clock.t = at(20.1)
    for s in names:
        cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 19, [1.0]))
    core.run_once()
    rs = dispatch.ROUND_SESSIONS
    assert 150 > 2 * rs  # several rounds
    accepted: list[int] = []
    put: list[int] = []
    for first in range(0, 150, rs):
        end = min(first + rs, 150)
        accepted += [end] * (end - first)  # the round's messages, all before its predictions
        put += [first] * (end - first)  # the earlier rounds' predictions, already put
    assert accepted_at_predict == accepted
    assert put_at_predict == put
    assert [s for s, kind in col.order[start:] if kind == "prediction"] == names


def test_the_queues_are_looked_at_between_the_rounds_of_a_pass(world, tmp_path):
    """Between the rounds of a long pass the worker drains its queues again: a message that
    arrived during the first round, for a session still ahead in the pass, is handled in
    that session's round with the message it already had (one prediction for both); a
    sample stamped in the step that began meanwhile is judged at its arrival, not refused
    as "future" against the pass's clock reading."""
    bus, clock, col, cli = world
    core, names = serve_many(world, tmp_path, "q", 150)
    calls: list[int] = []  # sessions that had accepted a packet at each look

    class HeldQueue:
        """A drain group whose second look finds two samples (the first look is the pass's
        own, before its first round)."""

        def drain(self, limit: int) -> int:
            calls.append(sum(core.session_status(s).counters["accepted"] > 0 for s in names))
            if len(calls) != 2:
                return 0
            clock.t = at(21.1)  # step 21 began while the first round ran
            cli.put(keys.sensor_key("q149", "ranger"), meas_bytes("q149", "ranger", 21, [2.0]))
            cli.put(keys.sensor_key("q000", "ranger"), meas_bytes("q000", "ranger", 21, [2.0]))
            return 2

        def arm(self) -> None:
            pass

    core.subs.group = HeldQueue()  # type: ignore[assignment]
    clock.t = at(20.1)
    for s in names:
        cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 19, [1.0]))
    start = len(col.order)
    core.run_once()
    rs = dispatch.ROUND_SESSIONS
    # the pass's look, then one after each round but the last; no look after the pass
    # (what it drained it handled: nothing waits, the next loop looks)
    assert calls == [0] + list(range(rs, 150, rs))
    assert not core.has_work()
    preds = [s for s, kind in col.order[start:] if kind == "prediction"]
    assert preds.count("q149") == 1  # its two samples, one prediction
    assert preds.count("q000") == 2  # served before the sample came: published again after
    for s in ("q149", "q000"):
        c = core.session_status(s).counters
        assert c["accepted"] == 2 and "future" not in c, c


def test_messages_for_many_sessions_set_the_wake_event_once(world, tmp_path, monkeypatch):
    """The worker's event is set by the first message that makes a session ready, not again
    by every other session's (Event.set takes a lock and notifies even when set: once per
    session and round, when the worker's own drains enqueue); all of them are served."""
    sets: list[object] = []
    real_set = threading.Event.set

    def counting_set(self):
        sets.append(self)
        real_set(self)

    monkeypatch.setattr(threading.Event, "set", counting_set)
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    names = [f"w{i}" for i in range(5)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(core)
    clock.t = at(20.1)
    core.wake.clear()
    before = sum(e is core.wake for e in sets)
    for s in names:
        for k in (18, 19):
            cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", k, [1.0]))
    assert sum(e is core.wake for e in sets) - before == 1
    assert core.wake.is_set()
    core.run_once()
    assert {s: core.session_status(s).counters["accepted"] for s in names} == dict.fromkeys(
        names, 2)


# ---------------------------------------------------------------- expiry, persistence -----

def test_idle_session_expires(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, expire_s=5.0)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    cli.put(keys.config_key("s2"), encode(paper_spec("s2")))
    core.run_once()
    seen_deletes = []
    cli.subscribe(keys.ALL_CONFIGS, lambda smp: seen_deletes.append(smp.key)
                  if smp.kind == "delete" else None)
    for t in range(1, 9):
        clock.t = t * 1_000_000_000
        cli.put(keys.sensor_key("s2", "ranger"), meas_bytes("s2", "ranger", 0, [1.0]))
        core.run_once()
    assert core.served_sessions() == ["s2"]  # s2 kept alive by its traffic (even refused)
    st = col.statuses["s1"][-1]
    assert st.state == "expired" and "idle" in st.detail
    assert not (tmp_path / "a" / "s1.msgpack").exists()
    assert seen_deletes == [keys.config_key("s1")]  # peers are told
    assert [s.state for s in col.statuses["s1"]].count("expired") == 1  # echo not re-answered


@pytest.mark.parametrize("setting, spec_expire, expires", [
    (5.0, None, {"s1"}),        # the setting's lifetime
    (5.0, 0.0, set()),          # the spec's 0: never, whatever the setting
    (0.0, None, set()),         # the setting's 0: never
    (0.0, 3.0, {"s1"}),         # the spec's own lifetime wins over "never"
    (1000.0, 3.0, {"s1"}),      # ... and over a longer setting
])
def test_a_sessions_lifetime_is_the_specs_else_the_settings(world, tmp_path, setting,
                                                           spec_expire, expires):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, expire_s=setting)
    spec = paper_spec("s1").model_copy(update={"expire_s": spec_expire})
    cli.put(keys.config_key("s1"), encode(spec))
    core.run_once()
    for t in range(1, 400, 7):  # 400 s without traffic
        clock.t = t * 1_000_000_000
        core.run_once()
    assert set(core.served_sessions()) == {"s1"} - expires
    gone = [st.state for st in col.statuses["s1"]].count("expired")
    assert gone == (1 if expires else 0)


def test_restart_restores_sessions_and_resumes_publishing(tmp_path):
    bus = InMemoryBus()
    clock = Clock(0)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    core = make_core(bus, clock, tmp_path)
    for s in ("s1", "s2"):
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    core.run_once()
    core.close()
    core.t.close()
    # a new process with the same state dir (no sender with a cache to wait for)
    clock.t = at(100.6)
    core2 = make_core(bus, clock, tmp_path, recover_samples=0)
    assert core2.served_sessions() == ["s1", "s2"]
    core2.run_once()
    assert col.predictions["s1"][-1].step == 110
    st = decode(cli.get(keys.status_key("s2"))[0].payload, SessionStatus)
    assert st.state == "restored" and "restored" in st.detail
    assert decode(cli.get(keys.service_status_key("a"))[0].payload,
                  ServiceStatus).sessions == ["s1", "s2"]


def test_unreadable_state_file_is_set_aside(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    d = tmp_path / "a"
    d.mkdir()
    (d / "s1.msgpack").write_bytes(b"not msgpack")
    SpecStore(d).save(paper_spec("s2"))
    core = make_core(bus, clock, tmp_path)
    assert core.served_sessions() == ["s2"]
    assert (d / "s1.msgpack.bad").exists()


# ---------------------------------------------------------------- scale-out ---------------

def test_two_instances_split_sessions_and_take_over(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    names = [f"s{i:02d}" for i in range(20)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(a)
    assert a.served_sessions() == names
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR)  # fetches the specs from inst-a
    assert sorted(b.known_specs()) == names
    assert sorted(p.name for p in (tmp_path / "inst-b").glob("*.msgpack")) == \
        [f"{s}.msgpack" for s in names]
    settle(a, b)  # a sees inst-b's token: hands its share over
    sa, sb = set(a.served_sessions()), set(b.served_sessions())
    assert sa.isdisjoint(sb) and sa | sb == set(names)
    assert 4 <= len(sb) <= 16  # a real split (rendezvous hash of 20 names)
    # both keep every spec; a new config reaches both, exactly one serves it
    cli.put(keys.config_key("late-one"), encode(paper_spec("late-one")))
    settle(a, b)
    assert ("late-one" in a.served_sessions()) != ("late-one" in b.served_sessions())
    assert len(col.statuses["late-one"]) == 1  # answered once, by the owner
    # sensor data is handled only by the owner
    clock.t = at(5.2)
    for s in names:
        cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 3, [1.0]))
    settle(a, b)
    ca, cb = a.service_status().counters, b.service_status().counters
    assert ca["accepted"] + cb["accepted"] == 20 and ca["accepted"] == len(sa)
    # inst-b goes away: inst-a takes its sessions over and says so
    moved = b.served_sessions()
    b.close()
    settle(a)
    assert set(a.served_sessions()) == set(names) | {"late-one"}
    for s in moved:
        assert "taken over" in col.statuses[s][-1].detail
        assert col.statuses[s][-1].instance == "inst-a"


def declared(core) -> set[str]:
    """Every key the core's transport holds declared (InMemoryTransport.declared)."""
    return {k for group in core.t.declared for k in group}


def busy_keys(session: str, sensors=("camera", "ranger")) -> set[str]:
    return {keys.command_key(session), keys.prediction_key(session), keys.error_key(session)} | {
        keys.sensor_key(session, s) for s in sensors}


def test_known_sessions_declare_their_busy_keys_and_withdraw_them(tmp_path):
    """Every instance declares the command, sensor, prediction and error keys of every
    session it serves (cached routes on Zenoh; it receives only its own partitions'
    samples); replaced, the old spec's keys are withdrawn; handed over, removed or
    expired, all."""
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR, expire_s=5.0)
    names = [f"s{i:02d}" for i in range(12)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(a)
    assert declared(a) == set().union(*(busy_keys(s) for s in names))
    # a new spec with one sensor renamed: the old sensor key is withdrawn, the new declared
    spec = paper_spec("s00")
    sensors = [spec.sensors[0].model_copy(update={"name": "lidar"}), *spec.sensors[1:]]
    cli.put(keys.config_key("s00"), encode(spec.model_copy(update={"sensors": sensors})))
    settle(a)
    assert {k for k in declared(a) if k.startswith(keys.session_prefix("s00") + "/")} == \
        busy_keys("s00", [s.name for s in sensors])
    assert len(a.t.declared) == len(names)  # one declaration per session, none left behind
    # removed
    cli.delete(keys.config_key("s01"))
    settle(a)
    assert not any(k.startswith(keys.session_prefix("s01") + "/") for k in declared(a))
    # a second instance: each serves a share and declares the keys of its share only
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR, expire_s=5.0)
    settle(a, b)
    served = {core: core.served_sessions() for core in (a, b)}
    assert served[a] and served[b] and set(served[a]).isdisjoint(served[b])
    want = set().union(*(busy_keys(s) for s in names if s not in ("s00", "s01")),
                       busy_keys("s00", [x.name for x in sensors]))
    for core in (a, b):
        assert declared(core) == {k for k in want if keys.session_of(k) in served[core]}
    assert len(a.t.declared) + len(b.t.declared) == len(names) - 1
    # expired (no traffic for 5 s): each owner removes its own and tells the other
    clock.t = 10 * 1_000_000_000
    for core in (a, b):
        core.run_once()
    settle(a, b)
    assert a.served_sessions() == b.served_sessions() == []
    assert a.t.declared == b.t.declared == []


def test_static_shards_split_without_coordination(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", shard="0/2")
    b = make_core(bus, clock, tmp_path, "inst-b", shard="1/2")
    names = [f"s{i:02d}" for i in range(20)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    while a.has_work() or b.has_work():  # one run_once returns after ~50 ms of configs
        a.run_once()
        b.run_once()
    sa, sb = set(a.served_sessions()), set(b.served_sessions())
    assert sa.isdisjoint(sb) and sa | sb == set(names) and sa and sb
    b.close()
    a.run_once()
    assert set(a.served_sessions()) == sa  # static: no takeover
    assert decode(cli.get(keys.service_status_key("inst-a"))[0].payload,
                  ServiceStatus).shard == "0/2"


def test_starting_instance_merges_disk_and_peer_specs(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    SpecStore(tmp_path / "inst-b").save(paper_spec("only-on-disk"))
    SpecStore(tmp_path / "inst-b").save(paper_spec("both", max_delay=20))  # older version
    cli.put(keys.config_key("both"), encode(paper_spec("both")))
    cli.put(keys.config_key("fresh"), encode(paper_spec("fresh")))
    a.run_once()
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR)
    assert sorted(b.known_specs()) == ["both", "fresh", "only-on-disk"]
    assert b.known_specs()["both"].max_delay == 12  # the peers' version wins
    assert SpecStore(tmp_path / "inst-b").load_all()[0]["both"].max_delay == 12
    # inst-a learns the disk-only spec through its member-joined sync
    a.run_once()
    assert "only-on-disk" in a.known_specs()


def test_instance_that_missed_peers_at_start_syncs_when_they_appear(tmp_path):
    """inst-b starts while inst-a's presence is not visible yet (a race on a real network):
    when inst-a's token shows up, inst-b fetches the specs it missed and takes its share."""
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    names = [f"s{i:02d}" for i in range(12)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    a.run_once()
    a._token.close()  # hide inst-a
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR)
    assert b.known_specs() == {}
    a.run_once()
    a._token = a.t.declare_token(keys.service_token_key("inst-a"))  # inst-a visible again
    b.run_once()
    a.run_once()
    assert sorted(b.known_specs()) == names
    sa, sb = set(a.served_sessions()), set(b.served_sessions())
    assert sa.isdisjoint(sb) and sa | sb == set(names) and sb


def test_a_join_decodes_only_the_specs_an_instance_lacks(tmp_path, monkeypatch):
    """Every peer answers a spec sync with all it holds: a starting instance decodes each
    session's spec once however many peers answer, and the instances already up, which sync
    again when it joins, decode none of the specs they hold (the models' validation would
    hold every worker of the fleet up at each join); a spec they lack they still get."""
    from pd_service.service import lifecycle

    decoded: list[str] = []
    real = lifecycle.decode

    def counting(data, cls):
        out = real(data, cls)
        decoded.append(out.session)
        return out

    monkeypatch.setattr(lifecycle, "decode", counting)
    trio = [*PAIR, "inst-c"]
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=trio)
    b = make_core(bus, clock, tmp_path, "inst-b", peers=trio)
    settle(a, b)
    names = [f"s{i:02d}" for i in range(12)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(a, b)
    # a spec only inst-b holds (put while inst-a did not listen): inst-a lacks it
    b.lifecycle.apply_sync({"only-b": paper_spec("only-b")}, clock())
    decoded.clear()
    c = make_core(bus, clock, tmp_path, "inst-c", peers=trio)
    assert sorted(decoded) == sorted([*names, "only-b"])  # two answers each, decoded once
    assert sorted(c.known_specs()) == sorted([*names, "only-b"])
    decoded.clear()
    settle(a, b, c)  # inst-a and inst-b see inst-c join and sync
    assert decoded == ["only-b"]
    assert "only-b" in a.known_specs()
    # the replies are the specs' encodings, the spec replaced in between included
    cli.put(keys.config_key("s00"), encode(paper_spec("s00", max_delay=20)))
    settle(a, b, c)
    replies = cli.get(keys.config_key("s00"))
    assert len(replies) == 3
    assert {(r.key, r.payload) for r in replies} == {
        (keys.config_key("s00"), encode(paper_spec("s00", max_delay=20)))}


def test_prediction_messages_decode_strictly(world, tmp_path):
    """What the daemon publishes passes the strict decoder (PSD check included)."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    feed = PaperFeed(core, cli, clock, col, "s1", steps=40)
    feed.configure()
    feed.run()
    for raw in col.raw["s1/prediction"]:
        decode(raw, Prediction)


def test_packed_prediction_is_byte_for_byte_what_the_codec_encodes():
    from pd_service.estimation import PredictedState
    from pd_service.service.health import inspect_packed
    from pd_service.wire.convert import PredictionEncoder, prediction_from

    spec = paper_spec("s1", epoch_ns=123)
    rng = np.random.default_rng(0)
    for newest in (None, 0, 17):
        L = rng.standard_normal((4, 4))
        pred = PredictedState(25, rng.standard_normal(4), L @ L.T, newest)
        counters = {"accepted": 3, "late": 1, "published": 9}
        bad, xb, pb = inspect_packed(pred.x, pred.P)
        assert bad is None
        got = PredictionEncoder(spec, "s1").encode_packed(pred, xb, pb, 7, 999, counters)
        assert got == encode(prediction_from(pred, spec, "s1", 7, 999, counters))
    bad = PredictedState(25, np.array([np.nan, 0, 0, 0]), np.eye(4), None)
    assert inspect_packed(bad.x, bad.P)[0] is not None  # the daemon does not encode it
    with pytest.raises(ValueError, match="not finite"):
        prediction_from(bad, spec, "s1", 0, 0, {})


def test_counters_snapshot_keeps_nonzero_counters_in_order_then_published():
    from pd_service.backends import build
    from pd_service.service.session import Session

    spec = paper_spec("s1")
    sess = Session(spec, build(spec), "active", "", 0, 10.0, 10)
    assert sess.counters_snapshot() == {"accepted": 0, "published": 0}
    sess.counters["late"] += 2
    sess.counters["accepted"] += 0  # a zero kept by the Counter (a resumed state's)
    sess.counters["future"] += 1
    sess.counters["published"] += 5  # shadowed by the session's own count, in its place
    sess.published = 7
    snap = sess.counters_snapshot()
    assert list(snap.items()) == [("late", 2), ("future", 1), ("published", 7),
                                  ("accepted", 0)]
    sess.counters["accepted"] += 3
    assert list(sess.counters_snapshot().items()) == [
        ("late", 2), ("accepted", 3), ("future", 1), ("published", 7)]
    assert type(snap) is dict


def test_error_reports_have_a_service_wide_budget(world, tmp_path):
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, error_rate_total=30.0)
    for s in ("s1", "s2", "s3"):
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    core.run_once()
    clock.t = at(3)
    for s in ("s1", "s2", "s3"):
        for _ in range(20):
            cli.put(keys.sensor_key(s, "ranger"), b"junk")
    core.run_once()
    assert sum(len(col.errors[s]) for s in ("s1", "s2", "s3")) == 30
    assert core.service_status().counters["errors_suppressed"] == 30


def test_refused_specs_of_new_names_share_the_service_wide_budget(world, tmp_path):
    """Every ErrorReport goes through one funnel (Outbox.refuse): the refusal of a spec for a
    name not served here is limited service-wide too, and one over it is counted."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path, error_rate_total=5.0)
    names = [f"n{i}" for i in range(10)]
    for s in names:
        cli.put(keys.config_key(s), b"junk")
    settle(core)
    c = core.service_status().counters
    assert c["config_refused"] == 10
    assert sum(len(col.errors[s]) for s in names) == 5
    assert c["errors_suppressed"] == 5


def test_refusals_are_counted_by_kind_and_echo_a_readable_seq(world, tmp_path):
    """A non-PSD R is malformed (not non_finite, though "semi-definite" contains "finite"),
    a NaN is non_finite; both ErrorReports echo the seq the message carried."""
    import msgpack

    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    clock.t = at(20.5)
    raw = msgpack.unpackb(meas_bytes("s1", "camera", 20, [1.0, 2.0], seq=41))
    raw["R"] = {"shape": [2, 2], "data": [1.0, 0.0, 0.0, -1.0]}  # not PSD
    cli.put(keys.sensor_key("s1", "camera"), msgpack.packb(raw))
    raw = msgpack.unpackb(meas_bytes("s1", "camera", 20, [1.0, 2.0], seq=42))
    raw["z"]["data"] = [1.0, float("nan")]
    cli.put(keys.sensor_key("s1", "camera"), msgpack.packb(raw))
    raw["seq"] = -3  # not a valid seq: nothing to echo
    cli.put(keys.sensor_key("s1", "camera"), msgpack.packb(raw))
    core.run_once()
    c = core.session_status("s1").counters
    assert (c["malformed"], c["non_finite"]) == (1, 2)
    reports = col.errors["s1"]
    assert [r.seq for r in reports] == [41, 42, None]
    assert "semi-definite" in reports[0].reason and "finite" in reports[1].reason


def test_window_refusals_name_the_stamp_field_the_message_used(world, tmp_path):
    """A future / late / duplicate sample stamped by t_ns is reported as Measurement.t_ns
    (by step: Measurement.step); a command stamped by issued_ns as Command.issued_ns."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    spec = paper_spec("s1")
    cli.put(keys.config_key("s1"), encode(spec))
    core.run_once()
    clock.t = at(20.5)
    key = keys.sensor_key("s1", "camera")

    def by_time(step: int, seq: int) -> bytes:
        return encode(Measurement(session="s1", sensor="camera", seq=seq,
                                  t_ns=spec.time_of(step), z=np.array([1.0, 2.0])))

    cli.put(key, by_time(25, 1))                       # future
    cli.put(key, by_time(2, 2))                        # late
    cli.put(key, by_time(19, 3))                       # accepted
    cli.put(key, by_time(19, 4))                       # duplicate (same sensor and step)
    cli.put(key, meas_bytes("s1", "camera", 19, [5.0, 6.0], seq=5))  # duplicate, by step
    far = spec.time_of(20 + 2 * spec.lead + spec.max_delay + 5)
    cli.put(keys.command_key("s1"), encode(Command(session="s1", seq=6, issued_ns=far,
                                               u=np.array([1.0]))))
    core.run_once()
    c = core.session_status("s1").counters
    assert (c["future"], c["late"], c["accepted"], c["duplicate"], c["commands_future"]) \
        == (1, 1, 1, 2, 1)
    heads = [(r.seq, r.reason.split(": ", 1)[0]) for r in col.errors["s1"]]
    assert heads == [(1, "Measurement.t_ns"), (2, "Measurement.t_ns"), (4, "Measurement.t_ns"),
                     (5, "Measurement.step"), (6, "Command.issued_ns")]


@pytest.mark.parametrize("publish_every, missed", [(1, 9), (2, 4)])
def test_steps_that_got_no_prediction_are_counted(world, tmp_path, publish_every, missed):
    """The worker stalls from step 2 to step 12: the due steps 3..11 (every step, or the
    even ones with publish_every 2) got no prediction; one late tick is one overrun."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1", publish_every=publish_every)))
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 10, [0.0]))  # traffic: not idle
    core.run_once()
    for k in range(3):
        clock.t = at(k + 0.6)
        core.run_once()
    st = core.session_status("s1")
    assert "steps_missed" not in st.counters
    clock.t = at(12.6)
    core.run_once()
    assert core.session_status("s1").counters["steps_missed"] == missed
    assert core.service_status().counters["steps_missed"] == missed
    assert core.session_status("s1").counters["tick_overruns"] == 1
    for k in (13, 14):  # back on time: nothing more is missed
        clock.t = at(k + 0.6)
        core.run_once()
    assert core.session_status("s1").counters["steps_missed"] == missed
    assert col.predictions["s1"][-1].counters["steps_missed"] == missed


def test_steps_an_idle_session_skips_are_not_missed(world, tmp_path):
    """A session without traffic skips steps on purpose (one prediction per idle_publish_s):
    after 22 s idle and a message that wakes it, no step counts as missed; a stall after
    the wake still does."""
    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    for k in range(0, 440, 5):  # 22 s of 50 ms steps, the worker awake every 5 steps
        clock.t = at(k + 0.6)
        core.run_once()
    assert len(col.predictions["s1"]) >= 3  # the start, then one per idle_publish_s
    clock.t = at(440.2)
    cli.put(keys.command_key("s1"), cmd_bytes("s1", 450, [0.0]))  # wakes it
    core.run_once()
    for k in (440, 441, 442):
        clock.t = at(k + 0.6)
        core.run_once()
    assert "steps_missed" not in core.session_status("s1").counters
    assert "steps_missed" not in core.service_status().counters
    clock.t = at(446.6)  # the worker stalls for steps 443..445
    core.run_once()
    assert core.session_status("s1").counters["steps_missed"] == 3


def _lock_free(lock) -> bool:
    """True if another thread could take ``lock`` now (the caller may hold it reentrantly)."""
    import threading

    free: list[bool] = []

    def probe() -> None:
        got = lock.acquire(blocking=False)
        if got:
            lock.release()
        free.append(got)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return free[0]


def test_status_queries_build_their_replies_without_the_lock(world, tmp_path, monkeypatch):
    """A query holds the core's lock only to copy: the message is built (percentiles,
    validation) and encoded with the lock free, so a slow reply never stalls the worker."""
    from pd_service.service import status as status_mod

    bus, clock, col, cli = world
    core = make_core(bus, clock, tmp_path)
    for s in ("s1", "s2"):
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    core.run_once()
    clock.t = at(20.5)
    cli.put(keys.sensor_key("s1", "camera"), meas_bytes("s1", "camera", 19, [1.0, 2.0]))
    core.run_once()
    seen: list[tuple[str, bool]] = []

    def checking(name, real):
        def wrapped(*a, **kw):
            seen.append((name, _lock_free(core.lock)))
            return real(*a, **kw)
        return wrapped

    names = ("SessionStatus", "ServiceStatus", "encode", "percentiles")
    for name in names:
        monkeypatch.setattr(status_mod, name, checking(name, getattr(status_mod, name)))
    replies = cli.get(keys.ALL_STATUS) + cli.get(keys.status_key("s1"))
    replies += cli.get(keys.service_status_key("a"))
    assert core.session_status("s1") is not None and core.service_status() is not None
    assert {n for n, _ in seen} == set(names)
    assert all(free for _, free in seen), seen
    by_session = {decode(r.payload, SessionStatus).session: decode(r.payload, SessionStatus)
                  for r in replies[:3]}
    assert (by_session["s1"].counters["accepted"], by_session["s2"].counters["accepted"]) == (1, 0)
    assert decode(replies[3].payload, ServiceStatus).sessions == ["s1", "s2"]


@pytest.mark.parametrize("n", [1, 2, 3, 10, 511, 4096])
def test_latency_percentiles_equal_numpys(n):
    from pd_service.service.latency import percentiles

    x = np.random.default_rng(n).exponential(100.0, n)
    want = tuple(np.percentile(x, [50.0, 99.0]))
    assert percentiles(x.tolist()) == pytest.approx(want, rel=1e-12, abs=0.0)
    assert percentiles(x) == pytest.approx(want, rel=1e-12, abs=0.0)  # numpy's own
    assert percentiles([]) == (0.0, 0.0) == percentiles(np.empty(0))


def test_a_latency_window_keeps_the_last_values_in_order():
    """The ring holds the newest ``size`` values, oldest first, as a deque(maxlen) would;
    its percentiles are those of that copy."""
    from collections import deque

    from pd_service.service.latency import LatencyWindow, percentiles

    w, ref = LatencyWindow(5), deque(maxlen=5)
    assert len(w) == 0 and w.values().size == 0 and w.percentiles() == (0.0, 0.0)
    for v in range(1, 13):
        w.add(float(v))
        ref.append(float(v))
        assert w.values().tolist() == list(ref) and len(w) == len(ref)
    assert w.percentiles() == percentiles(list(ref))
    assert not np.shares_memory(w.values(), w.values())  # copies: safe outside the lock
