"""Unscented information filter update (Lee 2008), batched over leading axes.

Prior N(x-, P-) in information form::

    Y- = (P-)^{-1},   y- = Y- x-

Per sensor s, sigma points chi_i of N(x-, P-), Z_i = h_s(chi_i)::

    z^_s   = sum W_i Z_i                          (bearing: circular mean)
    P_xz   = sum W_i (chi_i - x-)(Z_i - z^_s)^T   (bearing deviations wrapped)
    H_s    = (Y- P_xz)^T                          pseudo-measurement matrix, (m, n)
    nu_s   = z_s - z^_s                           (bearing innovation wrapped)
    i_s    = H_s^T R_s^{-1} (nu_s + H_s x-)       information-state contribution
    I_s    = H_s^T R_s^{-1} H_s                   information-matrix contribution

Fusion adds every contribution to ONE shared prior (eq. 8 / 16 of the paper)::

    Y = Y- + sum_s I_s,   y = y- + sum_s i_s,   P = Y^{-1},   x = Y^{-1} y

(Adding local posteriors instead, sum_s (Y- + I_s), would count the prior m times.)
The ``+ H_s x-`` term is what makes ``x = x- + P sum_s H_s^T R_s^{-1} nu_s``; with R_s the
sensor noise, not the innovation covariance P_zz. For a linear sensor z = H x + v this is
exactly the Kalman update.

Mode likelihoods use the linearised innovation covariance of the same pseudo-measurement::

    S_s = H_s P- H_s^T + R_s                     (marginal, one sensor)
    log N(nu; 0, S) for the stacked sensors, computed in information form:
        log det S   = sum_s log det R_s + log det Y - log det Y-
        nu^T S^-1 nu = sum_s nu_s^T R_s^-1 nu_s - b^T Y^-1 b,   b = sum_s H_s^T R_s^-1 nu_s
"""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass

import numpy as np

from ..nonlinear.registry import MeasurementModel, wrap_angle
from .unscented import apply_rows, mean_and_deviations, weighted_outer

_LOG_2PI = float(np.log(2.0 * np.pi))


def _sym(M: np.ndarray) -> np.ndarray:
    return 0.5 * (M + np.swapaxes(M, -1, -2))


def _mv(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product (..., a, b) x (..., b) -> (..., a)."""
    return np.einsum("...ab,...b->...a", M, v)


@dataclass(frozen=True, eq=False)
class Contribution:
    """One sensor's information contribution at one prior (leading axes ``...``).

    i (..., n), I (..., n, n), nu (..., m) innovation, H (..., m, n) pseudo-measurement
    matrix, Rinv (m, m), logdet_R (scalar), Pzz (..., m, m) unscented innovation covariance
    (diagnostic; the update does not use it).
    """

    i: np.ndarray
    I: np.ndarray
    nu: np.ndarray
    H: np.ndarray
    Rinv: np.ndarray
    logdet_R: float
    Pzz: np.ndarray


def information_prior(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(y-, Y-) = (P^{-1} x, P^{-1}); shapes (..., n), (..., n, n)."""
    Y = _sym(np.linalg.inv(P))
    return _mv(Y, x), Y


def information_contribution(
    H: np.ndarray, Rinv: np.ndarray, nu: np.ndarray, x_prior: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """i = H^T R^-1 (nu + H x-),  I = H^T R^-1 H  (Lee 2008)."""
    HtRinv = np.swapaxes(H, -1, -2) @ Rinv  # (..., n, m)
    i = _mv(HtRinv, nu + _mv(H, x_prior))
    I = _sym(HtRinv @ H)
    return i, I


def sensor_contribution(
    sensor: MeasurementModel,
    z: np.ndarray,
    R: np.ndarray,
    x_prior: np.ndarray,
    Y_prior: np.ndarray,
    X: np.ndarray,
    w: np.ndarray,
) -> Contribution:
    """Contribution of measurement ``z`` (broadcastable to (..., m)) with noise R (m, m).

    ``X`` (..., 2n+1, n) are the sigma points of the prior, ``w`` (2n+1,) their weights.
    """
    Z = apply_rows(sensor.h, X, sensor.vectorized)  # (..., 2n+1, m)
    zhat, dZ = mean_and_deviations(Z, w, sensor.angles)
    dX = X - x_prior[..., None, :]
    Pxz = weighted_outer(w, dX, dZ)  # (..., n, m)
    H = np.swapaxes(Y_prior @ Pxz, -1, -2)  # (Y- P_xz)^T, (..., m, n)
    nu = z - zhat
    if sensor.angles:
        idx = list(sensor.angles)
        nu[..., idx] = wrap_angle(nu[..., idx])
    Rinv = _sym(np.linalg.inv(R))
    i, I = information_contribution(H, Rinv, nu, x_prior)
    Pzz = weighted_outer(w, dZ, dZ) + R
    logdet_R = float(np.linalg.slogdet(R)[1])
    return Contribution(i=i, I=I, nu=nu, H=H, Rinv=Rinv, logdet_R=logdet_R, Pzz=Pzz)


def fuse(
    y_prior: np.ndarray, Y_prior: np.ndarray, contributions: list[Contribution]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Posterior (x, P, Y) from ONE prior plus every contribution::

    Y = Y- + sum_s I_s,  y = y- + sum_s i_s,  P = Y^-1,  x = Y^-1 y
    """
    Y = Y_prior + sum(c.I for c in contributions)
    y = y_prior + sum(c.i for c in contributions)
    Y = _sym(Y)
    P = _sym(np.linalg.inv(Y))
    x = np.linalg.solve(Y, y[..., None])[..., 0]
    return x, P, Y


def marginal_loglik(c: Contribution, P_prior: np.ndarray) -> np.ndarray:
    """log N(nu_s; 0, S_s), S_s = H_s P- H_s^T + R_s; shape (...)."""
    R = np.linalg.inv(c.Rinv)
    S = _sym(c.H @ P_prior @ np.swapaxes(c.H, -1, -2) + R)
    m = c.nu.shape[-1]
    sol = np.linalg.solve(S, c.nu[..., None])[..., 0]
    maha = np.einsum("...a,...a->...", c.nu, sol)
    logdet = np.linalg.slogdet(S)[1]
    return -0.5 * (maha + logdet + m * _LOG_2PI)


def joint_loglik(
    contributions: list[Contribution], Y_prior: np.ndarray, Y_post: np.ndarray
) -> np.ndarray:
    """log N(nu; 0, S) of all sensors stacked, S = H P- H^T + blockdiag(R_s), in
    information form (see module docstring); shape (...)."""
    m = sum(c.nu.shape[-1] for c in contributions)
    quad_R = sum(np.einsum("...a,ab,...b->...", c.nu, c.Rinv, c.nu) for c in contributions)
    b = functools.reduce(operator.add,
                         (_mv(np.swapaxes(c.H, -1, -2) @ c.Rinv, c.nu) for c in contributions))
    Pb = np.linalg.solve(Y_post, b[..., None])[..., 0]
    maha = quad_R - np.einsum("...a,...a->...", b, Pb)
    logdet = (
        sum(c.logdet_R for c in contributions)
        + np.linalg.slogdet(Y_post)[1]
        - np.linalg.slogdet(Y_prior)[1]
    )
    return -0.5 * (maha + logdet + m * _LOG_2PI)
