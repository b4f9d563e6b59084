"""Scaled sigma points: weights, exactness on affine maps, the Cholesky derivative."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear.sigma import SigmaWeights, cholesky_derivative, sqrt_cov


@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (1e-2, 2.0, 0.0),
                                              (1.0, 0.0, -2.0)])
def test_unscented_transform_is_exact_for_affine_maps(alpha, beta, kappa):
    rng = np.random.default_rng(1)
    n = 5
    w = SigmaWeights.make(n, alpha, beta, kappa)
    assert w.Wm.sum() == pytest.approx(1.0)
    assert w.Wc.sum() == pytest.approx(1.0 + 1.0 - alpha**2 + beta)
    x = rng.standard_normal(n)
    A = rng.standard_normal((n, n))
    P = A @ A.T + 0.1 * np.eye(n)
    X = w.points(x, sqrt_cov(P))
    assert X.shape == (2 * n + 1, n)
    F = rng.standard_normal((3, n))
    b = rng.standard_normal(3)
    Y = X @ F.T + b
    mean = w.Wm @ Y
    D = Y - mean
    cov = (D.T * w.Wc) @ D
    np.testing.assert_allclose(mean, F @ x + b, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov, F @ P @ F.T, rtol=1e-7, atol=1e-9)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="alpha"):
        SigmaWeights.make(3, alpha=0.0)
    with pytest.raises(ValueError, match="kappa"):
        SigmaWeights.make(3, alpha=1.0, kappa=-3.0)
    with pytest.raises(ValueError, match="beta"):
        SigmaWeights.make(3, beta=float("nan"))
    with pytest.raises(ValueError, match="n"):
        SigmaWeights.make(0)


def test_cholesky_derivative_matches_finite_differences():
    rng = np.random.default_rng(2)
    n = 4
    A = rng.standard_normal((n, n))
    P = A @ A.T + 0.5 * np.eye(n)
    B = rng.standard_normal((2, n, n))
    dP = B + np.swapaxes(B, 1, 2)
    L = np.linalg.cholesky(P)
    dL = cholesky_derivative(L, dP)
    h = 1e-6
    for j in range(2):
        fd = (np.linalg.cholesky(P + h * dP[j]) - np.linalg.cholesky(P - h * dP[j])) / (2 * h)
        np.testing.assert_allclose(dL[j], fd, rtol=1e-6, atol=1e-8)
        assert np.allclose(np.triu(dL[j], 1), 0.0)


def test_sqrt_cov_survives_a_slightly_indefinite_matrix():
    P = np.diag([1.0, 0.0, -1e-18])
    L = sqrt_cov(P)
    np.testing.assert_allclose(L @ L.T, np.diag([1.0, 0.0, 0.0]), atol=1e-12)
