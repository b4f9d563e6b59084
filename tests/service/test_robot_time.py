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
