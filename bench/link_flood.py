"""pd-link's memory under a 1 h-delay flood and under many keys, pd-link as its own process.

    .venv/bin/python bench/link_flood.py                       # defaults below
    .venv/bin/python bench/link_flood.py --messages 300000 --size 1000 --keys 20000

Setup, all on loopback: this process opens a Zenoh peer listening on a free port; pd-link
(``python -m pd_service.link``, default limits) connects to it.  Its rules: every robot sensor
key ``robot/*/flood<j>/sensor/*`` delayed by 1 h, one rule per j < ``--rules`` (the configuration
raises ``limits.max_delay`` to 2 h to allow it), a victim stream ``robot/p<k>/victim/sensor/s``
delayed by 20 ms.  Each rule may hold ``limits / (rules + 3)`` (victim rule and the two
directions' unmatched traffic included): more flooded rules, closer to the whole limit.

Phases (a bounded loop each):
1. flood: ``--messages`` puts of ``--size`` bytes, round-robin over the 1 h-delayed rules' keys,
   as fast as Zenoh takes them (congestion control BLOCK);
2. keys: ``--keys`` puts, each on a new key ``robot/p<k>/k<i>/sensor/s`` (passthrough: every one
   needs its own output publisher), with the victim stream sent every 10th put.

After each phase: pd-link's RSS (``/proc/<pid>/status`` VmRSS) and its stats queryable (held
messages and bytes, drops over the caps, keys and publishers).  The victim's delay is the
end-to-end one (receive - send - 20 ms, both Zenoh hops included).
Bar: RSS growth <= 100 MB over the whole run.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from link import query_json, wait_for_link  # bench/link.py (bench/ is on sys.path)

from pd_service.transport import zenoh_config
from pd_service.wire import keys

ROOT = Path(__file__).resolve().parents[1]
INSTANCE = "flood"
VICTIM_IN = keys.robot_sensor_key("victim", "s")
VICTIM_OUT = keys.sensor_key("victim", "s")
VICTIM_DELAY_MS = 20.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--messages", type=int, default=300_000, help="flood puts (phase 1)")
    ap.add_argument("--size", type=int, default=1000, help="flood payload, bytes")
    ap.add_argument("--keys", type=int, default=20_000, help="distinct keys (phase 2)")
    ap.add_argument("--rules", type=int, default=1, help="1 h-delayed rules flooded at once")
    args = ap.parse_args()

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    doc = {"limits": {"max_delay": "7200s"},
           "downlink": [{"name": "victim", "match": VICTIM_IN, "delay": VICTIM_DELAY_MS},
                        *({"name": f"hour{j}", "match": f"robot/*/flood{j}/sensor/*",
                           "delay": "3600s"} for j in range(args.rules))]}
    victim_ms: list[float] = []
    lock = threading.Lock()

    def on_victim(sample: zenoh.Sample) -> None:
        sent = int.from_bytes(sample.payload.to_bytes()[:8], "little")
        with lock:
            victim_ms.append((time.monotonic_ns() - sent) / 1e6 - VICTIM_DELAY_MS)

    rows: list[tuple[str, float, dict]] = []
    with zenoh.open(zenoh_config(listen=[endpoint])) as session, \
            tempfile.TemporaryDirectory() as tmp:  # fmt: skip
        cfg = Path(tmp) / "flood.json"
        cfg.write_text(json.dumps(doc))
        sub = session.declare_subscriber(VICTIM_OUT, on_victim)
        proc = subprocess.Popen(
            [sys.executable, "-m", "pd_service.link", "--config", str(cfg), "--connect", endpoint,
             "--instance", INSTANCE, "--log-level", "WARNING"],
            cwd=ROOT, env=os.environ | {"PYTHONPATH": str(ROOT)})
        try:
            floods = [session.declare_publisher(keys.robot_sensor_key(f"flood{j}", "cam"),
                                                congestion_control=zenoh.CongestionControl.BLOCK)
                      for j in range(args.rules)]
            flood = floods[0]
            wait_for_link(session, flood, 30.0, INSTANCE)
            time.sleep(1.0)

            def record(phase: str) -> None:
                time.sleep(2.0)  # let pd-link drain its inbox
                rows.append((phase, rss_mb(proc.pid),
                             query_json(session, keys.link_stats_key(INSTANCE))))

            record("start")
            payload = b"x" * args.size
            t0 = time.monotonic()
            for i in range(args.messages):
                floods[i % args.rules].put(payload)
            flood_s = time.monotonic() - t0
            record("after flood")
            victim = session.declare_publisher(VICTIM_IN)
            t0 = time.monotonic()
            for i in range(args.keys):
                session.put(keys.robot_sensor_key(f"k{i}", "s"), b"k")
                if i % 10 == 0:
                    victim.put(time.monotonic_ns().to_bytes(8, "little"))
                    time.sleep(0.001)
            keys_s = time.monotonic() - t0
            record("after keys")
        finally:
            sub.undeclare()
            proc.terminate()
            proc.wait(timeout=15)

    print("pd-link memory under a 1 h-delay flood (pd-link as its own process, Zenoh loopback, "
          f"default limits); {args.messages} x {args.size} B flood in {flood_s:.1f} s, "
          f"{args.keys} keys in {keys_s:.1f} s; {args.rules} flooded rule(s); "
          f"{os.cpu_count()} CPUs")
    print(f"{'phase':<12} {'RSS MB':>8} {'held':>7} {'held MB':>8} {'dropped_cap':>12} "
          f"{'overflow':>9} {'keys':>6} {'evicted':>8} {'publishers':>10}")
    for phase, rss, st in rows:
        print(f"{phase:<12} {rss:>8.1f} {st['pending']:>7} {st['pending_bytes'] / 2**20:>8.1f} "
              f"{st['dropped_capacity']:>12} {st['overflow']:>9} {st['keys']:>6} "
              f"{st['keys_evicted']:>8} {st['publishers']:>10}")
    growth = rows[-1][1] - rows[0][1]
    peak = max(r[1] for r in rows) - rows[0][1]
    v = np.array(victim_ms)
    if v.size:
        print(f"victim stream: {v.size} received, end-to-end delay - 20 ms: p50 "
              f"{np.percentile(v, 50):.2f} ms, p99 {np.percentile(v, 99):.2f} ms, "
              f"max {v.max():.2f} ms")
    print(f"RSS growth {growth:.1f} MB (largest {peak:.1f} MB); bar <= 100 MB: "
          f"{'met' if peak <= 100 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
