"""ObserverPredictor and AugmentedStateKF equal a from-scratch batch re-filter (property test).

Random systems (n 1..6, 1..4 sensors of dimension 1..3, some with rows of the identity),
max_delay 0..30, sample intervals 1..5, ~20% of samples lost, random per-packet delays (some
beyond the window), shuffled arrival inside each step, per-sample R overrides, duplicates,
and future stamps.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.research import AugmentedStateKF

from .reference import batch_predict

RTOL = 1e-9


def close(a: np.ndarray, b: np.ndarray) -> bool:
    scale = max(1.0, float(np.max(np.abs(b))))
    return bool(np.all(np.abs(a - b) <= RTOL * scale))


def spd(rng: np.random.Generator, k: int, lo: float, hi: float) -> np.ndarray:
    L = rng.standard_normal((k, k))
    M = L @ L.T
    M *= rng.uniform(lo, hi) / max(np.trace(M) / k, 1e-12)
    return M + lo * 1e-3 * np.eye(k)


def random_case(seed: int):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 7))
    nu = int(rng.integers(0, 3))
    A = rng.standard_normal((n, n))
    A *= rng.uniform(0.5, 1.05) / max(np.max(np.abs(np.linalg.eigvals(A))), 1e-9)
    B = rng.standard_normal((n, nu))
    Q = spd(rng, n, 1e-3, 0.5)
    if rng.random() < 0.2:  # singular Q, as in the paper's example
        Q[0, :] = Q[:, 0] = 0.0
    sensors, meta = [], []
    unit_rng = np.random.default_rng([seed, 1])  # its own stream: rng's draws stay as they were
    for i in range(int(rng.integers(1, 5))):
        m = int(rng.integers(1, 4))
        H = rng.standard_normal((m, n))
        if m <= n and unit_rng.random() < 0.3:  # rows of the identity: the unit-row path
            H = np.eye(n)[unit_rng.choice(n, size=m, replace=False)]
        sensors.append(Sensor(name=f"s{i}", H=H, R=spd(rng, m, 0.01, 1.0)))
        meta.append((int(rng.integers(1, 6)), int(rng.integers(0, 31))))  # interval, nominal delay
    max_delay = int(rng.integers(0, 31))
    lead = int(rng.integers(0, 11))
    x0 = rng.standard_normal(n)
    P0 = spd(rng, n, 0.1, 10.0)
    hold = bool(rng.random() < 0.7)
    return rng, LinearModel(A=A, B=B, Q=Q), sensors, meta, max_delay, lead, x0, P0, hold


def run_case(seed: int, ticks: int = 60) -> None:
    rng, model, sensors, meta, max_delay, lead, x0, P0, hold = random_case(seed)
    mode = "hold" if hold else "zero"
    op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay, command_hold=mode)
    aug = AugmentedStateKF(model, sensors, x0, P0, lead=lead, max_delay=max_delay, command_hold=mode)
    # Packets: (arrival tick, sensor index, stamp, z, R override or None)
    arrivals: dict[int, list] = {}
    for idx, (interval, delay) in enumerate(meta):
        s = sensors[idx]
        for stamp in range(int(rng.integers(0, interval)), ticks, interval):
            if rng.random() < 0.2:
                continue  # lost
            d = delay + int(rng.geometric(0.4)) - 1 if rng.random() < 0.7 else int(rng.integers(0, 40))
            z = rng.standard_normal(s.m) * 2
            R = spd(rng, s.m, 0.01, 1.0) if rng.random() < 0.2 else None
            arrivals.setdefault(stamp + d, []).append((idx, stamp, z, R))
            if rng.random() < 0.05:  # a duplicate of the same sample arrives later
                arrivals.setdefault(stamp + d + 1, []).append((idx, stamp, z, R))
        if rng.random() < 0.5:  # a sample stamped in the future (clock skew, forged stamp)
            k = int(rng.integers(0, ticks))
            arrivals.setdefault(k, []).append((idx, k + int(rng.integers(1, 5)), np.zeros(s.m), None))
    commands: dict[int, np.ndarray] = {}
    accepted: list = []
    checks = set(rng.choice(ticks, size=8, replace=False).tolist()) | {ticks - 1}
    for k in range(ticks):
        # The operator's command for step k + lead, sent ahead (both filters accept it).
        if model.nu and rng.random() < 0.6:
            u = rng.standard_normal(model.nu)
            assert op.add_command(step=k + lead, u=u, now=k)
            assert aug.add_command(step=k + lead, u=u, now=k)
            commands[k + lead] = u
        batch = arrivals.get(k, [])
        rng.shuffle(batch)
        for idx, stamp, z, R in batch:
            name = sensors[idx].name
            ok = op.add_measurement(name, step=stamp, z=z, now=k, R=R)
            ok_aug = aug.add_measurement(name, step=stamp, z=z, now=k, R=R)
            assert ok == ok_aug
            if ok:
                accepted.append((idx, stamp, z, R))
        if k in checks:
            want_x, want_P = batch_predict(model.A, model.B, model.Q, [(s.H, s.R) for s in sensors],
                                           x0, P0, commands, accepted, k + lead, hold=hold)
            for est in (op, aug):
                pred = est.predict(now=k)
                assert pred.step == k + lead
                assert close(pred.x, want_x), (type(est).__name__, k, pred.x, want_x)
                assert close(pred.P, want_P), (type(est).__name__, k, pred.P, want_P)
    assert op.counters == aug.counters
    c = op.counters
    total = sum(len(v) for kk, v in arrivals.items() if kk < ticks)
    assert c["accepted"] + c["late"] + c["future"] + c["duplicate"] == total
    assert c["accepted"] == len(accepted)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1))
def test_equals_batch_refilter(seed: int) -> None:
    run_case(seed)


def test_cases_exercise_every_refusal() -> None:
    """The generator really produces late, future and duplicate packets (the property test
    above would be weaker if it did not)."""
    totals = {"late": 0, "future": 0, "duplicate": 0, "accepted": 0}
    for seed in range(30):
        rng, model, sensors, meta, max_delay, lead, x0, P0, hold = random_case(seed)
        op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay)
        for k in range(40):
            for s in sensors:
                for stamp in (k - int(rng.integers(0, 40)), k + 2):
                    op.add_measurement(s.name, step=stamp, z=np.zeros(s.m), now=k)
        for key in totals:
            totals[key] += op.counters[key]
    assert all(v > 0 for v in totals.values()), totals


def test_late_commands_inside_window_are_replayed() -> None:
    """A command for a past step still inside the window changes the estimate exactly."""
    rng = np.random.default_rng(5)
    for seed in range(20):
        rng, model, sensors, meta, max_delay, lead, x0, P0, hold = random_case(1000 + seed)
        if model.nu == 0 or max_delay < 3:
            continue
        op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay)
        commands, accepted = {}, []
        for k in range(40):
            for i, s in enumerate(sensors):
                stamp = k - int(rng.integers(0, max_delay + 1))
                z = rng.standard_normal(s.m)
                if op.add_measurement(s.name, step=stamp, z=z, now=k):
                    accepted.append((i, stamp, z, None))
            j = k - int(rng.integers(0, max_delay))  # a command for a step in the past
            u = rng.standard_normal(model.nu)
            if op.add_command(step=j, u=u, now=k):
                commands[j] = u
            else:
                assert j < op.committed_step or j in commands
            want_x, want_P = batch_predict(model.A, model.B, model.Q, [(s.H, s.R) for s in sensors],
                                           x0, P0, commands, accepted, k + lead)
            pred = op.predict(now=k)
            assert close(pred.x, want_x) and close(pred.P, want_P)
