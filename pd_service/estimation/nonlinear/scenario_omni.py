"""The issue's omni-robot scenario as a seeded simulator (the "simulated robot" side).

Three-wheel omnidirectional robot (:mod:`.models_omni`), step 0.01 s, 20 s; wheel torques
follow a smooth open-loop profile (:func:`omni_torque`); the true process noise is
Q0 = diag(1e-14, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5) until t = 10 s and 100 Q0 after; the pose
(x, y, theta) is measured every step with R = 1e-8 I. Optional per-packet delays and loss
make the same run usable for the delayed, lossy path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .models_omni import OMNI_Q0, omni3
from .registry import wrap_angle

PERIOD_S = 0.01
DURATION_S = 20.0
JUMP_S = 10.0
JUMP_FACTOR = 100.0
R_POSE = 1e-8
X0 = np.zeros(6)
#: Filter prior: the true start is known to about 1 cm / 0.01 rad / 1 cm/s.
P0 = np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])


def omni_torque(k: int, period_s: float = PERIOD_S) -> np.ndarray:
    """Wheel torques (N m) at step k: a rotating three-phase drive (the robot runs loops of
    about 0.5 m/s) plus a slow common torque that turns the body back and forth."""
    t = k * period_s
    phase = 2.0 * np.pi * 0.1 * t + 2.0 * np.pi * np.arange(3) / 3.0
    return 0.25 * np.sin(phase) + 0.04 * np.sin(2.0 * np.pi * 0.05 * t)


def q_true(k: int, period_s: float = PERIOD_S, jump_s: float = JUMP_S,
           factor: float = JUMP_FACTOR) -> np.ndarray:
    """Diagonal of the true Q for the step k -> k+1."""
    q = np.array(OMNI_Q0)
    return q * factor if k * period_s >= jump_s else q


@dataclass
class OmniRun:
    """truth (K+1, 6) x(0..K); z (K+1, 3) pose samples; u (K+1, 3) torques u(k);
    q (K, 6) true Q diagonal of step k -> k+1; arrival (K+1,) step the sample arrives at,
    -1 if lost."""

    truth: np.ndarray
    z: np.ndarray
    u: np.ndarray
    q: np.ndarray
    arrival: np.ndarray

    @property
    def steps(self) -> int:
        return self.truth.shape[0] - 1


def simulate_omni(rng: np.random.Generator, duration_s: float = DURATION_S,
                  jump_s: float = JUMP_S, factor: float = JUMP_FACTOR, max_delay: int = 0,
                  loss: float = 0.0) -> OmniRun:
    """Simulate one seeded run. Each sample is delayed uniformly in [0, max_delay] steps and
    lost with probability ``loss``."""
    model = omni3()
    K = int(round(duration_s / PERIOD_S))
    x = X0.copy()
    truth = np.empty((K + 1, 6))
    z = np.empty((K + 1, 3))
    u = np.array([omni_torque(k) for k in range(K + 1)])
    q = np.array([q_true(k, PERIOD_S, jump_s, factor) for k in range(K)])
    for k in range(K + 1):
        truth[k] = x
        z[k] = x[:3] + np.sqrt(R_POSE) * rng.standard_normal(3)
        z[k, 2] = wrap_angle(z[k, 2])
        if k < K:
            x = model.f(x, u[k], k) + np.sqrt(q[k]) * rng.standard_normal(6)
    delay = rng.integers(0, max_delay + 1, K + 1) if max_delay else np.zeros(K + 1, int)
    lost = rng.random(K + 1) < loss if loss else np.zeros(K + 1, bool)
    arrival = np.where(lost, -1, np.arange(K + 1) + delay)
    return OmniRun(truth, z, u, q, arrival)


@dataclass
class Track:
    """Per-step results of one filter over one run: ``pos_err2`` (K+1,) squared position error
    of the filtered x(k) (m^2); ``theta_err`` (K+1,) wrapped heading error (rad); ``q`` (K+1, p)
    the adapted entries of Q after step k (the fixed ones for a plain UKF)."""

    pos_err2: np.ndarray
    theta_err: np.ndarray
    q: np.ndarray


def true_q_schedule(run: OmniRun):
    """Q(k) of the run, for ``UnscentedObserverPredictor(..., Q_schedule=...)``: the
    "true-Q UKF" oracle."""
    Qs = np.array([np.diag(q) for q in run.q])

    def Q_of(k: int) -> np.ndarray:
        return Qs[min(k, len(Qs) - 1)]

    return Q_of


def run_filter(op, run: OmniRun, indices=(3, 4, 5)) -> Track:
    """Drive an :class:`~.ukf.UnscentedObserverPredictor` (lead 0) through ``run``: at each
    step k the command u(k), the packets arriving at k, then ``predict(k)``."""
    K = run.steps
    by_arrival: dict[int, list[int]] = {}
    for s, a in enumerate(run.arrival):
        if a >= 0:
            by_arrival.setdefault(int(a), []).append(s)
    err2 = np.empty(K + 1)
    th = np.empty(K + 1)
    qs = np.empty((K + 1, len(indices)))
    idx = list(indices)
    for k in range(K + 1):
        op.add_command(k, run.u[k], now=k)
        for s in by_arrival.get(k, ()):
            op.add_measurement("pose", s, run.z[s], now=k)
        p = op.predict(k)
        err2[k] = float(np.sum((p.x[:2] - run.truth[k, :2]) ** 2))
        th[k] = float(wrap_angle(p.x[2] - run.truth[k, 2]))
        qs[k] = np.diag(op.Q)[idx]
    return Track(err2, th, qs)
