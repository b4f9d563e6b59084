"""The planar constant-velocity LinearModel: A, B, Q against closed forms and quadrature, the
lagged velocity command, and the linear observer-predictor on it."""

import numpy as np
import pytest

from pd_service.estimation import ObserverPredictor, Sensor
from pd_service.estimation.models_planar import (
    H_POSITION,
    lagged_axis,
    planar_cv,
    white_accel_block,
)


def _quadrature_q(dt, tau, q, n=200001):
    """q int_0^dt Phi(s) G G^T Phi(s)^T ds, Phi G = [(1 - e^{-s/tau}) tau, e^{-s/tau}]."""
    s = np.linspace(0.0, dt, n)
    g = np.stack([tau * -np.expm1(-s / tau), np.exp(-s / tau)])
    integrand = g[:, None, :] * g[None, :, :]
    trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz
    return q * trapezoid(integrand, s, axis=-1)


def test_cv_without_input():
    m = planar_cv(0.1, q=0.5)
    assert (m.n, m.nu) == (4, 0)
    F = np.array([[1, 0.1], [0, 1]])
    np.testing.assert_allclose(m.A[:2, :2], F)
    np.testing.assert_allclose(m.A[2:, 2:], F)
    assert not m.A[:2, 2:].any() and not m.A[2:, :2].any()
    blk = 0.5 * np.array([[0.1**3 / 3, 0.1**2 / 2], [0.1**2 / 2, 0.1]])
    np.testing.assert_allclose(m.Q[:2, :2], blk)
    np.testing.assert_allclose(m.Q[2:, 2:], blk)
    np.testing.assert_array_equal(white_accel_block(0.1, 0.5), m.Q[:2, :2])


@pytest.mark.parametrize("dt,q,tau", [(0.1, 0.5, None), (0.05, 2.0, 0.3), (0.02, 1.0, 1e4),
                                      (0.5, 0.1, 0.01)])
def test_q_symmetric_psd(dt, q, tau):
    Q = planar_cv(dt, q, tau).Q
    np.testing.assert_array_equal(Q, Q.T)
    assert np.linalg.eigvalsh(Q).min() >= -1e-18
    assert np.linalg.det(Q[:2, :2]) > 0


@pytest.mark.parametrize("dt,tau", [(0.05, 0.3), (0.05, 0.05), (0.05, 0.01), (0.02, 50.0),
                                    (0.1, 0.2)])
def test_lagged_q_equals_the_integral(dt, tau):
    _, _, Q = lagged_axis(dt, tau, 1.3)
    np.testing.assert_allclose(Q, _quadrature_q(dt, tau, 1.3), rtol=1e-8)


def test_lagged_series_and_closed_form_meet():
    # dt / tau on both sides of the switch (0.5)
    a = lagged_axis(0.5, 1.0 / (1 - 1e-12), 1.0)[2]
    b = lagged_axis(0.5, 1.0 / (1 + 1e-12), 1.0)[2]
    np.testing.assert_allclose(a, b, rtol=1e-12)


def test_lag_tends_to_cv_as_tau_grows():
    dt = 0.05
    cv = planar_cv(dt, 1.0)
    lag = planar_cv(dt, 1.0, tau=1e9)
    np.testing.assert_allclose(lag.A, cv.A, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(lag.Q, cv.Q, rtol=1e-7)
    assert np.abs(lag.B).max() < 1e-9


def test_velocity_command_through_the_lag():
    dt, tau = 0.02, 0.25
    m = planar_cv(dt, q=0.0, tau=tau)
    assert m.nu == 2
    x = np.array([1.0, 0.0, -1.0, 0.0])
    u = np.array([0.8, -0.4])
    for k in range(1, 201):
        x = m.A @ x + m.B @ u
        t = k * dt
        # v(t) = u (1 - e^{-t/tau}), p(t) = p0 + u (t - tau (1 - e^{-t/tau}))
        r = 1 - np.exp(-t / tau)
        np.testing.assert_allclose(x, [1.0 + 0.8 * (t - tau * r), 0.8 * r,
                                       -1.0 - 0.4 * (t - tau * r), -0.4 * r], atol=1e-12)


def test_parameters_checked():
    for kwargs, field in (({"period_s": 0.0, "q": 1.0}, "period_s"),
                          ({"period_s": 0.1, "q": -1.0}, "q"),
                          ({"period_s": 0.1, "q": 1.0, "tau": 0.0}, "tau"),
                          ({"period_s": 0.1, "q": float("inf")}, "q")):
        with pytest.raises(ValueError, match=field):
            planar_cv(**kwargs)


def test_observer_predictor_tracks_a_cv_target():
    """The linear observer-predictor on the planar CV model with a delayed position sensor:
    consistent (NEES ~ 4) over a few seeded runs."""
    dt, q, delay = 0.05, 0.2, 4
    m = planar_cv(dt, q)
    R = 0.05**2 * np.eye(2)
    L = np.linalg.cholesky(m.Q)
    nees = []
    for seed in range(5):
        rng = np.random.default_rng(seed)
        P0 = np.diag([0.1, 0.1, 0.1, 0.1])
        x = np.array([0.0, 0.5, 0.0, -0.3])
        op = ObserverPredictor(m, [Sensor("position", H_POSITION, R)],
                               x0=x + np.sqrt(np.diag(P0)) * rng.standard_normal(4), P0=P0,
                               lead=0, max_delay=delay)
        truth, zs = [], []
        for k in range(300):
            truth.append(x)
            zs.append(H_POSITION @ x + 0.05 * rng.standard_normal(2))
            if k >= delay:
                op.add_measurement("position", k - delay, zs[k - delay], now=k)
            p = op.predict(k)
            if k >= 50:
                e = truth[k] - p.x
                nees.append(float(e @ np.linalg.solve(p.P, e)))
            x = m.A @ x + L @ rng.standard_normal(4)
    assert 3.0 < np.mean(nees) < 5.0
