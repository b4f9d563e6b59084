"""A simulated robot (:class:`Scenario`) and its seeded step-by-step simulator
(:class:`ScenarioSim`): ground truth and sensor samples, no clock, no network, no filter.

Each scenario also gives its :class:`~pd_service.wire.SessionSpec`, so a session built
from it estimates the very robot the simulator moves.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from pd_service.estimation.nonlinear import NonlinearModel, wrap_angle
from pd_service.wire import LinearModelSpec, SensorSpec, SessionSpec, UnscentedModelSpec
from pd_service.wire.messages import PathSpec
from pd_service.wire.ros2 import Ros2Binding


@dataclass(frozen=True, eq=False)
class SensorDef:
    """One simulated sensor: z = H x + L v (``kind`` "linear") or z = h(x) + L v (``kind``
    "model": h is the nonlinear model's sensor of this name, ``H`` is None), v ~ N(0, I);
    R = L L^T. ``angles``: indices of z wrapped to [-pi, pi) after the noise is added.
    ``delay`` (steps) and ``interval`` (steps between samples) as in the SensorSpec.

    ``available(x)``: whether the sensor reports for the true state x (e.g. a range limit).
    """

    name: str
    H: np.ndarray | None
    L: np.ndarray
    delay: int
    interval: int
    available: Callable[[np.ndarray], bool] | None = None
    kind: Literal["linear", "model"] = "linear"
    h: Callable[[np.ndarray], np.ndarray] | None = None
    angles: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.kind == "linear" and self.H is None:
            raise ValueError(f"sensor {self.name!r}: a linear sensor needs H")
        if self.kind == "model" and self.h is None:
            raise ValueError(f"sensor {self.name!r}: a model sensor needs h")

    @property
    def R(self) -> np.ndarray:
        """Noise covariance R = L L^T, (m, m)."""
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


@dataclass(frozen=True)
class SensorTiming:
    """When one sensor samples and how late its samples arrive: ``rate_hz``, ``phase_s``
    (time of sample 0), ``jitter_s`` (std of a sample time around its nominal one, clipped to
    +-min(0.4 / rate, 3 jitter_s)), ``delay_s`` (sample time -> arrival), ``std`` (noise
    std per component)."""

    name: str
    rate_hz: float
    phase_s: float
    jitter_s: float
    delay_s: float
    std: tuple[float, ...]


@dataclass(frozen=True, eq=False)
class AsyncTiming:
    """The sensors' timings, the noise density ``Qc`` (n, n) per second and the truth's
    integration step ``truth_step_s`` (s) of an asynchronous scenario."""

    sensors: tuple[SensorTiming, ...]
    Qc: np.ndarray
    truth_step_s: float = 0.001


@dataclass(frozen=True, eq=False, kw_only=True)
class Scenario:
    """A simulated robot, linear or nonlinear.

    Linear (``A``, ``B`` given): x(k+1) = A x(k) + B u(k) + w(k), w = G e (e ~ N(0, I)), or
    w = sqrt(diag Q) * e when ``G`` is None (Q diagonal).

    Nonlinear (``nonlinear`` given, ``A`` = ``B`` = None): x(k+1) = f(x(k), u(k), k) + w(k),
    f the registered model's transition, w = sqrt(q(k)) * e with q(k) = ``Q_of(k)`` (the
    true, possibly time-varying diagonal; default diag Q). ``Q`` is then the nominal Q the
    session's filter starts from, and ``model_spec`` the session's wire model.

    ``period_s``: step period (s); ``x0_true``: the robot's true x(0); ``x0``, ``P0``: the
    session's prior; ``lead``, ``max_delay``: the session's (steps); ``command(k)``: the
    scenario's command u(k); ``default_steps``: its length (0: endless).
    ``angles``: state indices that are angles; the published truth has them wrapped to
    [-pi, pi) (as the estimators report them), the simulated state does not.
    ``loss_draw``: draw one uniform after each sample, the packet-loss decision (the
    ``paper`` scenario's reference stream has it; see :class:`ScenarioSim`).
    ``ros2``: the session's ROS 2 topic bindings, if the robot speaks ROS 2 (the spec keeps
    the bindings of the sensors it selects).
    ``timing``: for a robot whose sensors sample off the step grid, their rates, phases,
    jitters and delays (:class:`AsyncTiming`; simulated by :class:`~.asynchronous.AsyncSim`);
    ``sensors`` then give the nominal interval and delay.
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
    ros2: Ros2Binding | None = None
    timing: AsyncTiming | None = None

    def __post_init__(self) -> None:
        linear = self.A is not None and self.B is not None
        if linear == (self.nonlinear is not None):
            raise ValueError(f"scenario {self.name!r}: give either A and B, or a nonlinear "
                             "model")
        if self.nonlinear is not None and self.model_spec is None:
            raise ValueError(f"scenario {self.name!r}: a nonlinear scenario needs model_spec")

    @property
    def n(self) -> int:
        """State dimension."""
        if self.nonlinear is not None:
            return int(self.nonlinear.n)
        assert self.A is not None
        return int(self.A.shape[0])

    @property
    def nu(self) -> int:
        """Command dimension."""
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
             max_delay: int | None = None, publish_every: int = 1,
             path: PathSpec | None = None) -> SessionSpec:
        """The SessionSpec of this scenario: the model in model-time steps, the clock in real
        time (``period_ns`` = period / time_scale). ``sensors``: a subset by name (default
        all); ``lead``, ``max_delay``: override the scenario's (steps); ``path``: publish the
        predicted path too."""
        chosen = self.select(sensors)
        model: LinearModelSpec | UnscentedModelSpec
        if self.model_spec is not None:
            model = self.model_spec
        else:
            assert self.A is not None and self.B is not None
            model = LinearModelSpec(A=self.A, B=self.B, Q=self.Q)
        return SessionSpec(
            session=session, period_ns=self.period_ns(time_scale), epoch_ns=int(epoch_ns),
            model=model,
            x0=self.x0, P0=self.P0,
            sensors=[s.wire() for s in chosen],
            lead=self.lead if lead is None else lead,
            max_delay=self.max_delay if max_delay is None else max_delay,
            publish_every=publish_every,
            ros2=self._ros2_of(chosen),
            path=path,
        )

    def _ros2_of(self, chosen: Sequence[SensorDef]) -> Ros2Binding | None:
        """The ROS 2 bindings restricted to the ``chosen`` sensors."""
        if self.ros2 is None:
            return None
        names = {s.name for s in chosen}
        sensors = {n: b for n, b in self.ros2.sensors.items() if n in names}
        return self.ros2.model_copy(update={"sensors": sensors})

    def select(self, sensors: Sequence[str] | None) -> list[SensorDef]:
        """The sensors named (default: all), in the order given; ValueError for an unknown
        name or an empty list."""
        if sensors is None:
            return list(self.sensors)
        by_name = {s.name: s for s in self.sensors}
        unknown = [s for s in sensors if s not in by_name]
        if unknown or not sensors:
            raise ValueError(f"sensors: {unknown or 'none'} not in scenario {self.name!r} "
                             f"(has: {', '.join(by_name)})")
        return [by_name[s] for s in sensors]


@dataclass(frozen=True, eq=False)
class Detection:
    """One sensor sample z (m,) of the true x(``step``); ``lost``: dropped by the
    simulator's packet loss (a robot does not send it)."""

    sensor: str
    step: int
    z: np.ndarray
    lost: bool = False


class ScenarioSim:
    """Seeded simulation of a scenario, one step at a time (no clock, no network).

    At step k: :meth:`sample` gives the sensors' samples of x(k), then :meth:`advance`
    applies u(k): x(k+1) = A x(k) + B u(k) + w(k) (or f(x(k), u(k), k) + w(k)).

    Random stream, in this order per step: for each sensor in order, if it samples, its
    noise, then (if the scenario's ``loss_draw``) one uniform u, the sample lost iff
    u < ``loss``; then the process noise. Every sensor is sampled (even those a session does
    not use), so sessions given different sensor subsets of one run see the same truth.
    ``seed``: an int, None, or a Generator used as is.
    """

    def __init__(self, scenario: Scenario, seed: int | None | np.random.Generator = 0,
                 loss: float = 0.0) -> None:
        self.scenario = scenario
        self.rng = np.random.default_rng(seed)
        self.loss = loss
        self.k = 0
        self.x = np.array(scenario.x0_true, dtype=np.float64)
        self._qstd = np.sqrt(np.diag(scenario.Q)) if scenario.G is None else None

    def sample(self) -> list[Detection]:
        """The samples of x(k) of every sensor that reports at step k."""
        out = []
        for s in self.scenario.sensors:
            if self.k % s.interval != 0:
                continue
            if s.available is not None and not s.available(self.x):
                continue
            L = s.L
            e = self.rng.standard_normal(s.m)
            if np.count_nonzero(L - np.diag(np.diag(L))) == 0:
                noise = np.diag(L) * e  # L diagonal: elementwise
            else:
                noise = L @ e
            z = s.measure(self.x) + noise
            if s.angles:
                idx = list(s.angles)
                z[idx] = wrap_angle(z[idx])
            lost = bool(self.rng.random() < self.loss) if self.scenario.loss_draw else False
            out.append(Detection(s.name, self.k, z, lost))
        return out

    def advance(self, u: np.ndarray | Sequence[float],
                cuts: Sequence[tuple[float, np.ndarray]] = ()) -> np.ndarray:
        """x(k+1) = A x(k) + B u(k) + w(k), or f(x(k), u(k), k) + w(k); returns x(k+1).

        ``cuts``: commands taking effect inside the step, (offset s, u) sorted by offset: u
        from the step's start, each cut's u from its offset on (a robot applying commands on
        arrival), the flow over each piece: x(k+1) = flow(T - d_m)(... flow(d_1)(x, u) ...,
        u_m) + w(k); the same noise draw. ValueError for a model without ``flow``."""
        sc = self.scenario
        uv = np.asarray(u, dtype=np.float64).reshape(sc.nu)
        flow = None if sc.nonlinear is None else sc.nonlinear.flow
        if cuts and flow is None:
            raise ValueError("cuts: this scenario's model has no flow over part of a step")
        if sc.Q_of is not None:
            # w = sqrt(q(k)) * e: the true, time-varying diagonal Q
            w = np.sqrt(np.asarray(sc.Q_of(self.k), dtype=np.float64)) * \
                self.rng.standard_normal(sc.n)
        elif self._qstd is not None:
            w = self._qstd * self.rng.standard_normal(sc.n)
        else:
            assert sc.G is not None
            w = sc.G @ self.rng.standard_normal(sc.G.shape[1])
        if cuts and flow is not None:
            x, t0 = self.x, 0.0
            for d, ui in cuts:
                if d > t0:
                    x = flow(d - t0)(x, uv)
                t0, uv = d, np.asarray(ui, dtype=np.float64).reshape(sc.nu)
            self.x = flow(sc.period_s - t0)(x, uv) + w
        elif sc.nonlinear is not None:
            self.x = sc.nonlinear.f(self.x, uv, self.k) + w
        else:
            assert sc.A is not None and sc.B is not None
            self.x = sc.A @ self.x + sc.B @ uv + w
        self.k += 1
        return self.x
