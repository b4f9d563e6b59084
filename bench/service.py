#!/usr/bin/env python3
"""Load test of the pd-service daemon: N sessions of the paper's scenario at 20 Hz.

Starts the daemon (``python -m pd_service``, its own process, fresh state dir, free port)
and a load-generator process, for each N in --sessions. Per session and step (50 ms): one
command (20 Hz), one range-finder sample (20 Hz, stamp k - 12), one camera sample every
second step (10 Hz, stamp k - 10). Session i sends at phase i/N of every step, so the load
is spread over the step as independent robots would spread it.

Printed per N, over the measurement interval (after a warm-up); a line in brackets when the
load generator started any of its 1 ms send slots more than 1 ms late (it then sends a
burst: the daemon's latency is judged against a schedule that was not kept):
  pred/s/sess   predictions published per session per second (daemon counter); the tick
                guarantees >= 20, a measurement-triggered publish can add more
  rx/s/sess     predictions received per second, per session, by a probe process
                subscribed to sessions 0-9 (their phase is early in the step)
  p50/p99 us    packet receipt -> prediction put, inside the daemon (ServiceStatus; its
                window is sized to hold the measurements of the measurement interval but
                its first 0.5 s, which follow the probe's own status queries)
  daemon CPU    % of one core (utime + stime from /proc), generator CPU likewise
  us/sess-step  daemon CPU (all threads, utime + stime from /proc) per session and step:
                CPU seconds / (N * interval / 50 ms), in µs
  overruns, flood, late, refused: daemon counters over the interval
  gauge ms      bench/gauge.py just before the run: CPU time of a fixed workload (lower is
                faster); the machine's speed changes between hours, compare figures with it
  behind        more than 1 % of the input refused as late: the daemon did not keep up, and
                its CPU per session-step is then not the cost of the load
After the table, one JSON object per N with the same figures (and the repetition spread
when --repeat > 1: each figure is the median of the runs, ``*_runs`` lists them all).

Usage: python bench/service.py [--sessions 10,100,500,1000] [--duration 10] [--warmup 3]
       [--instances 1]    several daemon instances (rendezvous split), one process each
       [--repeat 1]       run each N this many times, report medians and the runs
       [--root DIR]       benchmark the pd_service of another checkout (daemon's PYTHONPATH),
                          e.g. a `git worktree` of the baseline, side by side (--compare)
       [--compare DIR]    alternate runs of this checkout and DIR (same N, same session)
       [--compare-pure]   alternate runs of this checkout compiled and as pure Python
                          (the daemon with PD_SERVICE_PURE=1; pd_service.native)
       [--profile]        cProfile the daemon's worker thread, print the top functions
       [--threads]        print the CPU seconds of the daemon's busiest threads
       [--pin no]         yes: the daemon's worker thread (pd-worker) alone on CPU 0, all
                          its other threads, the load generator and the probe on the last
                          CPU (taskset's affinity, set once the generator is ready);
                          compare: alternate runs as they are and pinned
       [--perf]           sample the daemon with Linux perf (Debian: linux-perf) over the
                          measurement interval: where its CPU goes by thread and library
                          (Zenoh's threads, the interpreter, the compiled modules, numpy,
                          the C kernels) and the worker's busiest functions
       [--clients declared]  the load generator's senders and displays: plain puts of keys
                          declared once and 10 subscriptions; "plain": the same puts of
                          undeclared keys (the key's string in every message); "sdk":
                          declared as pd_client declares them
Settings reach the daemon through the environment, e.g. PD_SERVICE_BATCH_BUDGET=32. The
benchmark raises admission's limits unless they are set: PD_SERVICE_CPU_BUDGET=1000,
PD_SERVICE_MEMORY_BUDGET_BYTES=8 GiB, PD_SERVICE_CONFIG_RATE_TOTAL and _BURST_TOTAL=100000,
PD_SERVICE_MAX_SESSIONS=100000 (so N sessions are admitted, and created in seconds).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from gauge import gauge_ms

ROOT = Path(__file__).resolve().parents[1]

PERIOD_NS = 50_000_000
#: Measurements a session sends per second (range finder 20 Hz, camera 10 Hz): the daemon
#: records one latency per measurement answered.
SENSOR_RATE = 30
#: The start of the measurement interval left out of the latency percentiles (s).
SETTLE_S = 0.5
CLK_TCK = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds of each thread of a process, by "name/tid" (diagnostics)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[f"{name}/{task.name}"] = (int(fields[11]) + int(fields[12])) / CLK_TCK
    return out


def busiest(before: dict[str, float], after: dict[str, float], wall: float) -> str:
    """The 8 busiest threads over an interval, as % of one core."""
    used = sorted(((after[k] - before.get(k, 0.0), k) for k in after), reverse=True)[:8]
    return ", ".join(f"{k.split('/')[0]} {100 * v / wall:.0f}%" for v, k in used)


def pin_worker(daemons: list[subprocess.Popen], gen_pid: int) -> None:
    """A core for the daemons' worker threads: CPU 0 for each ``pd-worker``, the last CPU for
    every other thread of the daemons, the load generator and this process (the probe).
    With several daemons, their workers share CPU 0."""
    last = (os.cpu_count() or 1) - 1
    for pid in [d.pid for d in daemons] + [gen_pid, os.getpid()]:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                worker = (task / "comm").read_text().strip() == "pd-worker"
                os.sched_setaffinity(int(task.name), {0} if worker else {last})
            except OSError:  # a thread that ended meanwhile
                continue


def unpin_self() -> None:
    """Every thread of this process on every CPU again (after a pinned run: the daemons and
    the generator started next inherit this process's affinity)."""
    cpus = set(range(os.cpu_count() or 1))
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        try:
            os.sched_setaffinity(int(task.name), cpus)
        except OSError:
            continue


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (and its threads), seconds."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


# ------------------------------------------------------------------ load generator ------

def session_name(i: int) -> str:
    return f"bench{i:04d}"


def _paper_spec(session: str, epoch_ns: int):
    from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario

    return paper_scenario().spec(session, epoch_ns, max_delay=RANGER_DELAY)


def run_loadgen(args: argparse.Namespace) -> None:
    import msgpack
    import numpy as np

    from pd_service.scenarios.paper import simulate_paper
    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire import encode, keys

    n = args.sessions
    t = ZenohTransport(zenoh_config(mode=args.mode, listen=[], connect=args.connect))
    epoch = args.epoch
    names = [session_name(i) for i in range(n)]
    # configure, wait for every answer (status put by the owner)
    answered: set[str] = set()
    cond = threading.Condition()

    def on_status(smp) -> None:
        with cond:
            answered.add(keys.session_of(smp.key) or "")
            cond.notify_all()

    h = t.subscribe(keys.ALL_STATUS, on_status)
    for s in names:
        t.put(keys.config_key(s), encode(_paper_spec(s, epoch)))
    with cond:
        ok = cond.wait_for(lambda: len(answered) >= n, timeout=60)
    h.close()
    if not ok:
        print(json.dumps({"error": f"only {len(answered)}/{n} sessions answered"}), flush=True)
        return
    # one simulated paper run, shared by all sessions (the content does not change the cost)
    run = simulate_paper(400, np.random.default_rng(1))
    cam = {smp.step: smp.z.tolist() for smp in run.samples if smp.sensor == "camera"}
    x = run.truth
    pack = msgpack.Packer(use_bin_type=True).pack
    sensor_keys = [(keys.sensor_key(s, "ranger"), keys.sensor_key(s, "camera"),
                    keys.command_key(s)) for s in names]
    put = t.put
    displays = []
    if args.clients == "declared":
        # the same plain puts, of keys declared once (Transport.declare_keys, as the daemon
        # declares its own): a put carries the key's id and reuses its cached route
        t.declare_keys([key for trio in sensor_keys for key in trio])
    if args.clients == "sdk":
        # what pd_client declares: Robot and Operator a cached publisher per sensor and
        # command key (zenoh-ext advanced publishers: a cache, a liveliness token), Display a
        # subscription to its session's predictions (here keeping the newest in Zenoh's
        # ring, read by nobody: no Python per sample)
        import zenoh

        from pd_service.transport import DEFAULT_SENDER_CACHE

        pubs = {key: t.publisher(key, cache=DEFAULT_SENDER_CACHE)
                for trio in sensor_keys for key in trio}
        displays = [t.session.declare_subscriber(keys.prediction_key(s), zenoh.handlers.RingChannel(1))
                    for s in names]

        def put(key: str, payload: bytes) -> None:
            pubs[key].put(payload)
    print(json.dumps({"ready": True}), flush=True)
    end = args.end_ns
    sent = 0
    seq = 0
    k = max(0, (time.time_ns() - epoch) // PERIOD_NS + 1)
    measure_start = args.measure_start_ns
    behind: list[int] = []  # ns by which a slot started late, over the measurement interval
    slot_ns = 1_000_000  # send in 1 ms slots: session i at phase i/N of the step
    # phases spread over the first 90 % of the step: the range finder's delay equals
    # max_delay (12), so a sample processed after the step boundary would be late
    slots = PERIOD_NS // slot_ns
    used = slots * 9 // 10
    per_slot = [[i for i in range(n) if (i * used) // n == j] for j in range(slots)]
    while True:
        t_step = epoch + k * PERIOD_NS
        if t_step >= end:
            break
        r = k % 400
        z_r = [float(x[r, 2] - x[r, 0])]
        z_c = cam.get((k - 10) % 400) if (k - 10) % 2 == 0 else None
        u = [0.5 if 0 < (k + 10) % 400 <= 80 else 0.0]
        for j in range(slots):
            due = t_step + j * slot_ns
            now = time.time_ns()
            dt = (due - now) / 1e9
            if dt > 0:
                time.sleep(dt)
            elif due >= measure_start:  # the generator itself is behind its schedule
                behind.append(now - due)
            for i in per_slot[j]:
                rk, ck, mk = sensor_keys[i]
                s = names[i]
                seq += 1
                put(mk, pack({"v": 1, "session": s, "seq": seq, "step": k + 10,
                              "u": {"shape": [1], "data": u}}))
                put(rk, pack({"v": 1, "session": s, "sensor": "ranger", "seq": seq,
                              "step": k - 12, "z": {"shape": [1], "data": z_r}}))
                sent += 2
                if z_c is not None:
                    put(ck, pack({"v": 1, "session": s, "sensor": "camera", "seq": seq,
                                  "step": k - 10, "z": {"shape": [2], "data": z_c}}))
                    sent += 1
        k += 1
    behind.sort()
    print(json.dumps({"sent": sent, "slots": slots * (end - measure_start) // PERIOD_NS,
                      "slots_late_1ms": sum(1 for b in behind if b > 1_000_000),
                      "slots_late_5ms": sum(1 for b in behind if b > 5_000_000),
                      "max_behind_ms": behind[-1] / 1e6 if behind else 0.0}), flush=True)
    for d in displays:
        d.undeclare()
    t.close()


# ------------------------------------------------------------------ driver --------------

def start_perf(pid: int, duration: float, tmp: str) -> tuple[subprocess.Popen, str]:
    """``perf record`` of the daemon ``pid`` (all its threads, 499 samples per second and
    CPU, no call graphs: little overhead) for ``duration`` s, into a file in ``tmp``."""
    out = f"{tmp}/perf.data"
    proc = subprocess.Popen(["perf", "record", "-F", "499", "-p", str(pid), "-o", out, "-q",
                             "--", "sleep", f"{duration:.1f}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return proc, out


def print_perf(proc: subprocess.Popen, out: str, top: int = 25) -> None:
    """Where the daemon's samples fell: per thread and library, then the worker thread's
    busiest functions (mypyc's compiled functions are named CPyDef_<module>___<name>)."""
    _, err = proc.communicate(timeout=120)
    if proc.returncode != 0:
        print(f"  perf record failed ({proc.returncode}): {err.strip()[-300:]}")
        return

    def report(*opts: str) -> list[str]:
        r = subprocess.run(["perf", "report", "-i", out, "--no-children", "-q", "-g", "none",
                            *opts], capture_output=True, text=True)
        return [ln.rstrip() for ln in r.stdout.splitlines() if ln.strip()]

    print("  perf, daemon's samples by thread and library:")
    for ln in report("--sort", "comm,dso")[:top]:
        print("   ", ln)
    print("  perf, the worker thread's busiest functions:")
    for ln in report("--comm", "pd-worker", "--sort", "dso,sym")[:top]:
        print("   ", ln)


def query_status(t, instance: str):
    """The instance's ServiceStatus; an overloaded daemon may answer late: three tries."""
    from pd_service.wire import ServiceStatus, decode, keys

    for _ in range(3):
        for r in t.get(keys.service_status_key(instance), timeout=5.0):
            if r.ok:
                return decode(r.payload, ServiceStatus)
    raise RuntimeError(f"{instance} did not answer its status query (overloaded?)")


BENCH_ENV = {
    "PD_SERVICE_CPU_BUDGET": "1000", "PD_SERVICE_MEMORY_BUDGET_BYTES": str(8 * 2**30),
    "PD_SERVICE_CONFIG_RATE_TOTAL": "100000", "PD_SERVICE_CONFIG_BURST_TOTAL": "100000",
    "PD_SERVICE_MAX_SESSIONS": "100000",
}


def one_run(n: int, args: argparse.Namespace, root: Path = ROOT, pure: bool = False,
            pin: bool = False) -> dict:
    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire import keys

    unpin_self()
    gauge = gauge_ms()  # how fast the machine is right now (bench/gauge.py)
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    state = tempfile.mkdtemp(prefix="pd-bench-")
    # the daemon's latency window: the measurements of the measurement interval (30 a
    # session and second: range finder 20 Hz, camera 10 Hz) but its first SETTLE_S, when
    # the probe's own status queries (and this process decoding them) take CPU from the
    # daemon; not the warm-up's
    window = max(16, int(SENSOR_RATE * n * max(args.duration - SETTLE_S, 0.5)))
    env = dict(os.environ, PD_SERVICE_LATENCY_WINDOW=str(window), PD_SERVICE_LOG_LEVEL="WARNING",
               PD_SERVICE_INBOX_SIZE="1024")
    env.pop("PD_SERVICE_CONFIG", None)
    for k, v in BENCH_ENV.items():
        env.setdefault(k, v)
    if pure:  # the daemon runs the hot modules from their .py files
        env["PD_SERVICE_PURE"] = "1"
    if root != ROOT:  # the daemon imports pd_service from that checkout
        env["PYTHONPATH"] = os.pathsep.join([str(root)] + [p for p in [env.get("PYTHONPATH")] if p])
    daemons = []
    instances = [f"bench-{j}" for j in range(args.instances)]
    endpoints: list[str] = []
    for j, inst in enumerate(instances):
        dport = port if j == 0 else free_port()
        endpoints.append(f"tcp/127.0.0.1:{dport}")
        cmd = [sys.executable, "-m", "pd_service", "--instance", inst, "--state-dir", f"{state}/{inst}",
                "--listen", f"tcp/127.0.0.1:{dport}"]
        if j > 0:
            cmd += ["--connect", ep]
        others = [i for i in instances if i != inst]
        if others:  # explicit membership: each instance trusts the others' tokens
            cmd += [x for o in others for x in ("--peer", o)]
        denv = dict(env, PD_SERVICE_PROFILE=f"{state}/{inst}.prof") if args.profile else env
        daemons.append(subprocess.Popen(cmd, env=denv, cwd=root))
    probe = ZenohTransport(zenoh_config(mode="peer", listen=[], connect=endpoints))
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            alive = probe.get_liveliness(keys.ALL_SERVICES, timeout=1.0)
            if len(alive) >= len(instances):
                break
        now = time.time_ns()
        epoch = now
        setup_s = 5.0 + n / 200.0
        measure_start = now + int((setup_s + args.warmup) * 1e9)
        end = measure_start + int(args.duration * 1e9)
        gen = subprocess.Popen(
            [sys.executable, __file__, "--loadgen", "--n", str(n)]
            + [x for e in endpoints for x in ("--connect", e)]
            + ["--clients", args.clients] + [
             "--epoch", str(epoch), "--measure-start", str(measure_start), "--end", str(end)],
            stdout=subprocess.PIPE, text=True, cwd=ROOT)
        from pd_service.wire import keys as _keys
        drv = {"n": 0}

        def on_pred(_smp) -> None:
            drv["n"] += 1

        for i in range(min(10, n)):
            probe.subscribe(_keys.prediction_key(session_name(i)), on_pred)
        line = gen.stdout.readline()
        if "ready" not in line:
            raise RuntimeError(f"load generator failed: {line}")
        if pin:
            pin_worker(daemons, gen.pid)
        while time.time_ns() < measure_start:
            time.sleep(0.05)
        s0 = [query_status(probe, i) for i in instances]
        c0 = [cpu_seconds(d.pid) for d in daemons]
        t0 = [thread_cpu(d.pid) for d in daemons] if args.threads else []
        g0 = cpu_seconds(gen.pid)
        d0 = drv["n"]
        w0 = time.monotonic()
        perf = start_perf(daemons[0].pid, args.duration, state) if args.perf else None
        from pd_service.wire import SessionStatus, decode
        pub0 = sum(decode(r.payload, SessionStatus).published for i in range(min(10, n))
                   for r in probe.get(_keys.status_key(session_name(i))) if r.ok)
        dd0 = drv["n"]
        while time.time_ns() < end:
            time.sleep(0.05)
        s1 = [query_status(probe, i) for i in instances]
        c1 = [cpu_seconds(d.pid) for d in daemons]
        if args.threads:
            for d, before in zip(daemons, t0, strict=True):
                print("  daemon's busiest threads (% of a core):",
                      busiest(before, thread_cpu(d.pid), time.monotonic() - w0), flush=True)
        g1 = cpu_seconds(gen.pid)
        wall = time.monotonic() - w0
        if perf is not None:
            print_perf(*perf)
        d1 = drv["n"]
        pub1 = sum(decode(r.payload, SessionStatus).published for i in range(min(10, n))
                   for r in probe.get(_keys.status_key(session_name(i))) if r.ok)
        dd1 = drv["n"]
        if pub1 - pub0 != dd1 - dd0:
            print(f"  (probe sessions: daemon published {pub1 - pub0}, probe received "
                  f"{dd1 - dd0})")
        out = json.loads(gen.stdout.readline() or "{}")
        if out.get("slots_late_1ms"):
            print(f"  (load generator behind its schedule: {out['slots_late_1ms']} of "
                  f"{out['slots']} 1 ms slots started > 1 ms late, {out['slots_late_5ms']} "
                  f"> 5 ms, the worst by {out['max_behind_ms']:.1f} ms)", flush=True)
        gen.wait(30)
    finally:
        probe.close()
        # one at a time, as a rolling restart would: an instance stopped while its
        # successor is stopping too waits 2 s for a confirmation that cannot come (a
        # `handover` warning with every state unconfirmed)
        for d in daemons:
            d.send_signal(signal.SIGTERM)
            try:
                d.wait(30)
            except subprocess.TimeoutExpired:
                d.kill()

    def delta(name: str) -> int:
        return sum(b.counters.get(name, 0) - a.counters.get(name, 0) for a, b in zip(s0, s1, strict=True))

    # latency percentiles: the daemon's window holds the last SENSOR_RATE * n *
    # (duration - SETTLE_S) samples, i.e. the measurement interval but its first half second
    # (weighted mean over instances if several)
    p50 = sum(s.latency_p50_us for s in s1) / len(s1)
    p99 = max(s.latency_p99_us for s in s1)
    res = {
        "n": n,
        "clients": args.clients,
        "gauge_ms": gauge,
        "pred_rate": delta("published") / n / wall,
        "rx_rate": (d1 - d0) / min(10, n) / wall,
        "sent": out.get("sent", 0),
        # the load generator's own schedule: slots (1 ms) it started more than 1 / 5 ms late
        # in the measurement interval, and its worst lag (a lagging generator sends a burst)
        "gen_late_1ms": out.get("slots_late_1ms", 0),
        "gen_late_5ms": out.get("slots_late_5ms", 0),
        "gen_max_behind_ms": out.get("max_behind_ms", 0.0),
        "p50_us": p50,
        "p99_us": p99,
        "cpu_daemon": 100 * sum(b - a for a, b in zip(c0, c1, strict=True)) / wall,
        "cpu_gen": 100 * (g1 - g0) / wall,
        # µs of daemon CPU (all processes, all threads) per session and 50 ms step
        "us_per_session_step": 1e6 * sum(b - a for a, b in zip(c0, c1, strict=True))
        / (n * wall / (PERIOD_NS / 1e9)),
        "overruns": delta("tick_overruns"),
        "flood": delta("flood"),
        "late": delta("late_total"),
        "refused": delta("refused"),
        "accepted": delta("accepted"),
        "in_rate": (delta("accepted") + delta("commands_accepted") + delta("refused")) / wall,
    }
    # behind: more than 1 % of the input refused as late (the daemon could not keep up; its
    # CPU per session-step then counts work it did not finish, not the cost of the load)
    res["saturated"] = res["late"] > 0.01 * res["in_rate"] * wall
    if args.profile:
        import pstats

        for inst in instances:
            print(f"--- cProfile of {inst}'s worker thread (by own time, top 25) ---")
            st = pstats.Stats(f"{state}/{inst}.prof")
            st.sort_stats("tottime").print_stats(25)
            print(f"--- cProfile of {inst}'s worker thread (cumulative, top 40) ---")
            st.sort_stats("cumulative").print_stats(40)
    shutil.rmtree(state, ignore_errors=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sessions", default="10,100,500,1000")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--instances", type=int, default=1)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--root", default="", help="checkout whose pd_service the daemon runs")
    ap.add_argument("--compare", default="", help="second checkout, runs alternate")
    ap.add_argument("--compare-pure", dest="compare_pure", action="store_true",
                    help="alternate compiled and pure-Python runs of this checkout")
    ap.add_argument("--threads", action="store_true", help="print the daemon's busiest threads")
    ap.add_argument("--pin", choices=("no", "yes", "compare"), default="no",
                    help="yes: the daemon's worker thread alone on CPU 0, everything else "
                         "(the daemon's other threads, the generator, the probe) on the last "
                         "CPU; compare: alternate runs without and with")
    ap.add_argument("--perf", action="store_true",
                    help="sample the (first) daemon with Linux perf over the measurement "
                         "interval: its CPU by thread and library, the worker's top functions")
    ap.add_argument("--clients", choices=("plain", "declared", "sdk"), default="declared",
                    help="declared: the load generator sends each message with a session put "
                         "of a key declared once (Transport.declare_keys) and subscribes to 10 "
                         "sessions' predictions; plain: the same puts of undeclared keys "
                         "(~40 %% more of the generator's CPU at 1,000 sessions); sdk: it declares what "
                         "pd_client's Robot, Operator and Display declare for every session "
                         "(cached publishers per sensor and command key, a subscription per "
                         "session's predictions)")
    # load-generator role (internal)
    ap.add_argument("--loadgen", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--connect", action="append", default=[], help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--mode", default="peer", help=argparse.SUPPRESS)  # client: via a router
    ap.add_argument("--epoch", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--measure-start", dest="measure_start_ns", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--end", dest="end_ns", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.loadgen:
        args.sessions = args.n
        run_loadgen(args)
        return
    if args.perf and shutil.which("perf") is None:
        sys.exit("--perf: Linux perf is not installed (Debian: apt-get install linux-perf)")
    print(f"pd-service load test: paper scenario, 20 Hz steps (cmd 20 Hz, ranger 20 Hz, camera "
          f"10 Hz), {args.instances} daemon instance(s), {os.cpu_count()} CPUs, "
          f"{args.duration:g} s measured after {args.warmup:g} s warm-up, "
          f"{args.repeat} run(s) per N, clients {args.clients!r}")
    from pd_service import native

    print(f"hot path of this checkout: {native.STATUS}")
    roots = [("this", ROOT, False)]
    if args.root:
        roots = [(args.root, Path(args.root).resolve(), False)]
    if args.compare:
        roots.append((args.compare, Path(args.compare).resolve(), False))
    if args.compare_pure:
        roots.append(("this, pure Python", roots[0][1], True))
    roots = [(label, root, pure, args.pin == "yes") for label, root, pure in roots]
    if args.pin == "compare":  # each build twice: as it is, then its worker on a core of its own
        roots = [r for label, root, pure, _ in roots
                 for r in ((label, root, pure, False), (label + ", pinned", root, pure, True))]
    hdr = (f"{'N':>5} {'in msg/s':>9} {'pred/s/sess':>11} {'rx/s/sess':>9} {'p50 us':>8} "
           f"{'p99 us':>9} {'daemon CPU':>10} {'us/sess-step':>12} {'gen CPU':>8} "
           f"{'overruns':>8} {'flood':>6} {'late':>6} {'refused':>7} {'gauge ms':>8}")
    if len(roots) > 1:
        hdr = f"{'build':>24} " + hdr
    print(hdr)
    summary = []
    for n in [int(x) for x in args.sessions.split(",")]:
        runs: dict[str, list[dict]] = {label: [] for label, _, _, _ in roots}
        for _ in range(args.repeat):
            for label, root, pure, pin in roots:  # alternate the builds: same machine load
                try:
                    r = one_run(n, args, root, pure, pin)
                except RuntimeError as exc:  # e.g. a daemon too overloaded to answer
                    print(f"{label[-24:]:>24} {n:>5} run failed: {exc}", flush=True)
                    continue
                runs[label].append(r)
                tag = f"{label[-24:]:>24} " if len(roots) > 1 else ""
                print(tag + f"{r['n']:>5} {r['in_rate']:>9.0f} {r['pred_rate']:>11.1f} "
                      f"{r['rx_rate']:>9.1f} {r['p50_us']:>8.0f} {r['p99_us']:>9.0f} "
                      f"{r['cpu_daemon']:>9.0f}% {r['us_per_session_step']:>12.1f} "
                      f"{r['cpu_gen']:>7.0f}% {r['overruns']:>8} {r['flood']:>6} "
                      f"{r['late']:>6} {r['refused']:>7} {r['gauge_ms']:>8.1f}"
                      + ("  behind" if r["saturated"] else ""),
                      flush=True)
        for label, rs in runs.items():
            if rs:
                summary.append(_summarise(label, n, args.instances, rs))
    for obj in summary:
        print(json.dumps(obj), flush=True)


def _summarise(label: str, n: int, instances: int, rs: list[dict]) -> dict:
    """Median of each figure over the runs, plus every run's value and the spread."""
    import statistics

    out: dict = {"build": label, "n": n, "instances": instances, "runs": len(rs),
                 "clients": rs[0]["clients"] if rs else None,
                 "saturated_runs": sum(1 for r in rs if r["saturated"])}
    for key in ("pred_rate", "rx_rate", "p50_us", "p99_us", "cpu_daemon", "us_per_session_step",
                "cpu_gen", "in_rate", "overruns", "late", "refused", "flood", "gauge_ms",
                "gen_late_5ms", "gen_max_behind_ms"):
        vals = [float(r[key]) for r in rs]
        out[key] = round(statistics.median(vals), 2)
        if len(vals) > 1:
            out[key + "_runs"] = [round(v, 2) for v in vals]
    return out

if __name__ == "__main__":
    main()
