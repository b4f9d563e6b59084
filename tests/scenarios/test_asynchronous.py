"""The asynchronous-sensor robot: sample times, continuous-time truth, stamping modes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pd_service.estimation.nonlinear import UnscentedObserverPredictor
from pd_service.scenarios import SCENARIOS, get_scenario
from pd_service.scenarios.asynchronous import (
    ASYNC_SENSORS,
    AsyncSim,
    AsyncTiming,
    async_model,
    async_scenario,
    simulate_async,
)
from pd_service.scenarios.filter_runs import drive_async, stamp


def test_registered_and_spec_is_valid():
    assert "async" in SCENARIOS
    scn = get_scenario("async")
    spec = scn.spec("bot", epoch_ns=1_000)
    assert spec.period_ns == 50_000_000
    assert {s.name: (s.interval, s.delay) for s in spec.sensors} == {
        "odom_twist": (1, 1), "imu": (1, 1), "pose": (4, 6)}
    assert spec.model.params["Q"] == pytest.approx([q * 0.05 for q in (5e-5, 5e-5, 5e-5, 5e-3,
                                                                        2e-2)])


def test_sample_times_rates_phases_jitter_and_delays():
    scn = async_scenario()
    run = simulate_async(scn, 200, seed=3)  # 10 s
    for t in ASYNC_SENSORS:
        ts = np.array([s.t_s for s in run.samples if s.sensor == t.name])
        ts.sort()
        j = np.arange(len(ts))
        dev = ts - (t.phase_s + j / t.rate_hz)
        assert len(ts) == pytest.approx(10.0 * t.rate_hz, abs=1)
        assert np.all(np.abs(dev) <= min(0.4 / t.rate_hz, 3 * t.jitter_s) + 1e-12)
        assert np.std(dev) == pytest.approx(t.jitter_s, rel=0.3)
        assert np.all(np.diff(ts) > 0)
        arr = [s.arrival_s - s.t_s for s in run.samples if s.sensor == t.name]
        assert np.allclose(arr, t.delay_s)
    offs = np.array([s.t_s % 0.05 for s in run.samples])
    assert np.mean(offs > 1e-3) > 0.95  # off the grid


def _circle(x0, v, w, t):
    """Pose after t s of constant speed v and yaw rate w from x0."""
    yaw = x0[2] + w * t
    return np.array([x0[0] + v / w * (np.sin(yaw) - np.sin(x0[2])),
                     x0[1] - v / w * (np.cos(yaw) - np.cos(x0[2])), yaw])


def test_noise_free_truth_and_samples_follow_the_exact_arc():
    """In steady state (v = v_cmd, w = w_cmd) without noise the truth is a circle; truth and
    every sample are that circle at their own times, wherever the events fall."""
    v, w = 0.5, 0.4
    base = async_scenario()
    quiet = tuple(dataclasses.replace(t, std=(0.0,) * len(t.std)) for t in ASYNC_SENSORS)
    x0 = np.array([1.0, -2.0, 0.3, v, w])
    scn = dataclasses.replace(base, x0_true=x0, command=lambda k: np.array([v, w]),
                              timing=AsyncTiming(quiet, np.zeros((5, 5))))
    run = simulate_async(scn, 40, seed=1)
    for k in (1, 17, 40):
        np.testing.assert_allclose(run.truth[k, :3], _circle(x0, v, w, k * 0.05), atol=1e-9)
    for s in run.samples:
        if s.sensor == "pose":
            ref = _circle(x0, v, w, s.t_s)
            np.testing.assert_allclose(s.z[:2], ref[:2], atol=1e-9)
        if s.sensor == "imu":
            assert s.z[0] == pytest.approx(w, abs=1e-12)


def test_same_seed_same_run_and_sensor_streams_are_separate():
    scn = async_scenario()
    a, b = simulate_async(scn, 30, seed=9), simulate_async(scn, 30, seed=9)
    assert np.array_equal(a.truth, b.truth)
    assert [s.t_s for s in a.samples] == [s.t_s for s in b.samples]


def test_not_an_async_scenario_is_refused():
    with pytest.raises(ValueError, match="asynchronous"):
        AsyncSim(get_scenario("diffdrive"))


def test_stamp_modes():
    T = 0.05
    assert stamp(0.123, T, "exact") == (2, pytest.approx(0.023))
    assert stamp(0.123, T, "floor") == (2, 0.0)
    assert stamp(0.140, T, "nearest") == (3, 0.0)
    assert stamp(0.1234, 0.001, "fine") == (123, 0.0)
    with pytest.raises(ValueError):
        stamp(0.1, T, "ceil")


def _score(mode, run, scn):
    sub = 50 if mode == "fine" else 1
    op = UnscentedObserverPredictor(async_model(scn.period_s / sub), scn.x0, scn.P0,
                                    lead=scn.lead * sub, max_delay=scn.max_delay * sub)
    tr = drive_async(op, run, mode, scn.period_s, scn.lead, sub)
    d = tr.pred[20:, :2] - tr.truth[20:, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))), tr


def test_exact_stamps_track_the_fine_grid_and_floor_does_not():
    """A small seeded instance of bench/stamps.py: exact stamps apply every sample and land
    within 2 % of the 1 ms filter; floored stamps lose most IMU samples and do worse."""
    scn = async_scenario()
    run = simulate_async(scn, 100, seed=0)
    fine, tr_f = _score("fine", run, scn)
    exact, tr_e = _score("exact", run, scn)
    floor, tr_fl = _score("floor", run, scn)
    assert tr_e.counters["accepted"] == tr_e.offered
    assert tr_fl.counters["duplicate"] > 0
    assert abs(exact / fine - 1.0) < 0.02
    assert floor > 1.1 * fine


def test_start_at_a_later_step_resumes_each_sensor_at_its_next_sample():
    sim = AsyncSim(async_scenario(), seed=2)
    sim.start_at(100)
    out = sim.step(np.zeros(2))
    assert sim.k == 101 and sim.t == pytest.approx(5.05)
    assert {s.sensor for s in out} >= {"odom_twist", "imu"}
    assert all(5.0 <= s.t_s < 5.05 for s in out)
    assert sum(s.sensor == "imu" for s in out) == 5
    with pytest.raises(ValueError):
        sim.start_at(-1)
