"""Seeded Monte-Carlo checks of the effect on the omni-robot scenario (Q jumps x100)."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear import UnscentedObserverPredictor, make_adapter, make_model
from pd_service.scenarios.filter_runs import run_filter
from pd_service.scenarios.omni import (
    P0,
    X0,
    simulate_omni,
    true_q_schedule,
)

MIT = {"method": "mit", "indices": [3, 4, 5]}


def _filters(run, max_delay=0, sage_husa=False, oracle=True):
    model = make_model("omni3")
    out = {}

    def op(adapt=None):
        return UnscentedObserverPredictor(model, X0, P0, lead=0, max_delay=max_delay,
                                          adapter=make_adapter(adapt, model.Q, [3]))

    out["nominal"] = run_filter(op(), run)
    if oracle:
        out["true"] = run_filter(
            UnscentedObserverPredictor(model, X0, P0, lead=0, max_delay=max_delay,
                                       Q_schedule=true_q_schedule(run)), run)
    out["mit"] = run_filter(op(MIT), run)
    if sage_husa:
        out["sage_husa"] = run_filter(op({"method": "sage_husa", "indices": [3, 4, 5]}), run)
    return out


def _rms(tracks, a, b, dt=0.01):
    e = np.array([t.pos_err2 for t in tracks])
    k = np.arange(e.shape[1]) * dt
    return float(np.sqrt(e[:, (k >= a) & (k < b)].mean()))


def test_adaptive_beats_nominal_after_the_jump_short():
    """Fast version: 3 runs of 6 s, jump at 3 s, packets delayed up to 3 steps, 10% lost."""
    res: dict[str, list] = {}
    for seed in range(3):
        run = simulate_omni(np.random.default_rng(100 + seed), duration_s=6.0, jump_s=3.0,
                            max_delay=3, loss=0.1)
        for name, tr in _filters(run, max_delay=3, oracle=False).items():
            res.setdefault(name, []).append(tr)
    before = _rms(res["mit"], 1.0, 3.0) / _rms(res["nominal"], 1.0, 3.0)
    after = _rms(res["mit"], 3.5, 6.0) / _rms(res["nominal"], 3.5, 6.0)
    assert before < 1.05
    assert after < 0.8  # 0.66 at the time of writing (0.33 without delays over 20 s)
    q = np.array([t.q for t in res["mit"]])  # (runs, steps, 3)
    assert np.all(np.median(q[:, 500:, :], axis=(0, 1)) > 20 * np.array([4e-6, 4e-6, 2.5e-5]))


@pytest.mark.slow
def test_issue_bar_on_ten_runs():
    """The issue's bar (the bench checks it on 50 runs): 10 runs of 20 s, jump at 10 s."""
    res: dict[str, list] = {}
    for seed in range(10):
        run = simulate_omni(np.random.default_rng(1000 + seed))
        for name, tr in _filters(run, sage_husa=False).items():
            res.setdefault(name, []).append(tr)
    assert _rms(res["mit"], 10, 20) <= 0.36 * _rms(res["nominal"], 10, 20)
    assert _rms(res["mit"], 0, 10) <= 1.01 * _rms(res["nominal"], 0, 10)
    assert _rms(res["mit"], 12, 20) <= 1.02 * _rms(res["true"], 12, 20)
    q = np.array([t.q for t in res["mit"]])[:, 1200:, :] / (100 * np.array([4e-6, 4e-6, 2.5e-5]))
    assert np.all((0.9 <= q.mean(axis=(0, 1))) & (q.mean(axis=(0, 1)) <= 1.1))


def test_true_q_oracle_uses_the_q_of_each_step():
    """The true-Q oracle (Q_schedule) through the window, with delays and loss, = a plain loop
    with Q(k) for the step k -> k+1 over the packets in stamp order."""
    from pd_service.estimation.nonlinear import SigmaWeights
    from pd_service.estimation.nonlinear.unscented import (
        ModelOps,
        UKFState,
        measurement_update,
        time_step,
    )
    from pd_service.estimation.replay import Packet

    run = simulate_omni(np.random.default_rng(5), duration_s=0.6, jump_s=0.3, loss=0.2,
                        max_delay=4)
    model = make_model("omni3")
    op = UnscentedObserverPredictor(model, X0, P0, lead=3, max_delay=4,
                                    Q_schedule=true_q_schedule(run))
    K = run.steps
    for k in range(K + 1):  # every packet arrives by K + 4: feed all, then look back
        op.add_command(k, run.u[k], now=k)
        for s in np.flatnonzero(run.arrival == k):
            op.add_measurement("pose", int(s), run.z[s], now=k)
    final = op.predict(K)
    ops, w = ModelOps(model, ["pose"]), SigmaWeights.make(6)
    st = UKFState(X0.copy(), P0.copy())
    for k in range(K + 3 + 1):
        if k:
            q = run.q[min(k - 1, K - 1)]
            st = time_step(ops, w, np.diag(q), st, run.u[min(k - 1, K)], k - 1)
        if k <= K and 0 <= run.arrival[k] <= K:
            st = measurement_update(ops, w, st, k, [Packet(0, run.z[k], None)])[0]
    assert final.step == K + 3
    np.testing.assert_allclose(final.x, st.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(final.P, st.P, rtol=1e-9, atol=1e-18)
