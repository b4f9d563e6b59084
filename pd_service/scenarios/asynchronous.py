"""A differential-drive robot whose sensors are not on the step grid (issue 42), step 50 ms::

    x = [x, y, yaw, v, yaw_rate] (m, m, rad, m/s, rad/s),  u = [v_cmd, yaw_rate_cmd] (a Twist)
    registered nonlinear model "unicycle" (exact arc, first-order lags tau_v, tau_w)

    sensor        rate    phase    jitter (std)   delay     noise std
    odom_twist    25 Hz    7 ms     1 ms           20 ms     0.02 m/s, 0.02 rad/s
    imu          100 Hz    3 ms     0.5 ms          5 ms     0.01 rad/s
    pose           5 Hz  130 ms     5 ms          300 ms     0.05 m, 0.05 m, 0.02 rad
    lead 2 (uplink 100 ms), max_delay 8 (400 ms)

Sample j of a sensor is taken at t_j = phase + j / rate + e_j (s after the epoch), e_j ~
N(0, jitter^2) clipped to +-min(0.4 / rate, 3 jitter) (the samples stay in order), and arrives at t_j + delay.
So the odometry falls at 5 offsets inside the 50 ms steps, the IMU at 5 per step, the pose fix
4 steps apart at a drifting offset: none on the grid.

Truth (:class:`AsyncSim`): continuous time, advanced from event to event (every
``truth_step_s`` = 1 ms and every sample time) through the model's flow over each interval dt
with noise w ~ N(0, Qc dt), Qc = Q / T the noise density (per second) of the filter's per-step
Q: Brownian increments, so the truth does not depend on where the events fall. The command
u(k) is held over [k T, (k+1) T) (commands stay on the grid). Each sample is the sensor's h of
the true state at its own time plus its noise, stamped with that time.

:func:`async_scenario` is a :class:`~.simulator.Scenario` (its SessionSpec: the nominal
interval and delay of each sensor in steps) with the :class:`AsyncTiming` of the sensors;
:class:`~.simulator.ScenarioSim` would sample it on the grid, :class:`AsyncSim` does not.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pd_service.estimation.nonlinear import NonlinearModel, make_model, wrap_angle
from pd_service.wire import UnscentedModelSpec

from .diffdrive import ROS2_BINDING, drive_turn_stop
from .simulator import AsyncTiming, Scenario, SensorDef, SensorTiming

PERIOD_S = 0.05
TAU_V = 0.25  # s, first-order lag of the forward speed
TAU_W = 0.15  # s, first-order lag of the yaw rate
ASYNC_LEAD = 2  # steps: uplink 100 ms
ASYNC_MAX_DELAY = 8  # steps: the pose fix's 300 ms plus 100 ms of slack
ASYNC_PARAMS: dict[str, float] = {"period_s": PERIOD_S, "tau_v": TAU_V, "tau_w": TAU_W}
#: Process noise density Qc (per second) of x, y, yaw, v, yaw_rate: the diffdrive scenario's
#: per-step Q (20 ms) spread over its step; the 50 ms filter's Q is Qc * 0.05.
QC_DIAG = (5e-5, 5e-5, 5e-5, 5e-3, 2e-2)
P0 = np.diag([0.05**2, 0.05**2, 0.05**2, 0.05**2, 0.05**2])
CYCLE_S = 20.0  # the drive_turn_stop profile's cycle


ASYNC_SENSORS = (
    SensorTiming("odom_twist", 25.0, 0.007, 0.001, 0.020, (0.02, 0.02)),
    SensorTiming("imu", 100.0, 0.003, 0.0005, 0.005, (0.01,)),
    SensorTiming("pose", 5.0, 0.130, 0.005, 0.300, (0.05, 0.05, 0.02)),
)


def async_model(period_s: float = PERIOD_S) -> NonlinearModel:
    """The robot's "unicycle" model for a filter of step ``period_s`` (s): Q = Qc period_s."""
    return make_model("unicycle", period_s=period_s, tau_v=TAU_V, tau_w=TAU_W,
                      Q=[q * period_s for q in QC_DIAG])


def async_command(k: int) -> np.ndarray:
    """The Twist for step k: the diffdrive scenario's drive / turn / stop profile."""
    return drive_turn_stop(k, PERIOD_S)


def async_scenario() -> Scenario:
    """The scenario (see the module docstring)."""
    model = async_model()
    sensors = []
    for t in ASYNC_SENSORS:
        ms = model.sensors[t.name]
        sensors.append(SensorDef(
            t.name, None, np.diag(t.std), delay=math.ceil(t.delay_s / PERIOD_S),
            interval=max(1, round(1.0 / (t.rate_hz * PERIOD_S))),
            kind="model", h=ms.h, angles=ms.angles))
    return Scenario(
        name="async",
        description="differential-drive robot with sensors off the step grid: odometry 25 Hz, "
                    "IMU 100 Hz, pose fix 5 Hz (300 ms late), each with its own phase and "
                    "jitter; 50 ms step; UKF",
        period_s=PERIOD_S,
        Q=np.asarray(model.Q, dtype=float).copy(),
        nonlinear=model,
        model_spec=UnscentedModelSpec(model="unicycle", params={
            **ASYNC_PARAMS, "Q": [q * PERIOD_S for q in QC_DIAG]}),
        sensors=tuple(sensors),
        x0_true=np.zeros(5), x0=np.zeros(5), P0=P0.copy(),
        lead=ASYNC_LEAD, max_delay=ASYNC_MAX_DELAY,
        state_names=("x", "y", "yaw", "v", "yaw_rate"),
        command=async_command,
        default_steps=int(round(CYCLE_S / PERIOD_S)),
        angles=model.angles,
        loss_draw=False,
        ros2=ROS2_BINDING,
        timing=AsyncTiming(ASYNC_SENSORS, np.diag(QC_DIAG)),
    )


@dataclass(frozen=True, eq=False)
class TimedSample:
    """One sample: ``z`` (m,) of the true state at ``t_s`` (s after the epoch), arriving at
    ``arrival_s``."""

    sensor: str
    t_s: float
    z: np.ndarray
    arrival_s: float


class AsyncSim:
    """Seeded continuous-time simulation of an asynchronous scenario, one step at a time.

    :meth:`step` with u(k) runs [k T, (k+1) T): returns the samples taken in it (in time
    order) and leaves :attr:`x` = x((k+1) T). Random streams: one per sensor (jitter, then
    noise, per sample) and one for the process noise, so a sensor's samples do not depend on
    the others'. ``seed``: an int or None.
    """

    def __init__(self, scenario: Scenario, seed: int | None = 0) -> None:
        if scenario.timing is None or scenario.nonlinear is None:
            raise ValueError(f"scenario {scenario.name!r} has no asynchronous sensors")
        model = scenario.nonlinear
        if model.flow is None:
            raise ValueError(f"model {model.name!r} cannot move part of a step (no flow)")
        self.scenario = scenario
        self.timing = scenario.timing
        self.model = model
        streams = np.random.SeedSequence(seed).spawn(1 + len(self.timing.sensors))
        self._rng_w = np.random.default_rng(streams[0])
        self._rngs = [np.random.default_rng(s) for s in streams[1:]]
        self._h = {t.name: model.sensors[t.name] for t in self.timing.sensors}
        self._j = [0] * len(self.timing.sensors)
        self._next = [self._draw_time(i) for i in range(len(self.timing.sensors))]
        self._qstd = np.sqrt(np.diag(self.timing.Qc))
        self._flows: dict[float, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {}
        self.k = 0
        self.t = 0.0
        self.x = np.array(scenario.x0_true, dtype=np.float64)

    def start_at(self, k: int) -> None:
        """Start at step k >= 0 (joining a running session): the clock at k T, each sensor
        at its first sample due from then on; the state stays the initial one."""
        if k < 0:
            raise ValueError(f"k: must be >= 0, got {k}")
        if k == self.k:
            return
        T = self.scenario.period_s
        self.k, self.t = k, k * T
        for i, t in enumerate(self.timing.sensors):
            self._j[i] = max(0, math.ceil((k * T - t.phase_s) * t.rate_hz))
            self._next[i] = max(self._draw_time(i), self.t)

    def _draw_time(self, i: int) -> float:
        """Time (s) of sensor i's next sample (index self._j[i])."""
        t = self.timing.sensors[i]
        half = min(0.4 / t.rate_hz, 3.0 * t.jitter_s)
        e = min(max(self._rngs[i].standard_normal() * t.jitter_s, -half), half)
        return t.phase_s + self._j[i] / t.rate_hz + e

    def _move(self, dt: float, u: np.ndarray) -> None:
        """x(t) -> x(t + dt): the flow over dt plus w ~ N(0, Qc dt)."""
        if dt <= 0.0:
            return
        key = round(dt, 12)
        fn = self._flows.get(key)
        if fn is None:
            assert self.model.flow is not None
            fn = self.model.flow(dt)
            if len(self._flows) < 64:
                self._flows[key] = fn
        self.x = fn(self.x, u) + self._qstd * math.sqrt(dt) * self._rng_w.standard_normal(
            self.x.shape[0])
        self.t += dt

    def step(self, u: np.ndarray) -> list[TimedSample]:
        """Run step k = :attr:`k` with u(k) held; see the class docstring."""
        T = self.scenario.period_s
        end = (self.k + 1) * T
        h = self.timing.truth_step_s
        uv = np.asarray(u, dtype=np.float64).reshape(self.scenario.nu)
        out: list[TimedSample] = []
        tick = self.k * T + h
        while True:
            i = int(np.argmin(self._next))
            ts = self._next[i]
            nxt = min(ts, tick, end)
            self._move(nxt - self.t, uv)
            self.t = nxt  # no drift of the clock from summed dt's
            if nxt == ts and ts < end:
                out.append(self._sample(i, ts))
                self._j[i] += 1
                self._next[i] = self._draw_time(i)
            if nxt == tick:
                tick = round((tick + h) / h) * h
            if nxt >= end:
                break
        self.k += 1
        self.t = end
        return out

    def _sample(self, i: int, ts: float) -> TimedSample:
        t = self.timing.sensors[i]
        ms = self._h[t.name]
        z = np.asarray(ms.h(self.x), dtype=np.float64) + np.asarray(t.std) * \
            self._rngs[i].standard_normal(len(t.std))
        if ms.angles:
            idx = list(ms.angles)
            z[idx] = wrap_angle(z[idx])
        return TimedSample(t.name, ts, z, ts + t.delay_s)


@dataclass(frozen=True, eq=False)
class AsyncRun:
    """One simulated run of ``steps`` steps: ``truth`` (steps + 1, n) the true x(k T),
    ``u`` (steps, nu) the commands u(k), ``samples`` every sample taken, by arrival time."""

    truth: np.ndarray
    u: np.ndarray
    samples: list[TimedSample]

    @property
    def steps(self) -> int:
        return int(self.u.shape[0])


def simulate_async(scenario: Scenario, steps: int, seed: int | None = 0) -> AsyncRun:
    """Run :class:`AsyncSim` over ``steps`` steps with the scenario's commands."""
    sim = AsyncSim(scenario, seed)
    truth = [sim.x.copy()]
    us, samples = [], []
    for k in range(steps):
        u = np.asarray(scenario.command(k), dtype=np.float64)
        samples.extend(sim.step(u))
        us.append(u)
        truth.append(sim.x.copy())
    samples.sort(key=lambda s: s.arrival_s)
    return AsyncRun(np.array(truth), np.array(us).reshape(steps, scenario.nu), samples)
