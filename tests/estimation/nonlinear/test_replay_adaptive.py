"""Exact replay with adaptation: shuffled, delayed, lossy packets and delayed commands give the
same answer as a from-scratch run (adaptive filter on the committed horizon, q frozen after)."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear import UnscentedObserverPredictor, make_adapter
from pd_service.scenarios.omni import omni_torque

from .reference import from_scratch, omni_with_beacon

SENSORS = ["pose", "beacon"]
ADAPT = {
    "mit": {"method": "mit", "indices": [3, 4, 5], "window": 4, "eta": 0.5},
    "mit-plain": {"method": "mit", "indices": [3, 5], "window": 6, "eta": 1e3, "rule": "plain"},
    "sage_husa": {"method": "sage_husa", "indices": [3, 4, 5], "forgetting": 0.9},
    "none": None,
}


def _scenario(seed, steps, max_delay, silent=(60, 95)):
    """Truth with 30x the model's velocity noise; packets (sensor, step, z, arrival)."""
    model = omni_with_beacon(fd_beacon=False)
    rng = np.random.default_rng(seed)
    qs = np.sqrt(30 * np.diag(model.Q))
    x = np.array([0.0, 0.0, 0.2, 0.1, 0.0, 0.2])
    samples, commands = [], []
    for k in range(steps):
        for i, name in enumerate(SENSORS):
            if name == "beacon" and k % 3:
                continue
            if silent[0] <= k < silent[1] or rng.random() < 0.2:
                continue  # lost (plus a silent stretch: the base rolls forward)
            s = model.sensors[name]
            z = s.h(x[None, :])[0] + np.sqrt(np.diag(s.R)) * rng.standard_normal(s.m)
            delay = int(rng.integers(0, max_delay + 4))  # some arrive too late
            samples.append((i, k, z, k + delay))
            if rng.random() < 0.1:  # a second copy (other z) arriving in the same tick:
                samples.append((i, k, z + 1e-3, k + delay))  # the first one in wins
        if rng.random() < 0.05:
            samples.append((0, k + 3, np.zeros(3), k))  # stamped in the future, refused
        u = omni_torque(k)
        if rng.random() < 0.8:
            commands.append((k, u, k + int(rng.integers(0, 3))))
        x = model.f(x, u, k) + qs * rng.standard_normal(6)
    return model, samples, commands


@pytest.mark.parametrize("method", list(ADAPT))
def test_replay_with_adaptation_equals_a_from_scratch_run(method):
    max_delay, lead, steps = 6, 4, 130
    model, samples, commands = _scenario(21, steps, max_delay)
    x0 = np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    P0 = np.diag([1e-4, 1e-4, 1e-3, 1e-2, 1e-2, 1e-1])
    dims = [model.sensors[s].m for s in SENSORS]
    op = UnscentedObserverPredictor(model, x0, P0, lead, max_delay, "hold", sensors=SENSORS,
                                    adapter=make_adapter(ADAPT[method], model.Q, dims))
    rng = np.random.default_rng(22)
    accepted, cmd_ok = [], {}
    checked = 0
    for now in range(steps):
        events = [("m", s) for s in samples if s[3] == now]
        events += [("c", c) for c in commands if c[2] == now]
        rng.shuffle(events)
        for kind, ev in events:
            if kind == "m":
                i, k, z, _ = ev
                if op.add_measurement(SENSORS[i], k, z, now=now):
                    accepted.append((i, k, z))
            elif op.add_command(ev[0], ev[1], now=now):
                cmd_ok[ev[0]] = ev[1]
        if now % 11 == 5 or now == steps - 1:
            pred = op.predict(now)
            adapter = make_adapter(ADAPT[method], model.Q, dims)
            x, P, Q = from_scratch(model, SENSORS, x0, P0, cmd_ok, accepted, now - max_delay,
                                   now + lead, adapter)
            assert pred.step == now + lead
            np.testing.assert_allclose(pred.x, x, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(pred.P, P, rtol=1e-9, atol=1e-9 * np.max(np.abs(P)))
            np.testing.assert_array_equal(op.Q, Q)
            checked += 1
    assert checked >= 12
    c = op.counters
    assert c["late"] > 0 and c["duplicate"] > 0 and c["future"] > 0 and c["accepted"] > 60
    if ADAPT[method] is not None:  # the adaptation really moved q, so freezing mattered
        q0 = np.diag(model.Q)[list(op.adapter.indices)]
        assert np.all(np.abs(np.log(op.q / q0)) > 0.05)


def test_call_pattern_does_not_matter():
    """Predicting every step or only at the end (different commit batches) agree."""
    max_delay, lead, steps = 5, 3, 70
    model, samples, commands = _scenario(31, steps, max_delay, silent=(0, 0))
    x0, P0 = np.zeros(6), np.diag([1e-4, 1e-4, 1e-3, 1e-2, 1e-2, 1e-1])
    dims = [3, 2]
    ops = [UnscentedObserverPredictor(model, x0, P0, lead, max_delay, sensors=SENSORS,
                                      adapter=make_adapter(ADAPT["mit"], model.Q, dims))
           for _ in range(2)]
    for now in range(steps):
        for i, k, z, arr in samples:
            if arr == now:
                for op in ops:
                    op.add_measurement(SENSORS[i], k, z, now=now)
        for k, u, arr in commands:
            if arr == now:
                for op in ops:
                    op.add_command(k, u, now=now)
        ops[0].predict(now)
    a, b = ops[0].predict(steps - 1), ops[1].predict(steps - 1)
    np.testing.assert_allclose(a.x, b.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(ops[0].Q, ops[1].Q)
