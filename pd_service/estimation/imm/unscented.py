"""Unscented moments with Julier's symmetric kappa sigma points, batched.

For x (..., n), P (..., n, n) and scaling kappa (n + kappa > 0), the points and weights are
:meth:`..nonlinear.sigma.SigmaWeights.julier` (alpha = 1, beta = 0)::

    L L^T = P   (Cholesky),   c = sqrt(n + kappa)
    chi_0 = x,  chi_i = x + c L[:, i-1],  chi_{n+i} = x - c L[:, i-1],   i = 1..n
    W_0 = kappa / (n + kappa),  W_i = 1 / (2 (n + kappa))

Angle components of transformed points are averaged on the circle and their deviations
wrapped, so a cloud straddling +-pi is handled (a plain average of -179 deg and +179 deg
would give 0 deg).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..nonlinear.registry import wrap_angle
from ..nonlinear.sigma import SigmaWeights, sqrt_cov

Array = NDArray[np.float64]


def apply_rows(fn: Callable[[Array], Array], X: Array, vectorized: bool) -> Array:
    """fn over the last axis of X (..., n) -> (..., m): one call on the (N, n) rows if
    ``vectorized``, else row by row."""
    rows = X.reshape(-1, X.shape[-1])
    out = fn(rows) if vectorized else np.stack([np.asarray(fn(r), dtype=float) for r in rows])
    return np.asarray(out, dtype=float).reshape(*X.shape[:-1], -1)


def weights(n: int, kappa: float) -> Array:
    """Weights (2n+1,) summing to 1; ValueError unless n + kappa > 0."""
    return SigmaWeights.julier(n, kappa).Wm


def sigma_points(x: Array, P: Array, kappa: float) -> Array:
    """Sigma points (..., 2n+1, n) of N(x, P)."""
    return SigmaWeights.julier(x.shape[-1], kappa).points(x, sqrt_cov(P))


def mean_and_deviations(
    Z: Array, w: Array, angles: tuple[int, ...]
) -> tuple[Array, Array]:
    """Weighted mean (..., m) of points Z (..., 2n+1, m) and deviations Z - mean (wrapped on
    the ``angles`` components)::

        zbar = sum_i W_i Z_i,   angle a:  zbar_a = atan2(sum_i W_i sin Z_ia, sum_i W_i cos Z_ia)
    """
    zbar = np.einsum("i,...im->...m", w, Z)
    if angles:
        idx = list(angles)
        A = Z[..., idx]
        zbar[..., idx] = np.arctan2(
            np.einsum("i,...ia->...a", w, np.sin(A)), np.einsum("i,...ia->...a", w, np.cos(A))
        )
    dZ = Z - zbar[..., None, :]
    if angles:
        dZ[..., idx] = wrap_angle(dZ[..., idx])
    return zbar, dZ


def weighted_outer(w: Array, dA: Array, dB: Array) -> Array:
    """sum_i W_i dA_i dB_i^T: (..., a, b) from deviations (..., 2n+1, a), (..., 2n+1, b)."""
    return np.einsum("i,...ia,...ib->...ab", w, dA, dB)


def unscented_propagate(
    f: Callable[[Array], Array], x: Array, P: Array, Q: Array, kappa: float,
    angles: tuple[int, ...] = (),
) -> tuple[Array, Array]:
    """Prior of x+ = f(x) + w, w ~ N(0, Q), through sigma points::

        chi_i+ = f(chi_i),   x- = sum W_i chi_i+,   P- = sum W_i (chi_i+ - x-)(.)^T + Q

    ``f`` maps points (..., 2n+1, n) -> (..., 2n+1, n) (see :func:`apply_rows`).
    """
    n = x.shape[-1]
    w = weights(n, kappa)
    X = f(sigma_points(x, P, kappa))
    xm, dX = mean_and_deviations(X, w, angles)
    Pm = weighted_outer(w, dX, dX) + Q
    return xm, 0.5 * (Pm + np.swapaxes(Pm, -1, -2))
