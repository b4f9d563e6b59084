"""Admission control: what a session will cost, computed from its spec before anything is
allocated, and the budgets a spec must fit.

Memory model (bytes, 8 per float64), from the spec's fields only. With n states, nu inputs,
W = max_delay + 1 and the input buffer's capacity C = 3 max_delay + lead + 4
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
    linear         cpu = STEP_US + lam SAMPLE_US + (U + 1) LIN_OP_US(n)      (the prediction
                                             is one multi-step product from the tables)
    unscented      cpu = STEP_US + lam SAMPLE_US + (D + lead) UKF_STEP_US(n) + U UKF_UPD_US(n)
    IMM (r modes)  the unscented figure with both per-op costs times r

The constants were measured on the 2-core development machine with
``bench/admission_calibrate.py`` (one estimator alone, median of a loop) and the service
benchmark (docs/service.md: ~80 µs per session-step in-process for the paper's linear
session, of which about a third is the estimator), then rounded up: a linear op costs
~5 µs of call overhead plus ~1e-4 n^3 µs (n = 64: ~33 µs measured), an omni3 (n = 6)
unscented propagated step ~61 µs and an update ~160 µs. They are a model, not a
measurement of the spec: a spec's real cost depends on its traffic.

Budgets (:class:`~pd_service.service.config.Settings`): one spec may use at most
``max_session_bytes`` and ``max_session_cpu`` (fraction of a core = cpu / period); all the
sessions this instance runs together at most ``memory_budget_bytes`` (shared tables
counted once) and ``cpu_budget`` (fraction of a core: the worker is one thread).
"""

from __future__ import annotations

import hashlib
import math
from collections import Counter
from dataclasses import dataclass

from pd_service.wire import LinearModelSpec, SessionSpec, UnscentedModelSpec
from pd_service.wire.convert import command_dim

SESSION_FIXED_BYTES = 32 * 1024
PACKET_OVERHEAD_BYTES = 200

STEP_US = 40.0  # pack and publish one prediction, tick bookkeeping
SAMPLE_US = 15.0  # decode, check and store one measurement


def lin_op_us(n: int) -> float:
    """One linear propagate or update (µs)."""
    return 5.0 + 1e-4 * n**3


def ukf_step_us(n: int) -> float:
    """One propagated step of the 2n+1 sigma points (µs; omni3, n = 6: ~61)."""
    return 10.0 * n + 1e-3 * n**3


def ukf_upd_us(n: int) -> float:
    """One unscented update (µs; omni3, n = 6: ~160)."""
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


def spec_cost(spec: SessionSpec) -> Cost:
    """The cost model of the module docstring. Allocates nothing in proportion to the spec
    (the nonlinear model's input dimension is read from the registered model, which is
    built once; WireError if it cannot be)."""
    model = spec.model
    n = spec.n
    nu = command_dim(spec)
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
        for a in (model.A, model.B, model.Q):
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
        h.update(str(C).encode())
        table_key = h.hexdigest()
        cpu += (updates + 1.0) * lin_op_us(n)
    else:
        r = 1 if isinstance(model, UnscentedModelSpec) else len(model.modes)
        cpu += r * ((D + spec.lead) * ukf_step_us(n) + updates * ukf_upd_us(n))
    return Cost(session_bytes, table_bytes, table_key, cpu, spec.period_ns)


class OverBudget(Exception):
    """A spec that does not fit a budget; ``reason`` is one readable line."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _mib(b: float) -> str:
    return f"{b / 2**20:.1f} MiB"


class Ledger:
    """The costs of the sessions this instance runs, against the budgets.

    ``admit(name, cost)`` raises :class:`OverBudget` (and changes nothing) if the session, or
    the service with it (its previous cost, if any, replaced), would exceed a budget;
    ``release(name)`` gives its share back."""

    def __init__(self, max_session_bytes: int, max_session_cpu: float,
                 memory_budget_bytes: int, cpu_budget: float) -> None:
        self.max_session_bytes = max_session_bytes
        self.max_session_cpu = max_session_cpu
        self.memory_budget_bytes = memory_budget_bytes
        self.cpu_budget = cpu_budget
        self.costs: dict[str, Cost] = {}
        self._tables: Counter[str] = Counter()  # table key -> sessions using it
        self._table_bytes: dict[str, int] = {}
        self.bytes = 0
        self.cpu = 0.0

    def check(self, name: str, cost: Cost) -> None:
        """Raise :class:`OverBudget` if ``cost`` does not fit (nothing changes either way)."""
        if cost.bytes > self.max_session_bytes:
            raise OverBudget(f"SessionSpec: needs {_mib(cost.bytes)} of tables and buffers "
                          f"(n, lead, max_delay, inputs), more than this service's "
                          f"{_mib(self.max_session_bytes)} per session (max_session_bytes)")
        if cost.cpu_share > self.max_session_cpu:
            raise OverBudget(f"SessionSpec: needs about {cost.cpu_us:.0f} µs per "
                          f"{cost.period_ns / 1e6:g} ms step ({cost.cpu_share:.0%} of a core), "
                          f"more than this service's {self.max_session_cpu:.0%} per session "
                          f"(max_session_cpu)")
        old = self.costs.get(name)
        b, c = self.bytes, self.cpu
        if old is not None:
            b -= old.session_bytes
            c -= old.cpu_share
            if old.table_key is not None and self._tables[old.table_key] == 1:
                b -= self._table_bytes[old.table_key]
        key = cost.table_key
        if key is not None:
            users = self._tables.get(key, 0) - (old is not None and old.table_key == key)
            if users <= 0:
                b += cost.table_bytes
        b += cost.session_bytes
        c += cost.cpu_share
        if b > self.memory_budget_bytes:
            raise OverBudget(f"SessionSpec: this service's memory budget is full "
                          f"({_mib(self.bytes)} of {_mib(self.memory_budget_bytes)} used, the "
                          f"spec needs {_mib(cost.bytes)}; memory_budget_bytes)")
        if c > self.cpu_budget + 1e-12:
            raise OverBudget(f"SessionSpec: this service's CPU budget is full ({self.cpu:.0%} of "
                          f"a core used of {self.cpu_budget:.0%}, the spec needs "
                          f"{cost.cpu_share:.1%}; cpu_budget)")

    def admit(self, name: str, cost: Cost) -> None:
        self.check(name, cost)
        self.release(name)
        self.costs[name] = cost
        self.bytes += cost.session_bytes
        self.cpu += cost.cpu_share
        if cost.table_key is not None:
            if not self._tables[cost.table_key]:
                self._table_bytes[cost.table_key] = cost.table_bytes
                self.bytes += cost.table_bytes
            self._tables[cost.table_key] += 1

    def release(self, name: str) -> None:
        cost = self.costs.pop(name, None)
        if cost is None:
            return
        self.bytes -= cost.session_bytes
        self.cpu -= cost.cpu_share
        key = cost.table_key
        if key is not None:
            self._tables[key] -= 1
            if self._tables[key] <= 0:
                del self._tables[key]
                self.bytes -= self._table_bytes.pop(key)
        if not self.costs:
            self.bytes, self.cpu = 0, 0.0  # no rounding drift when empty
