"""Mode models (registry) and measurement models."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.imm import make_sensor, position, range_bearing
from pd_service.estimation.imm.models import ct_transition, cv_transition, heading
from pd_service.estimation.imm.unscented import unscented_propagate
from pd_service.estimation.nonlinear.registry import make_model, registered_models

from .common import T, cv


def test_models_are_registered():
    assert {"imm_cv", "imm_ct"} <= set(registered_models())
    m = make_model("imm_ct", period_s=0.1, sigma_accel=0.0016, sigma_turn_accel=0.0035)
    assert (m.n, m.nu) == (5, 0)
    assert m.Q[4, 4] == pytest.approx((0.1 * 0.0035) ** 2)
    m = make_model("imm_ct", period_s=0.1, sigma_turn_step=0.01)
    assert m.Q[4, 4] == pytest.approx(1e-4)


@pytest.mark.parametrize(
    "name, params, msg",
    [
        ("imm_cv", {"sigma_accel": -1.0}, "sigma_accel"),
        ("imm_cv", {"period_s": 0.0}, "period_s"),
        ("imm_cv", {"colour": "red"}, "bad parameters"),
        ("imm_ct", {"sigma_turn_accel": 0.1, "sigma_turn_step": 0.1}, "at most one"),
        ("imm_ct", {"sigma_turn_step": "x"}, "sigma_turn_step"),
    ],
)
def test_bad_model_parameters(name, params, msg):
    with pytest.raises(ValueError, match=msg):
        make_model(name, **params)


def test_ct_is_an_exact_turn_and_tends_to_cv():
    w = np.radians(4.5)
    x = np.array([1.0, 0.3, 2.0, 0.0, w])
    y = x
    for _ in range(10):
        y = ct_transition(y, T)
    assert np.hypot(y[1], y[3]) == pytest.approx(0.3, rel=1e-12)  # speed kept
    assert heading(y) == pytest.approx(10 * w * T, rel=1e-12)  # heading turned by w t
    radius = 0.3 / w  # centre at (1, 2 + radius)
    assert np.hypot(y[0] - 1.0, y[2] - 2.0 - radius) == pytest.approx(radius, rel=1e-12)
    for w_small in (0.0, 1e-12, -1e-10):
        x = np.array([1.0, 0.3, 2.0, -0.1, w_small])
        np.testing.assert_allclose(ct_transition(x, T)[:4], cv_transition(x, T)[:4],
                                   rtol=0, atol=1e-10)
    # continuous across the switch to the small-rate series (|w| < 1e-12), and no
    # cancellation just above it
    for w0 in (1e-12, 1e-9, 1e-6):
        lo = ct_transition(np.array([1.0, 0.3, 2.0, -0.1, w0 * 0.999]), T)
        hi = ct_transition(np.array([1.0, 0.3, 2.0, -0.1, w0 * 1.001]), T)
        np.testing.assert_allclose(lo[:4], hi[:4], rtol=0, atol=1e-15 + 0.01 * w0)
        # from the origin along +xi: eta+ = (1 - cos(wT))/w * 0.3 ~ 0.3 w T^2 / 2
        eta = ct_transition(np.array([0.0, 0.3, 0.0, 0.0, w0]), T)[2]
        assert eta == pytest.approx(0.3 * w0 * T * T / 2, rel=1e-9)


def test_transitions_are_vectorised():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((3, 4, 5)) * [1, 0.3, 1, 0.3, 0.1]
    X[0, 0, 4] = 0.0
    for f in (ct_transition, cv_transition):
        batched = f(X, T)
        for i in range(3):
            for j in range(4):
                np.testing.assert_array_equal(batched[i, j], f(X[i, j], T))


def test_cv_resets_turn_rate_and_keeps_P_invertible():
    m = cv(sigma_omega=1e-4)
    x = np.array([0.0, 0.3, 0.0, 0.0, 0.07])
    P = np.diag([0.01, 1e-4, 0.01, 1e-4, 1e-2])
    xm, Pm = unscented_propagate(lambda X: m.f(X, None, 0), x, P, m.Q, 0.0)
    assert xm[4] == 0.0 and Pm[4, 4] == pytest.approx(1e-8)
    assert np.linalg.eigvalsh(Pm)[0] > 0.0


def test_range_bearing_and_position():
    rb = range_bearing("st", [1.0, 2.0], 0.3, 0.05)
    z = rb.h(np.array([4.0, 0.0, 6.0, 0.0, 0.0]))
    np.testing.assert_allclose(z, [5.0, np.arctan2(4.0, 3.0)])
    assert rb.angles == (1,) and rb.m == 2
    np.testing.assert_allclose(rb.R, np.diag([0.09, 0.0025]))
    z = rb.h(np.array([[-9.0, 0, 2.0 + 1e-3, 0, 0], [-9.0, 0, 2.0 - 1e-3, 0, 0]]))
    assert z[0, 1] > 3.1 and z[1, 1] < -3.1  # either side of the cut
    p = position("cam", sigma=0.1)
    np.testing.assert_allclose(p.h(np.arange(5.0)), [0.0, 2.0])
    assert p.angles == ()


@pytest.mark.parametrize(
    "spec, msg",
    [
        ({"kind": "range_bearing", "station": [0, 0], "sigma_range": 1, "sigma_bearing": 1}, "name"),
        ({"name": "a", "kind": "sonar"}, "kind"),
        ({"name": "a", "kind": "range_bearing", "station": [0], "sigma_range": 1,
          "sigma_bearing": 1}, "station"),
        ({"name": "a", "kind": "range_bearing", "station": [0, 0], "sigma_range": 0,
          "sigma_bearing": 1}, "sigma_range"),
        ({"name": "a", "kind": "range_bearing", "station": [0, 0]}, "bad parameters"),
        ({"name": "a", "kind": "position"}, "exactly one"),
        ({"name": "a", "kind": "position", "R": [[1, 0], [0, 0]]}, "positive definite"),
        ("st1", "expected"),
    ],
)
def test_bad_sensor_specs(spec, msg):
    with pytest.raises(ValueError, match=msg):
        make_sensor(spec)


def test_sensor_spec_builds_model():
    s = make_sensor({"name": "st1", "kind": "range_bearing", "station": [9.5, -8.5],
                     "sigma_range": 0.3, "sigma_bearing": 0.06})
    assert s.name == "st1" and s.angles == (1,)
    assert make_sensor(s) is s
