"""Exact discretisation of a continuous-time linear model over any interval (Van Loan 1978).

Continuous model (t in seconds, u held constant over the interval)::

    dx = (F x + G u) dt + dw,      E[dw dw^T] = Qc dt

Over an interval tau (seconds)::

    x(t + tau) = A(tau) x(t) + B(tau) u + w,     w ~ N(0, Q(tau))
    A(tau) = e^{F tau},   B(tau) = int_0^tau e^{F s} ds G,   Q(tau) = int_0^tau e^{F s} Qc e^{F^T s} ds

computed from two block matrix exponentials (Van Loan, "Computing integrals involving the
matrix exponential", IEEE TAC 23(3), 1978)::

    expm([[F, G], [0, 0]] tau)      = [[A, B], [0, I]]
    expm([[-F, Qc], [0, F^T]] tau)  = [[., E12], [0, E22]],   A = E22^T,   Q = A E12

Pure numpy (no SciPy): the exponential by scaling and squaring of a Taylor series.
"""

from __future__ import annotations

import math

import numpy as np

#: Terms of the Taylor series after scaling to norm <= 1/2: the remainder is below
#: 0.5^19 / 19! ~ 1e-23, far under float64 rounding.
_TERMS = 18


def expm(M: np.ndarray) -> np.ndarray:
    """e^M of a square matrix M (k, k): e^M = (e^{M / 2^s})^{2^s}, the inner exponential by
    its Taylor series, s chosen so that ||M / 2^s||_1 <= 1/2."""
    norm = float(np.abs(M).sum(axis=0).max()) if M.size else 0.0
    s = max(0, math.ceil(math.log2(norm / 0.5))) if norm > 0.5 else 0
    X = M / (2.0**s)
    E = np.eye(M.shape[0])
    term = np.eye(M.shape[0])
    for k in range(1, _TERMS + 1):
        term = term @ X / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


def van_loan(F: np.ndarray, G: np.ndarray, Qc: np.ndarray,
             tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (n, n), B (n, nu), Q (n, n)) of the continuous model (F (n, n), G (n, nu), Qc (n, n))
    over ``tau`` seconds (>= 0); Q made exactly symmetric."""
    n, nu = F.shape[0], G.shape[1]
    top = np.zeros((n + nu, n + nu))
    top[:n, :n] = F
    top[:n, n:] = G
    AB = expm(top * tau)
    vl = np.zeros((2 * n, 2 * n))
    vl[:n, :n] = -F
    vl[:n, n:] = Qc
    vl[n:, n:] = F.T
    E = expm(vl * tau)
    A = np.ascontiguousarray(E[n:, n:].T)
    Q = A @ E[:n, n:]
    Q = 0.5 * (Q + Q.T)
    return A, np.ascontiguousarray(AB[:n, n:]), Q


#: A model is evaluated by its Taylor polynomials (:class:`Taylor`) when ||F||_1 * period <=
#: this: the remainder of _TERMS terms is then below 0.5^19 / 19!.
TAYLOR_NORM = 0.5


class Taylor:
    """A(tau), B(tau), Q(tau) as polynomials in tau, for 0 <= tau with ||F tau||_1 <= 1/2:
    each a single product of the powers [tau, tau^2, ..., tau^(K+1)] with precomputed
    coefficients, no exponential per interval::

        A(tau) = I + sum_k F^k tau^k / k!                  (k = 1..K)
        B(tau) = sum_k F^k G tau^(k+1) / (k+1)!            (k = 0..K)
        Q(tau) = sum_k C_k tau^(k+1) / (k+1)!,   C_0 = Qc,  C_k = F C_(k-1) + C_(k-1) F^T

    (the derivatives at 0 of dA/dt = F A, dB/dt = F B (B' (0) = G), dQ/dt = F Q + Q F^T + Qc).
    For a nilpotent F (constant velocity, double integrators) the sums are finite: exact.
    Shapes: ``coef`` (k, n*n + n*nu + n*n), k <= K+1 (its trailing rows of zeros dropped),
    row j multiplying tau^(j+1), A's identity added apart."""

    def __init__(self, F: np.ndarray, G: np.ndarray, Qc: np.ndarray) -> None:
        n, nu = F.shape[0], G.shape[1]
        self.n, self.nu = n, nu
        K = _TERMS
        coef = np.zeros((K + 1, 2 * n * n + n * nu))
        Fk = np.eye(n)  # F^k
        C = Qc.copy()  # C_k
        fact = 1.0  # (k+1)!
        for k in range(K + 1):
            fact *= k + 1
            Fk1 = Fk @ F  # F^(k+1): tau^(k+1) / (k+1)! in A
            coef[k, : n * n] = (Fk1 / fact).ravel()
            coef[k, n * n : n * n + n * nu] = (Fk @ G / fact).ravel()
            coef[k, n * n + n * nu :] = (C / fact).ravel()
            C = F @ C + C @ F.T
            Fk = Fk1
        # rows that are all zero add nothing (a nilpotent F: a few rows): dropped
        nz = np.flatnonzero(np.any(coef != 0.0, axis=1))
        self.coef = np.ascontiguousarray(coef[: int(nz[-1]) + 1 if nz.size else 1])
        self._eye = np.eye(n)

    def at(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A (n, n), B (n, nu), Q (n, n)) over ``tau`` seconds; Q made exactly symmetric."""
        n, nu = self.n, self.nu
        p = np.cumprod(np.full(self.coef.shape[0], tau))  # tau, tau^2, ...
        v = p.dot(self.coef)
        A = v[: n * n].reshape(n, n) + self._eye
        B = v[n * n : n * n + n * nu].reshape(n, nu)
        Q = v[n * n + n * nu :].reshape(n, n)
        return A, B, 0.5 * (Q + Q.T)
