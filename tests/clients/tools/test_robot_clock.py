"""The emulated robot clock: offset, drift and step changes; the simulated robot stamping its
samples on it and applying (and echoing) commands on arrival."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from pd_client.tools.pd_robot_sim import RobotSim
from pd_client.tools.robot_clock import RobotClock, add_clock_flags, clock_from_args
from pd_service.scenarios import get_scenario
from pd_service.wire import Command, CommandEcho, Measurement, decode, encode, keys

from ..conftest import EPOCH_NS, Collector

S = 1_000_000_000


def test_offset_drift_and_a_step_change() -> None:
    c = RobotClock(10.0, 100.0, [(30.0, 0.2)], base=lambda: 0, t0_ns=0)
    assert c.at(0) == 10 * S
    assert c.at(20 * S) == 30 * S + 2_000_000  # 100 ppm of 20 s
    assert c.at(30 * S - 1) == 40 * S - 1 + 3_000_000
    assert c.at(30 * S) == 40 * S + 3_000_000 + 200_000_000  # the NTP correction
    assert c() == 10 * S


def test_the_command_line_flags() -> None:
    ap = argparse.ArgumentParser()
    add_clock_flags(ap)
    assert clock_from_args(ap.parse_args([])) is None
    args = ap.parse_args(["--clock-offset-s", "-10", "--clock-drift-ppm", "100",
                          "--clock-step", "30:0.2", "--apply-on-arrival"])
    c = clock_from_args(args)
    assert c is not None and (c.offset_s, c.drift_ppm, list(c.steps)) == (-10.0, 100.0, [(30.0, 0.2)])
    assert args.apply_on_arrival
    with pytest.raises(SystemExit):
        ap.parse_args(["--clock-step", "30"])


def test_the_simulated_robot_stamps_on_its_clock_and_echoes_on_arrival(bus) -> None:
    sc = get_scenario("paper")
    spec = sc.spec("s1", EPOCH_NS)
    now = [EPOCH_NS]
    robot_clock = RobotClock(10.0, 0.0, base=lambda: now[0], t0_ns=EPOCH_NS)
    sensors = Collector(bus, keys.robot_sensor_key("s1", "camera"))
    echoes = Collector(bus, keys.robot_echo_key("s1"))
    sim = RobotSim(bus.transport(), sc, [spec], seed=1, clock=lambda: now[0],
                   robot_clock=robot_clock, apply_on_arrival=True)
    sim.tick(0)
    now[0] = spec.time_of(3) + 1000
    bus.transport().put(keys.robot_command_key("s1"),
                        encode(Command(session="s1", seq=5, step=40, u=np.array([1.5]))))
    for k in range(1, 6):
        sim.tick(k)
    cams = [decode(p, Measurement) for p in sensors.payloads()]
    assert [m.t_ns for m in cams] == [spec.time_of(k) + 10 * S for k in (0, 2, 4)]
    assert all(m.step is None for m in cams)
    (echo,) = [decode(p, CommandEcho) for p in echoes.payloads()]
    assert echo.seq == 5 and echo.applied_ns == spec.time_of(3) + 1000 + 10 * S
    # applied on arrival: in force from step 3, not its stamped step 40
    assert sim.last_u.tolist() == [1.5]
    sim.close()
