"""Seeded statistics of the loss models against theory (rate and mean burst length)."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.link.model import (
    FourStateLoss,
    GilbertElliott,
    LinkModel,
    LinkParams,
    RandomLoss,
    loss_theory,
)

N = 200_000


def lost_flags(spec, n: int = N, seed: int = 1) -> np.ndarray:
    model = LinkModel(LinkParams(loss=spec), seed=seed)
    return np.fromiter(
        (not model.process(i, b"x").releases for i in range(n)), dtype=bool, count=n
    )


def rate_and_burst(lost: np.ndarray) -> tuple[float, float]:
    starts = lost & ~np.concatenate(([False], lost[:-1]))
    return float(lost.mean()), float(lost.sum() / max(1, starts.sum()))


# --- theory helper against closed forms ---------------------------------------------------


@pytest.mark.parametrize("p,rho", [(0.1, 0.0), (0.02, 0.5), (0.3, 0.25)])
def test_theory_random_closed_form(p, rho):
    rate, burst = loss_theory(RandomLoss(p, rho))
    assert rate == pytest.approx(p, rel=1e-9)
    assert burst == pytest.approx(1 / ((1 - p) * (1 - rho)), rel=1e-9)


@pytest.mark.parametrize("p,r", [(0.05, 0.3), (0.01, 0.5), (0.2, 0.9)])
def test_theory_simple_gilbert_closed_form(p, r):
    rate, burst = loss_theory(GilbertElliott(p, r))
    assert rate == pytest.approx(p / (p + r), rel=1e-9)
    assert burst == pytest.approx(1 / r, rel=1e-9)


def test_theory_four_state_isolated_only():
    # only 1 -> 4 -> 1: isolated losses, rate p14 / (1 + p14), bursts of exactly 1
    rate, burst = loss_theory(FourStateLoss(p13=0.0, p31=1.0, p14=0.05))
    assert rate == pytest.approx(0.05 / 1.05, rel=1e-9)
    assert burst == pytest.approx(1.0, rel=1e-9)


# --- simulation against theory ------------------------------------------------------------


CASES = [
    RandomLoss(0.1),
    RandomLoss(0.1, 0.5),
    RandomLoss(0.02, 0.8),
    GilbertElliott(0.05, 0.3),  # simple Gilbert
    GilbertElliott(0.02, 0.2, one_minus_h=0.7, one_minus_k=0.01),  # full GE
    FourStateLoss(p13=0.02, p31=0.3, p32=0.4, p23=0.1, p14=0.01),
    FourStateLoss(p13=0.05, p31=0.5),  # netem defaults p32 = 0, p23 = 1, p14 = 0
]


@pytest.mark.parametrize("spec", CASES, ids=lambda s: repr(s))
def test_loss_rate_and_burst_match_theory(spec):
    rate_t, burst_t = loss_theory(spec)
    lost = lost_flags(spec)
    rate, burst = rate_and_burst(lost)
    # standard errors: batch means for the (autocorrelated) rate; for the burst length, the
    # spread of a geometric length, sqrt(b (b - 1)), over the number of bursts seen
    se_rate = lost.reshape(100, -1).mean(axis=1).std(ddof=1) / 10
    n_bursts = lost.sum() / burst
    se_burst = np.sqrt(burst_t * max(burst_t - 1, 0.05)) / np.sqrt(n_bursts)
    assert abs(rate - rate_t) < 4.5 * se_rate, (rate, rate_t, se_rate)
    assert abs(burst - burst_t) < 4.5 * se_burst, (burst, burst_t, se_burst)
    # and the tolerances stay meaningful (3-25 % of the value, widest for rare long bursts)
    assert 4.5 * se_rate < 0.25 * rate_t and 4.5 * se_burst < 0.2 * burst_t


def test_correlation_makes_bursts_longer_at_same_rate():
    r0, b0 = rate_and_burst(lost_flags(RandomLoss(0.1, 0.0)))
    r1, b1 = rate_and_burst(lost_flags(RandomLoss(0.1, 0.6)))
    assert r1 == pytest.approx(r0, rel=0.1)
    assert b1 > 2 * b0


def test_same_seed_same_losses_other_seed_differs():
    spec = GilbertElliott(0.05, 0.3)
    a, b, c = lost_flags(spec, 5000, 3), lost_flags(spec, 5000, 3), lost_flags(spec, 5000, 4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_loss_zero_and_one():
    assert not lost_flags(RandomLoss(0.0), 2000).any()
    assert lost_flags(RandomLoss(1.0), 2000).all()
    assert lost_flags(GilbertElliott(1.0, 0.0), 2000)[1:].all()


@pytest.mark.parametrize(
    "make",
    [
        lambda: RandomLoss(1.5),
        lambda: RandomLoss(0.1, 1.0),
        lambda: GilbertElliott(0.0, 0.0),
        lambda: GilbertElliott(-0.1, 0.5),
        lambda: FourStateLoss(p13=0.7, p31=0.5, p14=0.5),
        lambda: FourStateLoss(p13=0.1, p31=0.7, p32=0.5),
        lambda: RandomLoss(float("nan")),
    ],
)
def test_bad_loss_parameters_raise(make):
    with pytest.raises(ValueError):
        make()
