"""A continuous-time model over any interval (pd_service.estimation.discretise, LinearModel.over)
against closed forms that share nothing with it (eigendecomposition; the constant-velocity
model's polynomials)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pd_service.estimation import LinearModel
from pd_service.estimation.discretise import Taylor, van_loan

from .reference import eigen_discretiser


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 6), nu=st.integers(0, 2),
       tau=st.floats(1e-6, 0.2))
def test_van_loan_and_taylor_equal_the_eigen_closed_form(seed: int, n: int, nu: int,
                                                         tau: float) -> None:
    rng = np.random.default_rng(seed)
    F = rng.standard_normal((n, n)) * rng.choice([0.5, 3.0])
    G = rng.standard_normal((n, nu))
    L = rng.standard_normal((n, n))
    Qc = L @ L.T
    want = eigen_discretiser(F, G, Qc)(tau)
    for got in (van_loan(F, G, Qc, tau),) + ((Taylor(F, G, Qc).at(tau),)
                                              if np.abs(F).sum(axis=0).max() * tau <= 0.5 else ()):
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-12 * max([1.0, *np.abs(w).ravel()]))
        assert np.array_equal(got[2], got[2].T)


def test_constant_velocity_is_exact_and_its_taylor_polynomials_are_short() -> None:
    q, T = 0.3, 0.05
    m = LinearModel.continuous([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], np.diag([0.0, q]), T)
    assert m.taylor is not None and m.taylor.coef.shape[0] == 3  # F^2 = 0
    for tau in (0.0, 0.013, 0.02, T):
        A, B, Q = m.over(tau)
        np.testing.assert_allclose(A, [[1.0, tau], [0.0, 1.0]], atol=1e-16)
        np.testing.assert_allclose(B, [[tau**2 / 2], [tau]], atol=1e-16)
        np.testing.assert_allclose(Q, q * np.array([[tau**3 / 3, tau**2 / 2],
                                                    [tau**2 / 2, tau]]), atol=1e-16)
    np.testing.assert_allclose(m.A, m.over(T)[0], atol=1e-16)
    assert m.over(0.013) is m.over(0.013)  # cached per distinct interval


def test_a_discrete_model_has_no_value_inside_a_step() -> None:
    m = LinearModel(A=np.eye(2), B=None, Q=np.eye(2))
    assert not m.continuous_time
    with pytest.raises(ValueError, match="discrete"):
        m.over(0.01)
    c = LinearModel.continuous(np.zeros((2, 2)), None, np.eye(2), 0.05)
    for bad in (-0.01, 0.06, float("nan")):
        with pytest.raises(ValueError, match="tau"):
            c.over(bad)
    with pytest.raises(ValueError, match="period"):
        LinearModel.continuous(np.zeros((2, 2)), None, np.eye(2), 0.0)
    with pytest.raises(ValueError, match="Qc"):
        LinearModel.continuous(np.zeros((2, 2)), None, -np.eye(2), 0.05)
