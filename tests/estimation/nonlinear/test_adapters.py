"""The adaptation rules on hand-made innovation records."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear.adaptive import (
    MITAdapter,
    MITSettings,
    SageHusaAdapter,
    SageHusaSettings,
)
from pd_service.estimation.nonlinear.unscented import InnovationRecord

Q0 = np.diag([1e-6, 2e-6])


def _rec(nu, S, dnu, dS, K=None, gap=1):
    m = len(nu)
    return InnovationRecord(0, ((0, 0, m),), np.asarray(nu, float), np.asarray(S, float),
                            np.zeros((2, m)) if K is None else np.asarray(K, float), gap, Q0,
                            np.asarray(dnu, float), np.asarray(dS, float))


def test_mit_waits_for_a_full_window_then_raises_q_when_innovations_are_too_big():
    ad = MITAdapter(MITSettings(indices=(0, 1), window=3, eta=0.5), Q0, [1])
    S = [[1.0]]
    dS = np.array([[[1e5]], [[0.0]]])          # S grows with q_0 only
    dnu = np.zeros((2, 1))
    assert ad.observe(_rec([3.0], S, dnu, dS), Q0) is None
    assert ad.observe(_rec([3.0], S, dnu, dS), Q0) is None
    Q1 = ad.observe(_rec([3.0], S, dnu, dS), Q0)
    # dS_11 = 9 - 1 = 8 > 0, d dS / dq_0 = -1e5: exponent -eta q (8 / 1)(-1e5) / 1 = +0.4 -> clip
    assert Q1[0, 0] == pytest.approx(1e-6 * np.exp(0.1))
    assert Q1[1, 1] == 2e-6  # no sensitivity, no change
    # innovations smaller than predicted: q goes down
    ad2 = MITAdapter(MITSettings(indices=(0,), window=1, eta=1e-3), Q0, [1])
    Q2 = ad2.observe(_rec([0.1], S, np.zeros((1, 1)), np.array([[[1e5]]])), Q0)
    expo = 1e-3 * 1e-6 * ((0.01 - 1.0) / 1.0) * (-1e5) / 1.0
    assert Q2[0, 0] == pytest.approx(1e-6 * np.exp(-expo))


def test_mit_plain_rule_and_bounds():
    ad = MITAdapter(MITSettings(indices=(0,), window=1, eta=1e-12, rule="plain",
                                q_min=(5e-7,), q_max=(1.5e-6,)), Q0, [1])
    S, dS = [[1.0]], np.array([[[1e5]]])
    # dJ/dq = dS (d dS/dq) = (4 - 1)(2 * 2 * 10 - 1e5) ; q <- q - eta dJ/dq (then clamped)
    g = 3.0 * (2 * 2.0 * 10.0 - 1e5)
    Q1 = ad.observe(_rec([2.0], S, [[10.0]], dS), Q0)
    assert Q1[0, 0] == pytest.approx(min(1.5e-6, 1e-6 - 1e-12 * g))


def test_sage_husa_is_the_classical_recursion_for_gap_one():
    rng = np.random.default_rng(0)
    K = rng.standard_normal((2, 2)) * 0.1
    S = np.array([[2.0, 0.3], [0.3, 1.0]])
    nu = np.array([1.5, -0.7])  # one channel is clamped at q_min on the way
    b = 0.9
    ad = SageHusaAdapter(SageHusaSettings(indices=(0, 1), forgetting=b, q_min=(1e-12, 1e-12),
                                          q_max=(1.0, 1.0)), Q0, [2])
    Q = Q0
    for k in range(3):
        d = (1 - b) / (1 - b ** (k + 1))
        # K nu nu^T K^T + P+ - (P- - Q) with P- - P+ = K S K^T
        sample = K @ np.outer(nu, nu) @ K.T - K @ S @ K.T + Q
        want = np.clip((1 - d) * np.diag(Q) + d * np.diag(sample), 1e-12, 1.0)
        Q = ad.observe(_rec(nu, S, np.zeros((2, 2)), np.zeros((2, 2, 2)), K=K), Q)
        np.testing.assert_allclose(np.diag(Q), want, rtol=1e-12)


def test_mit_keeps_one_window_per_sensor_and_gap():
    ad = MITAdapter(MITSettings(indices=(0,), window=2, eta=1e-3, max_gap=2), Q0, [1])
    S, dS, dnu = [[1.0]], np.array([[[1e5]]]), np.zeros((1, 1))
    assert ad.observe(_rec([3.0], S, dnu, dS, gap=1), Q0) is None
    assert ad.observe(_rec([3.0], S, dnu, dS, gap=2), Q0) is None   # another window
    assert ad.observe(_rec([3.0], S, dnu, dS, gap=3), Q0) is None   # > max_gap: unused
    assert ad.observe(_rec([3.0], S, dnu, dS, gap=0), Q0) is None   # first update: unused
    assert ad.observe(_rec([3.0], S, dnu, dS, gap=1), Q0) is not None  # gap-1 window full
    assert ad.observe(_rec([3.0], S, dnu, dS, gap=2), Q0) is not None  # gap-2 window full
