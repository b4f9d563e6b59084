"""Scenarios for the simulated robot: model, sensors, command profile and a seeded simulator.

- ``paper``: the vehicle chasing an object of Liang et al. 2017 (Sec. 4), built from
  :mod:`pd_service.estimation.scenarios`; noise settings ``journal`` (camera std 0.5, range
  finder 0.1) and ``english`` (0.3 / 0.2).
- ``maneuver``: a 2-D robot driving straight legs and turns, with a linear
  constant-velocity model the linear service can track exactly::

      x = [px, py, vx, vy],  u = [ax, ay] (m/s^2),  d = step period (s)
      A = [[I, d I], [0, I]],  B = [[d^2/2 I], [d I]],  w = B a,  a ~ N(0, sigma_a^2 I)
      gnss:     z = [px, py] + v,  every 4 steps, delay 8, std 0.2 m
      odometry: z = [vx, vy] + v,  every step,    delay 3, std 0.05 m/s
      lead 6 (uplink 0.3 s)

  The robot rests for 20 steps (so that the first commands, which apply from step lead
  on, are all delivered), accelerates along +x for 40 steps to 0.5 m/s, then repeats a
  pattern of legs and turns. A turn is open-loop centripetal acceleration: with nominal
  speed s and heading theta(k), u(k) = s ([cos, sin](theta(k) + omega d) -
  [cos, sin](theta(k))) / d, which rotates the nominal velocity by omega d per step
  exactly.
- ``omni``: the three-wheel omnidirectional robot of issue 9, stepped by the registered
  nonlinear model ``"omni3"`` of :mod:`pd_service.estimation.nonlinear` (one RK4 step of
  0.01 s, wheel torques held), built from
  :mod:`pd_service.estimation.nonlinear.scenario_omni`::

      x = [x, y, theta, vx, vy, omega] (m, m, rad, m/s, m/s, rad/s),  u = wheel torques (N m)
      x(k+1) = f(x(k), u(k)) + w(k),  w ~ N(0, diag q(k)),
      q(k) = Q0 = (1e-14, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5) for t < 10 s, 100 Q0 after
      pose:     z = [x, y, theta] + v (theta wrapped),  every step, delay 3, R = 1e-8 I
      lead 10 (uplink 0.1 s), max_delay 8;  commands: scenario_omni.omni_torque(k)

  Its session runs the unscented observer-predictor (model kind "unscented", model
  "omni3") with MIT-rule adaptation of Q's velocity-channel entries (indices 3, 4, 5),
  starting from the nominal Q0: the adapter must find the x100 jump by itself.

Simulators draw the noise of every sensor at every sample (even of sensors a session does
not use), so sessions given different sensor subsets of one run see the same truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from pd_service.estimation import scenarios as paper
from pd_service.estimation.nonlinear import NonlinearModel, make_model, wrap_angle
from pd_service.estimation.nonlinear import scenario_omni as omni
from pd_service.estimation.nonlinear.models_omni import OMNI_ACCEL_CHANNELS, OMNI_Q0
from pd_service.wire import LinearModelSpec, SensorSpec, SessionSpec, UnscentedModelSpec
from pd_service.wire.messages import AdaptSpec

NOISE_SETTINGS = tuple(paper.NOISE_STD)


@dataclass(frozen=True, eq=False)
class SensorDef:
    """One simulated sensor: z = H x + L v (``kind`` "linear") or z = h(x) + L v (``kind``
    "model": h is the nonlinear model's sensor of this name, ``H`` is None), v ~ N(0, I);
    R = L L^T. ``angles``: indices of z wrapped to [-pi, pi) after the noise is added.

    ``available(x)``: whether the sensor reports for the true state x (e.g. a range limit).
    """

    name: str
    H: np.ndarray | None
    L: np.ndarray
    delay: int
    interval: int
    available: Callable[[np.ndarray], bool] | None = None
    kind: str = "linear"
    h: Callable[[np.ndarray], np.ndarray] | None = None
    angles: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.kind == "linear" and self.H is None:
            raise ValueError(f"sensor {self.name!r}: a linear sensor needs H")
        if self.kind == "model" and self.h is None:
            raise ValueError(f"sensor {self.name!r}: a model sensor needs h")

    @property
    def R(self) -> np.ndarray:
        return self.L @ self.L.T

    @property
    def m(self) -> int:
        return int(self.L.shape[0])

    def measure(self, x: np.ndarray) -> np.ndarray:
        """The noise-free measurement of x: H x or h(x), (m,)."""
        if self.h is not None:
            return np.asarray(self.h(x), dtype=np.float64)
        assert self.H is not None
        return self.H @ x

    def wire(self) -> SensorSpec:
        """This sensor's SensorSpec."""
        if self.kind == "linear":
            return SensorSpec(name=self.name, H=self.H, R=self.R, delay=self.delay,
                              interval=self.interval)
        return SensorSpec(kind=self.kind, name=self.name, R=self.R, delay=self.delay,
                          interval=self.interval)


@dataclass(frozen=True, eq=False, kw_only=True)
class Scenario:
    """A simulated robot, linear or nonlinear.

    Linear (``A``, ``B`` given): x(k+1) = A x(k) + B u(k) + w(k), w = G e (e ~ N(0, I)), or
    w = sqrt(diag Q) * e when ``G`` is None (Q diagonal).

    Nonlinear (``nonlinear`` given, ``A`` = ``B`` = None): x(k+1) = f(x(k), u(k), k) + w(k),
    f the registered model's transition, w = sqrt(q(k)) * e with q(k) = ``Q_of(k)`` (the
    true, possibly time-varying diagonal; default diag Q). ``Q`` is then the nominal Q the
    session's filter starts from, and ``model_spec`` the session's wire model.

    ``angles``: state indices that are angles; the published truth has them wrapped to
    [-pi, pi) (as the estimators report them), the simulated state does not.
    ``loss_draw``: draw one uniform after each sample (kept so that the ``paper`` scenario
    reproduces its reference simulator, which draws a packet-loss decision there).
    """

    name: str
    description: str
    period_s: float
    Q: np.ndarray
    sensors: tuple[SensorDef, ...]
    x0_true: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    lead: int
    max_delay: int
    state_names: tuple[str, ...]
    command: Callable[[int], np.ndarray]
    A: np.ndarray | None = None
    B: np.ndarray | None = None
    default_steps: int = 0
    G: np.ndarray | None = None
    nonlinear: NonlinearModel | None = None
    model_spec: UnscentedModelSpec | None = None
    Q_of: Callable[[int], np.ndarray] | None = None
    angles: tuple[int, ...] = ()
    loss_draw: bool = True
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        linear = self.A is not None and self.B is not None
        if linear == (self.nonlinear is not None):
            raise ValueError(f"scenario {self.name!r}: give either A and B, or a nonlinear "
                             "model")
        if self.nonlinear is not None and self.model_spec is None:
            raise ValueError(f"scenario {self.name!r}: a nonlinear scenario needs model_spec")

    @property
    def n(self) -> int:
        if self.nonlinear is not None:
            return int(self.nonlinear.n)
        assert self.A is not None
        return int(self.A.shape[0])

    @property
    def nu(self) -> int:
        if self.nonlinear is not None:
            return int(self.nonlinear.nu)
        assert self.B is not None
        return int(self.B.shape[1])

    @property
    def kind(self) -> str:
        """The session's model kind: "linear" or the wire model's kind ("unscented")."""
        return "linear" if self.model_spec is None else self.model_spec.kind

    def truth_view(self, x: np.ndarray) -> np.ndarray:
        """x as published on the truth key: the ``angles`` wrapped to [-pi, pi)."""
        if not self.angles:
            return x
        out = np.array(x, dtype=np.float64)
        idx = list(self.angles)
        out[idx] = wrap_angle(out[idx])
        return out

    @property
    def sensor_names(self) -> list[str]:
        return [s.name for s in self.sensors]

    def period_ns(self, time_scale: float = 1.0) -> int:
        """Real-time step period, ns: the model's period divided by ``time_scale``."""
        if not (time_scale > 0 and math.isfinite(time_scale)):
            raise ValueError(f"time_scale: must be a positive number, got {time_scale}")
        return max(1, round(self.period_s * 1e9 / time_scale))

    def spec(self, session: str, epoch_ns: int, *, time_scale: float = 1.0,
             sensors: Sequence[str] | None = None, lead: int | None = None,
             max_delay: int | None = None, publish_every: int = 1) -> SessionSpec:
        """The SessionSpec of this scenario: the model in model-time steps, the clock in real
        time (``period_ns`` = period / time_scale). ``sensors``: a subset by name (default
        all)."""
        chosen = self.select(sensors)
        model = self.model_spec if self.model_spec is not None else \
            LinearModelSpec(A=self.A, B=self.B, Q=self.Q)
        return SessionSpec(
            session=session, period_ns=self.period_ns(time_scale), epoch_ns=int(epoch_ns),
            model=model,
            x0=self.x0, P0=self.P0,
            sensors=[s.wire() for s in chosen],
            lead=self.lead if lead is None else lead,
            max_delay=self.max_delay if max_delay is None else max_delay,
            publish_every=publish_every,
        )

    def select(self, sensors: Sequence[str] | None) -> list[SensorDef]:
        if sensors is None:
            return list(self.sensors)
        by_name = {s.name: s for s in self.sensors}
        unknown = [s for s in sensors if s not in by_name]
        if unknown or not sensors:
            raise ValueError(f"sensors: {unknown or 'none'} not in scenario {self.name!r} "
                             f"(has: {', '.join(by_name)})")
        return [by_name[s] for s in sensors]


class ScenarioSim:
    """Seeded simulation of a scenario, one step at a time (no clock, no network).

    At step k: :meth:`sample` gives the sensors' samples of x(k), then :meth:`advance`
    applies u(k): x(k+1) = A x(k) + B u(k) + w(k) (or f(x(k), u(k), k) + w(k)). Draw order
    per step, so that the scenarios reproduce their reference simulators exactly for the same
    seed and commands (``paper``: :func:`pd_service.estimation.scenarios.simulate_paper`;
    ``omni``: :func:`pd_service.estimation.nonlinear.scenario_omni.simulate_omni`): for each
    sensor in order, if it samples, its noise, then (if ``loss_draw``) one uniform (the
    reference's loss draw); then the process noise.
    """

    def __init__(self, scenario: Scenario, seed: int | None = 0) -> None:
        self.scenario = scenario
        self.rng = np.random.default_rng(seed)
        self.k = 0
        self.x = np.array(scenario.x0_true, dtype=np.float64)
        self._qstd = np.sqrt(np.diag(scenario.Q)) if scenario.G is None else None

    def sample(self) -> list[tuple[str, np.ndarray]]:
        """Samples (sensor name, z) of x(k) for every sensor that reports at step k."""
        out = []
        for s in self.scenario.sensors:
            if self.k % s.interval != 0:
                continue
            if s.available is not None and not s.available(self.x):
                continue
            L = s.L
            e = self.rng.standard_normal(s.m)
            if np.count_nonzero(L - np.diag(np.diag(L))) == 0:
                noise = np.diag(L) * e  # L diagonal: elementwise, as the reference does
            else:
                noise = L @ e
            z = s.measure(self.x) + noise
            if s.angles:
                idx = list(s.angles)
                z[idx] = wrap_angle(z[idx])
            out.append((s.name, z))
            if self.scenario.loss_draw:
                self.rng.random()  # the reference simulator's loss draw (kept for equality)
        return out

    def advance(self, u: np.ndarray | Sequence[float]) -> np.ndarray:
        """x(k+1) = A x(k) + B u(k) + w(k), or f(x(k), u(k), k) + w(k); returns x(k+1)."""
        sc = self.scenario
        uv = np.asarray(u, dtype=np.float64).reshape(sc.nu)
        if sc.Q_of is not None:
            # w = sqrt(q(k)) * e: the true, time-varying diagonal Q
            w = np.sqrt(np.asarray(sc.Q_of(self.k), dtype=np.float64)) * \
                self.rng.standard_normal(sc.n)
        elif self._qstd is not None:
            w = self._qstd * self.rng.standard_normal(sc.n)
        else:
            assert sc.G is not None
            w = sc.G @ self.rng.standard_normal(sc.G.shape[1])
        if sc.nonlinear is not None:
            self.x = sc.nonlinear.f(self.x, uv, self.k) + w
        else:
            assert sc.A is not None and sc.B is not None
            self.x = sc.A @ self.x + sc.B @ uv + w
        self.k += 1
        return self.x


# --- the paper's vehicle chasing an object ----------------------------------------------

#: Samples may arrive this many steps later than the nominal 12 (jitter on a real link).
PAPER_DELAY_SLACK = 4


def paper_scenario(noise: str = "journal") -> Scenario:
    """Liang et al. 2017, Sec. 4 (see :mod:`pd_service.estimation.scenarios`)."""
    if noise not in paper.NOISE_STD:
        raise ValueError(f"noise: expected one of {', '.join(paper.NOISE_STD)}, got {noise!r}")
    model = paper.paper_model()
    sensors = {s.name: s for s in paper.paper_sensors(noise)}
    cam_std, rng_std = paper.NOISE_STD[noise]
    x0, P0 = paper.paper_prior()

    def ranger_in_range(x: np.ndarray) -> bool:
        return bool(abs(x[2] - x[0]) <= paper.RANGER_MAX_RANGE)

    def command(k: int) -> np.ndarray:
        return np.array([paper.paper_command(k)])

    return Scenario(
        name="paper",
        description=f"vehicle chasing an object (Liang et al. 2017), {noise} noise",
        period_s=paper.PERIOD_S,
        A=np.array(model.A), B=np.array(model.B), Q=np.array(model.Q),
        sensors=(
            SensorDef("camera", np.array(sensors["camera"].H), cam_std * np.eye(2),
                      paper.CAMERA_DELAY, paper.CAMERA_INTERVAL),
            SensorDef("ranger", np.array(sensors["ranger"].H), rng_std * np.eye(1),
                      paper.RANGER_DELAY, paper.RANGER_INTERVAL, ranger_in_range),
        ),
        x0_true=paper.X0_TRUE.copy(), x0=x0, P0=P0,
        lead=paper.UPLINK_DELAY, max_delay=paper.RANGER_DELAY + PAPER_DELAY_SLACK,
        state_names=("p1", "v1", "p2", "v2"),
        command=command,
        default_steps=240,
        extra={"noise": noise},
    )


# --- a 2-D robot manoeuvring: straight legs and turns -------------------------------------

MANEUVER_PERIOD_S = 0.05
MANEUVER_SPEED = 0.5  # m/s, cruise speed
MANEUVER_REST_STEPS = 20  # steps at rest first (longer than the lead: every command arrives)
MANEUVER_ACCEL_STEPS = 40  # steps of constant acceleration from rest to cruise speed
MANEUVER_SIGMA_A = 0.05  # m/s^2, acceleration noise
#: The repeating pattern after the start: ("leg", steps) or ("turn", degrees, steps).
MANEUVER_PATTERN: tuple[tuple, ...] = (
    ("leg", 80), ("turn", 90.0, 60), ("leg", 60), ("turn", -90.0, 60),
    ("leg", 80), ("turn", 180.0, 100), ("leg", 40), ("turn", -90.0, 40),
)


def _pattern_total() -> tuple[int, float]:
    steps = sum(seg[-1] for seg in MANEUVER_PATTERN)
    degrees = sum(seg[1] for seg in MANEUVER_PATTERN if seg[0] == "turn")
    return steps, degrees


def maneuver_heading(k: int, d: float = MANEUVER_PERIOD_S) -> tuple[float, float]:
    """Nominal (heading at step k in radians, turn rate omega in rad/s during step k)."""
    start = MANEUVER_REST_STEPS + MANEUVER_ACCEL_STEPS
    if k < start:
        return 0.0, 0.0
    cycle_steps, cycle_deg = _pattern_total()
    j = k - start
    n_cycles, j = divmod(j, cycle_steps)
    heading = math.radians(cycle_deg) * n_cycles
    for seg in MANEUVER_PATTERN:
        steps = seg[-1]
        if seg[0] == "leg":
            if j < steps:
                return heading, 0.0
        else:
            omega = math.radians(seg[1]) / (steps * d)
            if j < steps:
                return heading + omega * d * j, omega
            heading += math.radians(seg[1])
        j -= steps
    raise AssertionError("unreachable")  # pragma: no cover


def maneuver_command(k: int, d: float = MANEUVER_PERIOD_S) -> np.ndarray:
    """u(k) = [ax, ay], m/s^2: rest, accelerate along +x, then legs (u = 0) and turns."""
    if k < MANEUVER_REST_STEPS:
        return np.zeros(2)
    if k < MANEUVER_REST_STEPS + MANEUVER_ACCEL_STEPS:
        return np.array([MANEUVER_SPEED / (MANEUVER_ACCEL_STEPS * d), 0.0])
    theta, omega = maneuver_heading(k, d)
    if omega == 0.0:
        return np.zeros(2)
    # u = s (e(theta + omega d) - e(theta)) / d: rotates the nominal velocity by omega d.
    a = theta + omega * d
    return MANEUVER_SPEED * np.array([math.cos(a) - math.cos(theta),
                                      math.sin(a) - math.sin(theta)]) / d


def maneuver_scenario() -> Scenario:
    d = MANEUVER_PERIOD_S
    eye, zero = np.eye(2), np.zeros((2, 2))
    A = np.block([[eye, d * eye], [zero, eye]])
    B = np.vstack([0.5 * d * d * eye, d * eye])
    G = MANEUVER_SIGMA_A * B  # w = B a, a ~ N(0, sigma_a^2 I)
    Q = G @ G.T
    return Scenario(
        name="maneuver",
        description="2-D robot: straight legs and turns, constant-velocity model",
        period_s=d, A=A, B=B, Q=Q,
        sensors=(
            SensorDef("gnss", np.hstack([eye, zero]), 0.2 * eye, delay=8, interval=4),
            SensorDef("odometry", np.hstack([zero, eye]), 0.05 * eye, delay=3, interval=1),
        ),
        x0_true=np.zeros(4), x0=np.zeros(4), P0=np.diag([1.0, 1.0, 0.1, 0.1]),
        lead=6, max_delay=12,
        state_names=("px", "py", "vx", "vy"),
        command=maneuver_command,
        default_steps=0,
        G=G,
    )


# --- issue 9: the three-wheel omnidirectional robot -------------------------------------

#: Parameters of the registered model "omni3" (the issue's robot), as sent in the spec.
OMNI_PARAMS: dict[str, float] = {
    "period_s": omni.PERIOD_S, "mass": 10.0, "inertia": 0.25, "wheel_inertia": 0.01,
    "wheel_radius": 0.05, "wheel_distance": 0.2, "friction": 0.02,
}
OMNI_LEAD = 10  # steps (uplink 0.1 s)
OMNI_POSE_DELAY = 3  # steps, nominal downlink delay of the pose samples
OMNI_MAX_DELAY = 8  # steps: the pose delay plus 50 ms of jitter


def omni_q_true(k: int) -> np.ndarray:
    """Diagonal of the true Q of step k -> k+1: Q0, x100 from t = 10 s (model time)."""
    return omni.q_true(k, omni.PERIOD_S, omni.JUMP_S, omni.JUMP_FACTOR)


def omni_scenario() -> Scenario:
    """Issue 9's three-wheel omnidirectional robot (see the module docstring)."""
    model = make_model("omni3", **OMNI_PARAMS)
    pose = model.sensors["pose"]
    wire_model = UnscentedModelSpec(
        model="omni3",
        params={**OMNI_PARAMS, "Q": [float(q) for q in OMNI_Q0]},
        adapt=AdaptSpec(method="mit", indices=list(OMNI_ACCEL_CHANNELS)),
    )
    return Scenario(
        name="omni",
        description="three-wheel omnidirectional robot, wheel torques, Q x100 at 10 s "
                    "(issue 9); adaptive UKF",
        period_s=omni.PERIOD_S,
        Q=np.diag(OMNI_Q0),
        nonlinear=model,
        model_spec=wire_model,
        Q_of=omni_q_true,
        sensors=(
            SensorDef("pose", None, math.sqrt(omni.R_POSE) * np.eye(3), delay=OMNI_POSE_DELAY,
                      interval=1, kind="model", h=pose.h, angles=pose.angles),
        ),
        x0_true=omni.X0.copy(), x0=np.zeros(6), P0=omni.P0.copy(),
        lead=OMNI_LEAD, max_delay=OMNI_MAX_DELAY,
        state_names=("x", "y", "theta", "vx", "vy", "omega"),
        command=omni.omni_torque,
        default_steps=int(round(omni.DURATION_S / omni.PERIOD_S)),
        angles=model.angles,
        loss_draw=False,
    )


SCENARIOS = ("paper", "maneuver", "omni")


def get_scenario(name: str, noise: str = "journal") -> Scenario:
    """A scenario by name: ``paper`` (``noise`` journal|english), ``maneuver`` or ``omni``."""
    if name == "paper":
        return paper_scenario(noise)
    if name == "maneuver":
        return maneuver_scenario()
    if name == "omni":
        return omni_scenario()
    raise ValueError(f"scenario: expected one of {', '.join(SCENARIOS)}, got {name!r}")
