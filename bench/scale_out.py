#!/usr/bin/env python3
"""Scale-out over a Zenoh router: what each of K instances receives and costs, and what a
join, a leave and a kill move (key layout 2: keys carry the session's partition).

Every process connects to one Python Zenoh router on loopback (a session in ``router``
mode, its own process): the daemon instances (``python -m pd_service``, each trusting the
others by name: explicit membership), the load generator of ``bench/service.py`` (N paper
sessions at 20 Hz: a command and a range-finder sample every step, a camera sample every
second step) and a probe. Per repetition:

1. **one**: one instance serves all N sessions. Over the measurement interval: the data
   samples it received (its ``samples_received`` counter), its CPU (utime + stime from
   /proc, all threads) per session and 50 ms step, its p50 / p99 receipt -> prediction
   (ServiceStatus, a window of the interval's measurements), its worker's loops a second
   and the samples each took (``worker_loops``) and its loops over 100 ms
   (``worker_slow_loops``).
2. **K**: K fresh instances behind the same router. Per instance the share of the data
   samples it received against total / K (goal: max <= 1.1), and the instances' CPU summed
   per session-step against phase 1's (goal: <= 1.2x).
3. **churn** (with --churn, on phase 2's instances, the load still running): a (K+1)-th
   instance joins, then one leaves (SIGTERM), then one is killed (-9); each event is given
   ``--settle`` s. Per event: the share of the partitions (of the sessions) whose owner
   changed (from the instances' ServiceStatus.sessions before and after), for the sessions
   that did not move the longest gap between two predictions the probe received (the probe
   watches every 10th session; goal: none > 250 ms) and their predictions received against
   those due over the settle (20 per second each: the gap accounting), the gaps by the
   instance that served the session and each old instance's worker loops over 100 ms (its
   ``worker_slow`` log lines say how long and how much of it was CPU; set
   PD_SERVICE_LOG_LEVEL=INFO to see the ``reassigned`` and ``synced`` timings), and for the moved
   sessions their SessionStatus.origin (goal: "replica", never "prior").
   **Exact afterwards**: the load generator sends every session the same values at the
   same steps (one simulated paper run shared by all), so a session that never moved is a
   reference for a moved one: two steps before the newest step the watched sessions all
   predicted, at least one window (lead + max_delay steps) after the event, each moved session's
   prediction (x and P) is compared with the one most of the sessions that stayed agree on
   (goal: within 1e-9). Printed beside it: how many of the stayed sessions agree with that
   one themselves (a session whose samples were refused as late under load, or lost,
   differs from the others without any move: the check's own noise on a saturated machine).

The machine has 2 cores for everything (router, instances, generator, probe): capacity
cannot grow here; the figures are the work each instance does and what it receives, and
the router's CPU per data sample it forwarded to the instances (everything else it carried
counted in: an upper bound of its cost per message, which docs/performance.md's sizing uses).
Printed: a table per phase, then one JSON line with every figure (medians over --repeat).

With the default senders (plain puts, no caches) what a kill -9 loses (the samples after
the newest replica) stays lost, and a taken-over session waits ``2 x recover_timeout_s``
for caches that never answer: ``--clients sdk`` runs the SDK's set-up (cached senders).

Usage: python bench/scale_out.py [--sessions 1000] [--instances 4] [--duration 6]
       [--warmup 4] [--repeat 1] [--churn] [--settle 6] [--clients declared|sdk]
       [--root DIR]  the instances run that checkout's pd_service (A/B against a baseline)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from children import popen, stop_children_on_exit
from gauge import gauge_ms
from service import (
    BENCH_ENV,
    PERIOD_NS,
    SENSOR_RATE,
    SETTLE_S,
    cpu_seconds,
    free_port,
    query_status,
    session_name,
    thread_cpu,
)

ROOT = Path(__file__).resolve().parents[1]


def run_router(port: int) -> None:
    """The router process: a Python Zenoh session in router mode on loopback, until killed."""
    from pd_service.transport import ZenohTransport, zenoh_config

    t = ZenohTransport(zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"]))
    print(json.dumps({"ready": True}), flush=True)
    try:
        signal.sigwait({signal.SIGTERM, signal.SIGINT})
    finally:
        t.close()


class Cluster:
    """The router, the instances and the probe of one phase."""

    def __init__(self, names: list[str], trusted: list[str], state: str,
                 latency_window: int, root: Path = ROOT) -> None:
        self.port = free_port()
        self.ep = f"tcp/127.0.0.1:{self.port}"
        self.state = state
        self.trusted = trusted
        self.epoch = 0  # the sessions' epoch (ns), set by the load's start
        # the instances' latency windows: their share of the measurement interval's
        # measurements (bench/service.py sizes one instance's so)
        self.env = dict(os.environ, PD_SERVICE_LATENCY_WINDOW=str(latency_window))
        self.env.setdefault("PD_SERVICE_LOG_LEVEL", "WARNING")  # INFO: the daemons' events
        self.env.pop("PD_SERVICE_CONFIG", None)
        self.root = root
        if root != ROOT:  # the instances import pd_service from that checkout
            self.env["PYTHONPATH"] = os.pathsep.join(
                [str(root)] + [p for p in [self.env.get("PYTHONPATH")] if p])
        for k, v in BENCH_ENV.items():
            self.env.setdefault(k, v)
        self.router = popen([sys.executable, __file__, "--router", str(self.port)],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
        if "ready" not in (self.router.stdout.readline() if self.router.stdout else ""):
            raise RuntimeError("the router did not start")
        self.daemons: dict[str, subprocess.Popen] = {}
        for name in names:
            self.start(name)
        from pd_service.transport import ZenohTransport, zenoh_config

        self.probe = ZenohTransport(zenoh_config(mode="client", connect=[self.ep]))
        try:
            self.wait_members(len(names))
        except BaseException:  # no process of this phase outlives the benchmark
            self.close()
            raise

    def start(self, name: str) -> None:
        others = [x for n in self.trusted if n != name for x in ("--peer", n)]
        self.daemons[name] = popen(
            [sys.executable, "-m", "pd_service", "--instance", name, "--state-dir",
             f"{self.state}/{name}", "--mode", "client", "--connect", self.ep,
             # the daemon's role listens by default (7447): one free port each
             "--listen", f"tcp/127.0.0.1:{free_port()}", *others],
            env=self.env, cwd=self.root)

    def wait_members(self, n: int, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if len(self.probe.get_liveliness("pd/@service/*", timeout=1.0)) >= n:
                return
            time.sleep(0.2)
        raise RuntimeError(f"fewer than {n} instances became alive")

    def statuses(self) -> dict:
        return {name: query_status(self.probe, name) for name, d in self.daemons.items()
                if d.poll() is None}

    def cpu(self) -> dict[str, float]:
        return {name: cpu_seconds(d.pid) for name, d in self.daemons.items() if d.poll() is None}

    def threads(self) -> dict[str, dict[str, float]]:
        return {name: thread_cpu(d.pid) for name, d in self.daemons.items() if d.poll() is None}

    def stop(self, name: str, sig: int) -> None:
        d = self.daemons.pop(name)
        d.send_signal(sig)
        try:
            d.wait(30)
        except subprocess.TimeoutExpired:
            d.kill()

    def close(self) -> None:
        self.probe.close()
        for name in list(self.daemons):  # one at a time, as a rolling restart would
            self.stop(name, signal.SIGTERM)
        self.router.send_signal(signal.SIGTERM)
        try:
            self.router.wait(10)
        except subprocess.TimeoutExpired:
            self.router.kill()


def received(st) -> int:
    """The data samples an instance took from its subscriptions (ServiceStatus counter)."""
    return int(st.counters.get("samples_received", 0))


def slow_loops(st) -> int:
    """The instance's worker loops over 100 ms while busy (``worker_slow_loops``)."""
    return int(st.counters.get("worker_slow_loops", 0))


def loops(st) -> int:
    """The instance's worker loops so far (``worker_loops``)."""
    return int(st.counters.get("worker_loops", 0))


def window(n: int, k: int, args: argparse.Namespace) -> int:
    """Latency samples an instance of ``k`` keeps: its share of the measurement interval's
    but its first SETTLE_S (bench/service.py)."""
    return max(16, int(SENSOR_RATE * n / k * max(args.duration - SETTLE_S, 0.5)))


def loadgen(c: Cluster, n: int, epoch: int, measure_start: int, end: int,
            clients: str) -> subprocess.Popen:
    gen = popen(
        [sys.executable, str(ROOT / "bench" / "service.py"), "--loadgen", "--n", str(n),
         "--connect", c.ep, "--clients", clients, "--epoch", str(epoch),
         "--measure-start", str(measure_start), "--end", str(end), "--mode", "client"],
        stdout=subprocess.PIPE, text=True, cwd=ROOT)
    line = gen.stdout.readline() if gen.stdout else ""
    if "ready" not in line:
        raise RuntimeError(f"load generator failed: {line}")
    return gen


def measure(c: Cluster, n: int, args: argparse.Namespace, churn: bool) -> dict:
    """Run the load on the cluster; the steady interval's figures, and the churn's if asked."""
    now = time.time_ns()
    setup_s = 5.0 + n / 200.0
    measure_start = now + int((setup_s + args.warmup) * 1e9)
    steady_end = measure_start + int(args.duration * 1e9)
    end = steady_end + (int(3 * args.settle * 1e9) + 2_000_000_000 if churn else 0)
    c.epoch = now
    gen = loadgen(c, n, now, measure_start, end, args.clients)
    while time.time_ns() < measure_start:
        time.sleep(0.05)
    s0, c0, w0 = c.statuses(), c.cpu(), time.monotonic()
    r0, t0 = cpu_seconds(c.router.pid), c.threads()
    while time.time_ns() < steady_end:
        time.sleep(0.05)
    s1, c1, wall = c.statuses(), c.cpu(), time.monotonic() - w0
    r1, t1 = cpu_seconds(c.router.pid), c.threads()
    steps = n * wall / (PERIOD_NS / 1e9)
    per = {name: received(s1[name]) - received(s0[name]) for name in s1}
    total = sum(per.values())
    published = sum(int(s1[k].counters.get("published", 0))
                    - int(s0[k].counters.get("published", 0)) for k in s1)
    res = {"n": n, "instances": len(s1), "wall_s": wall,
           "received": per, "received_total": total, "published": published,
           # the router's CPU per data sample it forwarded to an instance: an upper bound of
           # its cost per message (whatever else it carried is counted in, the predictions
           # the instances put included)
           "router_us_per_message": 1e6 * (r1 - r0) / max(1, total),
           "max_share": max(per.values()) / (total / len(per)) if total else float("nan"),
           "us_per_session_step": 1e6 * sum(c1[k] - c0[k] for k in c1) / steps,
           "late": sum(s1[k].counters.get("late_total", 0) - s0[k].counters.get("late_total", 0)
                       for k in s1),
           # receipt -> prediction put inside each instance (its window: its share of the
           # interval's measurements, see Cluster): the worst instance's p99, the mean p50
           "p99_us": max(s1[k].latency_p99_us for k in s1),
           "p50_us": statistics.mean(s1[k].latency_p50_us for k in s1),
           "slow_loops": sum(slow_loops(s1[k]) - slow_loops(s0[k]) for k in s1),
           # the workers' loops a second (summed over the instances; 0: a build without
           # the counter) and the data samples per loop
           "loops_per_s": sum(loops(s1[k]) - loops(s0[k]) for k in s1) / wall}
    res["samples_per_loop"] = total / (res["loops_per_s"] * wall) if res["loops_per_s"] \
        else float("nan")
    res["threads"] = by_thread(t0, t1, {k: c.daemons[k].pid for k in t1}, steps)
    if churn:
        res["churn"] = churn_events(c, args)
    gen.wait(max(30.0, (end - time.time_ns()) / 1e9 + 30))
    return res


def by_thread(t0: dict[str, dict[str, float]], t1: dict[str, dict[str, float]],
              pids: dict[str, int], steps: float) -> dict[str, float]:
    """The instances' CPU over the interval by kind of thread, summed over the instances, µs
    per session-step: a thread's kind is its name without a trailing number (Zenoh's
    ``rx-0``, ``rx-1``: ``rx``); an instance's main thread is ``main``."""
    out: dict[str, float] = {}
    for inst, after in t1.items():
        before = t0.get(inst, {})
        for key, sec in after.items():
            name, tid = key.rsplit("/", 1)
            kind = "main" if int(tid) == pids[inst] else re.sub(r"[-_ ]?[0-9]+$", "", name)
            out[kind] = out.get(kind, 0.0) + 1e6 * (sec - before.get(key, 0.0)) / steps
    return dict(sorted(((k, v) for k, v in out.items() if v >= 0.005), key=lambda kv: -kv[1]))


def owners(statuses: dict) -> dict[str, str]:
    """Session -> the instance that serves it, from every live instance's ServiceStatus."""
    return {s: name for name, st in statuses.items() for s in st.sessions}


#: Steps after an event before the moved sessions are compared (the paper spec's lead 10 +
#: max_delay 12: one window), and the most recent predictions kept per watched session.
WINDOW_STEPS = 22
KEEP_PREDICTIONS = 200


def agreement(preds: dict[str, dict[int, bytes]], moved: list[str], stayed: list[str],
              after_step: int) -> dict:
    """Moved sessions against the sessions that stayed, at the newest step >= ``after_step``
    every compared session predicted: the (x, P) most stayed sessions agree on (to 1e-9) is
    the reference. Returns the step, how many moved / stayed sessions are within 1e-9 of it,
    and the largest difference of a moved one."""
    import numpy as np

    from pd_service.wire import Prediction, decode

    both = [s for s in moved + stayed if preds.get(s)]
    steps = set.intersection(*(set(preds[s]) for s in both)) if both else set()
    # two steps before the newest: the sessions get their step's samples at phases spread
    # over the step, so at the newest some have predicted from them and some not yet
    newest = max(steps, default=0)
    steps = {k for k in steps if after_step <= k <= newest - 2}
    if not steps or not any(s in both for s in moved) or not any(s in both for s in stayed):
        return {"step": None}
    k = max(steps)
    got = {s: decode(preds[s][k], Prediction) for s in both}

    def same(a, b) -> bool:
        return bool(np.allclose(a.x, b.x, rtol=0, atol=1e-9)
                    and np.allclose(a.P, b.P, rtol=0, atol=1e-9))

    groups: list[list[str]] = []
    for s in (x for x in stayed if x in got):
        for g in groups:
            if same(got[g[0]], got[s]):
                g.append(s)
                break
        else:
            groups.append([s])
    ref = got[max(groups, key=len)[0]]
    m = [s for s in moved if s in got]
    dx = max(float(np.abs(got[s].x - ref.x).max()) for s in m)
    dP = max(float(np.abs(got[s].P - ref.P).max()) for s in m)
    return {"step": k, "moved_compared": len(m),
            "moved_exact_1e9": sum(1 for s in m if same(got[s], ref)),
            # P differs only if the packets used differ (one lost, refused or extra); x
            # differs also with the same packets if the state resumed from was not the same
            "moved_max_diff": max(dx, dP), "moved_max_diff_x": dx, "moved_max_diff_P": dP,
            "stayed_compared": sum(len(g) for g in groups),
            "stayed_agreeing": max(len(g) for g in groups)}


def churn_events(c: Cluster, args: argparse.Namespace) -> list[dict]:
    import msgpack

    from pd_service.wire import SessionStatus, decode, keys

    watched = [session_name(i) for i in range(0, args.sessions, 10)]
    last: dict[str, int] = {}
    gaps: dict[str, int] = {}
    count: dict[str, int] = {}
    preds: dict[str, dict[int, bytes]] = {s: {} for s in watched}
    lock = threading.Lock()

    def on_pred(smp) -> None:
        t = time.monotonic_ns()
        s = keys.parse_key(smp.key).session
        try:  # the step only (msgpack, no validation): decoded when compared
            step = int(msgpack.unpackb(smp.payload, raw=False)["step"])
        except Exception:
            step = None
        with lock:
            p = last.get(s)
            if p is not None and t - p > gaps.get(s, 0):
                gaps[s] = t - p
            last[s] = t
            count[s] = count.get(s, 0) + 1
            if step is not None:
                kept = preds[s]
                kept[step] = smp.payload
                if len(kept) > KEEP_PREDICTIONS:
                    del kept[min(kept)]

    handles = [c.probe.subscribe(keys.prediction_key(s), on_pred) for s in watched]
    events = []
    spare = [n for n in c.trusted if n not in c.daemons]
    plan = [("join", spare[0], None), ("leave (SIGTERM)", None, signal.SIGTERM),
            ("kill -9", None, signal.SIGKILL)]
    time.sleep(1.0)
    for what, name, sig in plan:
        st_before = c.statuses()
        before = owners(st_before)
        with lock:
            gaps.clear()
            count.clear()
        t_event = time.time_ns()
        event_step = (t_event - c.epoch) // PERIOD_NS
        if sig is None:
            assert name is not None
            c.start(name)
        else:
            name = sorted(c.daemons)[0]
            c.stop(name, sig)
        time.sleep(args.settle)
        settled_s = (time.time_ns() - t_event) / 1e9
        st_after = c.statuses()
        after = owners(st_after)
        with lock:
            g = dict(gaps)
            n_got = dict(count)
            kept = {s: dict(v) for s, v in preds.items()}
        moved = [s for s in before if after.get(s) != before[s]]
        parts_before = {keys.partition_of(s): o for s, o in before.items()}
        parts_after = {keys.partition_of(s): o for s, o in after.items()}
        moved_parts = [p for p in parts_before if parts_after.get(p) != parts_before[p]]
        stayed = [s for s in watched if s in before and s not in moved]
        origins: dict[str, int] = {}
        for s in moved[:50]:
            for r in c.probe.get(keys.status_key(s), timeout=5.0):
                if r.ok:
                    o = decode(r.payload, SessionStatus).origin
                    origins[o] = origins.get(o, 0) + 1
        worst = max((g.get(s, 0) for s in stayed), default=0) / 1e6
        gapped: dict[str, int] = {}  # the stayed sessions' gaps over 250 ms by their owner
        for s in stayed:
            if g.get(s, 0) > 250e6:
                gapped[before[s]] = gapped.get(before[s], 0) + 1
        slow = {k: slow_loops(st_after[k]) - slow_loops(st_before[k])
                for k in st_after if k in st_before}
        due = settled_s / (PERIOD_NS / 1e9)  # predictions due per session over the settle
        got = sorted(n_got.get(s, 0) / due for s in stayed)
        moved_watched = [s for s in watched if s in moved]
        exact = agreement(kept, moved_watched, stayed, event_step + WINDOW_STEPS + 1
                          + int(args.settle * 1e9 // PERIOD_NS) // 2)
        events.append({"event": what, "instance": name, "members_after": len(c.daemons),
                       "partitions_moved": len(moved_parts), "partitions": len(parts_before),
                       "sessions_moved": len(moved), "unserved_after": args.sessions - len(after),
                       "stayed_watched": len(stayed), "stayed_gap_max_ms": round(worst, 1),
                       "stayed_gaps_over_250ms": sum(1 for s in stayed if g.get(s, 0) > 250e6),
                       "stayed_gaps_by_owner": dict(sorted(gapped.items())),
                       "worker_slow_loops": dict(sorted(slow.items())),
                       "stayed_received_of_due_min": round(got[0], 3) if got else None,
                       "stayed_received_of_due_median": round(statistics.median(got), 3)
                       if got else None,
                       "moved_origins": origins, "moved_exact": exact})
    for h in handles:
        h.close()
    return events


def one_repetition(args: argparse.Namespace) -> dict:
    k = args.instances
    names = [f"inst-{j}" for j in range(k + 1)]
    out: dict = {"gauge_ms": gauge_ms()}
    state = tempfile.mkdtemp(prefix="pd-scale-")
    try:
        c = Cluster(["inst-0"], ["inst-0"], f"{state}/one", window(args.sessions, 1, args),
                    args.root)
        try:
            out["one"] = measure(c, args.sessions, args, churn=False)
        finally:
            c.close()
        c = Cluster(names[:k], names, f"{state}/many", window(args.sessions, k, args),
                    args.root)
        try:
            out["many"] = measure(c, args.sessions, args, churn=args.churn)
        finally:
            c.close()
    finally:
        shutil.rmtree(state, ignore_errors=True)
    out["cpu_ratio"] = out["many"]["us_per_session_step"] / out["one"]["us_per_session_step"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sessions", type=int, default=1000)
    ap.add_argument("--instances", type=int, default=4)
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--warmup", type=float, default=4.0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--churn", action="store_true", help="join, leave and kill after phase 2")
    ap.add_argument("--settle", type=float, default=6.0, help="seconds after each churn event")
    ap.add_argument("--clients", choices=("declared", "sdk"), default="declared",
                    help="the load's senders: plain puts of declared keys, or what the SDK "
                         "declares (a cached publisher per key, a display per session): "
                         "the set-up in which a takeover reads back what a kill lost")
    ap.add_argument("--root", type=Path, default=ROOT,
                    help="run the instances on the pd_service of another checkout (a baseline "
                         "worktree), with this benchmark's load, router and figures")
    ap.add_argument("--router", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.router:
        run_router(args.router)
        return
    # a SIGTERM / SIGINT or an exception stops the router, the instances and the load started
    stop_children_on_exit()
    from pd_service.wire import keys

    print(f"scale-out: {args.sessions} paper sessions at 20 Hz through one Python Zenoh router, "
          f"1 then {args.instances} instances, P = {keys.partitions()} partitions, "
          f"{os.cpu_count()} CPUs, {args.duration:g} s measured after {args.warmup:g} s warm-up, "
          f"senders: {args.clients}, instances' pd_service: {args.root}")
    reps = []
    for r in range(args.repeat):
        res = one_repetition(args)
        reps.append(res)
        one, many = res["one"], res["many"]
        print(f"run {r + 1}: gauge {res['gauge_ms']:.1f} ms")
        print(f"  1 instance: {one['received_total']} samples received, "
              f"{one['us_per_session_step']:.1f} µs CPU per session-step, late {one['late']}, "
              f"p50 {one['p50_us']:.0f} µs, p99 {one['p99_us']:.0f} µs, worker loops "
              f"{one['loops_per_s']:.0f}/s ({one['samples_per_loop']:.1f} samples each), over "
              f"100 ms {one['slow_loops']}; router {one['router_us_per_message']:.2f} µs CPU "
              f"per message")
        shares = ", ".join(f"{name} {v / (many['received_total'] / len(many['received'])):.3f}"
                           for name, v in sorted(many["received"].items()))
        print(f"  {many['instances']} instances: {many['received_total']} samples received; "
              f"share of total/{many['instances']}: {shares} (max {many['max_share']:.3f}); "
              f"{many['us_per_session_step']:.1f} µs CPU per session-step summed "
              f"({res['cpu_ratio']:.2f}x one), late {many['late']}, p50 {many['p50_us']:.0f} "
              f"µs (mean), p99 {many['p99_us']:.0f} µs (worst instance), worker loops "
              f"{many['loops_per_s']:.0f}/s summed ({many['samples_per_loop']:.1f} samples each), "
              f"over 100 ms {many['slow_loops']}; router {many['router_us_per_message']:.2f} µs "
              f"CPU per message")
        for label, ph in (("1", one), (str(many["instances"]), many)):
            print(f"  {label} by thread (µs per session-step, summed): " + ", ".join(
                f"{k} {v:.1f}" for k, v in ph["threads"].items() if v >= 0.05))
        for ev in many.get("churn", []):
            print(f"  {ev['event']:<16} {ev['instance']}: partitions moved "
                  f"{ev['partitions_moved']}/{ev['partitions']}, sessions moved "
                  f"{ev['sessions_moved']}, unserved {ev['unserved_after']}; sessions that "
                  f"stayed (watched {ev['stayed_watched']}): longest gap "
                  f"{ev['stayed_gap_max_ms']} ms, {ev['stayed_gaps_over_250ms']} over 250 ms "
                  f"(by owner {ev['stayed_gaps_by_owner']}; old instances' worker loops over "
                  f"100 ms {ev['worker_slow_loops']}); moved sessions' origin "
                  f"{ev['moved_origins']}", flush=True)
            ex = ev["moved_exact"]
            if ex.get("step") is not None:
                print(f"  {'':<16} predictions of sessions that stayed: "
                      f"{ev['stayed_received_of_due_median']} of those due (median; min "
                      f"{ev['stayed_received_of_due_min']}); at step {ex['step']} moved "
                      f"sessions within 1e-9 of the stayed ones: {ex['moved_exact_1e9']}/"
                      f"{ex['moved_compared']} (largest difference: x {ex['moved_max_diff_x']:.2e}, P "
                      f"{ex['moved_max_diff_P']:.2e});"
                      f" stayed agreeing among themselves {ex['stayed_agreeing']}/"
                      f"{ex['stayed_compared']}", flush=True)

    def med(get) -> float:
        return round(statistics.median(get(r) for r in reps), 3)

    print(json.dumps({
        "sessions": args.sessions, "instances": args.instances, "partitions": keys.partitions(),
        "clients": args.clients,
        "runs": len(reps), "gauge_ms": med(lambda r: r["gauge_ms"]),
        "one_us_per_session_step": med(lambda r: r["one"]["us_per_session_step"]),
        "many_us_per_session_step": med(lambda r: r["many"]["us_per_session_step"]),
        "cpu_ratio": med(lambda r: r["cpu_ratio"]),
        "cpu_ratio_runs": [round(r["cpu_ratio"], 3) for r in reps],
        "max_share": med(lambda r: r["many"]["max_share"]),
        "max_share_runs": [round(r["many"]["max_share"], 3) for r in reps],
        "router_us_per_message": med(lambda r: r["many"]["router_us_per_message"]),
        "one_p99_us": med(lambda r: r["one"]["p99_us"]),
        "many_p99_us": med(lambda r: r["many"]["p99_us"]),
        "p99_us_runs": [[round(r[ph]["p99_us"]) for ph in ("one", "many")] for r in reps],
        "loops_per_s": {ph: med(lambda r, ph=ph: r[ph]["loops_per_s"]) for ph in ("one", "many")},
        "samples_per_loop": {ph: med(lambda r, ph=ph: r[ph]["samples_per_loop"])
                             for ph in ("one", "many")},
        "threads": {ph: {k: med(lambda r, ph=ph, k=k: r[ph]["threads"].get(k, 0.0))
                         for k in reps[0][ph]["threads"]} for ph in ("one", "many")},
        "churn": [r["many"].get("churn", []) for r in reps]}))


if __name__ == "__main__":
    main()
