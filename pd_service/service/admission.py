"""Admission control: the budgets a session's cost must fit.

A spec's cost (:class:`~pd_service.backends.Cost`, bytes and µs per step) is computed from
its spec before anything is allocated, by :func:`pd_service.backends.build`, which hands it
to the caller's ``admit`` (the daemon passes :meth:`Ledger.check` or :meth:`Ledger.admit`)
before it builds the estimator (the cost model: :func:`pd_service.backends.spec_cost`).

Budgets (:class:`~pd_service.service.config.Settings`): one spec may use at most
``max_session_bytes`` and ``max_session_cpu`` (fraction of a core = cpu / period); all the
sessions this instance runs together at most ``memory_budget_bytes`` (shared tables
counted once) and ``cpu_budget`` (fraction of a core: the worker is one thread).
"""

from __future__ import annotations

from collections import Counter

from pd_service.backends import Cost


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
