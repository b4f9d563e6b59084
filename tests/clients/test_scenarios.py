"""Scenarios: the paper's example reproduced exactly; the manoeuvring robot's profile."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pd_client.scenarios import (
    MANEUVER_ACCEL_STEPS,
    MANEUVER_PATTERN,
    MANEUVER_REST_STEPS,
    MANEUVER_SPEED,
    ScenarioSim,
    get_scenario,
    maneuver_heading,
)
from pd_service.estimation.scenarios import paper_command, simulate_paper
from pd_service.wire import SessionSpec, decode, encode

from .conftest import EPOCH_NS


@pytest.mark.parametrize("noise", ["journal", "english"])
def test_paper_sim_equals_reference_simulator(noise):
    """Same seed, same commands: same truth and same samples as simulate_paper."""
    steps = 200
    ref = simulate_paper(steps, np.random.default_rng(11), noise=noise)
    sc = get_scenario("paper", noise)
    sim = ScenarioSim(sc, seed=11)
    truth, samples = [sim.x.copy()], []
    for k in range(steps + 1):
        samples += [(name, k, z) for name, z in sim.sample()]
        if k < steps:
            truth.append(sim.advance(sc.command(k)).copy())
    np.testing.assert_array_equal(np.array(truth), ref.truth)
    assert [(n, k) for n, k, _ in samples] == [(s.sensor, s.step) for s in ref.samples]
    for (_, _, z), s in zip(samples, ref.samples, strict=True):
        np.testing.assert_array_equal(z, s.z)
    assert sc.command(5)[0] == paper_command(5)
    # the range finder reports only within 3 m, so only part of the run
    ranger = [k for n, k, _ in samples if n == "ranger"]
    assert 0 < len(ranger) < steps


def test_paper_spec_and_time_scale():
    sc = get_scenario("paper", "english")
    spec = sc.spec("paper", EPOCH_NS, time_scale=4.0)
    assert spec.period_ns == 12_500_000 and spec.lead == 10
    assert [(s.name, s.delay, s.interval) for s in spec.sensors] == [("camera", 10, 2),
                                                                    ("ranger", 12, 1)]
    np.testing.assert_allclose(spec.sensors[0].R, 0.09 * np.eye(2))
    assert decode(encode(spec), SessionSpec) == spec
    cam = sc.spec("cam", EPOCH_NS, sensors=["camera"], lead=3, max_delay=20)
    assert [s.name for s in cam.sensors] == ["camera"] and (cam.lead, cam.max_delay) == (3, 20)
    with pytest.raises(ValueError, match="lidar"):
        sc.spec("x", EPOCH_NS, sensors=["lidar"])
    with pytest.raises(ValueError):
        sc.period_ns(0.0)
    with pytest.raises(ValueError):
        get_scenario("paper", "loud")
    with pytest.raises(ValueError):
        get_scenario("submarine")


def test_maneuver_profile_keeps_speed_and_turns_by_the_pattern():
    sc = get_scenario("maneuver")
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
    np.testing.assert_allclose(sc.Q, sc.G @ sc.G.T)
