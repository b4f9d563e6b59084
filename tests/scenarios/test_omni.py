"""The omnidirectional robot: its spec selects the adaptive UKF, the batch run is the
step-by-step simulator's, and its random stream is pinned."""

from __future__ import annotations

import numpy as np

from pd_service.backends import build, command_dim
from pd_service.estimation.nonlinear import UnscentedObserverPredictor
from pd_service.estimation.nonlinear.adaptive import MITAdapter
from pd_service.estimation.nonlinear.models_omni import OMNI_Q0
from pd_service.scenarios import SCENARIOS, ScenarioSim, get_scenario
from pd_service.scenarios.omni import (
    OMNI_LEAD,
    OMNI_MAX_DELAY,
    OMNI_POSE_DELAY,
    omni_torque,
    q_true,
    simulate_omni,
)
from pd_service.wire import SessionSpec, decode, encode

EPOCH_NS = 1_700_000_000_000_000_000


def test_omni_spec_selects_the_adaptive_ukf():
    sc = get_scenario("omni")
    assert "omni" in SCENARIOS and (sc.n, sc.nu) == (6, 3)
    spec = sc.spec("omni", EPOCH_NS, time_scale=2.0)
    assert decode(encode(spec), SessionSpec) == spec
    assert spec.period_ns == 5_000_000  # 10 ms of model time, run twice as fast
    m = spec.model
    assert m.kind == "unscented" and m.model == "omni3"
    assert m.adapt is not None and (m.adapt.method, m.adapt.indices) == ("mit", [3, 4, 5])
    np.testing.assert_array_equal(m.params["Q"], OMNI_Q0)  # the filter starts from Q0
    [pose] = spec.sensors
    assert (pose.kind, pose.name, pose.interval, pose.delay) == ("model", "pose", 1,
                                                                OMNI_POSE_DELAY)
    np.testing.assert_allclose(pose.R, 1e-8 * np.eye(3), rtol=1e-12)
    assert (spec.lead, spec.max_delay) == (OMNI_LEAD, OMNI_MAX_DELAY)
    assert command_dim(spec) == 3 and spec.n == 6

    est = build(decode(encode(spec), SessionSpec)).est
    assert isinstance(est, UnscentedObserverPredictor)
    assert isinstance(est.adapter, MITAdapter) and list(est.adapter.indices) == [3, 4, 5]
    np.testing.assert_array_equal(np.diag(est.Q), OMNI_Q0)


def test_simulate_omni_is_the_stepwise_simulator():
    """Same seed, same torques (from step 0): simulate_omni gives the truth and pose samples
    of ScenarioSim, bit for bit, across the Q jump at 10 s."""
    seed, duration = 21, 11.0
    ref = simulate_omni(np.random.default_rng(seed), duration_s=duration)
    sc = get_scenario("omni")
    s = ScenarioSim(sc, seed=seed)
    truth, z = [s.x.copy()], []
    for k in range(ref.steps + 1):
        z += [d.z for d in s.sample() if d.sensor == "pose"]
        if k < ref.steps:
            truth.append(s.advance(sc.command(k)).copy())
    np.testing.assert_array_equal(np.array(truth), ref.truth)
    np.testing.assert_array_equal(np.array(z), ref.z)
    np.testing.assert_array_equal(sc.command(123), omni_torque(123))
    assert sc.Q_of is not None
    for k in (0, 999, 1000, 1500):
        np.testing.assert_array_equal(sc.Q_of(k), q_true(k))
    assert sc.Q_of(1000)[3] == 100 * sc.Q_of(999)[3]
    np.testing.assert_array_equal(ref.q[999], q_true(999))


def test_random_stream_is_pinned():
    """Seed 5, 0.6 s, jump at 0.3 s, delays up to 4 steps, 20 % loss: the numbers the
    adaptive-UKF tests and benchmark were calibrated on."""
    run = simulate_omni(np.random.default_rng(5), duration_s=0.6, jump_s=0.3, loss=0.2,
                        max_delay=4)
    np.testing.assert_allclose(
        run.truth[-1], [-0.10106236747098407, 0.009708320648100614, 0.007558305391513193,
                        -0.27631333974094885, 0.11956588347948266, 0.042548392831324416],
        rtol=1e-12)
    np.testing.assert_allclose(
        run.z[-1], [-0.10126026628775442, 0.009522396355389776, 0.0076313943337664725],
        rtol=1e-12)
    assert run.arrival[:12].tolist() == [-1, 3, 6, -1, 8, 8, 9, 7, 12, 13, 14, 13]


def test_truth_wraps_theta_only():
    sc = get_scenario("omni")
    x = np.array([1.0, -2.0, 4.0, 0.5, -0.5, 7.0])
    np.testing.assert_allclose(sc.truth_view(x), [1.0, -2.0, 4.0 - 2 * np.pi, 0.5, -0.5, 7.0])
    assert x[2] == 4.0  # the simulated state itself is not wrapped
    x4 = x[:4]
    assert get_scenario("maneuver").truth_view(x4) is x4  # no angles: as simulated
