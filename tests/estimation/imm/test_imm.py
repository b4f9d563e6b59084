"""IMM mixing, mode probabilities, variants and the batched recursion."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.imm import ImmFilter, ImmState, uif
from pd_service.estimation.imm.mixing import (
    check_transition,
    combine,
    mix,
    posterior_probabilities,
)
from pd_service.estimation.imm.unscented import sigma_points, weights

from . import reference as ref
from .common import ct, cv, imm, position_sensors, prior, stations


def _random_mixture(rng, batch, r, n):
    mu = rng.random((*batch, r))
    mu /= mu.sum(-1, keepdims=True)
    x = rng.standard_normal((*batch, r, n))
    A = rng.standard_normal((*batch, r, n, n))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    Pi = rng.random((r, r)) + 0.1
    Pi /= Pi.sum(1, keepdims=True)
    return mu, x, P, Pi


def test_mix_and_combine_match_naive_loops():
    rng = np.random.default_rng(0)
    mu, x, P, Pi = _random_mixture(rng, (4,), 3, 5)
    cbar, x0, P0 = mix(mu, x, P, Pi)
    xc, Pc = combine(mu, x, P)
    for b in range(4):
        for j in range(3):
            c = sum(Pi[i, j] * mu[b, i] for i in range(3))
            w = [Pi[i, j] * mu[b, i] / c for i in range(3)]
            xm = sum(w[i] * x[b, i] for i in range(3))
            Pm = sum(w[i] * (P[b, i] + np.outer(x[b, i] - xm, x[b, i] - xm)) for i in range(3))
            assert cbar[b, j] == pytest.approx(c, rel=1e-13)
            np.testing.assert_allclose(x0[b, j], xm, rtol=1e-12, atol=1e-13)
            np.testing.assert_allclose(P0[b, j], Pm, rtol=1e-12, atol=1e-13)
        xr, Pr = ref.combine(list(mu[b]), list(x[b]), list(P[b]))
        np.testing.assert_allclose(xc[b], xr, rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(Pc[b], Pr, rtol=1e-12, atol=1e-13)


def test_mode_that_cannot_be_reached_keeps_its_own_estimate():
    rng = np.random.default_rng(1)
    mu, x, P, _ = _random_mixture(rng, (), 2, 3)
    Pi = np.array([[1.0, 0.0], [1.0, 0.0]])  # nobody enters mode 1
    cbar, x0, P0 = mix(mu, x, P, Pi)
    assert cbar[1] == 0.0
    np.testing.assert_array_equal(x0[1], x[1])
    np.testing.assert_array_equal(P0[1], P[1])
    mu_post = posterior_probabilities(cbar, np.array([-3.0, 10.0]))
    np.testing.assert_array_equal(mu_post, [1.0, 0.0])


def test_posterior_probabilities_in_log_space():
    cbar = np.array([0.7, 0.3])
    ll = np.array([-5000.0, -5003.0])  # exp() of either underflows to 0
    mu = posterior_probabilities(cbar, ll)
    w = np.array([0.7, 0.3 * np.exp(-3.0)])
    np.testing.assert_allclose(mu, w / w.sum(), rtol=1e-12)
    with pytest.raises(FloatingPointError):
        posterior_probabilities(cbar, np.array([-np.inf, -np.inf]))


@pytest.mark.parametrize(
    "Pi, msg",
    [
        ([[0.9, 0.2], [0.1, 0.9]], "sum to 1"),
        ([[1.1, -0.1], [0.5, 0.5]], ">= 0"),
        ([[1.0]], "shape"),
        ([[np.nan, 1.0], [0.5, 0.5]], "finite"),
        ("abc", "numeric"),
    ],
)
def test_bad_transition_matrix(Pi, msg):
    with pytest.raises(ValueError, match=msg):
        check_transition(Pi, 2)


def _run(f: ImmFilter, st: ImmState, Z, steps):
    outs = []
    for k in range(steps):
        st = f.predict(st, k)
        st = f.update(st, [(s, Z[k, s], None) for s in range(Z.shape[1])])
        outs.append((f.output(st), st))
    return outs


def _measurements(sensors, steps, seed):
    rng = np.random.default_rng(seed)
    x = np.array([2.0, 0.3, 1.0, 0.1, 0.05])
    Z = np.empty((steps, len(sensors), 2))
    for k in range(steps):
        x = x + np.array([0.03, 0.0, 0.01, 0.0, 0.0])
        for s, sen in enumerate(sensors):
            Z[k, s] = sen.h(x) + rng.standard_normal(2) * np.sqrt(np.diag(sen.R))
    return Z


@pytest.mark.parametrize("variant", ["centralised", "imm1", "imm2"])
def test_identical_modes_equal_the_single_filter(variant):
    sens = stations()
    Z = _measurements(sens, 60, 2)
    x0, P0 = prior(1)
    one = imm([ct()], sens, variant)
    two = ImmFilter([ct(), ct()], [[0.8, 0.2], [0.4, 0.6]], sens, variant=variant)
    a = _run(one, one.initial_state(x0, P0), Z, 60)
    b = _run(two, two.initial_state(x0, P0, mu0=[0.3, 0.7]), Z, 60)
    for ((xa, Pa), _), ((xb, Pb), _sb) in zip(a, b, strict=True):
        np.testing.assert_allclose(xb, xa, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(Pb, Pa, rtol=1e-8, atol=1e-14)
    # identical modes have identical likelihoods: mu just follows the Markov chain
    cbar = np.array([0.3, 0.7])
    Pi = np.array([[0.8, 0.2], [0.4, 0.6]])
    for _ in range(60):
        cbar = cbar @ Pi
    np.testing.assert_allclose(b[-1][1].mu[..., 0, :], cbar, rtol=1e-9)


@pytest.mark.parametrize("variant, likelihood", [("centralised", "joint"), ("imm2", "product")])
def test_imm_matches_textbook_reference_for_linear_sensors(variant, likelihood):
    """CV + CT IMM with position sensors: the UIF update is the Kalman update, so the whole
    recursion (mixing, UT prediction, update, mode probabilities) must equal the naive loop."""
    sens = position_sensors()
    modes = [cv(), ct(sigma_turn_step=0.01)]
    Pi = [[0.97, 0.03], [0.05, 0.95]]
    f = ImmFilter(modes, Pi, sens, variant=variant)
    x0, P0 = prior(2)
    st = f.initial_state(x0, P0, mu0=[0.6, 0.4])
    mu, xs, Ps = [0.6, 0.4], [x0.copy(), x0.copy()], [P0.copy(), P0.copy()]
    rng = np.random.default_rng(3)
    fs = [lambda p, m=m: m.f(p, np.zeros(0), 0) for m in modes]
    for k in range(40):
        present = [s for s in range(3) if rng.random() < 0.7]
        zs = {s: rng.standard_normal(2) + [2 + 0.03 * k, 1 + 0.01 * k] for s in present}
        st = f.update(f.predict(st, k), [(s, zs[s], None) for s in present])
        Hs = [sens[s].h(np.eye(5)).T for s in present]  # h is linear: rows of H
        mu, xs, Ps = ref.imm_step(mu, xs, Ps, Pi, fs, [m.Q for m in modes], Hs,
                                  [sens[s].R for s in present], [zs[s] for s in present], 0.0,
                                  likelihood)
    np.testing.assert_allclose(st.mu[0], mu, rtol=1e-8)
    for j in range(2):
        np.testing.assert_allclose(st.x[0, j], xs[j], rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(st.P[0, j], Ps[j], rtol=1e-7, atol=1e-12)


def test_batched_equals_one_at_a_time():
    sens = stations()
    f = ImmFilter([cv(), ct()], [[0.95, 0.05], [0.05, 0.95]], sens, variant="imm1", node=1)
    rng = np.random.default_rng(4)
    x0s = prior(0)[0] + rng.standard_normal((3, 5)) * [0.3, 0.02, 0.3, 0.02, 0.01]
    P0 = prior(0)[1]
    Z = np.stack([_measurements(sens, 15, 10 + b) for b in range(3)], axis=0)  # (3, K, S, 2)
    st = f.initial_state(x0s, P0, batch=(3,))
    for k in range(15):
        st = f.update(f.predict(st, k), [(s, Z[:, k, s], None) for s in range(3)])
    for b in range(3):
        one = _run(f, f.initial_state(x0s[b], P0), Z[b], 15)[-1][1]
        np.testing.assert_allclose(st.x[b], one.x, rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(st.mu[b], one.mu, rtol=1e-11, atol=1e-14)


def test_all_variants_coincide_with_one_sensor():
    sens = stations()[:1]
    Z = _measurements(sens, 30, 6)
    x0, P0 = prior(0)
    res = {}
    for v in ("single", "centralised", "imm1", "imm2"):
        f = ImmFilter([cv(), ct()], [[0.95, 0.05], [0.05, 0.95]], sens, variant=v)
        res[v] = _run(f, f.initial_state(x0, P0), Z, 30)[-1][1]
    for v in ("single", "imm1", "imm2"):
        np.testing.assert_allclose(res[v].x, res["centralised"].x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res[v].mu, res["centralised"].mu, rtol=1e-9)


def test_single_uses_only_its_sensor():
    sens = stations()
    Z = _measurements(sens, 20, 7)
    x0, P0 = prior(0)
    a = ImmFilter([cv(), ct()], [[0.95, 0.05], [0.05, 0.95]], sens, "single", node=2)
    b = ImmFilter([cv(), ct()], [[0.95, 0.05], [0.05, 0.95]], [sens[2]], "single")
    ra = _run(a, a.initial_state(x0, P0), Z, 20)[-1][1]
    rb = _run(b, b.initial_state(x0, P0), Z[:, 2:3], 20)[-1][1]
    np.testing.assert_array_equal(ra.x, rb.x)
    np.testing.assert_array_equal(ra.mu, rb.mu)


def test_imm1_nodes_use_all_contributions_but_only_their_own_likelihood():
    sens = stations()
    f = ImmFilter([cv(), ct()], [[0.9, 0.1], [0.2, 0.8]], sens, "imm1")
    x0, P0 = prior(0)
    x0 = x0 + np.array([6.0, 0, 4.0, 0, 0])
    st0 = f.initial_state(x0, P0)
    rng = np.random.default_rng(8)
    zs = [s.h(x0) + rng.standard_normal(2) * [0.3, 0.06] for s in sens]
    pred = f.predict(st0, 0)
    post = f.update(pred, [(1, zs[1], None), (2, zs[2], None)])  # node 0's sensor is silent
    # state: every node adds both contributions to its own prior (all nodes equal here)
    for node in range(3):
        xk, Pk = pred.x[node], pred.P[node]
        y, Y = uif.information_prior(xk, Pk)
        X = sigma_points(xk, Pk, 0.0)
        cs = [uif.sensor_contribution(sens[s], zs[s], sens[s].R, xk, Y, X, weights(5, 0.0))
              for s in (1, 2)]
        xf, _, _ = uif.fuse(y, Y, cs)
        np.testing.assert_allclose(post.x[node], xf, rtol=1e-12, atol=1e-13)
        own = {1: cs[0], 2: cs[1]}.get(node)
        ll = np.zeros(2) if own is None else uif.marginal_loglik(own, Pk)
        np.testing.assert_allclose(post.mu[node], posterior_probabilities(pred.mu[node], ll),
                                   rtol=1e-12)
    np.testing.assert_allclose(post.mu[0], pred.mu[0], rtol=1e-14)  # no own packet: mu = cbar


def test_filter_rejects_bad_configuration():
    sens = stations()
    with pytest.raises(ValueError, match="variant"):
        ImmFilter([cv()], [[1.0]], sens, variant="fancy")
    with pytest.raises(ValueError, match="node"):
        ImmFilter([cv()], [[1.0]], sens, variant="single", node=3)
    with pytest.raises(ValueError, match="sensors"):
        ImmFilter([cv()], [[1.0]], [], variant="single")
    with pytest.raises(ValueError, match="duplicate"):
        ImmFilter([cv()], [[1.0]], [sens[0], sens[0]])
    with pytest.raises(ValueError, match="transition"):
        ImmFilter([cv(), ct()], [[1.0]], sens)
    with pytest.raises(ValueError, match="kappa"):
        ImmFilter([cv()], [[1.0]], sens, kappa=-5.0)
    f = ImmFilter([cv(), ct()], [[0.9, 0.1], [0.1, 0.9]], sens)
    with pytest.raises(ValueError, match="P0"):
        f.initial_state(np.zeros(5), np.zeros((5, 5)))
    with pytest.raises(ValueError, match="x0"):
        f.initial_state(np.zeros(4), np.eye(5))
    with pytest.raises(ValueError, match="mu0"):
        f.initial_state(np.zeros(5), np.eye(5), mu0=[0.7, 0.7])
    with pytest.raises(ValueError, match="duplicate"):
        f.update(f.initial_state(np.zeros(5) + 1, np.eye(5)),
                 [(0, np.ones(2), None), (0, np.ones(2), None)])


def test_models_without_batch_support_are_evaluated_row_by_row():
    """A registry model whose f / h only take one point (n,) gives the same result."""
    from pd_service.estimation.nonlinear.registry import MeasurementModel, NonlinearModel

    def one_point(fn):
        def g(x, *a):
            x = np.asarray(x)
            assert x.shape == (5,), "called with a batch"
            return fn(x, *a)
        return g

    sens = stations()
    plain_sens = [MeasurementModel(s.name, one_point(s.h), s.R, s.angles) for s in sens]
    m = ct()
    plain_ct = NonlinearModel("ct_plain", 5, 0, one_point(m.f), m.Q)
    Z = _measurements(sens, 10, 9)
    x0, P0 = prior(0)
    a = ImmFilter([cv(), m], [[0.9, 0.1], [0.1, 0.9]], sens)
    b = ImmFilter([cv(), plain_ct], [[0.9, 0.1], [0.1, 0.9]], plain_sens)
    ra = _run(a, a.initial_state(x0, P0), Z, 10)[-1][1]
    rb = _run(b, b.initial_state(x0, P0), Z, 10)[-1][1]
    np.testing.assert_allclose(rb.x, ra.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(rb.mu, ra.mu, rtol=1e-12)
