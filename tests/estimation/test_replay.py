"""ReplayEstimator's roll-up of a base that fell far behind: a span without commands
longer than the input buffer is one closed-form jump for a linear backend (a spec whose
epoch is far in the past: the first prediction is O(log m), not m steps), and gives what
the step-by-step roll-up gives."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation import ObserverPredictor
from pd_service.scenarios.paper import paper_model, paper_prior, paper_sensors

#: The first prediction of an epoch-0 session at 50 ms in 2026 (steps since the epoch).
FAR_NOW = 36_000_000_000


class _Counted:
    """Wraps a backend; counts its per-step calls and stops a runaway roll-up by raising
    (the test fails instead of stalling for hours)."""

    def __init__(self, backend, limit: int = 10_000, hide_jump: bool = False) -> None:
        self._b, self.calls, self.limit, self.hide_jump = backend, 0, limit, hide_jump

    def __getattr__(self, name):
        if name == "propagate_constant" and self.hide_jump:
            raise AttributeError(name)
        attr = getattr(self._b, name)
        if name in ("propagate", "advance", "update"):
            def counted(*a, **k):
                self.calls += 1
                if self.calls > self.limit:
                    raise RuntimeError(f"{self.calls} backend calls: a step-by-step roll-up")
                return attr(*a, **k)
            return counted
        return attr


def _paper(lead: int = 2, max_delay: int = 12) -> ObserverPredictor:
    x0, P0 = paper_prior()
    return ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0, lead=lead,
                             max_delay=max_delay)


def test_a_far_epoch_is_one_long_jump():
    est = _paper()
    counted = _Counted(est._backend)
    est._backend = counted
    est.add_command(FAR_NOW + 2, np.array([0.5]), now=FAR_NOW)
    pred = est.predict(FAR_NOW)
    assert pred.step == FAR_NOW + 2
    assert est.long_jumps == 1
    assert counted.calls < 10
    assert np.all(np.isfinite(pred.P)) and np.all(np.diag(pred.P) > 0)
    assert est.add_measurement("ranger", FAR_NOW - 3, np.array([1.0]), now=FAR_NOW)
    assert est.predict(FAR_NOW + 1).step == FAR_NOW + 3


@pytest.mark.parametrize("hold", ["hold", "zero"])
@pytest.mark.parametrize("command_at", [None, 5, 40])
def test_the_long_jump_equals_the_step_by_step_roll_up(hold, command_at):
    """Same commands, same measurements: the estimate after a 3,000-step gap equals the
    step-by-step roll-up's (the backend without propagate_constant) to rounding."""
    x0, P0 = paper_prior()

    def run(jump: bool):
        est = ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0, lead=2,
                                max_delay=12, command_hold=hold)
        if not jump:
            est._backend = _Counted(est._backend, limit=10**9, hide_jump=True)
        est.add_measurement("ranger", 2, np.array([0.4]), now=3)
        if command_at is not None:
            est.add_command(command_at, np.array([0.7]), now=3)
        est.predict(3)
        est.add_measurement("ranger", 3000, np.array([1.1]), now=3001)
        return est, est.predict(3001)

    est_j, fast = run(True)
    est_s, slow = run(False)
    np.testing.assert_allclose(fast.x, slow.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9, atol=1e-12)
    assert (est_j.long_jumps, est_s.long_jumps) == (1, 0)
