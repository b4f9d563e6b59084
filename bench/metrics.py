#!/usr/bin/env python3
"""Cost of one Prometheus scrape of the daemon (``pd-service --metrics``) at N sessions.

A ServiceCore on the in-memory bus serves N paper sessions (created, each fed a few samples,
some late so that the top-N gauges are full); its metrics endpoint runs on loopback as in the
daemon. Measured per scrape, over R scrapes per run:

- ``collect_ms``: the collection alone (pd_service.service.scrape.collect: the status copy
  under the core's lock, the per-session counters, the families), process CPU time;
- ``lock_ms``: wall time the core's lock is held by one collection (what a scrape can delay
  the worker by);
- ``http_ms``: one whole scrape over HTTP (urllib GET of /metrics, text format), wall time.

Goal (issue 46): at most 50 ms per scrape at 1,000 sessions. Median and spread over runs;
the machine gauge (bench/gauge.py) beside the figures; the CPU model from /proc/cpuinfo.

Usage: python bench/metrics.py [--sessions 1000] [--scrapes 20] [--runs 3]
Last line: one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gauge import gauge_ms  # noqa: E402

from pd_service.metrics import serve  # noqa: E402
from pd_service.service.config import Settings  # noqa: E402
from pd_service.service.core import ServiceCore  # noqa: E402
from pd_service.service.scrape import collect  # noqa: E402
from pd_service.service.spec_store import SpecStore  # noqa: E402
from pd_service.transport import InMemoryBus  # noqa: E402
from pd_service.wire import encode, keys  # noqa: E402
from tests.service.helpers import PERIOD_NS, Clock, meas_bytes, paper_spec  # noqa: E402


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown"


class _TimedLock:
    """The core's lock, timing how long each holder keeps it (s)."""

    def __init__(self, lock: threading.RLock) -> None:
        self._lock = lock
        self.held: list[float] = []
        self._t0 = 0.0

    def __enter__(self) -> None:
        self._lock.acquire()
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.held.append(time.perf_counter() - self._t0)
        self._lock.release()


def build(n: int, state: Path) -> ServiceCore:
    """A core serving ``n`` sessions, each fed one sample, every third one late."""
    clock = Clock(0)
    settings = Settings(instance="bench", max_sessions=max(2_000, n), cpu_budget=1e6,
                        memory_budget_bytes=2**40, config_rate_total=1e9,
                        config_burst_total=10**9)
    bus = InMemoryBus()
    core = ServiceCore(bus.transport(), settings, store=SpecStore(state),
                       now_ns=clock, run_clock_ns=lambda: 0, spawn=lambda fn: fn())
    core.start()
    bus_cli = bus.transport()
    for i in range(n):
        bus_cli.put(keys.config_key(f"s{i}"), encode(paper_spec(f"s{i}")))
    _settle(core)
    clock.t = 100 * PERIOD_NS
    for i in range(n):
        step = 1 if i % 3 == 0 else 99
        bus_cli.put(keys.sensor_key(f"s{i}", "camera"),
                    meas_bytes(f"s{i}", "camera", step, [0.0, 0.0]))
    _settle(core)
    return core


def _settle(core: ServiceCore) -> None:
    core.run_once()
    while core.has_work():
        core.run_once()


def run_once(core: ServiceCore, scrapes: int) -> dict[str, float]:
    log = logging.getLogger("bench.metrics")
    timed = _TimedLock(core.queries.lock)
    core.queries.lock = timed  # type: ignore[assignment]
    collect_cpu: list[float] = []
    for _ in range(scrapes):
        t0 = time.process_time()
        list(collect(core.queries))
        collect_cpu.append(time.process_time() - t0)
    server = serve("127.0.0.1:0", lambda: collect(core.queries), log)
    http: list[float] = []
    try:
        for _ in range(scrapes):
            t0 = time.perf_counter()
            with urllib.request.urlopen(server.url, timeout=30) as resp:
                body = resp.read()
            http.append(time.perf_counter() - t0)
    finally:
        server.close()
        core.queries.lock = timed._lock  # type: ignore[assignment]
    return {"collect_ms": 1e3 * statistics.median(collect_cpu),
            "lock_ms": 1e3 * statistics.median(timed.held),
            "http_ms": 1e3 * statistics.median(http),
            "bytes": float(len(body)), "series": float(body.count(b"\n") - body.count(b"\n#"))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=1000, help="sessions served (default 1000)")
    ap.add_argument("--scrapes", type=int, default=20, help="scrapes per run (default 20)")
    ap.add_argument("--runs", type=int, default=3, help="runs (default 3)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        core = build(args.sessions, Path(tmp))
        served = len(core.queries.served_sessions())
        runs = []
        for r in range(args.runs):
            res = run_once(core, args.scrapes)
            res["gauge_ms"] = gauge_ms()
            runs.append(res)
            print(f"run {r + 1}: collect {res['collect_ms']:.2f} ms CPU, lock held "
                  f"{res['lock_ms']:.2f} ms, HTTP scrape {res['http_ms']:.2f} ms, "
                  f"{int(res['series'])} series, {int(res['bytes'])} bytes, "
                  f"gauge {res['gauge_ms']:.1f} ms")
        core.close()

    def med(key: str) -> float:
        return round(statistics.median(r[key] for r in runs), 3)

    def spread(key: str) -> float:
        vals = [r[key] for r in runs]
        return round(max(vals) - min(vals), 3)

    print(f"\nCPU: {cpu_model()}; sessions served: {served}")
    print(f"{'figure':22}{'median':>10}{'spread':>10}")
    for key in ("collect_ms", "lock_ms", "http_ms", "gauge_ms"):
        print(f"{key:22}{med(key):10.2f}{spread(key):10.2f}")
    print(json.dumps({"bench": "metrics", "sessions": served, "scrapes": args.scrapes,
                      "runs": len(runs), "cpu": cpu_model(),
                      **{k: med(k) for k in ("collect_ms", "lock_ms", "http_ms", "gauge_ms",
                                             "series", "bytes")},
                      "spread_http_ms": spread("http_ms"), "goal_ms": 50}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
