"""The "unicycle" (differential-drive) model: step map against closed forms, Jacobian,
batches, yaw wrapping, lags, the yaw_rate -> 0 limit, sensors and parameters."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear import make_model, registered_models
from pd_service.estimation.nonlinear.models_unicycle import (
    UNICYCLE_SENSORS,
    chord_factor,
    chord_factor_derivative,
)

DT = 0.02


def _states(rng, n=6):
    X = rng.standard_normal((n, 5))
    X[:, 2] = rng.uniform(-np.pi, np.pi, n)
    X[0, 4] = 0.0          # exactly straight
    X[1, 4] = 1e-9         # nearly straight
    return X


def test_registered_with_its_sensors():
    assert "unicycle" in registered_models()
    m = make_model("unicycle")
    assert (m.n, m.nu, m.angles) == (5, 2, (2,))
    assert set(m.sensors) == {"odom", "odom_twist", "imu", "pose", "position"}
    dims = {name: m.sensors[name].m for name in m.sensors}
    assert dims == {"odom": 5, "odom_twist": 2, "imu": 1, "pose": 3, "position": 2}
    assert m.sensors["odom"].angles == (2,) and m.sensors["pose"].angles == (2,)
    assert m.sensors["imu"].angles == () and m.sensors["position"].angles == ()
    x = np.array([1.0, 2.0, 0.3, 0.4, 0.5])
    for name, (idx, _) in UNICYCLE_SENSORS.items():
        np.testing.assert_array_equal(m.sensors[name].h(x), x[list(idx)])


@pytest.mark.parametrize("taus", [(0.25, 0.15), (0.0, 0.0), (0.05, 3.0)])
def test_jacobian_matches_finite_differences(taus):
    m = make_model("unicycle", period_s=0.05, tau_v=taus[0], tau_w=taus[1])
    rng = np.random.default_rng(7)
    X = _states(rng)
    for u in (np.array([0.7, -0.4]), np.array([0.3, 0.0]), np.zeros(2)):
        F = m.jac(X, u, 0)
        h = 1e-6
        for j in range(5):
            e = np.zeros(5)
            e[j] = h
            d = m.f(X + e, u, 0) - m.f(X - e, u, 0)
            d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi  # the yaw wraps
            np.testing.assert_allclose(F[:, :, j], d / (2 * h), rtol=1e-6, atol=1e-8)


def test_vectorized_equals_looped():
    m = make_model("unicycle")
    rng = np.random.default_rng(1)
    X = _states(rng, 9)
    u = np.array([0.5, 0.8])
    FX, JX = m.f(X, u, 3), m.jac(X, u, 3)
    for i in range(X.shape[0]):
        np.testing.assert_array_equal(FX[i], m.f(X[i], u, 3))
        np.testing.assert_array_equal(JX[i], m.jac(X[i], u, 3))
    for s in m.sensors.values():
        HX, JH = s.h(X), s.jac(X)
        for i in range(X.shape[0]):
            np.testing.assert_array_equal(HX[i], s.h(X[i]))
            np.testing.assert_array_equal(JH[i], s.jac(X[i]))


def test_yaw_wraps_to_minus_pi_pi():
    m = make_model("unicycle", tau_w=0.0)
    x = np.array([0.0, 0.0, np.pi - 0.01, 0.0, 1.0])
    y = m.f(x, np.array([0.0, 1.0]), 0)  # turns by 0.02 rad through +pi
    assert y[2] == pytest.approx(-np.pi + 0.01, abs=1e-12)
    rng = np.random.default_rng(2)
    X = np.column_stack([np.zeros((500, 2)), rng.uniform(-3 * np.pi, 3 * np.pi, 500),
                         rng.standard_normal(500), 50 * rng.standard_normal(500)])
    yaw = m.f(X, np.array([0.0, 40.0]), 0)[:, 2]
    assert np.all((yaw >= -np.pi) & (yaw < np.pi))


def test_lags_reach_the_set_point_exactly_as_the_first_order_response():
    tau_v, tau_w = 0.3, 0.1
    m = make_model("unicycle", period_s=DT, tau_v=tau_v, tau_w=tau_w)
    u = np.array([1.2, -0.7])
    x = np.zeros(5)
    for k in range(1, 101):
        x = m.f(x, u, k)
        t = k * DT
        assert x[3] == pytest.approx(1.2 * (1 - np.exp(-t / tau_v)), rel=1e-12)
        assert x[4] == pytest.approx(-0.7 * (1 - np.exp(-t / tau_w)), rel=1e-12)
        # the yaw integrates w(t) exactly: w_cmd (t - tau_w (1 - exp(-t / tau_w)))
        assert x[2] == pytest.approx(-0.7 * (t - tau_w * (1 - np.exp(-t / tau_w))), rel=1e-10)
    assert abs(x[3] - 1.2) < 1.2 * np.exp(-6) and abs(x[4] + 0.7) < 1e-8
    # tau = 0: the set-point at once
    m0 = make_model("unicycle", tau_v=0.0, tau_w=0.0)
    np.testing.assert_array_equal(m0.f(np.zeros(5), u, 0)[3:], u)


def test_straight_line_from_rest_against_closed_form():
    """w = 0: the distance is the integral of the lag's response, exact at every step."""
    tau = 0.4
    m = make_model("unicycle", period_s=DT, tau_v=tau)
    yaw0, vc = 0.7, 0.9
    x = np.array([1.0, -2.0, yaw0, 0.0, 0.0])
    for k in range(1, 151):
        x = m.f(x, np.array([vc, 0.0]), k)
        t = k * DT
        s = vc * (t - tau * (1 - np.exp(-t / tau)))
        np.testing.assert_allclose(x[:3], [1.0 + s * np.cos(yaw0), -2.0 + s * np.sin(yaw0), yaw0],
                                   rtol=0, atol=1e-12)


@pytest.mark.parametrize("w", [0.8, -2.5, 1e-7])
def test_constant_turn_against_closed_form(w):
    """Steady v, w: the pose stays on the circle of radius v / w, exactly (any step size)."""
    v, yaw0 = 1.1, -2.9
    for period in (DT, 0.5):
        m = make_model("unicycle", period_s=period)
        x = np.array([0.5, 0.2, yaw0, v, w])
        for k in range(1, 41):
            x = m.f(x, np.array([v, w]), k)
        t = 40 * period
        yaw = yaw0 + w * t
        # x(t) = x0 + v/w (sin yaw - sin yaw0), y(t) = y0 - v/w (cos yaw - cos yaw0)
        #      = x0 + v t S(w t) cos(yaw0 + w t / 2), ...  (the chord form: finite as w -> 0)
        chord = v * t * np.sinc(w * t / (2 * np.pi))
        expect = [0.5 + chord * np.cos(yaw0 + w * t / 2), 0.2 + chord * np.sin(yaw0 + w * t / 2)]
        if abs(w) > 1e-3:
            np.testing.assert_allclose(expect, [0.5 + v / w * (np.sin(yaw) - np.sin(yaw0)),
                                                0.2 - v / w * (np.cos(yaw) - np.cos(yaw0))],
                                       atol=1e-12)
        np.testing.assert_allclose(x[:2], expect, atol=1e-11)
        assert x[2] == pytest.approx((yaw + np.pi) % (2 * np.pi) - np.pi, abs=1e-11)
        np.testing.assert_allclose(x[3:], [v, w], rtol=1e-14)


def test_yaw_rate_to_zero_is_continuous():
    m = make_model("unicycle", tau_w=0.0)
    x0 = np.array([0.3, 0.1, 1.0, 2.0, 0.0])
    ws = np.array([-1e-3, -1e-6, -1e-12, 0.0, 1e-12, 1e-6, 1e-3])
    X = np.tile(x0, (ws.size, 1))
    X[:, 4] = ws
    Y = np.array([m.f(X, np.array([2.0, w]), 0)[i] for i, w in enumerate(ws)])
    J = np.array([m.jac(X, np.array([2.0, w]), 0)[i] for i, w in enumerate(ws)])
    assert np.all(np.isfinite(Y)) and np.all(np.isfinite(J))
    # change across w = 0 is of the order of w itself (Lipschitz), no jump
    dY = np.abs(np.diff(Y, axis=0)).max(axis=1)
    dw = np.abs(np.diff(ws))
    assert np.all(dY <= 1.0 * dw + 1e-15)
    assert np.abs(np.diff(J, axis=0)).max() < 1e-2
    # S and dS/da: the series and the closed form meet at the switch (|a/2| = 1e-2)
    a = np.array([2e-2 * (1 - 1e-12), 2e-2 * (1 + 1e-12)])
    assert abs(np.diff(chord_factor_derivative(a))[0]) < 1e-14
    hh = np.linspace(-0.5, 0.5, 1001)
    fd = (chord_factor(hh + 1e-6) - chord_factor(hh - 1e-6)) / 2e-6
    np.testing.assert_allclose(chord_factor_derivative(hh), fd, atol=1e-9)


def test_one_step_against_fine_integration_while_the_speeds_change():
    """While v and w both change the pose step is the arc of their step means: close to the
    continuous solution (here 3e-9 m over one 0.02 s step from rest)."""
    tau_v, tau_w = 0.25, 0.15
    m = make_model("unicycle", period_s=DT, tau_v=tau_v, tau_w=tau_w)
    u = np.array([1.0, 2.0])
    x = np.array([0.0, 0.0, 0.4, 0.0, 0.0])
    y = m.f(x, u, 0)
    t = np.linspace(0.0, DT, 20001)
    v = u[0] * (1 - np.exp(-t / tau_v))
    yaw = 0.4 + u[1] * (t - tau_w * (1 - np.exp(-t / tau_w)))
    trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz
    px, py = trapezoid(v * np.cos(yaw), t), trapezoid(v * np.sin(yaw), t)
    assert abs(y[0] - px) < 1e-8 and abs(y[1] - py) < 1e-8
    assert y[2] == pytest.approx(yaw[-1], abs=1e-14)


def test_q_and_parameters():
    m = make_model("unicycle")
    Q = m.Q
    np.testing.assert_array_equal(Q, Q.T)
    assert np.linalg.eigvalsh(Q).min() > 0
    m2 = make_model("unicycle", Q=[1e-8, 1e-8, 1e-8, 1e-3, 1e-3])
    assert m2.Q[3, 3] == 1e-3 and np.count_nonzero(m2.Q - np.diag(np.diag(m2.Q))) == 0
    with pytest.raises(ValueError, match="Q"):
        make_model("unicycle", Q=[1.0, 2.0])
    with pytest.raises(ValueError, match="Q"):
        make_model("unicycle", Q=[1.0, 1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="period_s"):
        make_model("unicycle", period_s=0.0)
    with pytest.raises(ValueError, match="tau_v"):
        make_model("unicycle", tau_v=-0.1)
    with pytest.raises(ValueError, match="tau_w"):
        make_model("unicycle", tau_w=float("nan"))
    with pytest.raises(ValueError, match="bad parameters"):
        make_model("unicycle", tau=0.1)
    with pytest.raises(ValueError, match="u"):
        m.f(np.zeros(5), np.zeros(3), 0)
