"""The stacked engine equals ObserverPredictor, and a session's bits do not depend on its batch."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.service.stacked import MAX_PENDING_DEPTH, Node, StackedObserverPredictor, resolve


def random_system(rng):
    n = int(rng.integers(1, 7))
    A = rng.standard_normal((n, n))
    A *= 0.99 / max(1e-9, max(abs(np.linalg.eigvals(A))))
    nu = int(rng.integers(1, 3))
    B = rng.standard_normal((n, nu))
    L = rng.standard_normal((n, n)) * 0.1
    model = LinearModel(A=A, B=B, Q=L @ L.T + 1e-4 * np.eye(n))
    sensors = []
    for i in range(int(rng.integers(1, 4))):
        m = int(rng.integers(1, 4))
        Lr = rng.standard_normal((m, m)) * 0.3
        sensors.append(Sensor(name=f"s{i}", H=rng.standard_normal((m, n)),
                              R=Lr @ Lr.T + 0.05 * np.eye(m)))
    Lp = rng.standard_normal((n, n))
    return model, sensors, rng.standard_normal(n), Lp @ Lp.T + np.eye(n)


def script(rng, sensors, nu, steps, max_delay):
    """Per step: the (kind, args) calls to make, with shuffled, delayed, lost packets."""
    calls: dict[int, list] = {k: [] for k in range(steps)}
    for k in range(steps):
        if rng.random() < 0.7:
            calls[k].append(("cmd", int(k + rng.integers(-2, 12)), rng.standard_normal(nu)))
        for s in sensors:
            if rng.random() < 0.6:
                arrive = k + int(rng.integers(0, max_delay + 3))  # some arrive too late
                if arrive < steps:
                    R = None
                    if rng.random() < 0.2:
                        Lr = rng.standard_normal((s.m, s.m)) * 0.2
                        R = Lr @ Lr.T + 0.01 * np.eye(s.m)
                    calls[arrive].append(("meas", s.name, k, rng.standard_normal(s.m), R))
        if rng.random() < 0.05:
            calls[k].append(("meas", sensors[0].name, k + 3, np.zeros(sensors[0].m), None))
    for k in calls:
        rng.shuffle(calls[k])
    return calls


def apply(op, call, k):
    if call[0] == "cmd":
        return op.add_command(call[1], call[2], now=k)
    return op.add_measurement(call[1], call[2], call[3], now=k, R=call[4])


@pytest.mark.parametrize("seed", range(12))
def test_stacked_equals_observer_predictor_in_batches(seed):
    rng = np.random.default_rng(seed)
    model, sensors, x0, P0 = random_system(rng)
    max_delay = int(rng.integers(0, 15))
    lead = int(rng.integers(0, 12))
    steps = 80
    sessions = 5  # same model, different data: they share stacked groups
    scripts = [script(rng, sensors, model.nu, steps, max_delay) for _ in range(sessions)]
    ref = [ObserverPredictor(model, sensors, x0, P0, lead, max_delay) for _ in range(sessions)]
    stk = [StackedObserverPredictor(model, sensors, x0, P0, lead, max_delay)
           for _ in range(sessions)]
    alone = [StackedObserverPredictor(model, sensors, x0, P0, lead, max_delay)
             for _ in range(sessions)]
    for k in range(steps):
        preds, solo = [], []
        for i in range(sessions):
            for call in scripts[i][k]:
                a = apply(ref[i], call, k)
                assert apply(stk[i], call, k) == a == apply(alone[i], call, k)
            # sessions publish at different steps, as in the daemon
            if (k + i) % (1 + i % 3) == 0:
                preds.append((i, ref[i].predict(k), stk[i].predict(k)))
                solo.append(alone[i].predict(k))
        resolve([p.x for _, _, p in preds])
        for (_, r, p), q in zip(preds, solo, strict=True):
            x, P = q.x.value()  # resolved on its own: identical bits to the batched one
            assert np.array_equal(p.x.x, x) and np.array_equal(p.x.P, P)
            assert p.step == r.step and p.newest_step == r.newest_step
            np.testing.assert_allclose(p.x.x, r.x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(p.x.P, r.P, rtol=1e-9, atol=1e-9)
    for i in range(sessions):
        assert stk[i].counters == ref[i].counters


def test_idle_gap_longer_than_the_horizon_and_bounded_pending_chains():
    rng = np.random.default_rng(7)
    model, sensors, x0, P0 = random_system(rng)
    ref = ObserverPredictor(model, sensors, x0, P0, lead=3, max_delay=4)
    stk = StackedObserverPredictor(model, sensors, x0, P0, lead=3, max_delay=4)
    s = sensors[0]
    for k in (0, 1, 500, 501, 3000):
        z = rng.standard_normal(s.m)
        assert ref.add_measurement(s.name, k, z, now=k) == stk.add_measurement(s.name, k, z, now=k)
        p, q = ref.predict(k), stk.predict(k)
        np.testing.assert_allclose(q.x.value()[0], p.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(q.x.value()[1], p.P, rtol=1e-9, atol=1e-9)
    # never predicting: the pending chain is resolved on the way, never deeper than the cap
    for k in range(3001, 3400):
        stk.add_command(k + 3, rng.standard_normal(model.nu), now=k)
        stk.add_measurement(s.name, k, rng.standard_normal(s.m), now=k)
    stk._replay(None)
    node = stk._newest()[1]
    assert isinstance(node, Node) and 0 < node.depth <= MAX_PENDING_DEPTH + 1


def test_a_singular_innovation_in_one_session_leaves_the_others_bits_alone():
    """R = 0 on a direction P already knows exactly: S is singular for that session only."""
    model = LinearModel(A=np.eye(2), B=np.eye(2), Q=np.zeros((2, 2)))
    sensors = [Sensor(name="p", H=np.eye(2), R=np.zeros((2, 2)))]
    ests = [StackedObserverPredictor(model, sensors, np.zeros(2), P0, lead=1, max_delay=3)
            for P0 in (np.zeros((2, 2)), np.eye(2), 2 * np.eye(2), 3 * np.eye(2))]
    alone = [StackedObserverPredictor(model, sensors, np.zeros(2), P0, lead=1, max_delay=3)
             for P0 in (np.zeros((2, 2)), np.eye(2), 2 * np.eye(2), 3 * np.eye(2))]
    ref = ObserverPredictor(model, sensors, np.zeros(2), np.zeros((2, 2)), lead=1, max_delay=3)
    for op in (*ests, *alone, ref):
        op.add_measurement("p", 0, np.array([1.0, 2.0]), now=0)
    preds = [e.predict(0) for e in ests]
    resolve([p.x for p in preds])
    for p, a in zip(preds, alone, strict=True):
        x, P = a.predict(0).x.value()
        assert np.array_equal(p.x.x, x) and np.array_equal(p.x.P, P)
    np.testing.assert_allclose(preds[0].x.x, ref.predict(0).x, atol=1e-12)
