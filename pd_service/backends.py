"""SessionSpec -> (estimator, command dimension, cost): the one place a spec becomes an
estimator, in one trip.

:func:`build` reads a spec once, in one call: it builds the nonlinear model (the first IMM
mode) that gives the command dimension ``nu``, prices the session (:func:`spec_cost`) and hands
the cost to the caller's ``admit`` (the daemon's budget check) before allocating anything in
proportion to it, then builds the estimator on the model already built and returns a
:class:`Built` (estimator, nu, cost) that the session, its intake and the admission ledger
take as they are. :func:`command_dim` is the first step alone (a client's ``nu``).

- "linear": :class:`~pd_service.estimation.ObserverPredictor` (LinearModel, [Sensor], x0,
  P0, lead, max_delay, command_hold); nu = the columns of B;
- "unscented": :func:`~pd_service.estimation.nonlinear.make_unscented` with the registered
  model built here, its adapt and sigma settings, the session's sensors in order and their R;
  nu = the model's;
- "imm": :func:`~pd_service.estimation.imm.make_imm` with the modes (the first built here),
  transition, variant, node, mu0, kappa and the sensors as IMM sensor maps
  (:func:`imm_sensor`, R as the spec gives it); nu = the first mode's (0: no commands).

What the wire layer cannot check alone (a model that is not registered, a parameter it does
not take, x0 / R of the wrong size for the model) is refused here: any error of a model's or
the estimator's constructor becomes a WireError "SessionSpec.<field>: refused by the
estimator: <reason>" (:func:`estimator_refusal`). A valid linear spec is never refused.

Cost model (:func:`spec_cost`; bytes, 8 per float64), from the spec's fields and nu only.
With n states, W = max_delay + 1 and the input buffer's capacity C = 3 max_delay + lead + 4
(:class:`~pd_service.estimation.replay.ReplayEstimator`)::

    state       g = 8 (n + n^2) * k          k = 1 linear, 2 unscented (x, P and the
                                             sensitivities an adapter tracks), 2 r IMM (r modes)
    window      W g  (posterior checkpoints) + sum_s ceil(W / interval_s) (8 (m_s + m_s^2) + 200)
    inputs      16 C nu                      (the command buffer holds 2 C rows)
    fixed       SESSION_FIXED_BYTES          (Python objects, latency window, counters)
    tables      8 ((C + 1) 2 n^2 + C n nu)   linear only: A^m, Qs(m) for m <= C and the
                                             stacked [A^{C-1}B ... B]; shared by every session
                                             with the same (A, B, Q, C), charged once

CPU model (µs per step), "nominal": every sensor delivers a sample every ``interval`` steps
after its declared ``delay``; a late sample re-runs the measured steps after its stamp
(ReplayEstimator), which per step coalesces to a replay of D = max_s delay_s steps; the
prediction rolls the newest posterior forward to now + lead::

    samples/step   lam = sum_s 1 / interval_s
    updates        U = 1 + lam D
    linear         cpu = STEP_US + lam SAMPLE_US + (lam + 1) LIN_OP_US(n) + lam D REPLAY_US(n)
                   (each packet one covariance update, the prediction one multi-step
                   product from the tables; a replayed step keeps its covariance and gains
                   and re-runs only its mean)
    unscented      cpu = STEP_US + lam SAMPLE_US + (D + lead) UKF_STEP_US(n) + U UKF_UPD_US(n)
    IMM (r modes)  the unscented figure with both per-op costs times r

The constants price the worker thread's time (the one thread every session shares, which
``cpu_budget`` bounds) as measured on the current hot path and rounded up: the paper's
session (n = 4, camera every 2nd step delayed 10, ranger every step delayed 12) comes to
~32 µs per step, where the worker alone was measured at 26-29 µs per session-step at
1,000-2,000 sessions (docs/performance.md, "Admission's cost model", with the command);
``bench/admission_calibrate.py`` times the estimator's part. Fixed constants, not a
measurement at start-up: a budget must admit the same specs on every restart and on every
peer, whatever the machine's load at that moment. They are a model, not a measurement of
the spec: a spec's real cost depends on its traffic. The budgets it is checked against are
:class:`pd_service.service.admission.Ledger`'s.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from pd_service.estimation import Estimator, LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.imm import make_imm, make_mode
from pd_service.estimation.nonlinear import NonlinearModel, make_model, make_unscented
from pd_service.wire import (
    ImmModelSpec,
    LinearModelSpec,
    SensorSpec,
    SessionSpec,
    UnscentedModelSpec,
    WireError,
)
from pd_service.wire.messages import ModeSpec

__all__ = ["Built", "Cost", "build", "command_dim", "estimator_refusal", "imm_sensor",
           "spec_cost"]

SESSION_FIXED_BYTES = 32 * 1024
PACKET_OVERHEAD_BYTES = 200

STEP_US = 15.0  # tick, health check, snapshot, pack and put one prediction
SAMPLE_US = 6.0  # decode, check and store one measurement


def lin_op_us(n: int) -> float:
    """One linear propagate or covariance update (µs)."""
    return 2.0 + 1e-4 * n**3


def replay_us(n: int) -> float:
    """One replayed linear step whose covariance and gains are reused: its mean only (µs)."""
    return 0.15 + 1e-3 * n**2


def ukf_step_us(n: int) -> float:
    """One propagated step of the 2n+1 sigma points (µs)."""
    return 10.0 * n + 1e-3 * n**3


def ukf_upd_us(n: int) -> float:
    """One unscented update (µs)."""
    return 27.0 * n + 3e-3 * n**3


@dataclass(frozen=True, slots=True)
class Cost:
    """What one session costs. ``table_key`` identifies its shared tables (None: none)."""

    session_bytes: int
    table_bytes: int
    table_key: str | None
    cpu_us: float
    period_ns: int

    @property
    def cpu_share(self) -> float:
        """Fraction of one core: cpu_us per step over the step period."""
        return self.cpu_us * 1000.0 / self.period_ns

    @property
    def bytes(self) -> int:
        return self.session_bytes + self.table_bytes


def spec_cost(spec: SessionSpec, nu: int) -> Cost:
    """The cost model of the module docstring for ``spec`` with ``nu`` inputs (the
    :func:`command_dim`). Allocates nothing in proportion to the spec."""
    model = spec.model
    n = spec.n
    W = spec.max_delay + 1
    C = 3 * spec.max_delay + spec.lead + 4
    if isinstance(model, LinearModelSpec):
        k = 1
    elif isinstance(model, UnscentedModelSpec):
        k = 2
    else:
        k = 2 * len(model.modes)
    g = 8 * (n + n * n) * k
    packets = sum(math.ceil(W / s.interval) * (8 * (s.m + s.m * s.m) + PACKET_OVERHEAD_BYTES)
                  for s in spec.sensors)
    session_bytes = SESSION_FIXED_BYTES + W * g + packets + 16 * C * max(nu, 1)
    lam = sum(1.0 / s.interval for s in spec.sensors)
    D = max(s.delay for s in spec.sensors)
    updates = 1.0 + lam * D
    cpu = STEP_US + lam * SAMPLE_US
    table_bytes, table_key = 0, None
    if isinstance(model, LinearModelSpec):
        table_bytes = 8 * ((C + 1) * 2 * n * n + C * n * nu)
        h = hashlib.blake2b(digest_size=16)
        for a in model.matrices():
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
        h.update(str(C).encode())
        if model.continuous:  # its tables are those of one period
            h.update(str(spec.period_ns).encode())
        table_key = h.hexdigest()
        cpu += (lam + 1.0) * lin_op_us(n) + lam * D * replay_us(n)
    else:
        r = 1 if isinstance(model, UnscentedModelSpec) else len(model.modes)
        cpu += r * ((D + spec.lead) * ukf_step_us(n) + updates * ukf_upd_us(n))
    return Cost(session_bytes, table_bytes, table_key, cpu, spec.period_ns)


#: The estimator factories start a refusal with what they refuse ("x0: ...",
#: "sensor_R['pose']: ..."); the SessionSpec field each such word stands for (else "model").
_ESTIMATOR_FIELDS = {"x0": "x0", "P0": "P0", "sensors": "sensors", "sensor_R": "sensors",
                     "indices": "model.unscented.adapt.indices", "modes": "model.imm.modes"}


def estimator_refusal(exc: Exception) -> WireError:
    """A spec the estimator refused, as ``SessionSpec.<field>: refused by the estimator:
    <reason>`` (the field its reason starts with, else ``model``)."""
    text = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
    head = re.match(r"[A-Za-z0-9_]+", text)
    field = _ESTIMATOR_FIELDS.get(head.group(0) if head else "", "model")
    return WireError(f"SessionSpec.{field}: refused by the estimator: {text}")


def _params(params: Mapping[str, Any]) -> dict[str, Any]:
    """Fresh copies of a model's parameter values (lists are mutable)."""
    return {k: list(v) if isinstance(v, list) else v for k, v in params.items()}


def _mode_map(mode: ModeSpec) -> dict[str, Any]:
    """An IMM mode as the registry's {"model": name, "params": {...}} map."""
    return {"model": mode.model, "params": _params(mode.params)}


@dataclass(frozen=True, slots=True)
class Built:
    """A spec's estimator with what serving it needs: its command dimension ``nu`` (0: the
    session takes no commands) and its :class:`Cost`."""

    est: Estimator
    nu: int
    cost: Cost


def command_dim(spec: SessionSpec) -> int:
    """The spec's command dimension ``nu`` (0: it takes no commands), as :func:`build` finds
    it: linear, the columns of B; nonlinear, the registered model's (IMM: the first mode's).

    WireError "SessionSpec.model: refused by the estimator: ..." if that model cannot be built.
    """
    return _nu_model(spec)[0]


def _nu_model(spec: SessionSpec) -> tuple[int, NonlinearModel | None]:
    """``nu`` and the nonlinear model built to find it (None: linear), kept for the build."""
    model = spec.model
    try:
        if isinstance(model, LinearModelSpec):
            return model.r, None
        if isinstance(model, UnscentedModelSpec):
            built = make_model(model.model, **_params(model.params))
        else:
            built = make_mode(_mode_map(model.modes[0]))
        return int(built.nu), built
    except Exception as exc:  # ValueError, or a registered model's own code failing
        raise estimator_refusal(exc) from None


def linear_model(model: LinearModelSpec, period_ns: int) -> LinearModel:
    """The estimation model of a linear spec: (A, B, Q) as given, or (F, G, Qc) discretised
    exactly for any interval, one step being ``period_ns``."""
    a, b, c = (np.array(m) for m in model.matrices())
    if model.continuous:
        return LinearModel.continuous(a, b, c, period_ns / 1e9)
    return LinearModel(A=a, B=b, Q=c)


#: Most steps between a spec's epoch and now that a model without a closed-form long jump
#: (unscented, IMM) takes: its first prediction propagates the prior step by step from the
#: epoch (a linear model jumps a span without commands in O(log m) products).
MAX_PRIOR_STEPS = 1000


def prior_span(spec: SessionSpec, now_ns: int) -> str | None:
    """Why ``spec`` is refused at ``now_ns`` for an epoch too far in the past (None: it is
    not): a model other than linear with more than :data:`MAX_PRIOR_STEPS` steps from
    ``epoch_ns`` to now would stall the worker at its first prediction."""
    if isinstance(spec.model, LinearModelSpec):
        return None
    steps = (now_ns - spec.epoch_ns) // spec.period_ns
    if steps <= MAX_PRIOR_STEPS:
        return None
    return (f"SessionSpec.epoch_ns: {steps} steps before now; a {spec.model.kind} model "
            f"propagates its prior step by step from the epoch, at most {MAX_PRIOR_STEPS} "
            f"steps (give an epoch near the present)")


def build(spec: SessionSpec, admit: Callable[[Cost], None] | None = None) -> Built:
    """The spec's estimator, nu and cost, by ``spec.model.kind`` (see the module docstring).

    ``admit(cost)`` is called once the spec is priced and before anything is allocated in
    proportion to it (the daemon's budget check: whatever it raises, e.g. ``OverBudget``,
    leaves here with nothing built); None: no budget.

    WireError "SessionSpec.<field>: refused by the estimator: ..." if the model or the
    estimator's constructor refuses the spec.
    """
    nu, first = _nu_model(spec)
    cost = spec_cost(spec, nu)
    if admit is not None:
        admit(cost)
    model = spec.model
    try:
        if isinstance(model, LinearModelSpec):
            est: Estimator = ObserverPredictor(
                linear_model(model, spec.period_ns),
                [Sensor(name=s.name, H=np.array(s.H), R=np.array(s.R))
                 for s in spec.sensors],
                np.array(spec.x0), np.array(spec.P0), spec.lead, spec.max_delay,
                spec.command_hold,
            )
        elif isinstance(model, UnscentedModelSpec):
            assert first is not None  # built by _nu_model
            est = _unscented(spec, model, first)
        elif isinstance(model, ImmModelSpec):
            assert first is not None  # the first mode, built by _nu_model
            est = _imm(spec, model, first)
        else:  # a model kind the wire accepts but no backend builds: a programming error
            raise TypeError(f"no backend for model kind {model.kind!r}")
    except WireError:
        raise
    except Exception as exc:  # ValueError, or a registered model's own code failing
        raise estimator_refusal(exc) from None
    if est.n != spec.n:  # the constructors check x0 against the model; kept as a guard
        raise WireError(f"SessionSpec.x0: refused by the estimator: the model has "
                        f"n={est.n} states, x0 has {spec.n}")
    return Built(est, nu, cost)


def _unscented(spec: SessionSpec, model: UnscentedModelSpec,
               built: NonlinearModel) -> Estimator:
    adapt = None
    if model.adapt is not None:
        adapt = {k: v for k, v in model.adapt.model_dump().items() if v is not None}
    sigma = None if model.sigma is None else model.sigma.model_dump()
    return make_unscented(
        built, None,
        x0=np.array(spec.x0), P0=np.array(spec.P0),
        lead=spec.lead, max_delay=spec.max_delay, command_hold=spec.command_hold,
        adapt=adapt, sigma=sigma,
        sensors=[s.name for s in spec.sensors],
        sensor_R={s.name: np.array(s.R) for s in spec.sensors},
    )


def _imm(spec: SessionSpec, model: ImmModelSpec, first: NonlinearModel) -> Estimator:
    modes: list[NonlinearModel | Mapping[str, object]] = [
        first, *(_mode_map(m) for m in model.modes[1:])]
    return make_imm(
        modes=modes,
        transition=np.array(model.transition),
        sensors=[imm_sensor(s) for s in spec.sensors],
        variant=model.variant,
        x0=np.array(spec.x0), P0=np.array(spec.P0),
        lead=spec.lead, max_delay=spec.max_delay,
        mu0=None if model.mu0 is None else np.array(model.mu0),
        node=model.node, kappa=model.kappa, command_hold=spec.command_hold,
    )


def imm_sensor(sensor: SensorSpec) -> dict[str, Any]:
    """The IMM factory's sensor map of a "range_bearing" or "position" SensorSpec, with the
    spec's R (2, 2) as it is (range-bearing: station too; R diagonal, as the wire checks)."""
    if sensor.kind == "range_bearing":
        assert sensor.station is not None  # guaranteed by SensorSpec's validator
        return {"name": sensor.name, "kind": "range_bearing",
                "station": [float(v) for v in sensor.station], "R": np.array(sensor.R)}
    if sensor.kind == "position":
        return {"name": sensor.name, "kind": "position", "R": np.array(sensor.R)}
    raise WireError(f"SessionSpec.sensors: sensor {sensor.name!r} of kind {sensor.kind!r} does not "
                    "fit an IMM model")
