#!/usr/bin/env python3
"""The cost of idle sessions: one daemon on loopback, N sessions (the paper's spec, 20 Hz)
created at once and never sent to, the daemon's CPU (utime + stime from /proc, % of one
core) over windows after the creation burst. No other session, no subscriber.

    .venv/bin/python bench/idle.py                       # 2,000 sessions, ~40 s
    .venv/bin/python bench/idle.py --env PD_SERVICE_IDLE_PUBLISH_S=1000   # no idle ticks

The daemon's budgets are raised through the environment as in bench/attack.py's idle row
(the defaults refuse 2,000 sessions); ``--env KEY=VALUE`` adds more.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pd_service.transport import ZenohTransport, zenoh_config  # noqa: E402
from pd_service.wire import encode, keys  # noqa: E402
from tests.service.helpers import paper_spec  # noqa: E402
from tests.service.procs import Daemon, Presence, endpoint, free_port  # noqa: E402

PERIOD = 50_000_000
#: As in bench/attack.py (IDLE_ENV): admit 2,000 sessions at once.
ENV = {"PD_SERVICE_MAX_SESSIONS": "5000", "PD_SERVICE_CONFIG_RATE_TOTAL": "100000",
       "PD_SERVICE_CONFIG_BURST_TOTAL": "100000", "PD_SERVICE_CPU_BUDGET": "1000",
       "PD_SERVICE_MEMORY_BUDGET_BYTES": str(16 * 2**30)}
CLK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """utime + stime of ``pid`` (s)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=2000)
    ap.add_argument("--marks", default="5,14,30",
                    help="window ends, s after the last config was put")
    ap.add_argument("--env", action="append", default=[], help="KEY=VALUE for the daemon")
    args = ap.parse_args()
    env_before = dict(os.environ)
    os.environ.update(ENV)
    os.environ.update(dict(e.split("=", 1) for e in args.env))
    ep = endpoint(free_port())
    t = ZenohTransport(zenoh_config(mode="peer", listen=[ep], multicast=False))
    pres = Presence(t)
    work = Path(tempfile.mkdtemp(prefix="pd-idle-"))
    d = Daemon("idle", work / "state", [ep]).start()
    os.environ.clear()
    os.environ.update(env_before)
    try:
        if not pres.wait("idle", timeout=30):
            print("daemon did not come up", file=sys.stderr)
            return 1
        assert d.proc is not None
        pid = d.proc.pid
        time.sleep(1.0)
        epoch = time.time_ns()
        c_prev, t_prev = cpu_s(pid), time.monotonic()
        created = t_prev  # the first config put
        for i in range(args.sessions):
            name = f"idle{i:04d}"
            t.put(keys.config_key(name), encode(paper_spec(name, epoch_ns=epoch,
                                                           period_ns=PERIOD)))
            if i % 100 == 99:
                time.sleep(0.02)
        for mark in (float(m) for m in args.marks.split(",")):
            time.sleep(max(0.0, created + mark - time.monotonic()))
            c, now = cpu_s(pid), time.monotonic()
            print(f"{t_prev - created:5.1f}-{now - created:5.1f} s after the first config put: "
                  f"{100.0 * (c - c_prev) / (now - t_prev):.1f} % of a core", flush=True)
            c_prev, t_prev = c, now
    finally:
        d.stop(timeout=15)
        t.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
