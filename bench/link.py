"""Benchmark pd-link's timing: |applied - configured| delay at 1,000 and 10,000 messages/s.

    .venv/bin/python bench/link.py                    # pd-link as a separate process (default)
    .venv/bin/python bench/link.py --in-process       # relay in this process (shares the GIL)
    .venv/bin/python bench/link.py --rates 1000 10000 --seconds 5 --delay-ms 100

Setup, all on loopback: this process opens a Zenoh peer listening on a free port; pd-link
connects to it.  This process publishes ``robot/p57/bench/sensor/s`` at the given rate (payload: the
send time, ``time.monotonic_ns``, CLOCK_MONOTONIC is system-wide so comparable across
processes) and subscribes to ``pd/p57/bench/sensor/s`` (p57: the partition of "bench" at
P = 64).  The rule is a fixed delay, no jitter, so
the configured delay of every message is known.

Two figures per rate:
* relay:      publish time - (arrival time + configured delay), as pd-link measures it itself
              (stats queryable, "lateness"): what the timer thread could not hit;
* end-to-end: receive time - send time - configured delay, measured here: includes both
              Zenoh hops and this process's own scheduling (it is also the load generator).
The relay quantiles cover the last 20,000 copies of each run (pd-link's stats reservoir).
A baseline line per rate gives the same sender and receiver through one Zenoh loopback hop
without pd-link: the floor the machine itself puts under the end-to-end column.
Bar: relay p99 <= 1 ms at 10,000 messages/s.  BENCH_DEBUG=1 prints the worst
messages of each run (a run of consecutive ones = a stall of the machine or of a process).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from pd_service.link.config import parse_config
from pd_service.transport import zenoh_config
from pd_service.wire import keys

ROOT = Path(__file__).resolve().parents[1]

INSTANCE = "bench"
ANY_PORT = "tcp/127.0.0.1:0"  # the listen endpoint of the peers that connect
IN_KEY = keys.robot_sensor_key("bench", "s")
OUT_KEY = keys.sensor_key("bench", "s")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rules(delay_ms: float) -> dict:
    return {"downlink": [{"name": "bench", "match": IN_KEY, "delay": delay_ms}]}


def query_json(session, key: str, payload: bytes | None = None) -> dict:
    replies = list(session.get(key, payload=payload, timeout=5.0))
    if not replies:
        raise RuntimeError(f"no reply from {key}")
    r = replies[0]
    if r.ok is None:
        raise RuntimeError(r.err.payload.to_bytes().decode())
    return json.loads(r.ok.payload.to_bytes())


def wait_for_link(session, pub, timeout_s: float, instance: str = INSTANCE) -> None:
    """Wait until pd-link ``instance`` answers its stats query and its subscriber matches
    ``pub`` (also used by bench/link_flood.py)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            query_json(session, keys.link_stats_key(instance))
            if pub.matching_status.matching:
                return
        except RuntimeError:
            pass
        if time.monotonic() > deadline:
            raise RuntimeError("pd-link did not come up")
        time.sleep(0.05)


def cpu_seconds(pid: int | None) -> float:
    """utime + stime of a process (this one if pid is None), seconds."""
    if pid is None:
        t = os.times()
        return t.user + t.system
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def send_paced(pub, rate: int, n: int, size: int) -> None:
    """Publish ``n`` messages at ``rate``/s (batches once per ms); payload = send time."""
    pad = b"\0" * max(0, size - 8)
    batch = max(1, rate // 1000)  # one batch per ms
    period_ns = int(1e9 * batch / rate)
    t_next = time.monotonic_ns()
    sent = 0
    while sent < n:
        now = time.monotonic_ns()
        if now < t_next:
            d = t_next - now
            if d > 300_000:
                time.sleep((d - 200_000) / 1e9)
            continue
        for _ in range(min(batch, n - sent)):
            pub.put(struct.pack("<q", time.monotonic_ns()) + pad)
            sent += 1
        t_next += period_ns


def run_rate(session, pub, received: list, rate: int, seconds: float, delay_ms: float,
             size: int, relay_pid: int | None) -> dict:  # fmt: skip
    query_json(session, keys.link_rules_key(INSTANCE), json.dumps(rules(delay_ms)).encode())
    received.clear()
    cpu0, wall0 = cpu_seconds(relay_pid), time.monotonic()
    n = int(rate * seconds)
    send_paced(pub, rate, n, size)
    deadline = time.monotonic() + delay_ms / 1e3 + 5.0
    while len(received) < n and time.monotonic() < deadline:
        time.sleep(0.05)
    cpu = (cpu_seconds(relay_pid) - cpu0) / (time.monotonic() - wall0)
    stats = query_json(session, keys.link_stats_key(INSTANCE))
    rule = next(r for r in stats["rules"] if r["name"] == "bench")
    arr = np.array(received, dtype=np.int64)
    e2e_ms = (arr[:, 0] - arr[:, 1]) / 1e6 - delay_ms if len(arr) else np.array([np.nan])
    dev = np.abs(e2e_ms)
    if os.environ.get("BENCH_DEBUG") and len(arr):
        order = np.argsort(arr[:, 1])
        d_sorted = dev[order]
        worst = np.argsort(d_sorted)[-5:]
        print(f"rate {rate}: worst at send index {worst.tolist()} of {len(arr)}: "
              f"{np.round(d_sorted[worst], 2).tolist()}; p99.9 {np.percentile(dev, 99.9):.2f}")
    return {
        "rate": rate,
        "sent": n,
        "received": len(received),
        "relay_p50": rule["lateness_ms"]["p50"],
        "relay_p99": rule["lateness_ms"]["p99"],
        "relay_samples": rule["samples"],
        "e2e_p50": float(np.percentile(dev, 50)),
        "e2e_p99": float(np.percentile(dev, 99)),
        "e2e_max": float(np.max(dev)),
        "cpu": cpu,
    }


def run_baseline(endpoint: str, rate: int, seconds: float, size: int,
                 express: bool) -> dict:  # fmt: skip
    """The same sender and receiver, one Zenoh hop over loopback, no pd-link: what the
    machine and Zenoh alone add (the floor under the e2e column)."""
    got: list[tuple[int, int]] = []

    def on_sample(sample: zenoh.Sample) -> None:
        got.append((time.monotonic_ns(), struct.unpack_from("<q", sample.payload.to_bytes())[0]))

    key = "bench/baseline"
    with zenoh.open(zenoh_config(listen=[ANY_PORT], connect=[endpoint])) as other, \
            zenoh.open(zenoh_config(listen=[ANY_PORT], connect=[endpoint])) as sender:  # fmt: skip
        sub = other.declare_subscriber(key, on_sample)
        pub = sender.declare_publisher(key, express=express,
                                       congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        n = int(rate * seconds)
        send_paced(pub, rate, n, size)
        deadline = time.monotonic() + 5
        while len(got) < n and time.monotonic() < deadline:
            time.sleep(0.05)
        sub.undeclare()
    arr = np.array(got, dtype=np.int64)
    lat = (arr[:, 0] - arr[:, 1]) / 1e6
    return {"rate": rate, "sent": n, "received": len(got), "p50": float(np.percentile(lat, 50)),
            "p99": float(np.percentile(lat, 99)), "max": float(lat.max())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--repeat", type=int, default=3, help="runs per rate (medians reported)")
    ap.add_argument("--delay-ms", type=float, default=100.0)
    ap.add_argument("--size", type=int, default=64, help="payload bytes")
    ap.add_argument("--in-process", action="store_true", help="run the relay in this process")
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip the Zenoh-only baseline (same sender/receiver, no pd-link)")
    ap.add_argument("--spin-us", type=int, default=100)
    ap.add_argument("--switch-interval-us", type=int, default=1000)
    ap.add_argument("--express", action=argparse.BooleanOptionalAction, default=False,
                    help="Zenoh express flag on pd-link's and this process's publishers")
    args = ap.parse_args()

    load0 = f"{os.getloadavg()[0]:.2f}"
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    received: list[tuple[int, int]] = []

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        received.append((now, struct.unpack_from("<q", sample.payload.to_bytes())[0]))

    proc = None
    relay = None
    relay_session = None
    with zenoh.open(zenoh_config(listen=[endpoint])) as session, tempfile.TemporaryDirectory() as tmp:
        sub = session.declare_subscriber(OUT_KEY, on_sample)
        cfg_path = Path(tmp) / "bench.json"
        cfg_path.write_text(json.dumps(rules(args.delay_ms)))
        if args.in_process:
            from pd_service.link.relay import LinkRelay

            if args.switch_interval_us > 0:
                sys.setswitchinterval(args.switch_interval_us / 1e6)
            from pd_service.transport.zenoh_transport import ZenohTransport

            relay_session = ZenohTransport(zenoh_config(listen=[ANY_PORT], connect=[endpoint]))
            relay = LinkRelay(relay_session, parse_config(rules(args.delay_ms)), INSTANCE,
                              spin_ns=args.spin_us * 1000, express=args.express).start()
            where = "in-process relay (shares this process's GIL with the load generator)"
        else:
            cmd = [sys.executable, "-m", "pd_service.link", "--config", str(cfg_path),
                   "--connect", endpoint, "--instance", INSTANCE, "--log-level", "WARNING",
                   "--spin-us", str(args.spin_us),
                   "--switch-interval-us", str(args.switch_interval_us),
                   "--express" if args.express else "--no-express"]  # fmt: skip
            proc = subprocess.Popen(cmd, cwd=ROOT, env=os.environ | {"PYTHONPATH": str(ROOT)})
            where = "pd-link as a separate process"
        pub = session.declare_publisher(IN_KEY, express=args.express,
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        try:
            wait_for_link(session, pub, 20.0)
            relay_pid = proc.pid if proc is not None else None
            run_rate(session, pub, received, 500, 1.0, args.delay_ms, args.size, relay_pid)
            rows = [run_rate(session, pub, received, rate, args.seconds, args.delay_ms,
                             args.size, relay_pid)
                    for _ in range(args.repeat) for rate in args.rates]  # fmt: skip
            baseline = [] if args.no_baseline else [
                run_baseline(endpoint, rate, args.seconds, args.size, args.express)
                for rate in args.rates]  # fmt: skip
        finally:
            sub.undeclare()
            if relay is not None:
                relay.close()
                relay_session.close()
            if proc is not None:
                proc.terminate()
                proc.wait(timeout=10)

    print(f"pd-link timing benchmark: {where}")
    print(f"configured delay {args.delay_ms:g} ms fixed, {args.size}-byte payloads, "
          f"{args.seconds:g} s per run, {args.repeat} runs per rate, spin {args.spin_us} us, "
          f"switch interval {args.switch_interval_us} us, express {args.express}; "
          f"{os.cpu_count()} CPUs, load average {load0} before / {os.getloadavg()[0]:.2f} after")
    print("|applied - configured| delay, ms.  relay = pd-link's publish time - due time (its own "
          "stats); e2e = receive - send - configured (both Zenoh hops and this process)")
    cols = ("relay_p50", "relay_p99", "e2e_p50", "e2e_p99", "e2e_max")
    cpu_label = "process CPU" if args.in_process else "pd-link CPU"
    print(f"{'msg/s':>7} {'run':>6} {'sent':>7} {'recv':>7} {'relay p50':>10} {'relay p99':>10} "
          f"{'e2e p50':>9} {'e2e p99':>9} {'e2e max':>9} {cpu_label:>11}")
    if args.in_process:
        print("(in-process: the CPU column is this whole process, load generator included)")
    for rate in args.rates:
        runs = [r for r in rows if r["rate"] == rate]
        for i, r in enumerate(runs, 1):
            print(f"{rate:>7} {i:>6} {r['sent']:>7} {r['received']:>7} "
                  + " ".join(f"{r[c]:>{10 if c.startswith('relay') else 9}.3f}" for c in cols)
                  + f" {r['cpu']:>10.0%}")
        med = {c: float(np.median([r[c] for r in runs])) for c in (*cols, "cpu")}
        print(f"{rate:>7} {'median':>6} {'':>7} {'':>7} "
              + " ".join(f"{med[c]:>{10 if c.startswith('relay') else 9}.3f}" for c in cols)
              + f" {med['cpu']:>10.0%}")
    for b in baseline:
        print(f"baseline, Zenoh only (one loopback hop, no pd-link, no delay) at {b['rate']} "
              f"msg/s: latency p50 {b['p50']:.3f} ms, p99 {b['p99']:.3f} ms, max {b['max']:.3f} "
              f"ms ({b['received']}/{b['sent']} received)")
    fast = [r["relay_p99"] for r in rows if r["rate"] == max(args.rates)]
    print(f"bar: relay p99 <= 1 ms at {max(args.rates)} msg/s -> median p99 "
          f"{np.median(fast):.3f} ms: {'met' if np.median(fast) <= 1.0 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
