"""LinearBackend.propagate_constant: the closed-form long jump equals the same span made
step by step (up to rounding), for a span of any length, with and without an input."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.linear import Gaussian
from pd_service.scenarios.paper import paper_model, paper_prior, paper_sensors


def _backend(model: LinearModel):
    est = ObserverPredictor(model, [Sensor(name="s", H=np.eye(model.n)[:1], R=np.eye(1))],
                            np.zeros(model.n), np.eye(model.n), 0, 3)
    return est._backend


def _stepwise(model: LinearModel, x, P, m: int, u):
    for _ in range(m):
        x = model.A @ x + model.B @ u
        P = model.A @ P @ model.A.T + model.Q
    return x, P


@pytest.mark.parametrize("m", [1, 2, 3, 7, 64, 100, 1023, 4097])
def test_long_jump_equals_single_steps(m):
    rng = np.random.default_rng(m)
    A = 0.97 * np.linalg.qr(rng.normal(size=(4, 4)))[0]  # stable: the powers stay O(1)
    B = rng.normal(size=(4, 2))
    G = rng.normal(size=(4, 4))
    model = LinearModel(A=A, B=B, Q=0.01 * G @ G.T)
    x0, P0 = rng.normal(size=4), np.eye(4)
    u = rng.normal(size=2)
    got = _backend(model).propagate_constant(Gaussian(x0, P0), m, u)
    x, P = _stepwise(model, x0, P0, m, u)
    np.testing.assert_allclose(got.x, x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got.P, P, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(got.P, got.P.T)


def test_long_jump_of_the_paper_model_grows_like_single_steps():
    """The paper's model (an integrator: P grows without bound) over 5,000 steps."""
    model = paper_model()
    x0, P0 = paper_prior()
    u = np.array([0.3])
    got = _backend(model).propagate_constant(Gaussian(x0, P0), 5000, u)
    x, P = _stepwise(model, x0, P0, 5000, u)
    np.testing.assert_allclose(got.x, x, rtol=1e-9)
    np.testing.assert_allclose(got.P, P, rtol=1e-9)
    assert paper_sensors()  # the model the daemon's paper sessions use
