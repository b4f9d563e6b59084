"""Textbook IMM with a Kalman update, written naively (loops, no batching, no shared code).

For linear measurements z = H x + v the UIF update is exactly the Kalman update, so an IMM-UIF
with such sensors must equal this reference. Prediction uses the same symmetric sigma points
(Julier, kappa) re-implemented here point by point.
"""

from __future__ import annotations

import math

import numpy as np


def ut_predict(f, x, P, Q, kappa):
    n = len(x)
    L = np.linalg.cholesky((n + kappa) * P)
    pts = [x] + [x + L[:, i] for i in range(n)] + [x - L[:, i] for i in range(n)]
    w = [kappa / (n + kappa)] + [1.0 / (2 * (n + kappa))] * (2 * n)
    ys = [f(p) for p in pts]
    xm = sum(wi * yi for wi, yi in zip(w, ys, strict=True))
    Pm = Q.copy()
    for wi, yi in zip(w, ys, strict=True):
        d = yi - xm
        Pm = Pm + wi * np.outer(d, d)
    return xm, Pm


def gauss_logpdf(nu, S):
    m = len(nu)
    maha = nu @ np.linalg.solve(S, nu)
    return -0.5 * (maha + math.log(np.linalg.det(S)) + m * math.log(2 * math.pi))


def kf_update(x, P, Hs, Rs, zs):
    """Stacked Kalman update; returns x, P, joint loglik, list of marginal logliks."""
    H = np.vstack(Hs)
    R = np.zeros((H.shape[0], H.shape[0]))
    i = 0
    for Ri in Rs:
        k = Ri.shape[0]
        R[i:i + k, i:i + k] = Ri
        i += k
    z = np.concatenate(zs)
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    nu = z - H @ x
    marg = [gauss_logpdf(zi - Hi @ x, Hi @ P @ Hi.T + Ri)
            for Hi, Ri, zi in zip(Hs, Rs, zs, strict=True)]
    return x + K @ nu, P - K @ S @ K.T, gauss_logpdf(nu, S), marg


def imm_step(mu, xs, Ps, Pi, fs, Qs, Hs, Rs, zs, kappa, likelihood="joint"):
    """One IMM cycle; likelihood "joint" (centralised) or "product" (UIF-IMM 2)."""
    r = len(mu)
    cbar = [sum(Pi[i][j] * mu[i] for i in range(r)) for j in range(r)]
    new_x, new_P, logl = [], [], []
    for j in range(r):
        wts = [Pi[i][j] * mu[i] / cbar[j] for i in range(r)]
        x0 = sum(wts[i] * xs[i] for i in range(r))
        P0 = sum(wts[i] * (Ps[i] + np.outer(xs[i] - x0, xs[i] - x0)) for i in range(r))
        xp, Pp = ut_predict(fs[j], x0, P0, Qs[j], kappa)
        if Hs:
            xu, Pu, joint, marg = kf_update(xp, Pp, Hs, Rs, zs)
            logl.append(joint if likelihood == "joint" else sum(marg))
        else:
            xu, Pu = xp, Pp
            logl.append(0.0)
        new_x.append(xu)
        new_P.append(Pu)
    a = [math.log(cbar[j]) + logl[j] for j in range(r)]
    amax = max(a)
    e = [math.exp(v - amax) for v in a]
    mu = [v / sum(e) for v in e]
    return mu, new_x, new_P


def combine(mu, xs, Ps):
    x = sum(m * xi for m, xi in zip(mu, xs, strict=True))
    P = sum(m * (Pi + np.outer(xi - x, xi - x)) for m, xi, Pi in zip(mu, xs, Ps, strict=True))
    return x, P
