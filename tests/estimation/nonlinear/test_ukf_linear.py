"""On a linear model the UKF is the Kalman filter (the unscented transform is exact)."""

import numpy as np
import pytest

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.nonlinear import SigmaWeights, UnscentedObserverPredictor
from pd_service.estimation.nonlinear.models_linear import linear_as_nonlinear
from pd_service.scenarios.paper import (
    paper_command,
    paper_model,
    paper_prior,
    paper_sensors,
    simulate_paper,
)
from tests.estimation.reference import batch_predict


def _drive(ops, run, commands, steps, seed, every=7):
    """Feed commands (uplink delay 2) and packets in arrival order; yield (now, pred...)."""
    rng = np.random.default_rng(seed)
    arrivals: dict[int, list] = {}
    for smp in run.samples:
        if smp.arrival is not None:
            arrivals.setdefault(smp.arrival, []).append(smp)
    accepted = []
    for now in range(steps):
        if now - 2 >= 0 and (now - 2) in commands:
            for op in ops:
                op.add_command(now - 2, [commands[now - 2]], now=now)
        batch = arrivals.get(now, [])
        rng.shuffle(batch)
        for smp in batch:
            oks = [op.add_measurement(smp.sensor, smp.step, smp.z, now=now) for op in ops]
            assert len(set(oks)) == 1
            if oks[0]:
                accepted.append(smp)
        if now % every == 0:
            yield now, [op.predict(now) for op in ops], accepted


@pytest.mark.parametrize("sigma", [None, SigmaWeights.make(4, alpha=0.3, beta=2.0, kappa=1.0)])
def test_ukf_equals_kalman_filter_on_the_paper_example(sigma):
    model, sensors = paper_model(), paper_sensors()
    x0, P0 = paper_prior()
    nl = linear_as_nonlinear(model, sensors)
    ukf = UnscentedObserverPredictor(nl, x0, P0, lead=10, max_delay=12, sigma=sigma)
    kf = ObserverPredictor(model, sensors, x0, P0, lead=10, max_delay=12)
    run = simulate_paper(150, np.random.default_rng(5), loss=0.2)
    commands = {k: paper_command(k) for k in range(150)}
    checked = 0
    for _now, (pu, pk), _accepted in _drive([ukf, kf], run, commands, 150, seed=6):
        scale = max(1.0, float(np.max(np.abs(pk.P))))
        np.testing.assert_allclose(pu.x, pk.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(pu.P, pk.P, rtol=1e-8, atol=1e-10 * scale)
        assert pu.step == pk.step and pu.newest_step == pk.newest_step
        checked += 1
    assert checked > 10
    assert ukf.counters == kf.counters


def test_ukf_equals_naive_kalman_filter_reference():
    rng = np.random.default_rng(7)
    n = 3
    A = np.array([[1.0, 0.1, 0.0], [0.0, 0.95, 0.1], [0.0, 0.0, 0.9]])
    B = np.array([[0.0], [0.1], [0.2]])
    Q = np.diag([1e-4, 1e-3, 1e-2])
    model = LinearModel(A=A, B=B, Q=Q)
    sensors = [Sensor("a", np.array([[1.0, 0, 0]]), np.array([[0.04]])),
               Sensor("b", np.array([[0.0, 1, 1], [1, 0, 0]]), np.diag([0.1, 0.2]))]
    ukf = UnscentedObserverPredictor(linear_as_nonlinear(model, sensors), np.zeros(n),
                                     np.eye(n), lead=3, max_delay=5, command_hold="zero")
    commands, packets = {}, []
    for now in range(60):
        if now % 3 == 0:
            u = rng.standard_normal(1)
            commands[now] = u
            ukf.add_command(now, u, now=now)
        for idx, name in enumerate(("a", "b")):
            if rng.random() < 0.7:
                step = now - int(rng.integers(0, 4))
                z = rng.standard_normal(sensors[idx].m)
                if ukf.add_measurement(name, step, z, now=now):
                    packets.append((idx, step, z, None))
    pred = ukf.predict(59)
    x_ref, P_ref = batch_predict(A, B, Q, [(s.H, s.R) for s in sensors], np.zeros(n), np.eye(n),
                                 commands, packets, 62, hold=False)
    np.testing.assert_allclose(pred.x, x_ref, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(pred.P, P_ref, rtol=1e-8, atol=1e-12)
