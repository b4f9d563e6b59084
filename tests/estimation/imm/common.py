"""Small builders shared by the IMM tests."""

from __future__ import annotations

import numpy as np

from pd_service.estimation.imm import ImmFilter, position, range_bearing
from pd_service.estimation.imm.models import cv_transition
from pd_service.estimation.nonlinear.registry import make_model

T = 0.1


def cv(**kw):
    return make_model("imm_cv", period_s=T, **kw)


def ct(**kw):
    return make_model("imm_ct", period_s=T, **kw)


def cv_matrix() -> np.ndarray:
    """The CV map is linear: its matrix, column by column."""
    return np.stack([cv_transition(e, T) for e in np.eye(5)], axis=1)


SIGMA_BEARING = float(np.radians(3.5))


def stations(sigma_range=0.3, sigma_bearing=SIGMA_BEARING):
    pts = [(9.5, -8.5), (25.1, 18.5), (-6.1, 18.5)]
    return [range_bearing(f"st{i + 1}", p, sigma_range, sigma_bearing) for i, p in enumerate(pts)]


def position_sensors():
    """Three linear sensors with different, correlated noise."""
    R1 = np.array([[0.5, 0.1], [0.1, 0.3]])
    R2 = np.array([[0.2, -0.05], [-0.05, 0.8]])
    R3 = np.array([[1.0, 0.0], [0.0, 0.4]])
    return [position("p1", R=R1), position("p2", R=R2), position("p3", R=R3)]


H_POS = np.array([[1.0, 0, 0, 0, 0], [0, 0, 1.0, 0, 0]])


def prior(seed=0, spread=1.0):
    """A generic prior N(x, P) on [xi, xi_dot, eta, eta_dot, omega] with correlations."""
    rng = np.random.default_rng(seed)
    x = np.array([3.0, 0.3, -2.0, 0.1, 0.05])
    A = rng.standard_normal((5, 5)) * np.array([0.8, 0.05, 0.8, 0.05, 0.02]) * spread
    P = A @ A.T + np.diag([0.05, 1e-3, 0.05, 1e-3, 1e-4])
    return x, P


def imm(modes, sensors, variant="imm2", node=0, p_stay=0.95):
    r = len(modes)
    Pi = np.full((r, r), (1 - p_stay) / max(r - 1, 1)) if r > 1 else np.ones((1, 1))
    if r > 1:
        np.fill_diagonal(Pi, p_stay)
    return ImmFilter(modes, Pi, sensors, variant=variant, node=node)
