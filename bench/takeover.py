#!/usr/bin/env python3
"""How long a takeover's read-back holds the sessions taken over.

Two daemon instances (inst-x, inst-y; explicit peers) share N paper sessions. A sender
process keeps, for every session, one cached publisher (``cache=64``: the SDK's Robot and
Operator keep such caches) on each of its data keys (ranger, camera, command), and has put
``--steps`` steps of data on each. Then inst-y is killed (SIGKILL: no handover). inst-x takes
its sessions over, parks them, and reads their senders' caches back
(``Lifecycle.read_back_taken``): until a session's own read-back ends, its live messages wait.
With ``--signal term`` inst-y is stopped gracefully instead: it hands its sessions' states
over and waits until inst-x confirms it holds them; the table then adds that hand-over's
time and what was left unconfirmed (inst-y's ``event=handover`` line), and the time from the
signal to inst-y's exit.

Three sender modes:

* ``live``: the caches answer at once (loopback);
* ``slow``: each cache answers ``--answer-ms`` late (300 ms: a sender across a slow link;
  emulated with a token and a queryable on zenoh-ext's cache layout, as loopback here
  cannot be given a delay);
* ``stalled``: the sender is stopped (SIGSTOP) before the kill: its caches' tokens stay,
  their queries go unanswered until ``recover_timeout_s`` (2 s), or until Zenoh's lease
  declares the sender gone (~10 s), whichever is first.

Printed per N and mode (medians of --repeat runs, spread in brackets): the sessions taken
over, the samples read back, the read-back's wall time from inst-x's ``event=read_back`` log
line, the time from the kill to that line, the time from the kill to the first prediction
of each session taken over (the median session's and the last one's: a taken-over session
publishes only once its senders' caches were read, or ``2 x recover_timeout_s`` passed) and
how their wait ended (``SessionStatus.readback``: answered / timeout); then one JSON object.

    .venv/bin/python bench/takeover.py --sessions 50,200 --repeat 3
    .venv/bin/python bench/takeover.py --sessions 50 --modes slow --root ../baseline
    .venv/bin/python bench/takeover.py --sessions 50,200 --modes live --signal term
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STEP_NS = 50_000_000
HANDOVER = re.compile(r"event=handover successor=inst-x sessions=(\d+) unconfirmed=(\d+) "
                      r"seconds=([\d.]+) resent=(\d+)")
READ_BACK = re.compile(r"ts=(\S+) .*event=read_back sessions=(\d+) samples=(\d+) seconds=(\S+)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_senders(args: argparse.Namespace) -> None:
    """Child: cached publishers for every session, ``--steps`` steps of data each, then
    wait (stdin closed: exit)."""
    import numpy as np

    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire import Command, Measurement, encode, keys

    t = ZenohTransport(zenoh_config(mode="peer", listen=[], connect=[args.connect]))
    now = (time.time_ns() - args.epoch) // STEP_NS
    held = []
    for i in range(args.n):
        s = f"take{i:04d}"
        data = {keys.sensor_key(s, "ranger"): [
                    encode(Measurement(session=s, sensor="ranger", seq=k, step=k - 2,
                                       z=np.array([5.0]))) for k in range(now - args.steps, now)],
                keys.sensor_key(s, "camera"): [
                    encode(Measurement(session=s, sensor="camera", seq=k, step=k - 2,
                                       z=np.array([5.0, 0.0])))
                    for k in range(now - args.steps, now)],
                keys.command_key(s): [
                    encode(Command(session=s, seq=k, step=k + 10, u=np.array([0.1])))
                    for k in range(now - args.steps, now)]}
        for j, (key, payloads) in enumerate(data.items()):
            if args.answer_ms > 0:
                held += emulated_cache(t, key, payloads, args.answer_ms / 1e3, 3 * i + j)
                continue
            pub = t.publisher(key, cache=64)
            for payload in payloads:
                pub.put(payload)
    print("ready", flush=True)
    sys.stdin.read()
    t.close()


def emulated_cache(t, key: str, payloads: list[bytes], delay_s: float, eid: int) -> list:
    """A sender's cache across a slow link: its token and queryable on zenoh-ext's layout
    (``<key>/@adv/pub/<zid>/<eid>/...``), answering each query ``delay_s`` late."""
    import zenoh

    at = f"{key}/@adv/pub/{t.session.info.zid()}/{eid}/_"

    def answer(q: zenoh.Query) -> None:
        for payload in payloads:
            q.reply(key, payload)
        q.drop()

    def on_query(q: zenoh.Query) -> None:
        threading.Timer(delay_s, answer, (q,)).start()

    return [t.session.declare_queryable(at, on_query),
            t.session.liveliness().declare_token(at)]


def one_run(n: int, mode: str, args: argparse.Namespace, root: Path) -> dict:
    from pd_service.scenarios.paper import paper_scenario
    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire import encode, keys

    state = Path(tempfile.mkdtemp(prefix="pd-takeover-"))
    port = free_port()
    hub_ep = f"tcp/127.0.0.1:{port}"
    hub = ZenohTransport(zenoh_config(mode="peer", listen=[hub_ep], multicast=False))
    env = dict(os.environ, PD_SERVICE_LOG_LEVEL="INFO", PD_SERVICE_MAX_SESSIONS="100000",
               PD_SERVICE_CPU_BUDGET="1000", PD_SERVICE_CONFIG_RATE_TOTAL="100000",
               PD_SERVICE_CONFIG_BURST_TOTAL="100000")
    env.pop("PD_SERVICE_CONFIG", None)
    if root != ROOT:
        env["PYTHONPATH"] = str(root)
    procs: dict[str, subprocess.Popen] = {}
    eps: dict[str, str] = {}
    statuses: dict[str, str] = {}
    cond = threading.Condition()

    def on_status(smp) -> None:
        from pd_service.wire import SessionStatus, decode
        st = decode(smp.payload, SessionStatus)
        with cond:
            statuses[st.session] = st.instance
            cond.notify_all()

    first: dict[str, float] = {}  # session -> its first prediction after the kill (wall s)
    t_kill = float("inf")

    def on_prediction(smp) -> None:
        t = time.time()
        s = keys.session_of(smp.key)
        with cond:
            if t >= t_kill and s is not None and s not in first:
                first[s] = t
                cond.notify_all()

    h = hub.subscribe(keys.ALL_STATUS, on_status)
    hp = hub.subscribe(keys.ALL_PREDICTIONS, on_prediction)
    try:
        for inst, other in (("inst-x", "inst-y"), ("inst-y", "inst-x")):
            eps[inst] = f"tcp/127.0.0.1:{free_port()}"
            cmd = [sys.executable, "-m", "pd_service", "--instance", inst, "--state-dir",
                   str(state / inst), "--listen", eps[inst], "--connect", hub_ep,
                   "--peer", other] + (["--connect", eps["inst-x"]] if inst == "inst-y" else [])
            procs[inst] = subprocess.Popen(cmd, env=env, cwd=root, stdout=subprocess.DEVNULL,
                                           stderr=open(state / f"{inst}.log", "wb"))
            deadline = time.monotonic() + 30
            while not hub.get_liveliness(keys.service_token_key(inst), timeout=1.0):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{inst} did not start: {(state / f'{inst}.log').read_text()}")
        epoch = time.time_ns()
        names = [f"take{i:04d}" for i in range(n)]
        for s in names:
            hub.put(keys.config_key(s), encode(paper_scenario().spec(s, epoch)))
        with cond:
            if not cond.wait_for(lambda: len(statuses) >= n, timeout=120):
                raise RuntimeError(f"only {len(statuses)} of {n} sessions answered")
            moved = [s for s, v in statuses.items() if v == "inst-y"]
            taken = len(moved)
        time.sleep(0.5 + args.steps * STEP_NS / 1e9)  # steps of history behind the senders
        snd = subprocess.Popen([sys.executable, __file__, "--senders", "--n", str(n),
                                "--connect", hub_ep, "--epoch", str(epoch),
                                "--steps", str(args.steps),
                                "--answer-ms", str(args.answer_ms if mode == "slow" else 0)],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, cwd=ROOT,
                               env=dict(os.environ))
        procs["senders"] = snd
        assert snd.stdout is not None and snd.stdout.readline().strip() == b"ready"
        time.sleep(1.0)  # the caches' tokens reach both instances
        if mode == "stalled":
            snd.send_signal(signal.SIGSTOP)
        with cond:
            t_kill = time.time()
        stop: dict = {}
        if args.signal == "term":
            procs["inst-y"].send_signal(signal.SIGTERM)
            procs["inst-y"].wait(60)
            stop["stop_s"] = round(time.time() - t_kill, 3)
            hm = HANDOVER.search((state / "inst-y.log").read_text(errors="replace"))
            if hm is None:
                raise RuntimeError(f"inst-y logged no handover: "
                                   f"{(state / 'inst-y.log').read_text()[-2000:]}")
            stop.update(handed_over=int(hm.group(1)), unconfirmed=int(hm.group(2)),
                        handover_s=float(hm.group(3)), resent=int(hm.group(4)))
        else:
            procs["inst-y"].kill()
        log = state / "inst-x.log"
        deadline = time.monotonic() + args.timeout
        m = None
        while m is None and time.monotonic() < deadline:
            m = READ_BACK.search(log.read_text(errors="replace"))
            time.sleep(0.05)
        if m is None:
            raise RuntimeError(f"no read_back within {args.timeout} s: {log.read_text()[-2000:]}")
        done = datetime.strptime(m.group(1), "%Y-%m-%dT%H:%M:%S.%fZ").replace(
            tzinfo=UTC).timestamp()
        if int(m.group(2)) != taken:  # a read-back of part of them would measure too little
            raise RuntimeError(f"the read-back covered {m.group(2)} sessions, inst-y served "
                               f"{taken}")
        with cond:  # every session taken over predicts: answered, or at the bound (4 s)
            cond.wait_for(lambda: all(s in first for s in moved), timeout=30)
            firsts = sorted(first[s] - t_kill for s in moved if s in first)
        how: dict[str, int] = {}
        for s in moved:
            for r in hub.get(keys.status_key(s), timeout=5.0):
                if r.ok:
                    from pd_service.wire import SessionStatus, decode
                    rb = decode(r.payload, SessionStatus).readback or "-"
                    how[rb] = how.get(rb, 0) + 1
        return {"sessions": n, "mode": mode, "taken": taken,
                "samples": int(m.group(3)), "read_back_s": float(m.group(4)),
                "kill_to_done_s": round(done - t_kill, 3),
                "first_prediction_s": round(statistics.median(firsts), 3) if firsts else None,
                "last_first_prediction_s": round(firsts[-1], 3) if firsts else None,
                "never_predicted": len(moved) - len(firsts), "readback": how, **stop}
    finally:
        h.close()
        hp.close()
        if "senders" in procs:
            procs["senders"].send_signal(signal.SIGCONT)
        for p in procs.values():
            if p.poll() is None:
                p.kill()
            p.wait(10)
        hub.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", default="50,200")
    ap.add_argument("--modes", default="live,slow,stalled")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--steps", type=int, default=8, help="steps of data in each cache")
    ap.add_argument("--answer-ms", dest="answer_ms", type=float, default=300.0,
                    help="mode slow: each cache answers this late (ms)")
    ap.add_argument("--timeout", type=float, default=900.0, help="longest wait for read_back")
    ap.add_argument("--root", default=str(ROOT), help="checkout whose daemon runs")
    ap.add_argument("--signal", choices=("kill", "term"), default="kill",
                    help="how inst-y stops: SIGKILL (no handover) or SIGTERM (handover)")
    ap.add_argument("--senders", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--connect", default="", help=argparse.SUPPRESS)
    ap.add_argument("--epoch", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.senders:
        run_senders(args)
        return
    root = Path(args.root).resolve()
    out = []
    term = args.signal == "term"
    print(f"{'sessions':>8} {'mode':>8} {'taken':>6} {'samples':>8} {'read-back s':>22} "
          f"{'kill->done s':>22} {'kill->1st pred s (median, last)':>32} {'readback':>24}"
          + (f" {'handover s':>22} {'resent':>9} {'unconfirmed':>11} "
                                     f"{'stop s':>22}" if term else ""), flush=True)
    for n in [int(x) for x in args.sessions.split(",")]:
        for mode in args.modes.split(","):
            runs = []
            for r in range(args.repeat):
                print(f"  ... N={n} {mode} run {r + 1}/{args.repeat}", file=sys.stderr, flush=True)
                runs.append(one_run(n, mode, args, root))
            rb = [x["read_back_s"] for x in runs]
            kd = [x["kill_to_done_s"] for x in runs]
            row = {"sessions": n, "mode": mode, "taken": runs[0]["taken"],
                   "samples": statistics.median(x["samples"] for x in runs),
                   "read_back_s": statistics.median(rb), "read_back_runs": rb,
                   "kill_to_done_s": statistics.median(kd), "kill_to_done_runs": kd,
                   "first_prediction_runs": [x["first_prediction_s"] for x in runs],
                   "last_first_prediction_runs": [x["last_first_prediction_s"] for x in runs],
                   "never_predicted": max(x["never_predicted"] for x in runs),
                   "readback_runs": [x["readback"] for x in runs], "root": str(root)}
            more = ""
            if term:
                ho, st = [x["handover_s"] for x in runs], [x["stop_s"] for x in runs]
                rs = [x["resent"] for x in runs]
                row.update(handover_s=statistics.median(ho), handover_runs=ho,
                           resent_runs=rs, unconfirmed=max(x["unconfirmed"] for x in runs),
                           stop_s=statistics.median(st), stop_runs=st)
                more = (f" {row['handover_s']:>8.3f} ({min(ho):.3f}-{max(ho):.3f}) "
                        f"{','.join(map(str, rs)):>9} {row['unconfirmed']:>11} "
                        f"{row['stop_s']:>8.3f} ({min(st):.3f}-{max(st):.3f})")
            out.append(row)
            print(f"{n:>8} {mode:>8} {row['taken']:>6} {row['samples']:>8.0f} "
                  f"{row['read_back_s']:>8.3f} ({min(rb):.3f}-{max(rb):.3f}) "
                  f"{row['kill_to_done_s']:>8.3f} ({min(kd):.3f}-{max(kd):.3f}) "
                  f"{','.join(str(x) for x in row['first_prediction_runs']):>16} "
                  f"{','.join(str(x) for x in row['last_first_prediction_runs']):>15} "
                  f"{' '.join(f'{k}:{v}' for r_ in row['readback_runs'] for k, v in r_.items()):>24}"
                  + more,
                  flush=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
