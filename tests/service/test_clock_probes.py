"""The daemon in the robot's time, on the in-memory bus with injected clocks: a robot whose
clock runs 10 s ahead (and 10 s behind), stamps mapped before the window check, probes answered
by the SDK's Robot, commands entering at their echoed times; predictions equal an offline
estimator fed the true steps; bad echoes, silent robots and probe floods counted, another
session unaffected."""

from __future__ import annotations

import numpy as np
import pytest

from pd_client import Robot
from pd_service.estimation import ObserverPredictor
from pd_service.scenarios.paper import (
    paper_command,
    paper_model,
    paper_prior,
    paper_sensors,
    simulate_paper,
)
from pd_service.service import ServiceCore, Settings, SpecStore
from pd_service.service.clock_probes import ECHO_INBOX
from pd_service.transport import InMemoryBus, Query
from pd_service.wire import (
    ClockProbe,
    ClockProbeReply,
    Command,
    CommandEcho,
    Measurement,
    decode,
    encode,
    keys,
)

from .helpers import PERIOD_NS, Clock, Collector, paper_spec

SECOND = 1_000_000_000


def make_core(bus, clock, tmp_path, **kw) -> ServiceCore:
    settings = Settings(instance="a", probe_interval_s=0, **kw)  # probes driven by the test
    core = ServiceCore(bus.transport(), settings, store=SpecStore(tmp_path / "a"),
                       now_ns=clock, run_clock_ns=lambda: 0, spawn=lambda fn: fn())
    core.start()
    return core


def at(step: float) -> int:
    return int(round(step * PERIOD_NS))


def spec(session: str, robot_clock: str = "estimated", timing: str = "stamped"):
    return paper_spec(session).model_copy(update={"robot_clock": robot_clock,
                                                  "command_timing": timing})


def run_paper(tmp_path, offset_ns: int, robot_clock: str, timing: str, steps: int = 120,
              probe_every: int = 10):
    """The paper run with the robot's clock ``offset_ns`` off the daemon's: samples stamped
    on the robot's clock, commands issued by the operator at 10 % of each step and echoed by
    a robot that applies them on arrival. Returns (core, samples sent, offline predictor's
    predictions by step, the daemon's predictions by step)."""
    bus, clock = InMemoryBus(), Clock(at(0) - 1)
    col = Collector().attach(bus.transport())
    core = make_core(bus, clock, tmp_path)
    op = bus.transport()
    sp = spec("s1", robot_clock, timing)
    op.put(keys.config_key("s1"), encode(sp))
    core.run_once()
    robot = Robot(bus.transport(), "s1", direct=True, apply_on_arrival=True,
                  clock=lambda: clock.t + offset_ns)
    run = simulate_paper(steps, np.random.default_rng(4), loss=0.1)
    arrivals: dict[int, list] = {}
    for smp in run.samples:
        if smp.arrival is not None:
            arrivals.setdefault(smp.arrival, []).append(smp)
    x0, P0 = paper_prior()
    offline = ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0, lead=sp.lead,
                                max_delay=sp.max_delay)
    ours, theirs = {}, {}
    sent = 0
    for k in range(steps):
        clock.t = at(k + 0.1)
        if k % probe_every == 0:
            core.robot_io.probe_all(core.clocked_sessions())
        u = paper_command(k + sp.lead)
        op.put(keys.command_key("s1"),
               encode(Command(session="s1", seq=k, issued_ns=clock.t, u=np.array([u]))))
        # stamped: apply step issued + lead; echoed: the step it took effect (on arrival: k)
        offline.add_command(k + sp.lead if timing == "stamped" else k, [u], now=k)
        for smp in arrivals.get(k, []):
            robot.publish(smp.sensor, smp.z, t_ns=at(smp.step + 0.05) + offset_ns)
            sent += 1
            offline.add_measurement(smp.sensor, smp.step, smp.z, now=k)
        core.run_once()
        theirs[k] = offline.predict(now=k)
        if col.predictions["s1"]:
            ours[k] = col.predictions["s1"][-1]
    robot.close()
    return core, sent, theirs, ours


@pytest.mark.parametrize("offset_s", [10, -10])
def test_an_offset_robot_clock_is_estimated_and_its_samples_taken_at_their_steps(
        tmp_path, offset_s: int) -> None:
    core, sent, theirs, ours = run_paper(tmp_path, offset_s * SECOND, "estimated", "stamped")
    st = core.session_status("s1")
    assert st is not None and st.clock is not None and st.clock.known
    err = st.clock.offset_ns - offset_s * SECOND
    print(f"\nrobot clock {offset_s:+} s, in-memory bus: offset error {err} ns, uncertainty "
          f"{st.clock.uncertainty_ns} ns, drift {st.clock.drift_ppm:.2f} ppm")
    assert st.clock.uncertainty_ns is not None and abs(err) <= st.clock.uncertainty_ns + 1
    assert abs(err) <= 1_000_000
    c = st.counters
    assert c.get("future", 0) == 0 and c.get("late", 0) == 0
    assert c["accepted"] == sent > 50
    assert st.delays["camera"].count > 0 and st.recommended_max_delay is not None
    # exactness: the same estimate as the offline filter fed the true steps
    compared = 0
    for k, pred in ours.items():
        if pred.step == k + 10:  # this step's own prediction (lead 10)
            np.testing.assert_allclose(pred.x, theirs[k].x, rtol=0, atol=1e-9)
            compared += 1
    assert compared > 100
    core.close()


def test_today_an_offset_clock_makes_every_sample_future(tmp_path) -> None:
    core, _, _, _ = run_paper(tmp_path, 10 * SECOND, "shared", "stamped", steps=40)
    st = core.session_status("s1")
    assert st is not None and st.clock is None
    assert st.counters.get("accepted", 0) == 0 and st.counters["future"] > 0
    core.close()


def test_echoed_commands_move_to_the_time_they_took_effect(tmp_path) -> None:
    core, _, theirs, ours = run_paper(tmp_path, 10 * SECOND, "estimated", "echoed")
    st = core.session_status("s1")
    assert st is not None
    c = st.counters
    assert c["echoes"] == 120 and c.get("echoes_unknown", 0) == 0
    # each entered at its stamped step k + lead, then moved to k, where it took effect
    assert (c["commands_accepted"], c["commands_moved"]) == (120, 120)
    assert st.recommended_lead == 0  # on arrival, in the same step
    compared = 0
    for k, pred in ours.items():
        if pred.step == k + 10:
            np.testing.assert_allclose(pred.x, theirs[k].x, rtol=0, atol=1e-9)
            np.testing.assert_allclose(pred.P, theirs[k].P, rtol=0, atol=1e-9)
            compared += 1
    assert compared > 100
    core.close()


def test_bad_echoes_silent_robots_and_flooding_probe_answers_are_counted(tmp_path) -> None:
    bus, clock = InMemoryBus(), Clock(at(0) - 1)
    core = make_core(bus, clock, tmp_path)
    op = bus.transport()
    for name in ("s1", "s2", "s3"):
        op.put(keys.config_key(name), encode(spec(name, timing="echoed")))
    core.run_once()
    clock.t = at(5)
    # s1: a robot answering each probe three times, once with garbage
    robot_t = bus.transport()

    def flood(q: Query) -> None:
        p = decode(q.payload or b"", ClockProbe)
        rep = ClockProbeReply(session="s1", probe=p.probe, t1_ns=p.t1_ns,
                              t2_ns=clock.t + 7 * SECOND, t3_ns=clock.t + 7 * SECOND)
        q.reply(keys.robot_clock_key("s1"), b"\x00nonsense")
        q.reply(keys.robot_clock_key("s1"), encode(rep))
        q.reply(keys.robot_clock_key("s1"), encode(rep))

    robot_t.queryable(keys.robot_clock_key("s1"), flood)
    # s2: no robot answers at all; s3: a well-behaved robot 10 s ahead
    r3 = Robot(bus.transport(), "s3", direct=True, clock=lambda: clock.t + 10 * SECOND)
    assert core.robot_io.probe_all(core.clocked_sessions()) == 2
    op.put(keys.command_key("s1"),
           encode(Command(session="s1", seq=1, issued_ns=clock.t, u=np.array([0.5]))))
    core.run_once()
    echo = op.publisher(keys.echo_key("s1"))
    echo.put(encode(CommandEcho(session="s1", seq=99, applied_ns=clock.t)))  # unknown seq
    echo.put(b"\xc1garbage")
    echo.put(encode(CommandEcho(session="s2", seq=1, applied_ns=clock.t)))  # wrong session
    # far from plausible: an hour before the command was issued
    echo.put(encode(CommandEcho(session="s1", seq=1, applied_ns=clock.t + 7 * SECOND
                                - 3600 * SECOND)))
    core.run_once()
    s1, s2, s3 = (core.session_status(n) for n in ("s1", "s2", "s3"))
    assert s1 is not None and s2 is not None and s3 is not None
    c = s1.counters
    assert (c["echoes_unknown"], c["echoes_invalid"], c["echoes_implausible"]) == (1, 2, 1)
    assert c.get("echoes", 0) == 0
    sc = core.service_status().counters
    assert sc["probes_sent"] == 3 and sc["probes_unanswered"] == 1
    assert sc["probe_replies_invalid"] == 1 and sc["probe_replies_extra"] == 1
    assert s1.clock is not None and abs(s1.clock.offset_ns - 7 * SECOND) <= 1
    assert s2.clock is not None and not s2.clock.known and s2.clock.warning
    assert s3.clock is not None and abs(s3.clock.offset_ns - 10 * SECOND) <= 1
    # the good echo now: it enters, and the silent robot's session is as it was
    echo.put(encode(CommandEcho(session="s1", seq=1, applied_ns=clock.t + 7 * SECOND)))
    core.run_once()
    s1 = core.session_status("s1")
    assert s1 is not None and s1.counters["echoes"] == 1
    # the robot stops answering: the last offset holds, its bound grows, a warning says so
    before = s3.clock.uncertainty_ns
    r3.close()
    clock.t = at(5) + 60 * SECOND
    assert core.robot_io.probe_all(["s3"]) == 0
    core.run_once()
    assert core.service_status().counters["probes_unanswered"] == 2
    s3 = core.session_status("s3")
    assert s3 is not None and s3.clock is not None
    assert s3.clock.uncertainty_ns is not None and before is not None
    assert s3.clock.uncertainty_ns > before and "stale" in s3.clock.warning
    assert abs(s3.clock.offset_ns - 10 * SECOND) <= 1
    core.close()


def test_probe_answers_beyond_the_queue_are_counted_and_the_rest_reach_their_session(
        tmp_path) -> None:
    bus, clock = InMemoryBus(), Clock(at(0) - 1)
    core = make_core(bus, clock, tmp_path)
    bus.transport().put(keys.config_key("s1"), encode(spec("s1")))
    core.run_once()
    robot = Robot(bus.transport(), "s1", direct=True, clock=lambda: clock.t + 10 * SECOND)
    for i in range(ECHO_INBOX + 3):  # probes answered faster than the worker takes them
        clock.t = at(5) + i * 1000
        assert core.robot_io.probe(core.clocked_sessions()[0])
    assert core.service_status().counters["probe_answers_flood"] == 3
    core.run_once()
    st = core.session_status("s1")
    assert st is not None and st.counters["probe_replies"] == ECHO_INBOX
    assert st.clock is not None and abs(st.clock.offset_ns - 10 * SECOND) <= 1
    robot.close()
    core.close()


def test_the_learned_window_goes_through_the_normal_config_path(tmp_path) -> None:
    from pd_service.wire import SessionSpec
    from pd_service.wire import decode as wire_decode

    bus, clock = InMemoryBus(), Clock(at(0) - 1)
    core = make_core(bus, clock, tmp_path, learned_window=True, learn_interval_s=1.0)
    op = bus.transport()
    configs: list[SessionSpec] = []
    op.subscribe(keys.config_key("s1"), lambda s: configs.append(wire_decode(s.payload,
                                                                             SessionSpec)))
    op.put(keys.config_key("s1"), encode(paper_spec("s1", max_delay=20)))
    core.run_once()
    rng = np.random.default_rng(2)
    for i in range(1100):  # ranger samples 13 to 14 steps (650-700 ms) late
        k = 20 + i // 2
        clock.t = at(k + 0.2)
        d = 13 + int(rng.random() < 0.3)
        op.put(keys.sensor_key("s1", "ranger"),
               encode(Measurement(session="s1", sensor="ranger", seq=i, t_ns=at(k - d + 0.1),
                                  z=np.array([1.0]))))
        core.run_once()
    st = core.session_status("s1")
    assert st is not None and st.recommended_max_delay == 15  # W* 14, + floor(10 %) = 1
    assert len(configs) == 2 and configs[-1].max_delay == 15
    assert core.known_specs()["s1"].max_delay == 15  # installed, as any spec put
    assert core.service_status().counters["learned_windows_put"] == 1
    core.close()


def _paper_run_beside(tmp_path, name: str, flood: bool) -> tuple[list[bytes], dict, dict]:
    """Session s2 (shared clock, stamped) fed the paper run while, with ``flood``, session s1's
    robot floods the echo queue and echoes arrive for a session served nowhere. Returns s2's
    prediction bytes, s1's counters and the service's."""
    bus, clock = InMemoryBus(), Clock(at(0) - 1)
    col = Collector().attach(bus.transport())
    core = make_core(bus, clock, tmp_path / name)
    op = bus.transport()
    op.put(keys.config_key("s1"), encode(spec("s1", timing="echoed")))
    op.put(keys.config_key("s2"), encode(paper_spec("s2")))
    core.run_once()
    run = simulate_paper(60, np.random.default_rng(5))
    echo = op.publisher(keys.echo_key("s1"))
    stray = op.publisher(keys.echo_key("nobody"))
    for k in range(60):
        clock.t = at(k + 0.1)
        for s in ("s1", "s2"):
            op.put(keys.command_key(s), encode(Command(session=s, seq=k, issued_ns=clock.t,
                                                       u=np.array([paper_command(k + 10)]))))
        for smp in run.samples:
            if smp.arrival == k:
                op.put(keys.sensor_key("s2", smp.sensor),
                       encode(Measurement(session="s2", sensor=smp.sensor, seq=k, step=smp.step,
                                          z=smp.z)))
        if flood and k % 20 == 5:  # more echoes than the queue holds, before the worker runs
            for i in range(ECHO_INBOX + 100):
                echo.put(encode(CommandEcho(session="s1", seq=10_000 + i, applied_ns=clock.t)))
            stray.put(encode(CommandEcho(session="nobody", seq=1, applied_ns=clock.t)))
        core.run_once()
    s1 = core.session_status("s1")
    assert s1 is not None
    out = list(col.raw["s2/prediction"]), dict(s1.counters), dict(core.service_status().counters)
    core.close()
    return out


def test_an_echo_flood_is_bounded_and_counted_and_another_session_unaffected(tmp_path) -> None:
    quiet, _, _ = _paper_run_beside(tmp_path, "quiet", flood=False)
    loud, s1, service = _paper_run_beside(tmp_path, "loud", flood=True)
    assert len(quiet) > 50 and loud == quiet  # s2's predictions byte for byte
    # per flood the oldest 100 beyond the queue, and one more pushed out by the stray echo
    assert service["echoes_flood"] == 3 * 101
    assert s1["echoes_unknown"] == 3 * (ECHO_INBOX - 1)  # no command of theirs was kept
    assert service["echoes_unrouted"] == 3
