"""The paper's simulation example (Liang et al. 2017, Sec. 4): a vehicle (p1, v1) chases an
object in uniform motion (p2, v2); step d = 0.05 s::

    x = [p1, v1, p2, v2],  A = [[1 d 0 0] [0 1 0 0] [0 0 1 d] [0 0 0 1]],  B = [0 d 0 0]^T
    Q = diag(0, 0.01^2, 0, 0.01^2),   u(k) = 0.5 for 0 < k <= 80, else 0
    camera:  z = [p1, p2] + v0, every 2 steps, delay 10 steps
    ranger:  z = p2 - p1 + v1,  every step, delay 12 steps, only while |p2 - p1| <= 3
    uplink delay 10 steps;  x(0) = [0, 0, 5, 0.5],  initial estimate 0

Noise settings: "journal" (camera std 0.5, ranger 0.1) and "english" (0.3 / 0.2).

:func:`paper_scenario` is the scenario (simulated by :class:`~.simulator.ScenarioSim`, with
its SessionSpec); :func:`simulate_paper` runs it for a whole run at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pd_service.estimation.model import LinearModel, Sensor

from .simulator import Scenario, ScenarioSim, SensorDef

PERIOD_S = 0.05
CAMERA_DELAY, RANGER_DELAY, UPLINK_DELAY = 10, 12, 10
CAMERA_INTERVAL, RANGER_INTERVAL = 2, 1
RANGER_MAX_RANGE = 3.0
X0_TRUE = np.array([0.0, 0.0, 5.0, 0.5])
NOISE_STD = {"journal": (0.5, 0.1), "english": (0.3, 0.2)}
NOISE_SETTINGS = tuple(NOISE_STD)
#: Samples may arrive this many steps later than the nominal 12 (jitter on a real link).
PAPER_DELAY_SLACK = 4
DEFAULT_STEPS = 240


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


def _ranger_in_range(x: np.ndarray) -> bool:
    return bool(abs(x[2] - x[0]) <= RANGER_MAX_RANGE)


def _command(k: int) -> np.ndarray:
    return np.array([paper_command(k)])


def paper_scenario(noise: str = "journal") -> Scenario:
    """The scenario, ``noise`` journal|english; its session's max_delay is the ranger's 12
    steps plus PAPER_DELAY_SLACK."""
    if noise not in NOISE_STD:
        raise ValueError(f"noise: expected one of {', '.join(NOISE_STD)}, got {noise!r}")
    model = paper_model()
    sensors = {s.name: s for s in paper_sensors(noise)}
    cam_std, rng_std = NOISE_STD[noise]
    x0, P0 = paper_prior()
    return Scenario(
        name="paper",
        description=f"vehicle chasing an object (Liang et al. 2017), {noise} noise",
        period_s=PERIOD_S,
        A=np.array(model.A), B=np.array(model.B), Q=np.array(model.Q),
        sensors=(
            SensorDef("camera", np.array(sensors["camera"].H), cam_std * np.eye(2),
                      CAMERA_DELAY, CAMERA_INTERVAL),
            SensorDef("ranger", np.array(sensors["ranger"].H), rng_std * np.eye(1),
                      RANGER_DELAY, RANGER_INTERVAL, _ranger_in_range),
        ),
        x0_true=X0_TRUE.copy(), x0=x0, P0=P0,
        lead=UPLINK_DELAY, max_delay=RANGER_DELAY + PAPER_DELAY_SLACK,
        state_names=("p1", "v1", "p2", "v2"),
        command=_command,
        default_steps=DEFAULT_STEPS,
    )


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
    """Run :func:`paper_scenario` for ``steps`` steps with its own commands
    (:class:`~.simulator.ScenarioSim` seeded with ``rng``): the truth x(0..steps) and every
    sample, arriving after its sensor's nominal delay unless lost.

    The range finder reports only while |p2 - p1| <= 3 on the *simulated truth*; ``loss`` is
    an extra independent packet-loss probability for every sample.
    """
    sc = paper_scenario(noise)
    delay = {s.name: s.delay for s in sc.sensors}
    sim = ScenarioSim(sc, rng, loss=loss)
    truth = [sim.x.copy()]
    run = PaperRun(truth=np.empty(0))
    for k in range(steps + 1):
        run.samples += [Sample(d.sensor, d.step, d.z, None if d.lost else d.step + delay[d.sensor])
                        for d in sim.sample()]
        if k == steps:
            break
        truth.append(sim.advance(sc.command(k)).copy())
    run.truth = np.array(truth)
    return run
