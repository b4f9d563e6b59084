"""Delay distributions (mean, std, quantiles vs closed forms) and correlation."""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest

from pd_service.link.model import DelaySpec, LinkModel, LinkParams, quantile

MS = 1_000_000
N = 100_000
MU, SIGMA = 100.0, 10.0  # ms


def delays_ms(distribution: str, correlation: float = 0.0, n: int = N, seed: int = 5,
              mu: float = MU, sigma: float = SIGMA) -> np.ndarray:  # fmt: skip
    spec = DelaySpec(round(mu * MS), round(sigma * MS), correlation, distribution)  # type: ignore[arg-type]
    model = LinkModel(LinkParams(delay=spec), seed=seed)
    out = np.empty(n)
    for i in range(n):
        t = i * 10 * MS
        out[i] = (model.process(t, b"x").releases[0].time_ns - t) / MS
    return out


# Closed forms of netem's tables (t = standardised jitter):
#   pareto: X = U^(-1/3) ~ Pareto(1, 3), t = (X - 1.5) * 4/3, X clipped at c = 4 * 3/4 + 1.5
#   E[min(X, c)] = 1.5 - 0.5 c^-2,  E[min(X, c)^2] = 3 - 2/c
C = 4 * 0.75 + 1.5
_PAR_MEAN_X = 1.5 - 0.5 / C**2
_PAR_STD_X = math.sqrt(3 - 2 / C - _PAR_MEAN_X**2)
PARETO_MEAN_T = (_PAR_MEAN_X - 1.5) * 4 / 3
PARETO_STD_T = _PAR_STD_X * 4 / 3


def pareto_q(u: float) -> float:
    return ((1 - u) ** (-1 / 3) - 1.5) * 4 / 3


def norm_q(u: float) -> float:
    return NormalDist().inv_cdf(u)


EXPECTED = {
    # distribution: (mean t, std t or None, {u: Q(u)})
    "uniform": (0.0, 1 / math.sqrt(3), {0.1: -0.8, 0.5: 0.0, 0.9: 0.8}),
    "normal": (0.0, 1.0, {0.025: -1.959964, 0.5: 0.0, 0.975: 1.959964}),
    "pareto": (PARETO_MEAN_T, PARETO_STD_T, {0.1: pareto_q(0.1), 0.5: pareto_q(0.5),
                                             0.9: pareto_q(0.9)}),
    "paretonormal": (0.75 * PARETO_MEAN_T, None,
                     {u: (norm_q(u) + 3 * pareto_q(u)) / 4 for u in (0.1, 0.5, 0.9)}),
}  # fmt: skip


@pytest.mark.parametrize("distribution", list(EXPECTED))
def test_delay_distribution_matches_netem_tables(distribution):
    d = delays_ms(distribution)
    mean_t, std_t, quantiles = EXPECTED[distribution]
    se = d.std() / math.sqrt(N)
    assert d.mean() == pytest.approx(MU + SIGMA * mean_t, abs=5 * se)
    if std_t is not None:
        assert d.std() == pytest.approx(SIGMA * std_t, rel=0.02)
    for u, q in quantiles.items():
        assert np.quantile(d, u) == pytest.approx(MU + SIGMA * q, abs=0.2), (u, q)


def test_pareto_is_skewed_and_bounded_like_netem():
    d = delays_ms("pareto")
    assert d.min() >= MU - SIGMA * 2 / 3 - 1e-3  # X >= 1  ->  t >= -2/3
    assert d.max() <= MU + SIGMA * 32767 / 8192 + 1e-3  # int16 table limit
    assert np.mean(d) > np.median(d)


def test_quantile_function_limits():
    assert quantile("uniform", 0.0) == -1.0
    assert quantile("normal", 0.0) == pytest.approx(-32767 / 8192)
    assert quantile("pareto", 0.999999) == pytest.approx(32767 / 8192)
    with pytest.raises(ValueError):
        quantile("lognormal", 0.5)


def test_normal_correlation_is_exact_lag1_and_keeps_the_marginal():
    rho = 0.6
    d = delays_ms("normal", rho)
    r1 = np.corrcoef(d[:-1], d[1:])[0, 1]
    assert r1 == pytest.approx(rho, abs=0.01)
    # AR(1): effective sample size n (1 - rho) / (1 + rho)
    se = SIGMA / math.sqrt(N * (1 - rho) / (1 + rho))
    assert d.mean() == pytest.approx(MU, abs=5 * se)
    assert d.std() == pytest.approx(SIGMA, rel=0.03)


def test_uniform_correlation_keeps_uniform_and_has_copula_rank_correlation():
    rho = 0.5
    d = delays_ms("uniform", rho)
    # the marginal is still uniform on [mu - sigma, mu + sigma)
    assert d.std() == pytest.approx(SIGMA / math.sqrt(3), rel=0.02)
    assert np.quantile(d, 0.1) == pytest.approx(MU - 0.8 * SIGMA, abs=0.3)
    # Gaussian copula: Spearman (= Pearson of uniform margins) = 6/pi asin(rho/2)
    r1 = np.corrcoef(d[:-1], d[1:])[0, 1]
    assert r1 == pytest.approx(6 / math.pi * math.asin(rho / 2), abs=0.015)


def test_uncorrelated_delays_are_uncorrelated():
    d = delays_ms("normal", 0.0, n=50_000)
    assert abs(np.corrcoef(d[:-1], d[1:])[0, 1]) < 0.02


def test_fixed_delay_without_jitter_is_exact():
    model = LinkModel(LinkParams(delay=DelaySpec(delay_ns=500 * MS)), seed=0)
    for t in (0, 17, 123_456_789):
        (rel,) = model.process(t, b"p").releases
        assert rel.time_ns == t + 500 * MS and rel.payload == b"p"


def test_delay_never_negative():
    d = delays_ms("normal", mu=1.0, sigma=10.0, n=5000)
    assert d.min() == 0.0 and (d == 0).mean() > 0.3


@pytest.mark.parametrize(
    "kwargs",
    [
        {"delay_ns": -1},
        {"jitter_ns": 1.5},
        {"correlation": 1.0},
        {"correlation": -0.1},
        {"distribution": "gauss"},
    ],
)
def test_bad_delay_spec_raises(kwargs):
    with pytest.raises(ValueError):
        DelaySpec(**kwargs)
