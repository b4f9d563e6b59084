"""IMM interaction, mode-probability update and output combination (Blom and Bar-Shalom 1988).

Shapes: mode probabilities mu (..., r), per-mode means x (..., r, n) and covariances
P (..., r, n, n); transition Pi (r, r) with Pi[i, j] = P(mode j at k | mode i at k-1).
"""

from __future__ import annotations

import numpy as np


def check_transition(Pi: object, r: int) -> np.ndarray:
    """Validate a row-stochastic (r, r) transition matrix; ValueError otherwise."""
    try:
        arr = np.array(Pi, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"transition: not a numeric matrix ({exc})") from None
    if arr.shape != (r, r):
        raise ValueError(f"transition: expected shape ({r}, {r}), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0.0):
        raise ValueError("transition: entries must be finite and >= 0")
    if np.max(np.abs(arr.sum(axis=1) - 1.0)) > 1e-9:
        raise ValueError("transition: every row must sum to 1")
    arr = arr / arr.sum(axis=1, keepdims=True)
    arr.setflags(write=False)
    return arr


def mix(
    mu: np.ndarray, x: np.ndarray, P: np.ndarray, Pi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interaction step. Returns (cbar (..., r), x0 (..., r, n), P0 (..., r, n, n))::

        cbar_j    = sum_i Pi_ij mu_i                         predicted mode probability
        mu_{i|j}  = Pi_ij mu_i / cbar_j                      mixing weights
        x0_j      = sum_i mu_{i|j} x_i
        P0_j      = sum_i mu_{i|j} [P_i + (x_i - x0_j)(x_i - x0_j)^T]

    A mode that no mode can reach (cbar_j = 0) keeps its own estimate (mu_{j|j} = 1).
    """
    cbar = np.einsum("...i,ij->...j", mu, Pi)
    num = mu[..., :, None] * Pi  # (..., i, j)
    dead = cbar <= 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        wts = num / np.where(dead, 1.0, cbar)[..., None, :]
    if np.any(dead):
        eye = np.broadcast_to(np.eye(Pi.shape[0]), wts.shape)
        wts = np.where(dead[..., None, :], eye, wts)
    x0 = np.einsum("...ij,...in->...jn", wts, x)
    d = x[..., :, None, :] - x0[..., None, :, :]  # (..., i, j, n)
    P0 = np.einsum("...ij,...inm->...jnm", wts, P) + np.einsum(
        "...ij,...ijn,...ijm->...jnm", wts, d, d
    )
    return cbar, x0, 0.5 * (P0 + np.swapaxes(P0, -1, -2))


def posterior_probabilities(cbar: np.ndarray, loglik: np.ndarray) -> np.ndarray:
    """mu_j = cbar_j Lambda_j / sum_l cbar_l Lambda_l, in log space (no underflow)::

        log mu_j = log cbar_j + log Lambda_j - logsumexp_l(log cbar_l + log Lambda_l)
    """
    with np.errstate(divide="ignore"):
        a = np.log(cbar) + loglik
    amax = np.max(a, axis=-1, keepdims=True)
    if not np.all(np.isfinite(amax)):
        raise FloatingPointError("mode likelihoods: no mode has a finite posterior weight")
    e = np.exp(a - amax)
    return e / e.sum(axis=-1, keepdims=True)


def combine(mu: np.ndarray, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Output moments of the mixture::

    x = sum_j mu_j x_j,   P = sum_j mu_j [P_j + (x_j - x)(x_j - x)^T]
    """
    xc = np.einsum("...j,...jn->...n", mu, x)
    d = x - xc[..., None, :]
    Pc = np.einsum("...j,...jnm->...nm", mu, P) + np.einsum("...j,...jn,...jm->...nm", mu, d, d)
    return xc, 0.5 * (Pc + np.swapaxes(Pc, -1, -2))
