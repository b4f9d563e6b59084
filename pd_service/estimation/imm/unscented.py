"""Symmetric sigma points (Julier's kappa form) and unscented moments, batched.

For x (..., n), P (..., n, n) and scaling kappa (> -n)::

    L L^T = (n + kappa) P                                   (Cholesky)
    chi_0 = x,  chi_i = x + L[:, i-1],  chi_{n+i} = x - L[:, i-1],   i = 1..n
    W_0 = kappa / (n + kappa),  W_i = 1 / (2 (n + kappa))

Angle components of transformed points are averaged on the circle and their deviations
wrapped, so a cloud straddling +-pi is handled (a plain average of -179 deg and +179 deg
would give 0 deg).
"""

from __future__ import annotations

import numpy as np

from ..nonlinear.registry import wrap_angle


def is_vectorized(model: object) -> bool:
    """True if a model's f / h accepts a batch of rows (registry flag ``vectorized``, or a
    ``vectorized`` attribute on the function itself for registries without the flag)."""
    if getattr(model, "vectorized", False):
        return True
    fn = getattr(model, "f", None) or getattr(model, "h", None)
    return bool(getattr(fn, "vectorized", False))


def apply_rows(fn, X: np.ndarray, vectorized: bool) -> np.ndarray:
    """fn over the last axis of X (..., n) -> (..., m): one call on the (N, n) rows if
    ``vectorized``, else row by row."""
    rows = X.reshape(-1, X.shape[-1])
    out = fn(rows) if vectorized else np.stack([np.asarray(fn(r), dtype=float) for r in rows])
    return np.asarray(out, dtype=float).reshape(*X.shape[:-1], -1)


def weights(n: int, kappa: float) -> np.ndarray:
    """Weights (2n+1,) summing to 1."""
    lam = n + kappa
    if lam <= 0.0:
        raise ValueError(f"kappa: n + kappa must be > 0, got n={n}, kappa={kappa}")
    w = np.full(2 * n + 1, 1.0 / (2.0 * lam))
    w[0] = kappa / lam
    return w


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    """A square root L (L L^T = P) of a batch of symmetric PSD matrices."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        # Not numerically positive definite (e.g. a zero-variance direction): symmetric root.
        vals, vecs = np.linalg.eigh(P)
        return vecs * np.sqrt(np.clip(vals, 0.0, None))[..., None, :]


def sigma_points(x: np.ndarray, P: np.ndarray, kappa: float) -> np.ndarray:
    """Sigma points (..., 2n+1, n) of N(x, P)."""
    n = x.shape[-1]
    L = _sqrt_psd((n + kappa) * P)
    cols = np.swapaxes(L, -1, -2)  # (..., n, n): row i is column i of L
    xe = x[..., None, :]
    return np.concatenate([xe, xe + cols, xe - cols], axis=-2)


def mean_and_deviations(
    Z: np.ndarray, w: np.ndarray, angles: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray]:
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


def weighted_outer(w: np.ndarray, dA: np.ndarray, dB: np.ndarray) -> np.ndarray:
    """sum_i W_i dA_i dB_i^T: (..., a, b) from deviations (..., 2n+1, a), (..., 2n+1, b)."""
    return np.einsum("i,...ia,...ib->...ab", w, dA, dB)


def unscented_propagate(
    f, x: np.ndarray, P: np.ndarray, Q: np.ndarray, kappa: float, angles: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray]:
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
