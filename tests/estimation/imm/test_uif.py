"""The UIF update and its pitfalls.

Each pitfall has a check, and a mutant test that re-runs the same check with the pitfall
patched in and asserts the check fails (so the check is known to catch it):

* missing ``+ H x-`` in i = H^T R^-1 (nu + H x-)      -> UIF != Kalman for a linear sensor
* P_zz used instead of R in i and I                   -> UIF != Kalman for a linear sensor
* local posteriors summed instead of contributions    -> multi-sensor UIF != stacked Kalman
* unwrapped bearings (innovation or sigma-point mean) -> result depends on where +-pi lies
"""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.imm import ImmState, range_bearing, uif
from pd_service.estimation.imm.unscented import sigma_points, weights
from pd_service.estimation.nonlinear.registry import wrap_angle

from .common import H_POS, cv, imm, position_sensors, prior
from .reference import gauss_logpdf, kf_update


def _state(x, P):
    return ImmState(mu=np.ones((1, 1)), x=x[None, None].copy(), P=P[None, None].copy())


def uif_vs_kalman(sensor_idx: list[int], seed: int = 0) -> float:
    """Largest relative difference between the IMM-UIF update (one CV mode, linear position
    sensors) and the stacked Kalman update, over x, P and the log-likelihood."""
    sensors = position_sensors()
    f = imm([cv()], sensors, "centralised")
    x, P = prior(seed)
    rng = np.random.default_rng(seed + 100)
    zs = [H_POS @ x + rng.standard_normal(2) for _ in sensors]
    out = f.update(_state(x, P), [(s, zs[s], None) for s in sensor_idx])
    xr, Pr, joint, _ = kf_update(
        x, P, [H_POS] * len(sensor_idx), [sensors[s].R for s in sensor_idx],
        [zs[s] for s in sensor_idx],
    )
    ex = np.max(np.abs(out.x[0, 0] - xr)) / np.max(np.abs(xr))
    eP = np.max(np.abs(out.P[0, 0] - Pr)) / np.max(np.abs(Pr))
    # the log-likelihood enters only through mu; recompute it the way the filter does
    y, Y = uif.information_prior(x, P)
    X = sigma_points(x, P, 0.0)
    cs = [uif.sensor_contribution(sensors[s], zs[s], sensors[s].R, x, Y, X, weights(5, 0.0))
          for s in sensor_idx]
    _, _, Ypost = uif.fuse(y, Y, cs)
    el = abs(float(uif.joint_loglik(cs, Y, Ypost)) - joint) / abs(joint)
    return float(max(ex, eP, el))


# --- the checks -----------------------------------------------------------------------------


def test_single_linear_sensor_equals_kalman():
    for seed in range(3):
        assert uif_vs_kalman([0], seed) < 1e-9


def test_several_sensors_equal_stacked_kalman():
    for seed in range(3):
        assert uif_vs_kalman([0, 1, 2], seed) < 1e-9
        assert uif_vs_kalman([0, 2], seed) < 1e-9


# --- mutants: the checks above catch each pitfall ---------------------------------------------


def test_check_catches_missing_Hx_term(monkeypatch):
    def no_Hx(H, Rinv, nu, x_prior):
        HtRinv = np.swapaxes(H, -1, -2) @ Rinv
        return np.einsum("...ab,...b->...a", HtRinv, nu), HtRinv @ H  # i = H^T R^-1 nu (wrong)

    monkeypatch.setattr(uif, "information_contribution", no_Hx)
    assert uif_vs_kalman([0]) > 1e-2


def test_check_catches_Pzz_instead_of_R(monkeypatch):
    original = uif.sensor_contribution

    def with_Pzz(sensor, z, R, x_prior, Y_prior, X, w):
        c = original(sensor, z, R, x_prior, Y_prior, X, w)
        Sinv = np.linalg.inv(c.Pzz)
        HtSinv = np.swapaxes(c.H, -1, -2) @ Sinv
        Hx = np.einsum("...ab,...b->...a", c.H, x_prior)
        i = np.einsum("...ab,...b->...a", HtSinv, c.nu + Hx)
        return uif.Contribution(i=i, I=HtSinv @ c.H, nu=c.nu, H=c.H, Rinv=c.Rinv,
                                logdet_R=c.logdet_R, Pzz=c.Pzz)

    monkeypatch.setattr(uif, "sensor_contribution", with_Pzz)
    assert uif_vs_kalman([0]) > 1e-2


def test_check_catches_summed_posteriors(monkeypatch):
    def summed(y_prior, Y_prior, contributions):
        Y = sum(Y_prior + c.I for c in contributions)  # prior counted once per sensor (wrong)
        y = sum(y_prior + c.i for c in contributions)
        P = np.linalg.inv(Y)
        return np.linalg.solve(Y, y[..., None])[..., 0], P, Y

    monkeypatch.setattr(uif, "fuse", summed)
    assert uif_vs_kalman([0]) < 1e-9  # with one sensor the two coincide
    assert uif_vs_kalman([0, 1, 2]) > 1e-2


# --- bearings ---------------------------------------------------------------------------------


def _rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    G = np.eye(5)
    for i, j in ((0, 2), (1, 3)):  # rotate positions and velocities alike
        G[i, i], G[i, j], G[j, i], G[j, j] = c, -s, s, c
    return G


def bearing_frame_mismatch() -> float:
    """A target due west of the station (bearing ~ +-pi), prior cloud straddling the cut and
    the measured bearing on the other side of it. The same problem rotated by 90 deg (bearing
    ~ -pi/2, far from the cut) must give the rotated answer."""
    st = range_bearing("st", [0.0, 0.0], 0.3, np.radians(3.5))
    f = imm([cv()], [st], "single")
    x = np.array([-10.0, 0.3, 0.05, 0.0, 0.0])  # bearing pi - 0.005
    P = np.diag([0.3, 0.01, 0.5, 0.01, 1e-6])
    z = np.array([10.1, -np.pi + 0.01])  # = pi + 0.01, reported wrapped
    a = f.update(_state(x, P), [(0, z, None)])
    G = _rot(np.pi / 2)
    zr = np.array([z[0], wrap_angle(z[1] + np.pi / 2)])
    b = f.update(_state(G @ x, G @ P @ G.T), [(0, zr, None)])
    ex = np.max(np.abs(G @ a.x[0, 0] - b.x[0, 0]))
    eP = np.max(np.abs(G @ a.P[0, 0] @ G.T - b.P[0, 0])) / np.max(np.abs(b.P[0, 0]))
    return float(max(ex, eP))


def test_bearing_result_does_not_depend_on_the_cut():
    assert bearing_frame_mismatch() < 1e-9


def test_bearing_measurement_modulo_2pi_gives_same_posterior():
    st = range_bearing("st", [0.0, 0.0], 0.3, np.radians(3.5))
    f = imm([cv()], [st], "single")
    x = np.array([-10.0, 0.3, 0.05, 0.0, 0.0])
    P = np.diag([0.3, 0.01, 0.5, 0.01, 1e-6])
    a = f.update(_state(x, P), [(0, np.array([10.1, np.pi - 0.02]), None)])
    b = f.update(_state(x, P), [(0, np.array([10.1, np.pi - 0.02 - 2 * np.pi]), None)])
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.mu, b.mu, rtol=0, atol=1e-12)


def test_check_catches_unwrapped_innovation(monkeypatch):
    monkeypatch.setattr(uif, "wrap_angle", lambda a: a)
    assert bearing_frame_mismatch() > 1e-2


def test_check_catches_unwrapped_sigma_point_mean(monkeypatch):
    original = uif.mean_and_deviations
    monkeypatch.setattr(uif, "mean_and_deviations", lambda Z, w, angles: original(Z, w, ()))
    assert bearing_frame_mismatch() > 1e-2


# --- likelihoods ------------------------------------------------------------------------------


def test_joint_loglik_information_form_equals_stacked_gaussian():
    """log N(nu; 0, H P H^T + blockdiag R) with the pseudo-measurement H of nonlinear sensors."""
    from .common import stations

    sens = stations()
    x, P = prior(3)
    x = x + np.array([8.0, 0, 5.0, 0, 0])
    rng = np.random.default_rng(5)
    zs = [s.h(x) + rng.standard_normal(2) * [0.3, 0.06] for s in sens]
    y, Y = uif.information_prior(x, P)
    X = sigma_points(x, P, 0.0)
    cs = [uif.sensor_contribution(s, z, s.R, x, Y, X, weights(5, 0.0))
          for s, z in zip(sens, zs, strict=True)]
    _, _, Ypost = uif.fuse(y, Y, cs)
    H = np.vstack([c.H for c in cs])
    R = np.zeros((6, 6))
    for k, s in enumerate(sens):
        R[2 * k:2 * k + 2, 2 * k:2 * k + 2] = s.R
    direct = gauss_logpdf(np.concatenate([c.nu for c in cs]), H @ P @ H.T + R)
    assert float(uif.joint_loglik(cs, Y, Ypost)) == pytest.approx(direct, rel=1e-10)
    # one sensor: joint == marginal
    _, _, Y1 = uif.fuse(y, Y, cs[:1])
    assert float(uif.joint_loglik(cs[:1], Y, Y1)) == pytest.approx(
        float(uif.marginal_loglik(cs[0], P)), rel=1e-10
    )
    # the product of marginals is not the joint (the innovations share the prior)
    prod = sum(float(uif.marginal_loglik(c, P)) for c in cs)
    assert abs(prod - direct) > 1e-6
