"""The manoeuvring robot: its command profile and its seeded simulator."""

from __future__ import annotations

import math

import numpy as np

from pd_service.scenarios import ScenarioSim, get_scenario
from pd_service.scenarios.maneuver import (
    MANEUVER_ACCEL_STEPS,
    MANEUVER_PATTERN,
    MANEUVER_REST_STEPS,
    MANEUVER_SPEED,
    maneuver_heading,
)

EPOCH_NS = 1_700_000_000_000_000_000


def test_maneuver_profile_keeps_speed_and_turns_by_the_pattern():
    sc = get_scenario("maneuver")
    assert sc.A is not None and sc.B is not None
    x = np.zeros(4)
    speeds = []
    cycle = sum(seg[-1] for seg in MANEUVER_PATTERN)
    start = MANEUVER_REST_STEPS + MANEUVER_ACCEL_STEPS
    assert not np.any([sc.command(k) for k in range(MANEUVER_REST_STEPS)])
    for k in range(start + cycle):
        x = sc.A @ x + sc.B @ sc.command(k)
        if k >= start:
            speeds.append(math.hypot(x[2], x[3]))
    np.testing.assert_allclose(speeds, MANEUVER_SPEED, rtol=1e-9)
    # after one pattern the heading has turned by the sum of the pattern's turns
    total = math.radians(sum(seg[1] for seg in MANEUVER_PATTERN if seg[0] == "turn"))
    np.testing.assert_allclose(x[2:], MANEUVER_SPEED * np.array([math.cos(total),
                                                                 math.sin(total)]), atol=1e-9)
    theta, omega = maneuver_heading(start + 80)  # first turn starts
    assert theta == 0.0 and omega > 0
    assert np.all(sc.command(start + 10) == 0)  # straight leg


def test_maneuver_sim_is_seeded_and_model_consistent():
    sc = get_scenario("maneuver")
    runs = []
    for _ in range(2):
        sim = ScenarioSim(sc, seed=3)
        for k in range(100):
            sim.sample()
            sim.advance(sc.command(k))
        runs.append(sim.x.copy())
    np.testing.assert_array_equal(runs[0], runs[1])
    spec = sc.spec("rover", EPOCH_NS)
    assert spec.n == 4 and spec.r == 2 and [s.name for s in spec.sensors] == ["gnss", "odometry"]
    # process noise enters through B only (acceleration noise): Q = sigma^2 B B^T
    assert sc.G is not None
    np.testing.assert_allclose(sc.Q, sc.G @ sc.G.T)

