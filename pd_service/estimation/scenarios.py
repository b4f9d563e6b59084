"""The paper's simulation example (Liang et al. 2017, Sec. 4), as data and a seeded simulator.

A vehicle (p1, v1) chases an object in uniform motion (p2, v2); step d = 0.05 s::

    x = [p1, v1, p2, v2],  A = [[1 d 0 0] [0 1 0 0] [0 0 1 d] [0 0 0 1]],  B = [0 d 0 0]^T
    Q = diag(0, 0.01^2, 0, 0.01^2),   u(k) = 0.5 for 0 < k <= 80, else 0
    camera:  z = [p1, p2] + v0, every 2 steps, delay 10 steps
    ranger:  z = p2 - p1 + v1,  every step, delay 12 steps, only while |p2 - p1| <= 3
    uplink delay 10 steps;  x(0) = [0, 0, 5, 0.5],  initial estimate 0

Noise settings: "journal" (camera std 0.5, ranger 0.1) and "english" (0.3 / 0.2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .model import LinearModel, Sensor

PERIOD_S = 0.05
CAMERA_DELAY, RANGER_DELAY, UPLINK_DELAY = 10, 12, 10
CAMERA_INTERVAL, RANGER_INTERVAL = 2, 1
RANGER_MAX_RANGE = 3.0
X0_TRUE = np.array([0.0, 0.0, 5.0, 0.5])
NOISE_STD = {"journal": (0.5, 0.1), "english": (0.3, 0.2)}


def paper_model(period_s: float = PERIOD_S) -> LinearModel:
    d = period_s
    A = np.array([[1, d, 0, 0], [0, 1, 0, 0], [0, 0, 1, d], [0, 0, 0, 1]], dtype=float)
    B = np.array([[0.0], [d], [0.0], [0.0]])
    Q = np.diag([0.0, 0.01**2, 0.0, 0.01**2])
    return LinearModel(A=A, B=B, Q=Q)


def paper_sensors(noise: str = "journal") -> list[Sensor]:
    cam_std, rng_std = NOISE_STD[noise]
    return [
        Sensor(name="camera", H=np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]]),
               R=cam_std**2 * np.eye(2)),
        Sensor(name="ranger", H=np.array([[-1.0, 0, 1.0, 0]]), R=np.array([[rng_std**2]])),
    ]


def paper_command(k: int) -> float:
    """The operator's acceleration command at step k: 0.5 for 0 < k <= 80, else 0."""
    return 0.5 if 0 < k <= 80 else 0.0


def paper_prior() -> tuple[np.ndarray, np.ndarray]:
    """Initial estimate 0 with a broad covariance (the paper's P(0) = p I, 'p large')."""
    return np.zeros(4), np.diag([1.0, 1.0, 30.0, 1.0])


@dataclass
class Sample:
    """One sensor sample: taken at ``step``, arriving at ``arrival`` (None if lost)."""

    sensor: str
    step: int
    z: np.ndarray
    arrival: int | None


@dataclass
class PaperRun:
    truth: np.ndarray  # (steps + 1, 4): x(0) .. x(steps)
    samples: list[Sample] = field(default_factory=list)


def simulate_paper(steps: int, rng: np.random.Generator, noise: str = "journal",
                   loss: float = 0.0) -> PaperRun:
    """Simulate the paper's example for ``steps`` steps with seeded noise.

    The range finder reports only while |p2 - p1| <= 3 on the *simulated truth*; ``loss`` is
    an extra independent packet-loss probability for every sample.
    """
    model = paper_model()
    sensors = {s.name: s for s in paper_sensors(noise)}
    cam_std, rng_std = NOISE_STD[noise]
    x = X0_TRUE.copy()
    truth = [x.copy()]
    run = PaperRun(truth=np.empty(0))
    qstd = np.sqrt(np.diag(model.Q))
    for k in range(steps + 1):
        if k % CAMERA_INTERVAL == 0:
            z = sensors["camera"].H @ x + cam_std * rng.standard_normal(2)
            lost = rng.random() < loss
            run.samples.append(Sample("camera", k, z, None if lost else k + CAMERA_DELAY))
        if abs(x[2] - x[0]) <= RANGER_MAX_RANGE:
            z = sensors["ranger"].H @ x + rng_std * rng.standard_normal(1)
            lost = rng.random() < loss
            run.samples.append(Sample("ranger", k, z, None if lost else k + RANGER_DELAY))
        if k == steps:
            break
        x = model.A @ x + model.B[:, 0] * paper_command(k) + qstd * rng.standard_normal(4)
        truth.append(x.copy())
    run.truth = np.array(truth)
    return run
