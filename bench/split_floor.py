#!/usr/bin/env python3
"""The machine's floor for issue 41's CPU goal: what splitting a fixed per-message work over K
processes costs on this machine, with no pd-service code in the receivers.

``bench/scale_out.py`` compares the summed CPU of K daemon instances with one instance's
(goal <= 1.2x). This benchmark runs the same router (a Python Zenoh session in router mode on
loopback, its own process), the same load (``bench/service.py``'s generator: N paper sessions
at 20 Hz, key layout 2) and the same measurement (utime + stime of every thread of every
receiver from /proc, per session and 50 ms step), but the receivers are *stubs*: a Zenoh
client that subscribes to its partitions' sensor and command wildcards with the daemon's
drained FIFO channels (one sensor and one command wildcard over all partitions when it owns
them all, as the daemon), and one worker thread that looks at the channels every
millisecond, unpacks each message (msgpack), does a fixed work on the session's own arrays (``--work-us``
µs a message, calibrated at the stub's start: numpy operations on a 4 x 4 state and its
window of 12 covariances, so each session's memory is touched as the daemon's is), and puts
one ~250 B reply per command (the prediction's size) on the session's prediction key through
a publisher declared once. A stub owns partitions ``p`` with ``p % K == j`` (an exact
quarter each with 64 partitions) and answers a session's config with a status put so that
the generator starts.

What it measures: the summed CPU of K stubs over one stub's, when each stub's per-message work
is the same by construction. Whatever exceeds 1.0 here is what this machine (2 cores shared by
the router, the generator and K receivers), Zenoh's per-process threads and a 1 ms polling
loop charge for the split itself: the part of scale_out's ratio that no change inside the
daemon removes. Also printed: each phase's stubs' CPU by thread, the router's CPU per message,
the samples each worker loop took.

Usage: python bench/split_floor.py [--sessions 500] [--instances 4] [--work-us 10]
       [--duration 6] [--warmup 4] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

from children import popen, stop_children_on_exit
from gauge import gauge_ms
from scale_out import by_thread, loadgen
from service import PERIOD_NS, cpu_seconds, free_port, thread_cpu

ROOT = Path(__file__).resolve().parents[1]
#: The stub's worker loop period (s): the daemon's ``round_interval_us`` default.
LOOP_S = 1e-3
#: The reply's payload size (B): a paper session's Prediction.
REPLY_BYTES = 250


def run_stub(index: int, k: int, endpoint: str, work_us: float) -> None:
    """One receiver: partitions p with p % k == index; prints "ready", then a JSON line of its
    counters on each SIGUSR1, until SIGTERM."""
    import msgpack
    import numpy as np
    import zenoh

    from pd_service.transport import zenoh_config
    from pd_service.wire import keys

    parts = [p for p in range(keys.partitions()) if p % k == index]
    session = zenoh.open(zenoh_config(mode="client", connect=[endpoint]))
    counts = {"received": 0, "published": 0, "loops": 0}
    pubs: dict[str, zenoh.Publisher] = {}
    state: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    lock = threading.Lock()
    f = np.eye(4) + np.diag(np.full(3, 0.05), 1)
    q = np.eye(4) * 1e-3

    def new_state() -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(4), np.tile(np.eye(4), (12, 1, 1))

    def work(x: np.ndarray, window: np.ndarray, reps: int) -> None:
        for i in range(reps):  # P' = F P F^T + Q on the window's covariances, in turn
            j = i % 12
            window[j] = f @ window[j] @ f.T + q
            x += 1e-9 * window[j][0]

    # calibrate the repetitions that take work_us µs on this machine, now
    x0, w0 = new_state()
    reps = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(200):
            work(x0, w0, reps)
        per = (time.perf_counter() - t0) / 200 * 1e6
        if per >= work_us or reps > 10_000:
            break
        reps = max(reps + 1, int(reps * work_us / max(per, 1e-3)))
    pad = b"\0" * (REPLY_BYTES - 40)
    pack = msgpack.Packer(use_bin_type=True).pack

    def on_config(smp: zenoh.Sample) -> None:
        s = keys.session_of(str(smp.key_expr)) or ""
        if keys.partition_of(s) % k != index:
            return
        with lock:
            if s not in pubs:
                pubs[s] = session.declare_publisher(keys.prediction_key(s))
                state[s] = new_state()
        session.put(keys.status_key(s), b"stub")

    handles = [session.declare_subscriber(keys.ALL_CONFIGS, on_config)]
    channels = []
    # as the daemon: one owning every partition subscribes the two wildcards
    exprs = [keys.ALL_SENSORS, keys.ALL_COMMANDS] if k == 1 else \
        [ke for p in parts for ke in (keys.partition_sensors(p), keys.partition_commands(p))]
    for ke in exprs:
        sub = session.declare_subscriber(ke, zenoh.handlers.FifoChannel(65_536))
        handles.append(sub)
        channels.append(sub.try_recv)
    stop = threading.Event()

    def worker() -> None:
        unpack = msgpack.unpackb
        while not stop.is_set():
            t0 = time.monotonic()
            n = 0
            for try_recv in channels:
                while (smp := try_recv()) is not None:
                    msg = unpack(smp.payload.to_bytes())
                    s = msg.get("session", "")
                    st = state.get(s)
                    n += 1
                    if st is None:
                        continue
                    work(st[0], st[1], reps)
                    if "u" in msg:  # one reply per session-step, as the daemon's prediction
                        pubs[s].put(pack({"session": s, "step": msg.get("step", 0),
                                          "x": st[0].tolist(), "pad": pad}))
                        counts["published"] += 1
            counts["received"] += n
            counts["loops"] += 1
            left = LOOP_S - (time.monotonic() - t0)
            if left > 0:
                time.sleep(left)

    th = threading.Thread(target=worker, name="stub-worker", daemon=True)
    th.start()

    def on_usr1(_signum: int, _frame: object) -> None:
        print(json.dumps(dict(counts, reps=reps)), flush=True)

    done = threading.Event()
    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    print(json.dumps({"ready": True, "partitions": len(parts), "reps": reps}), flush=True)
    try:
        while not done.is_set():  # not sigwait: the SIGUSR1 handler needs the main thread
            time.sleep(0.05)
    finally:
        stop.set()
        th.join(1.0)
        for h in handles:
            h.undeclare()
        session.close()


def counters(stub: subprocess.Popen) -> dict:
    stub.send_signal(signal.SIGUSR1)
    line = stub.stdout.readline() if stub.stdout else ""
    return json.loads(line)


def phase(k: int, args: argparse.Namespace) -> dict:
    """Router, k stubs and the load; the steady interval's figures."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = popen([sys.executable, str(ROOT / "bench" / "scale_out.py"), "--router", str(port)],
                   stdout=subprocess.PIPE, text=True, cwd=ROOT)
    if "ready" not in (router.stdout.readline() if router.stdout else ""):
        raise RuntimeError("the router did not start")
    stubs: list[subprocess.Popen] = []
    try:
        for j in range(k):
            stubs.append(popen([sys.executable, __file__, "--stub", str(j), str(k), ep,
                                str(args.work_us)], stdout=subprocess.PIPE, text=True, cwd=ROOT))
        ready = [json.loads(s.stdout.readline()) for s in stubs if s.stdout]
        if not all(r.get("ready") for r in ready):
            raise RuntimeError(f"a stub did not start: {ready}")
        n = args.sessions
        now = time.time_ns()
        measure_start = now + int((5.0 + n / 200.0 + args.warmup) * 1e9)
        end = measure_start + int(args.duration * 1e9)
        gen = loadgen(SimpleNamespace(ep=ep), n, now, measure_start, end, "declared")
        while time.time_ns() < measure_start:
            time.sleep(0.05)
        k0 = [counters(s) for s in stubs]
        c0 = [cpu_seconds(s.pid) for s in stubs]
        t0 = {str(j): thread_cpu(s.pid) for j, s in enumerate(stubs)}
        r0, w0 = cpu_seconds(router.pid), time.monotonic()
        while time.time_ns() < end:
            time.sleep(0.05)
        k1 = [counters(s) for s in stubs]
        c1 = [cpu_seconds(s.pid) for s in stubs]
        t1 = {str(j): thread_cpu(s.pid) for j, s in enumerate(stubs)}
        r1, wall = cpu_seconds(router.pid), time.monotonic() - w0
        gen.wait(60)
        steps = n * wall / (PERIOD_NS / 1e9)
        got = [b["received"] - a["received"] for a, b in zip(k0, k1, strict=True)]
        total = sum(got)
        loops = sum(b["loops"] - a["loops"] for a, b in zip(k0, k1, strict=True))
        return {"instances": k, "wall_s": wall, "received": got, "received_total": total,
                "reps": [r["reps"] for r in ready],
                "published": sum(b["published"] - a["published"] for a, b in zip(k0, k1, strict=True)),
                "max_share": max(got) / (total / k) if total else float("nan"),
                "us_per_session_step": 1e6 * sum(b - a for a, b in zip(c0, c1, strict=True)) / steps,
                "router_us_per_message": 1e6 * (r1 - r0) / max(1, total),
                "samples_per_loop": total / max(1, loops),
                "threads": by_thread(t0, t1, {str(j): s.pid for j, s in enumerate(stubs)},
                                     steps)}
    finally:
        for s in stubs:
            s.send_signal(signal.SIGTERM)
        for s in stubs:
            try:
                s.wait(15)
            except subprocess.TimeoutExpired:
                s.kill()
        router.send_signal(signal.SIGTERM)
        try:
            router.wait(10)
        except subprocess.TimeoutExpired:
            router.kill()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sessions", type=int, default=500)
    ap.add_argument("--instances", type=int, default=4)
    ap.add_argument("--work-us", type=float, default=10.0,
                    help="the stub's fixed work per message (µs on this machine)")
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--warmup", type=float, default=4.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--stub", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.stub:
        j, k, ep, w = args.stub
        run_stub(int(j), int(k), ep, float(w))
        return
    stop_children_on_exit()
    from pd_service.wire import keys

    print(f"split floor: {args.sessions} paper sessions at 20 Hz through one Python Zenoh "
          f"router, 1 then {args.instances} stub receivers ({args.work_us:g} µs of work a "
          f"message), P = {keys.partitions()}, {os.cpu_count()} CPUs, {args.duration:g} s "
          f"measured after {args.warmup:g} s warm-up", file=sys.stderr, flush=True)
    reps = []
    for r in range(args.repeat):
        g = gauge_ms()
        one = phase(1, args)
        many = phase(args.instances, args)
        ratio = many["us_per_session_step"] / one["us_per_session_step"]
        reps.append({"gauge_ms": g, "one": one, "many": many, "cpu_ratio": ratio})
        print(f"run {r + 1}: gauge {g:.1f} ms")
        for label, ph in (("1 stub", one), (f"{args.instances} stubs", many)):
            print(f"  {label:<8}: {ph['received_total']} samples received (max share "
                  f"{ph['max_share']:.3f}), {ph['us_per_session_step']:.1f} µs CPU per "
                  f"session-step summed, {ph['samples_per_loop']:.1f} samples a loop, router "
                  f"{ph['router_us_per_message']:.2f} µs per message; by thread: " + ", ".join(
                      f"{t} {v:.1f}" for t, v in ph["threads"].items() if v >= 0.05))
        print(f"  ratio {ratio:.2f}x", flush=True)

    def med(get) -> float:
        return round(statistics.median(get(r) for r in reps), 3)

    print(json.dumps({
        "sessions": args.sessions, "instances": args.instances, "work_us": args.work_us,
        "partitions": keys.partitions(), "runs": len(reps),
        "gauge_ms": med(lambda r: r["gauge_ms"]),
        "one_us_per_session_step": med(lambda r: r["one"]["us_per_session_step"]),
        "many_us_per_session_step": med(lambda r: r["many"]["us_per_session_step"]),
        "cpu_ratio": med(lambda r: r["cpu_ratio"]),
        "cpu_ratio_runs": [round(r["cpu_ratio"], 3) for r in reps],
        "samples_per_loop": {ph: med(lambda r, ph=ph: r[ph]["samples_per_loop"])
                             for ph in ("one", "many")},
        "threads": {ph: {t: med(lambda r, ph=ph, t=t: r[ph]["threads"].get(t, 0.0))
                         for t in reps[0][ph]["threads"]} for ph in ("one", "many")}}))


if __name__ == "__main__":
    main()
