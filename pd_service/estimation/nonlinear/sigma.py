"""Sigma points, the one implementation: the scaled form (Julier 2002; van der Merwe 2004),
the symmetric kappa form (Julier 1997) as its special case, and the square-root derivative.

For a mean x (..., n) and covariance P = L L^T (L lower triangular)::

    lambda = alpha^2 (n + kappa) - n,         c = sqrt(n + lambda)
    chi_0 = x,   chi_i = x + c L[:, i-1],   chi_{n+i} = x - c L[:, i-1]      (i = 1..n)
    Wm_0 = lambda / (n + lambda)
    Wc_0 = lambda / (n + lambda) + (1 - alpha^2 + beta)
    Wm_i = Wc_i = 1 / (2 (n + lambda))                                      (i = 1..2n)

The default (alpha, beta, kappa) = (1, 2, 0) keeps every weight >= 0 (Wm_0 = 0, Wc_0 = 2),
which is robust with the tiny covariances of a well-observed robot; alpha << 1 (e.g. 1e-3)
gives a huge negative Wm_0 and loses digits. For a linear map every choice with
n + lambda > 0 reproduces the mean and covariance exactly.

The kappa form (:meth:`SigmaWeights.julier`, used by the IMM filters) is alpha = 1, beta = 0:
lambda = kappa, c = sqrt(n + kappa), Wm = Wc, W_0 = kappa / (n + kappa).

Sensitivities (the MIT rule, :mod:`.adaptive`) need d(chi)/dq, hence dL for a change dP of P.
From L L^T = P:  dP = dL L^T + L dL^T, so with X = L^{-1} dL (lower triangular)::

    L^{-1} dP L^{-T} = X + X^T   =>   X = Phi(L^{-1} dP L^{-T}),   dL = L X

where Phi keeps the strictly lower triangle and halves the diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class SigmaWeights:
    """Weights of the 2n + 1 scaled sigma points. Shapes: Wm (2n+1,), Wc (2n+1,)."""

    n: int
    alpha: float
    beta: float
    kappa: float
    c: float  # spread factor sqrt(n + lambda)
    Wm: Array
    Wc: Array

    @classmethod
    def make(cls, n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaWeights:
        """Weights for dimension n; ValueError if the parameters give n + lambda <= 0."""
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"n: expected a positive integer, got {n!r}")
        for name, v in (("alpha", alpha), ("beta", beta), ("kappa", kappa)):
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        if alpha <= 0:
            raise ValueError(f"alpha: must be > 0, got {alpha}")
        n_lam = alpha**2 * (n + kappa)  # n + lambda
        lam = kappa if alpha == 1.0 else n_lam - n
        if n_lam <= 0:
            raise ValueError(f"kappa: n + lambda = alpha^2 (n + kappa) must be > 0, got {n_lam}")
        w = 1.0 / (2.0 * n_lam)
        Wm = np.full(2 * n + 1, w)
        Wc = np.full(2 * n + 1, w)
        Wm[0] = lam / n_lam
        Wc[0] = lam / n_lam + (1.0 - alpha**2 + beta)
        for arr in (Wm, Wc):
            arr.setflags(write=False)
        return cls(n, float(alpha), float(beta), float(kappa), float(np.sqrt(n_lam)), Wm, Wc)

    @staticmethod
    @lru_cache(maxsize=64)
    def julier(n: int, kappa: float) -> SigmaWeights:
        """The symmetric kappa form: :meth:`make` with alpha = 1, beta = 0 (n + kappa > 0)."""
        return SigmaWeights.make(n, alpha=1.0, beta=0.0, kappa=kappa)

    def points(self, x: Array, L: Array) -> Array:
        """Sigma points (..., 2n+1, n) around means x (..., n) with square roots L (..., n, n):
        chi_0 = x, chi_i = x + c L[:, i-1], chi_{n+i} = x - c L[:, i-1]."""
        cL = self.c * np.swapaxes(L, -1, -2)  # rows are c L[:, i]
        xe = x[..., None, :]
        return np.concatenate((xe, xe + cL, xe - cL), axis=-2)

    def point_offsets(self, dx: Array, dL: Array) -> Array:
        """Derivatives of the sigma points, (p, 2n+1, n), for dx (p, n) and dL (p, n, n)."""
        cL = self.c * np.swapaxes(dL, 1, 2)
        return np.concatenate((dx[:, None, :], dx[:, None, :] + cL, dx[:, None, :] - cL), axis=1)


def sqrt_cov(P: Array) -> Array:
    """Lower-triangular L (..., n, n) with L L^T = P (Cholesky), for P (..., n, n).

    A covariance that rounding made slightly indefinite (or a zero-variance direction) gets a
    symmetric square root of its eigenvalue-clipped version instead (still L L^T ~= P, no
    longer triangular; in a batch, every matrix of the batch); this keeps the filter alive,
    but the sensitivity formula assumes a Cholesky factor, so it is then only approximate
    for that step.
    """
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, -1, -2)))
        w = np.clip(w, 0.0, None)
        L = (V * np.sqrt(w)[..., None, :]) @ np.swapaxes(V, -1, -2)
    return np.asarray(L, dtype=np.float64)


def cholesky_derivative(L: Array, dP: Array) -> Array:
    """dL (p, n, n) for dP (p, n, n) symmetric, given L (n, n) lower triangular.

        dL = L Phi(L^{-1} dP L^{-T})

    A singular L (a state known exactly) has no unique dL: the zero pivots use the
    pseudo-inverse, which drops the undefined part.
    """
    n = L.shape[0]
    try:
        Linv = np.linalg.solve(L, np.eye(n))  # L is small (n <= 64): an explicit inverse is fine
    except np.linalg.LinAlgError:
        Linv = np.linalg.pinv(L)
    M = Linv @ dP @ Linv.T  # (p, n, n)
    X = np.tril(M, -1) + 0.5 * np.eye(n) * np.diagonal(M, axis1=1, axis2=2)[:, None, :]
    return L @ X
