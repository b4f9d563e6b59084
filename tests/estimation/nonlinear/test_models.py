"""Registered models: omni3 physics and Jacobian, the linear model, registry behaviour."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear import make_model, registered_models
from pd_service.estimation.nonlinear.models_omni import OmniDynamics


def test_builtin_models_are_registered():
    assert {"omni3", "linear"} <= set(registered_models())


def test_omni_jacobian_matches_finite_differences():
    model = make_model("omni3")
    rng = np.random.default_rng(3)
    X = rng.standard_normal((4, 6))
    u = np.array([0.3, -0.2, 0.1])
    F = model.jac(X, u, 0)
    h = 1e-6
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        fd = (model.f(X + e, u, 0) - model.f(X - e, u, 0)) / (2 * h)
        np.testing.assert_allclose(F[:, :, j], fd, rtol=1e-6, atol=1e-9)
    # single-state calls work too
    np.testing.assert_allclose(model.f(X[0], u, 0), model.f(X, u, 0)[0])


def test_omni_physics():
    dyn = OmniDynamics(10.0, 0.25, 0.01, 0.05, 0.2, 0.02, 0.01)
    # equal torques on all wheels: pure rotation, no net force
    s = np.zeros((1, 6))
    d = dyn.deriv(s, np.array([0.1, 0.1, 0.1]))
    assert abs(d[0, 3]) < 1e-12 and abs(d[0, 4]) < 1e-12 and d[0, 5] > 0
    # I_eff = 0.25 + 3 * 0.01 * 0.2^2 / 0.05^2 = 0.73; moment L * sum(tau) / r = 1.2 N m
    assert d[0, 5] == pytest.approx(0.2 * 0.3 / 0.05 / 0.73)
    # the force direction turns with the body: rotating theta by 120 deg permutes the wheels
    tau = np.array([0.3, -0.1, 0.05])
    f0 = dyn.force(np.array([0.0]), tau)
    f1 = dyn.force(np.array([2 * np.pi / 3]), np.roll(tau, 1))
    np.testing.assert_allclose(f0[0, 2], f1[0, 2])
    np.testing.assert_allclose(np.hypot(*f0[0, :2]), np.hypot(*f1[0, :2]))
    # no torque: friction only dissipates kinetic energy
    s = np.array([[0.0, 0.0, 0.0, 0.4, -0.2, 0.3]])
    for _ in range(50):
        s = dyn.step(s, np.zeros(3))
    assert 0 < abs(s[0, 3]) < 0.4 and 0 < abs(s[0, 5]) < 0.3


def test_omni_parameters_are_checked():
    with pytest.raises(ValueError, match="mass"):
        make_model("omni3", mass=-1.0)
    with pytest.raises(ValueError, match="Q"):
        make_model("omni3", Q=[1.0, 2.0])
    with pytest.raises(ValueError, match="bad parameters"):
        make_model("omni3", masss=1.0)
    with pytest.raises(ValueError, match="unknown model"):
        make_model("no-such-model")
    m = make_model("omni3", Q=[1e-12] * 6, R=[[1e-6, 0, 0], [0, 1e-6, 0], [0, 0, 1e-6]])
    assert m.Q[0, 0] == 1e-12 and m.sensors["pose"].R[2, 2] == 1e-6


def test_linear_model_from_plain_lists():
    m = make_model("linear", A=[[1, 0.1], [0, 1]], B=[[0], [0.1]], Q=[[0, 0], [0, 1e-3]],
                   sensors={"pos": {"H": [[1, 0]], "R": [[0.01]]}})
    assert (m.n, m.nu) == (2, 1)
    np.testing.assert_allclose(m.f(np.array([1.0, 2.0]), np.array([1.0]), 0), [1.2, 2.1])
    with pytest.raises(ValueError, match="sensors"):
        make_model("linear", A=[[1.0]], B=None, Q=[[1.0]], sensors={"s": {"H": [[1.0]]}})
    with pytest.raises(ValueError, match="A"):
        make_model("linear", A=[[1.0, 2.0]], B=None, Q=[[1.0]], sensors={})
