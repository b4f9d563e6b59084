"""The three-wheel omnidirectional robot (registered nonlinear model ``"omni3"`` of
:mod:`pd_service.estimation.nonlinear`: one RK4 step of 0.01 s, wheel torques held), 20 s::

    x = [x, y, theta, vx, vy, omega] (m, m, rad, m/s, m/s, rad/s),  u = wheel torques (N m)
    x(k+1) = f(x(k), u(k)) + w(k),  w ~ N(0, diag q(k)),
    q(k) = Q0 = (1e-14, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5) for t < 10 s, 100 Q0 after
    pose:     z = [x, y, theta] + v (theta wrapped),  every step, delay 3, R = 1e-8 I
    lead 10 (uplink 0.1 s), max_delay 8;  commands: omni_torque(k)

Its session runs the unscented observer-predictor (model kind "unscented", model "omni3")
with MIT-rule adaptation of Q's velocity-channel entries (indices 3, 4, 5), starting from
the nominal Q0: the adapter must find the x100 jump by itself.

:func:`omni_scenario` is the scenario (simulated by :class:`~.simulator.ScenarioSim`, with
its SessionSpec); :func:`simulate_omni` runs it for a whole run at once, with optional
per-packet delays and loss for the delayed, lossy path.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from pd_service.estimation.nonlinear import make_model
from pd_service.estimation.nonlinear.models_omni import OMNI_ACCEL_CHANNELS, OMNI_Q0
from pd_service.wire import UnscentedModelSpec
from pd_service.wire.messages import AdaptSpec

from .simulator import Scenario, ScenarioSim, SensorDef

PERIOD_S = 0.01
DURATION_S = 20.0
JUMP_S = 10.0
JUMP_FACTOR = 100.0
R_POSE = 1e-8
X0 = np.zeros(6)
#: Filter prior: the true start is known to about 1 cm / 0.01 rad / 1 cm/s.
P0 = np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])
#: Parameters of the registered model "omni3" (the robot), as sent in the spec.
OMNI_PARAMS: dict[str, float] = {
    "period_s": PERIOD_S, "mass": 10.0, "inertia": 0.25, "wheel_inertia": 0.01,
    "wheel_radius": 0.05, "wheel_distance": 0.2, "friction": 0.02,
}
OMNI_LEAD = 10  # steps (uplink 0.1 s)
OMNI_POSE_DELAY = 3  # steps, nominal downlink delay of the pose samples
OMNI_MAX_DELAY = 8  # steps: the pose delay plus 50 ms of jitter


def omni_torque(k: int, period_s: float = PERIOD_S) -> np.ndarray:
    """Wheel torques (N m) at step k: a rotating three-phase drive (the robot runs loops of
    about 0.5 m/s) plus a slow common torque that turns the body back and forth."""
    t = k * period_s
    phase = 2.0 * np.pi * 0.1 * t + 2.0 * np.pi * np.arange(3) / 3.0
    return 0.25 * np.sin(phase) + 0.04 * np.sin(2.0 * np.pi * 0.05 * t)


def q_true(k: int, period_s: float = PERIOD_S, jump_s: float = JUMP_S,
           factor: float = JUMP_FACTOR) -> np.ndarray:
    """Diagonal of the true Q for the step k -> k+1: Q0, x ``factor`` from ``jump_s``."""
    q = np.array(OMNI_Q0)
    return q * factor if k * period_s >= jump_s else q


def omni_scenario(jump_s: float = JUMP_S, factor: float = JUMP_FACTOR) -> Scenario:
    """The scenario (see the module docstring); the true Q jumps x ``factor`` at ``jump_s``
    (model time, s)."""
    model = make_model("omni3", **OMNI_PARAMS)
    pose = model.sensors["pose"]
    wire_model = UnscentedModelSpec(
        model="omni3",
        params={**OMNI_PARAMS, "Q": [float(q) for q in OMNI_Q0]},
        adapt=AdaptSpec(method="mit", indices=list(OMNI_ACCEL_CHANNELS)),
    )
    return Scenario(
        name="omni",
        description="three-wheel omnidirectional robot, wheel torques, Q x100 at 10 s; "
                    "adaptive UKF",
        period_s=PERIOD_S,
        Q=np.diag(OMNI_Q0),
        nonlinear=model,
        model_spec=wire_model,
        Q_of=partial(q_true, period_s=PERIOD_S, jump_s=jump_s, factor=factor),
        sensors=(
            SensorDef("pose", None, math.sqrt(R_POSE) * np.eye(3), delay=OMNI_POSE_DELAY,
                      interval=1, kind="model", h=pose.h, angles=pose.angles),
        ),
        x0_true=X0.copy(), x0=np.zeros(6), P0=P0.copy(),
        lead=OMNI_LEAD, max_delay=OMNI_MAX_DELAY,
        state_names=("x", "y", "theta", "vx", "vy", "omega"),
        command=omni_torque,
        default_steps=int(round(DURATION_S / PERIOD_S)),
        angles=model.angles,
        loss_draw=False,
    )


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
    """Run :func:`omni_scenario` for ``duration_s`` with its own torques
    (:class:`~.simulator.ScenarioSim` seeded with ``rng``). After the run, each sample is
    given a delay uniform in [0, max_delay] steps and lost with probability ``loss`` (drawn
    from the same ``rng``)."""
    sc = omni_scenario(jump_s, factor)
    assert sc.Q_of is not None
    K = int(round(duration_s / PERIOD_S))
    sim = ScenarioSim(sc, rng)
    truth = np.empty((K + 1, 6))
    z = np.empty((K + 1, 3))
    u = np.array([sc.command(k) for k in range(K + 1)])
    q = np.array([sc.Q_of(k) for k in range(K)])
    for k in range(K + 1):
        truth[k] = sim.x
        (pose,) = sim.sample()
        z[k] = pose.z
        if k < K:
            sim.advance(u[k])
    delay = rng.integers(0, max_delay + 1, K + 1) if max_delay else np.zeros(K + 1, int)
    lost = rng.random(K + 1) < loss if loss else np.zeros(K + 1, bool)
    arrival = np.where(lost, -1, np.arange(K + 1) + delay)
    return OmniRun(truth, z, u, q, arrival)


def true_q_schedule(run: OmniRun) -> Callable[[int], np.ndarray]:
    """Q(k) (6, 6) of the run, for ``UnscentedObserverPredictor(..., Q_schedule=...)``: the
    "true-Q UKF" oracle."""
    Qs = np.array([np.diag(q) for q in run.q])

    def Q_of(k: int) -> np.ndarray:
        return Qs[min(k, len(Qs) - 1)]

    return Q_of
