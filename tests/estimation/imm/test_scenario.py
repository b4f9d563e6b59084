"""The paper's scenario: truth geometry and the issue's bars (fast version + slow full one)."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.imm.scenario import monte_carlo, paper_scenario, simulate


def test_truth_track_geometry():
    scn = paper_scenario()
    X = scn.truth
    assert X.shape == (3001, 5)
    np.testing.assert_allclose(np.hypot(X[:, 1], X[:, 3]), 0.3, rtol=1e-12)
    # 70 s east, half circle left (r = 0.3 / 4.5 deg/s), 70 s west, half circle right, 60 s east
    r1, r2 = 0.3 / np.radians(4.5), 0.3 / np.radians(3.0)
    np.testing.assert_allclose(X[700, [0, 2]], [21.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(X[1100, [0, 2]], [21.0, 2 * r1], atol=1e-9)
    np.testing.assert_allclose(X[1800, [0, 2]], [0.0, 2 * r1], atol=1e-9)
    np.testing.assert_allclose(X[2400, [0, 2]], [0.0, 2 * r1 + 2 * r2], atol=1e-9)
    np.testing.assert_allclose(X[3000, [0, 2]], [18.0, 2 * r1 + 2 * r2], atol=1e-9)
    assert scn.turning.sum() == 400 + 600
    with pytest.raises(ValueError, match="turn_noise"):
        paper_scenario("sometimes")


def test_common_random_numbers_are_seeded():
    scn = paper_scenario()
    a = simulate(scn, 3, 5)
    b = simulate(scn, 3, 5)
    np.testing.assert_array_equal(a[1], b[1])
    assert np.all(np.abs(a[1][..., 1]) <= np.pi)


def _ratios(runs, seed):
    mc = monte_carlo(paper_scenario(), runs, seed)
    p = {k: mc.rms_position(k) for k in mc.pos2}
    return p, mc


def test_bars_fast():
    """6 runs: the same ordering as the 100-run bench, with margins for the small sample."""
    p, mc = _ratios(6, 1)
    assert 0.30 <= p["centralised"] / p["single"] <= 0.46
    assert p["imm1"] / p["centralised"] > 1.01  # UIF-IMM 1 worse than centralised
    assert abs(p["imm2"] / p["centralised"] - 1.0) < 0.003  # UIF-IMM 2 == centralised
    assert mc.p_wrong("imm2") < mc.p_wrong("imm1")  # fused likelihoods pick the mode better


@pytest.mark.slow
def test_bars_issue_100_runs():
    """The issue's bars on the bench's 100 runs (about a minute)."""
    p, _ = _ratios(100, 1)
    assert 0.34 <= p["centralised"] / p["single"] <= 0.40
    assert p["imm1"] > p["centralised"]
    assert 0.998 <= p["imm2"] / p["centralised"] <= 1.002
