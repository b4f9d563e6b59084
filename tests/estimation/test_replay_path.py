"""ReplayEstimator.predict_path: the predicted states from the newest posterior to now + lead.

Its last point must be the very bits of ``predict`` (the same jump on the same operands); every
point must equal a naive one-step-at-a-time roll (x <- A x + B u, P <- A P A' + Q) from the
path's first point, with the commands the estimator accepted.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from pd_service.estimation import ObserverPredictor

from .reference import applied_inputs
from .test_estimator_state import feed, linear_events

RTOL = 1e-9


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.allclose(a, b, rtol=RTOL, atol=RTOL * max(1.0, float(np.max(np.abs(b))))))


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("stride", [1, 3, 1000])
def test_path_ends_at_the_prediction_and_equals_a_stepwise_roll(seed: int, stride: int) -> None:
    (model, sensors, max_delay, lead, x0, P0, hold), events = linear_events(seed, 50)
    op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay,
                           command_hold="hold" if hold else "zero")
    commands: dict[int, np.ndarray] = {}
    A, B, Q = model.A, model.B, model.Q
    checked = 0
    for k in range(50):
        for ev in feed(op, events.get(k, []), k):
            if ev[0] == "c" and ev[3]:
                commands[ev[1]] = np.asarray(ev[2], float)
        path = op.predict_path(k, stride)
        pred = op.predict(k)
        last = path[-1]
        assert last.step == pred.step == k + lead
        assert np.array_equal(last.x, pred.x) and np.array_equal(last.P, pred.P)
        assert last.newest_step == pred.newest_step
        steps = [p.step for p in path]
        assert steps == sorted(set(steps))
        assert all(b - a <= stride for a, b in pairwise(steps))
        assert len(path) == -(-(steps[-1] - steps[0]) // stride) + 1
        # the naive roll from the first point, one step at a time
        us = applied_inputs(commands, model.nu, steps[-1], hold)
        x, P = np.array(path[0].x, float), np.array(path[0].P, float)
        j = steps[0]
        for p in path[1:]:
            while j < p.step:
                x = A @ x + (B @ us[j] if model.nu else 0.0)
                P = A @ P @ A.T + Q
                j += 1
            assert _close(p.x, x) and _close(p.P, P), (seed, k, p.step)
            checked += 1
    assert checked or lead == 0


def test_path_refuses_a_bad_stride() -> None:
    (model, sensors, max_delay, lead, x0, P0, _), _ = linear_events(0, 5)
    op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay)
    for bad in (0, -1):
        with pytest.raises(ValueError, match="stride"):
            op.predict_path(0, bad)
    with pytest.raises((ValueError, TypeError)):  # compiled: refused at the call (TypeError)
        op.predict_path(0, 1.5)  # type: ignore[arg-type]


@pytest.mark.parametrize("cap", [2, 3, 7])
def test_max_points_widens_the_stride(cap: int) -> None:
    (model, sensors, max_delay, lead, x0, P0, hold), events = linear_events(3, 40)
    op = ObserverPredictor(model, sensors, x0, P0, lead=lead + 20, max_delay=max_delay)
    for k in range(40):
        feed(op, events.get(k, []), k)
    full = op.predict_path(39)
    capped = op.predict_path(39, 1, cap)
    assert len(capped) <= cap < len(full)
    assert capped[0].step == full[0].step and capped[-1].step == full[-1].step
    by_step = {p.step: p for p in full}
    for p in capped:  # the same jumps, fewer of them
        assert np.array_equal(p.x, by_step[p.step].x) and np.array_equal(p.P, by_step[p.step].P)
    with pytest.raises(ValueError, match="max_points"):
        op.predict_path(39, 1, 1)
