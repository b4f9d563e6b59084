"""The daemon's metrics (``pd-service --metrics HOST:PORT``): what a Prometheus scrape reads.

Read at scrape time from what the status queries already serve: the instance's counters
(``ServiceStatus.counters``, one ``pd_service_<counter>_total`` each), its gauges, and per
session only aggregates and a top-N (:data:`pd_service.metrics.TOP_N` sessions by late,
future and refused samples and by missed steps), so the series count does not grow with the
sessions; per-session detail stays in ``pd/<s>/status`` (docs/service.md, "Metrics").

The core's lock is held only to copy the sessions' counters (dict copies), as a status
query does; everything else runs after it is released.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from typing import Any

from pd_service.metrics import counter, gauge, top

from .status import Queries, phase_of

#: ServiceStatus.counters entries that are levels, not counts (exported as gauges).
GAUGES = {"sessions_served": "Sessions this instance runs.",
          "sessions_known": "Session specs this instance knows (its own and its peers').",
          "members": "Live daemon instances this one shares sessions with, itself included."}
#: Derived sums already exported through their parts.
DERIVED = {"late_total"}
#: Per-session counters ranked in the top-N gauges.
RANKED = ("late", "future", "refused", "steps_missed")


def collect(queries: Queries) -> Iterator[Any]:
    """The metric families of one instance (see the module docstring)."""
    status = queries.service_status()
    per_session: dict[str, dict[str, int]] = {}
    states: Counter[str] = Counter()
    with queries.lock:
        for name, route in queries.routes.items():
            sess = route.sess
            if sess is not None:
                per_session[name] = dict(sess.counters)
                states[phase_of(sess)] += 1
    for name, value in sorted(status.counters.items()):
        if name in GAUGES:
            yield gauge(f"pd_service_{name}", GAUGES[name], value)
        elif name not in DERIVED:
            yield counter(f"pd_service_{name}",
                          f"Instance counter {name} (docs/protocol.md, counters).", value)
    yield gauge("pd_service_owned_partitions", "Key partitions this instance owns.",
                status.owned_partitions)
    yield gauge("pd_service_partitions", "Key partitions of the deployment (PD_PARTITIONS).",
                status.partitions)
    yield gauge("pd_service_uptime_seconds", "Seconds since the instance started.",
                status.uptime_s)
    yield gauge("pd_service_latency_p50_seconds", "Median processing latency over the last "
                "window (ServiceStatus.latency_p50_us).", status.latency_p50_us / 1e6)
    yield gauge("pd_service_latency_p99_seconds", "99th percentile processing latency over "
                "the last window (ServiceStatus.latency_p99_us).", status.latency_p99_us / 1e6)
    yield gauge("pd_service_sessions", "Sessions this instance runs, by how they started.",
                labels=dict(states), label="state")
    for name in RANKED:
        ranked = top({s: c.get(name, 0) for s, c in per_session.items()})
        yield gauge(f"pd_service_top_session_{name}", f"The sessions with the most {name} "
                    "(counter value; at most pd_service.metrics.TOP_N sessions).",
                    labels=ranked, label="session")

