"""RobotTime alone: stamps mapped and never after their receipt, delays learned per sensor,
the kept commands bounded, the clock status' warnings."""

from __future__ import annotations

import numpy as np

from pd_service.service.robot_time import COMMANDS_KEPT, RobotTime
from pd_service.wire import CommandEcho, encode

from .helpers import PERIOD_NS, paper_spec

S = 1_000_000_000


def robot(clock: str = "estimated", timing: str = "stamped") -> RobotTime:
    return RobotTime(paper_spec("s1").model_copy(update={"robot_clock": clock,
                                                         "command_timing": timing}))


def test_a_shared_clock_maps_nothing_and_reports_no_clock() -> None:
    r = robot("shared")
    r.recv_ns = 5 * S
    assert r.to_daemon(7 * S) == 7 * S  # even in the future: the window refuses it
    assert r.clock_status(5 * S) is None


def test_stamps_are_mapped_and_never_after_their_receipt() -> None:
    r = robot()
    r.probe(100 * S, 110 * S + 1000, 110 * S + 2000, 100 * S + 3000)  # offset ~ +10 s
    r.recv_ns = 101 * S
    assert abs(r.to_daemon(111 * S - 50_000_000) - (101 * S - 50_000_000)) < 5_000
    r.recv_ns = 102 * S
    assert r.to_daemon(112 * S + 3 * S) == 102 * S  # 3 s "in the future": held at receipt
    assert r.counters["stamps_clamped"] == 1


def test_delays_are_learned_per_sensor_and_the_window_recommended() -> None:
    r = robot()
    rng = np.random.default_rng(1)
    for i in range(2000):
        t = 100 * S + i * PERIOD_NS
        d = int(rng.uniform(0.55, 0.65) * S)
        r.sample("camera" if i % 2 else "ranger", t, t + d, late=False)
    ds = r.delay_status()
    assert set(ds) == {"camera", "ranger"} and 550 <= ds["camera"].p50_ms <= 650
    w = r.recommended_max_delay()
    assert w is not None and 13 <= w <= int(1.2 * 13) + 1  # 650 ms = 13 steps of 50 ms


def test_kept_commands_are_bounded_and_unknown_echoes_counted() -> None:
    r = robot(timing="echoed")
    for seq in range(COMMANDS_KEPT + 5):
        r.keep_command(seq, 100 * S, np.zeros(1), 30, (100 * S, seq))
    assert len(r.kept) == COMMANDS_KEPT and r.counters["commands_kept_dropped"] == 5
    assert r.echo(encode(CommandEcho(session="s1", seq=0, applied_ns=110 * S)), 101 * S) is None
    assert r.counters["echoes_unknown"] == 1


def test_probe_answers_the_estimator_refuses_are_counted_and_change_nothing() -> None:
    r = robot()
    r.probe(100 * S, 110 * S + 1000, 110 * S + 2000, 100 * S + 3000)  # offset ~ +10 s
    before = r.clock.estimate(101 * S)
    r.probe(101 * S, 111 * S, 111 * S + 1000, 101 * S - 5)  # answered before it was asked
    r.probe(103 * S, 10**18, 10**18, 103 * S + 3000)  # ~30 years
    after = r.clock.estimate(101 * S)
    assert (after.offset_s, after.half_width_s) == (before.offset_s, before.half_width_s)
    # an hour ahead: its lower bound is held aside (a step only if confirmed), its upper one
    # is a loose but true bound (with one earlier probe it still sets the drift: clipped)
    r.probe(102 * S, 112 * S + 3600 * S, 112 * S + 3600 * S, 102 * S + 3000)
    e = r.clock.estimate(102 * S)
    assert abs(e.offset_s - 10.0) <= r.clock.max_drift * 2 + 1e-5 and e.steps == 0
    c = r.counters
    assert c["probe_replies"] == 4
    assert (c["probe_probes_invalid"], c["probe_inconsistent"], c["probe_implausible"]) \
        == (1, 1, 1)


def test_an_echo_applied_after_it_arrived_or_before_its_command_is_implausible() -> None:
    r = robot(timing="echoed")
    r.probe(100 * S, 110 * S + 1000, 110 * S + 2000, 100 * S + 3000)  # offset ~ +10 s, +-2 µs
    for seq in (1, 2, 3):
        r.keep_command(seq, 101 * S, np.zeros(1), 30, (101 * S, seq))
    # robot time 112 s = daemon 102 s: after the echo arrived (101.5 s)
    assert r.echo(encode(CommandEcho(session="s1", seq=1, applied_ns=112 * S)),
                  101 * S + S // 2) is None
    # robot 110.5 s = daemon 100.5 s: before the command was issued (101 s)
    assert r.echo(encode(CommandEcho(session="s1", seq=2, applied_ns=110 * S + S // 2)),
                  101 * S + S // 2) is None
    assert r.counters["echoes_implausible"] == 2 and r.counters.get("echoes", 0) == 0
    assert set(r.kept) == {1, 2, 3}  # kept: a good echo may still come
    got = r.echo(encode(CommandEcho(session="s1", seq=3, applied_ns=111 * S + S // 4)),
                 101 * S + S // 2)
    assert got is not None and abs(got[0] - (101 * S + S // 4)) < 5_000
    assert r.counters["echoes"] == 1


def test_a_spec_without_echoes_keeps_commands_only_from_its_robots_first_echo() -> None:
    r = robot("shared", "stamped")
    assert not r.listening  # a robot that never echoes costs nothing per command
    r.echo(encode(CommandEcho(session="s1", seq=3, applied_ns=110 * S)), 111 * S)
    assert r.listening and r.counters["echoes_unknown"] == 1
    r.keep_command(4, 112 * S, np.zeros(1), 50, (112 * S, 4))
    r.echo(encode(CommandEcho(session="s1", seq=4, applied_ns=112 * S + 5)), 113 * S)
    assert r.counters["echoes"] == 1 and r.applied.seen == 1
    r2 = robot("shared", "stamped")
    r2.echo(encode(CommandEcho(session="s2", seq=3, applied_ns=110 * S)), 111 * S)
    assert not r2.listening  # another session's echo does not start it
    assert robot("estimated").listening and robot("shared", "echoed").listening


def test_the_status_view_is_a_copy_read_after_the_lock() -> None:
    r = robot("shared")
    for i in range(50):
        r.sample("ranger", 100 * S + i * PERIOD_NS, 100 * S + i * PERIOD_NS + 300_000_000,
                 late=i % 10 == 0)
    v = r.view(200 * S)
    assert v.clock is None and v.late_share == 0.1
    before = (v.delay_status(), v.recommended_max_delay())
    for _ in range(50):  # later samples, far slower: the view does not see them
        r.sample("ranger", 200 * S, 209 * S, late=True)
    assert (v.delay_status(), v.recommended_max_delay()) == before
    assert before[1] == 6 and before[0]["ranger"].p50_ms == 300.0  # 300 ms: 6 steps of 50 ms
    assert r.delay_status() != before[0] and r.recommended_max_delay() != before[1]


def test_the_clock_status_warns_when_unknown_one_sided_or_jumping() -> None:
    r = robot()
    st = r.clock_status(S)
    assert st is not None and not st.known and "unknown" in st.warning
    r.recv_ns = 2 * S
    r.to_daemon(12 * S - 100)
    st = r.clock_status(2 * S)
    assert st is not None and st.uncertainty_ns is None and "one side" in st.warning
    r.probe(3 * S, 13 * S, 13 * S, 3 * S + 1000)
    assert r.clock_status(3 * S) is not None
    for k in range(4):  # the robot's clock moves by 5 s: confirmed, re-anchored
        r.probe((4 + k) * S, (19 + k) * S, (19 + k) * S, (4 + k) * S + 1000)
    st = r.clock_status(8 * S)
    assert st is not None and st.steps == 1 and "jumped" in st.warning
    assert abs(st.offset_ns - 15 * S) < 2_000


def test_the_clock_status_widens_and_warns_while_a_step_is_suspected() -> None:
    """A probe 200 ms off the estimate is held aside until confirmed (4 probes): the status
    meanwhile warns of a suspected step and reports an uncertainty that covers it (the
    estimate itself has not moved: its own half-width is a few µs)."""
    r = robot()
    for k in range(5):  # offset +10 s, 1 µs round trips
        r.probe((3 + k) * S, (13 + k) * S, (13 + k) * S, (3 + k) * S + 1000)
    st = r.clock_status(8 * S)
    assert st is not None and st.warning == "" and st.uncertainty_ns is not None
    assert st.uncertainty_ns < 1_000_000
    r.probe(9 * S, 19 * S + 200_000_000, 19 * S + 200_000_000, 9 * S + 1000)  # +200 ms
    st = r.clock_status(9 * S + 2000)
    assert st is not None and "step suspected" in st.warning
    assert st.uncertainty_ns is not None and st.uncertainty_ns >= 199_000_000
    assert abs(st.offset_ns - 10 * S) < 1_000_000  # not moved: unconfirmed
    for k in range(3):  # confirmed: re-anchored, no longer suspected
        r.probe((10 + k) * S, (20 + k) * S + 200_000_000, (20 + k) * S + 200_000_000,
                (10 + k) * S + 1000)
    st = r.clock_status(13 * S)
    assert st is not None and "suspected" not in st.warning
    assert st.uncertainty_ns is not None and st.uncertainty_ns < 1_000_000
    assert abs(st.offset_ns - round(10.2 * S)) < 1_000_000


def test_echoed_instants_and_mapped_stamps_give_the_continuous_discrete_batch_prediction() -> None:
    """Exactness (issue 43): a robot 3 s ahead applies each command on arrival (uplink 500 ms
    +- 20 ms) and echoes it; its samples carry its own stamps. Given the instants the daemon
    mapped (each accepted sample's t_ns, each echo's applied_ns), its predictions equal the
    continuous-discrete Kalman filter over those instants, computed with no code of the
    package (tests/estimation/reference.py), to 1e-9."""
    from pd_service.backends import build
    from pd_service.service.robot_time import feed_applied_command
    from pd_service.service.session import Session
    from pd_service.wire import Command, Measurement, SessionSpec
    from tests.estimation.reference import continuous_batch_predict, eigen_discretiser
    from tests.wire.factories import paper_continuous_spec

    base = paper_continuous_spec("s1", epoch_ns=0)
    F = np.array(base.model.F)  # type: ignore[union-attr]
    F[1, 1] = F[3, 3] = -0.5  # damped: F diagonalisable, as the reference needs
    spec = SessionSpec.model_validate({**base.model_dump(), "model": {**base.model.model_dump(),
                                       "F": F}, "robot_clock": "estimated",
                                       "command_timing": "echoed"})
    sess = Session(spec, build(spec), "active", "", 0, 10.0, 10)
    P, theta, T = spec.period_ns, 3 * S, spec.period_ns / 1e9
    rng = np.random.default_rng(43)
    events: list[tuple[int, int, object]] = []  # (receipt, order, what)
    for k in range(1, 120):
        if k % 2 == 0:  # a command every other step, issued at a random instant inside it
            issued = k * P + int(rng.integers(0, P))
            up = 500_000_000 + int(rng.integers(-20_000_000, 20_000_000))
            events.append((issued, 0, ("cmd", k, issued, issued + up, rng.standard_normal(1))))
        for sp in spec.sensors:
            if k % sp.interval == 0:
                t = k * P + int(rng.integers(0, P))  # sampled on the daemon's timeline
                recv = t + int(rng.integers(100_000_000, 550_000_000))
                events.append((recv, 1, ("meas", sp.name, t, rng.standard_normal(sp.m))))
    for _, _, what in list(events):
        if what[0] == "cmd":  # the echo: applied on the robot's clock, 60 ms down
            events.append((what[3] + 60_000_000, 2, ("echo", what[1], what[3])))
    events.sort(key=lambda e: (e[0], e[1]))
    stored: dict[int, tuple[int, float, np.ndarray]] = {}  # seq -> where the command is
    accepted: list[tuple[int, float, np.ndarray, None]] = []
    names = [sp.name for sp in spec.sensors]
    ref = eigen_discretiser(F, np.array(spec.model.G), np.array(spec.model.Qc))  # type: ignore[union-attr]
    sensors = [(np.array(sp.H), np.array(sp.R)) for sp in spec.sensors]
    compared = 0
    for i, (recv, _, what) in enumerate(events):
        now_step = recv // P
        if what[0] == "cmd":
            _, seq, issued, _, u = what
            msg = Command(session="s1", seq=seq, issued_ns=issued, u=u)
            assert sess.on_command("pd/p0/s1/cmd", encode(msg), now_step, recv) is None
            j, off = spec.command_at(issued)
            stored[seq] = (j, off, u)
        elif what[0] == "meas":
            _, name, t, z = what
            msg = Measurement(session="s1", sensor=name, seq=i, t_ns=t + theta, z=z)
            if sess.on_measurement(f"pd/p0/s1/sensor/{name}", encode(msg), now_step, recv) is None:
                tm = sess.intake.last_t_ns  # the mapped stamp
                assert tm is not None and tm <= recv  # (one-sided until the first echo)
                accepted.append((names.index(name), tm / 1e9, z, None))
        else:
            _, seq, applied = what
            got = sess.robot.echo(encode(CommandEcho(session="s1", seq=seq, applied_ns=applied
                                                     + theta)), recv)
            assert got is not None
            moved = feed_applied_command(sess.intake, sess.robot.counters, got, now_step)
            if moved:
                a = got[0]  # the mapped apply instant
                stored[seq] = (a // P, (a - (a // P) * P) / 1e9, stored[seq][2])
        if i % 25 == 24:
            pred = sess.est.predict(now_step)
            cmds = [(j, off, u) for j, off, u in stored.values()]
            want_x, want_P = continuous_batch_predict(
                ref, sensors, np.array(spec.x0), np.array(spec.P0), cmds, accepted,
                pred.step * T, 1, T)
            scale = max(1.0, float(np.max(np.abs(want_x))))
            assert np.max(np.abs(pred.x - want_x)) <= 1e-9 * scale, (i, pred.x, want_x)
            assert np.max(np.abs(pred.P - want_P)) <= 1e-9 * max(1.0, float(np.max(want_P)))
            compared += 1
    c = sess.robot.counters
    assert c["commands_moved"] > 40 and c["commands_echo_refused"] == 0 and compared > 10
    assert len(accepted) > 100


def test_a_sample_in_flight_across_a_clock_step_is_late_only_beyond_the_estimates_move() -> None:
    """Issue 43: the robot's clock (+10 s) steps +200 ms at 20 s, inside the band a 250 /
    300 ms link leaves. The first fast stamp after it lifts the band's lower side, so the
    estimate moves by half the step at once; a sample taken just before the step and still
    in flight is then mapped 100 ms early. Inside the window (600 ms) by its true delay
    (590 ms), it goes in at the instant the estimate before the move gives it (the latest
    it may have been taken at: here its true instant), counted, not refused as late; one
    whose true delay (800 ms) is outside the window is refused and counted."""
    from pd_service.backends import build
    from pd_service.service.session import Session
    from pd_service.wire import Measurement

    spec = paper_spec("s1").model_copy(update={"robot_clock": "estimated"})
    sess = Session(spec, build(spec), "active", "", 0, 10.0, 10)
    P, ms = spec.period_ns, 1_000_000
    ranger = [sp.name for sp in spec.sensors].index("ranger")

    def robot_clock(t: int) -> int:
        return t + 10 * S + (200 * ms if t >= 20 * S else 0)

    events: list[tuple[int, tuple[object, ...]]] = []
    for j in range(21):  # probes once a second: up 250 ms, down 300 ms
        t1 = j * S
        t2 = robot_clock(t1 + 250 * ms)
        events.append((t1 + 551 * ms, ("probe", t1, t2, t2 + ms)))
    for i in range(1, 205):  # the camera every 100 ms, 300 ms down
        t = i * 100 * ms
        events.append((t + 300 * ms, ("meas", "camera", t, i)))
    for t, d in ((19_940 * ms, 590 * ms), (19_800 * ms, 800 * ms)):  # in flight at the step
        events.append((t + d, ("meas", "ranger", t, t // P)))
    events.sort(key=lambda e: e[0])
    outcomes: dict[int, str | None] = {}
    slacks: list[int] = []
    for recv, what in events:
        if what[0] == "probe":
            _, t1, t2, t3 = what
            sess.robot.probe(t1, t2, t3, recv)  # type: ignore[arg-type]
            continue
        _, name, t, seq = what
        z = np.zeros(2 if name == "camera" else 1)
        msg = Measurement(session="s1", sensor=name, seq=seq, t_ns=robot_clock(t), z=z)  # type: ignore[arg-type]
        got = sess.on_measurement(f"pd/p0/s1/sensor/{name}", encode(msg), recv // P, recv)
        outcomes[seq] = None if got is None else got.reason  # type: ignore[index]
        if name == "ranger":
            slacks.append(getattr(sess.robot, "slack_ns", 0))
            if got is None:  # where it went: its true step (the old estimate's mapping)
                at = [k for k, b in sess.est._packets.items()  # type: ignore[attr-defined]
                      if any(p.sensor == ranger for p in b)]
                assert at == [spec.sample_at(t)[0]] and at[0] >= recv // P - spec.max_delay
                assert abs(sess.intake.last_t_ns - t) < 30 * ms  # type: ignore[operator]
    assert outcomes[19_940 * ms // P] is None  # inside the window by its true delay
    assert outcomes[19_800 * ms // P] == "late"  # outside it by more than the move
    assert all(90 * ms < x < 110 * ms for x in slacks)  # the estimate moved ~100 ms meanwhile
    assert sess.robot.counters["stamps_remapped"] == 1
