"""The differential-drive robot: its spec (unscented ``unicycle``, model sensors, ROS 2 bindings)
validates and round-trips, and the estimator the spec builds tracks the simulated robot offline
(each sensor at its own rate and delay, commands known over the lead) with a consistent
covariance."""

from __future__ import annotations

import numpy as np

from pd_service.backends import build, command_dim
from pd_service.estimation.nonlinear import UnscentedObserverPredictor, wrap_angle
from pd_service.scenarios import SCENARIOS, ScenarioSim, get_scenario
from pd_service.scenarios.diffdrive import PROFILE, drive_turn_stop
from pd_service.wire import SessionSpec, decode, encode

EPOCH_NS = 1_700_000_000_000_000_000


def test_spec_is_an_unscented_unicycle_session_with_ros2_topics():
    sc = get_scenario("diffdrive")
    assert {"diffdrive", "diffdrive-stationary"} <= set(SCENARIOS)
    spec = sc.spec("bot", EPOCH_NS)
    assert decode(encode(spec), SessionSpec) == spec
    assert SessionSpec.model_validate_json(spec.model_dump_json()) == spec
    assert spec.model.kind == "unscented" and spec.model.model == "unicycle"
    assert (spec.n, command_dim(spec), spec.period_ns) == (5, 2, 20_000_000)
    timing = {s.name: (s.kind, s.interval, s.delay) for s in spec.sensors}
    assert timing == {"odom_twist": ("model", 2, 2), "imu": ("model", 1, 1),
                      "pose": ("model", 10, 15)}
    np.testing.assert_allclose(spec.sensor("pose").R, np.diag([0.05**2, 0.05**2, 0.02**2]))
    ros2 = spec.ros2
    assert ros2 is not None
    b = ros2.sensors
    assert (b["odom_twist"].topic, b["odom_twist"].msg_type, b["odom_twist"].fields) == (
        "odom", "nav_msgs/msg/Odometry", ["vx", "yaw_rate"])
    assert (b["imu"].topic, b["imu"].msg_type, b["imu"].fields) == (
        "imu", "sensor_msgs/msg/Imu", ["yaw_rate"])
    assert (b["pose"].topic, b["pose"].msg_type, b["pose"].fields) == (
        "pose_fix", "geometry_msgs/msg/PoseWithCovarianceStamped", ["x", "y", "yaw"])
    assert ros2.commands is not None
    assert (ros2.commands.topic, ros2.commands.msg_type) == ("cmd_vel", "geometry_msgs/msg/Twist")
    assert ros2.outputs is not None
    assert ros2.outputs.layout.indices() == {"x": 0, "y": 1, "yaw": 2, "vx": 3, "yaw_rate": 4}
    assert ros2.outputs.layout.velocity_frame == "body"
    assert isinstance(build(spec).est, UnscentedObserverPredictor)


def test_a_sensor_subset_keeps_only_its_bindings():
    spec = get_scenario("diffdrive").spec("bot", EPOCH_NS, sensors=["imu", "pose"])
    assert spec.ros2 is not None and set(spec.ros2.sensors) == {"imu", "pose"}
    assert decode(encode(spec), SessionSpec) == spec


def test_command_profile_drives_turns_and_stops():
    us = np.array([drive_turn_stop(k) for k in range(1000)])
    assert np.all(us[:50] == 0.0)  # 1 s at rest
    assert set(map(tuple, us)) == {(v, w) for _, v, w in PROFILE}
    np.testing.assert_array_equal(drive_turn_stop(1000), drive_turn_stop(0))  # 20 s cycle
    still = get_scenario("diffdrive-stationary")
    assert all(not still.command(k).any() for k in range(0, 2000, 7))


def run_offline(name: str, seed: int, steps: int):
    """Simulate the scenario and feed its spec's estimator as the link would: each sample
    arrives ``delay`` steps after it was taken, the command for step k + lead is sent at k.
    Returns (NEES of x(k + lead), position error m) per step k."""
    sc = get_scenario(name)
    spec = sc.spec("bot", EPOCH_NS)
    est = build(spec).est
    sim = ScenarioSim(sc, seed=seed)
    lead = spec.lead
    for j in range(lead):
        assert est.add_command(j, sc.command(j), now=0)
    pending: dict[int, list] = {}
    truth = []
    for k in range(steps + lead + 1):
        if k:
            sim.advance(sc.command(k - 1))
        truth.append(sc.truth_view(sim.x))
        for d in sim.sample():
            pending.setdefault(k + sc.select([d.sensor])[0].delay, []).append(d)
    nees, err = [], []
    for k in range(steps + 1):
        est.add_command(k + lead, sc.command(k + lead), now=k)
        for d in pending.get(k, ()):
            assert est.add_measurement(d.sensor, d.step, d.z, now=k)
        p = est.predict(k)
        e = truth[k + lead] - p.x
        e[2] = wrap_angle(e[2])
        nees.append(float(e @ np.linalg.solve(p.P, e)))
        err.append(float(np.hypot(e[0], e[1])))
    assert est.counters["late"] == 0
    return np.array(nees), np.array(err)


def test_tracks_the_driving_robot():
    """One 20 s cycle (drive, turn left and right, stop): the prediction 100 ms ahead stays
    within a few cm and its covariance is not overconfident."""
    nees, err = run_offline("diffdrive", seed=3, steps=1000)
    assert np.sqrt(np.mean(err[100:] ** 2)) < 0.05
    assert 2.0 < nees[100:].mean() < 8.0, nees[100:].mean()


def test_stationary_robot_covariance_is_consistent():
    """At rest, 6 seeded runs of 8 s: the mean NEES of the 5-state prediction after the first
    2 s is near 5 (chi-square with 5 dof; one run's mean wanders, its samples are correlated)."""
    tails = [run_offline("diffdrive-stationary", seed=seed, steps=400)[0][100:]
             for seed in range(11, 17)]
    nees = np.concatenate(tails)
    assert 3.5 < nees.mean() < 7.0, nees.mean()
    assert np.quantile(nees, 0.99) < 25.0


def test_a_command_applied_inside_a_step_flows_over_each_piece() -> None:
    """ScenarioSim.advance(u, cuts): the robot that applies a command on arrival. A cut at
    the step's start is the plain step under its u; a cut at d is flow(d) under u, then
    flow(T - d) under the new one, with the same noise draw; a model without flow refuses."""
    import pytest

    sc = get_scenario("diffdrive")
    flow, T = sc.nonlinear.flow, sc.period_s  # type: ignore[union-attr]
    u0, u1 = np.array([0.5, 0.0]), np.array([0.4, 0.5])
    a, b, c = ScenarioSim(sc, 3), ScenarioSim(sc, 3), ScenarioSim(sc, 3)
    for s in (a, b, c):
        s.x = np.array([0.1, 0.2, 0.3, 0.4, 0.1])
    x = c.x.copy()
    np.testing.assert_allclose(a.advance(u0, [(0.0, u1)]), b.advance(u1), rtol=0, atol=1e-12)
    noise = a.x - flow(T)(x, u1)  # the step's noise draw, the same in every sim
    got = c.advance(u0, [(0.007, u1)])
    np.testing.assert_allclose(got, flow(T - 0.007)(flow(0.007)(x, u0), u1) + noise,
                               rtol=0, atol=1e-12)
    assert not np.allclose(got, a.x)
    with pytest.raises(ValueError, match="cuts"):
        ScenarioSim(get_scenario("paper"), 0).advance([0.0], [(0.01, np.zeros(1))])
