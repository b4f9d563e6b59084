#!/usr/bin/env python3
"""A partition between two daemon instances, then its heal, on loopback with Python routers.

Two Zenoh routers (Python sessions in router mode): router-b connects to router-a through a
TCP relay in this process; stopping the relay (its listener and every connection it carries)
cuts the router-to-router link, starting it again heals it (router-b reconnects by itself).
Daemon pd-a (a process, ``--peer pd-b``) connects to router-a, pd-b to router-b. N paper
sessions; session i's sender (cached publishers, ``cache=64``, as the SDK's Robot and Operator
keep) sits on router-a for even i, router-b for odd i, and puts each step its command and
one ranger and one camera sample. On each router one SDK ``Display`` per session, and a raw
subscriber to every prediction. Timeline: ``--warm`` s with the link up, ``--partition`` s
cut, ``--after`` s healed.

Printed (one row per run, medians and spread over ``--repeat`` runs):

- ``two_owner_keys``: sessions whose predictions of two different terms arrived interleaved
  (A, B, A) at a raw subscriber: what a reader without fencing would have shown;
- ``display_interleaved``: sessions for which a Display delivered an older term after a
  newer one (must be 0), and ``stale_dropped``: predictions the Displays dropped;
- ``one_owner_s``: from the relay's restart until each session is served by exactly one
  instance (both instances' ServiceStatus), and ``members_back_s``: until pd-a sees pd-b's
  token again;
- ``diagP_after``: largest diag P ratio, display prediction / uninterrupted reference
  (every sample sent, fed in order to an offline estimator of the same spec), over the
  predictions published after one owner per session; ``diagP_during``: the same over the
  partition (a side that does not receive a session's data predicts with a growing
  covariance: honest, not a failure);
- ``exact_after``: sessions whose last prediction matches the reference to 1e-9.

Then one JSON line. Loopback on one host: a benchmark of behaviour, not of speed.

    .venv/bin/python bench/partition.py --sessions 20 --partition 10 --repeat 3
    .venv/bin/python bench/partition.py --sessions 6 --partition 3 --after 5   # quick
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))  # also when a test loads this file
from children import popen, stop_children_on_exit  # noqa: E402

INSTANCES = ("pd-a", "pd-b")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LinkRelay:
    """A TCP relay 127.0.0.1:<port> -> 127.0.0.1:<target>: the router-to-router link.
    :meth:`cut` closes its listener and every connection (both routers see the link go
    at once); :meth:`restore` listens again on the same port. :attr:`one_way` set: the bytes
    from the target (router-a) to the connecting side (router-b) are no longer read (they
    wait in the sockets' buffers, as over a path that stopped delivering one way); the
    other direction flows: an asymmetric partition, b no longer hears a."""

    def __init__(self, target: int) -> None:
        self.port, self.target = free_port(), target
        self._lock = threading.Lock()
        self._socks: list[socket.socket] = []
        self._listener: socket.socket | None = None
        self.one_way = threading.Event()

    def restore(self) -> None:
        ls = socket.socket()
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind(("127.0.0.1", self.port))
        ls.listen(8)
        self._listener = ls
        threading.Thread(target=self._accept, args=(ls,), daemon=True).start()

    def _accept(self, ls: socket.socket) -> None:
        while True:
            try:
                a, _ = ls.accept()
            except OSError:
                return
            try:
                b = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                a.close()
                continue
            with self._lock:
                self._socks += [a, b]
            for (src, dst), gate in (((a, b), None), ((b, a), self.one_way)):
                threading.Thread(target=self._pump, args=(src, dst, gate), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket, gate: threading.Event | None) -> None:
        try:
            while True:
                if gate is not None and gate.is_set():
                    if src.fileno() < 0:  # closed by cut()
                        return
                    time.sleep(0.01)  # not read: held in the buffers
                    continue
                data = src.recv(65536)
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self) -> None:
        if self._listener is not None:
            try:  # wakes the accept() blocked on it (a close alone would not: Linux)
                self._listener.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._listener.close()
            self._listener = None
        with self._lock:
            socks, self._socks = self._socks, []
        for s in socks:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()


class Feed:
    """Every prediction a raw subscriber received: session -> [(term, step, x, P)]."""

    def __init__(self, t: Any) -> None:
        from pd_service.wire import keys

        self.lock = threading.Lock()
        self.preds: dict[str, list[tuple[int, int, np.ndarray, np.ndarray, float, dict]]] = \
            defaultdict(list)
        self.h = t.subscribe(keys.ALL_PREDICTIONS, self._on)

    def _on(self, sample: Any) -> None:
        from pd_service.wire import Prediction, decode

        p = decode(sample.payload, Prediction)
        with self.lock:
            self.preds[p.session].append((p.term, p.step, p.x, p.P, time.monotonic(),
                                          p.counters))


def interleaved(terms: list[int]) -> bool:
    """An older term seen after a newer one (A ... B ... A)."""
    top = -1
    for t in terms:
        if t < top:
            return True
        top = max(top, t)
    return False


def membership_events(log: str, since_wall: float) -> list[tuple[str, str, float]]:
    """(event, instance, s after ``since_wall``) of each member_left / member_joined line."""
    from datetime import UTC, datetime

    out = []
    for line in log.splitlines():
        if "event=member_" not in line:
            continue
        f = dict(x.split("=", 1) for x in line.split() if "=" in x)
        ts = datetime.strptime(f["ts"], "%Y-%m-%dT%H:%M:%S.%fZ").replace(
            tzinfo=UTC).timestamp()
        out.append((f["event"], f.get("instance", ""), round(ts - since_wall, 3)))
    return out


def one_run(args: argparse.Namespace) -> dict[str, Any]:
    from pd_client import Display
    from pd_service.backends import build
    from pd_service.scenarios.paper import paper_scenario
    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire import Command, Measurement, ServiceStatus, decode, encode, keys

    state = Path(tempfile.mkdtemp(prefix="pd-partition-"))
    one_way = getattr(args, "one_way", False)
    pa, pb = free_port(), free_port()
    ep = {"a": f"tcp/127.0.0.1:{pa}", "b": f"tcp/127.0.0.1:{pb}"}
    relay = LinkRelay(pa)
    closing: list[Any] = []
    procs: list[subprocess.Popen] = []
    try:
        # no gossip: a router that learnt the other's own locator would reconnect to it
        # directly, around the relay (seen: a "partition" of 0.1 s)
        no_gossip = state / "no-gossip.json5"
        no_gossip.write_text('{"scouting": {"gossip": {"enabled": false}}}')

        def conf(mode: str, listen: list[str], connect: list[str]) -> Any:
            return zenoh_config(file=no_gossip, mode=mode, listen=listen, connect=connect,
                                multicast=False)

        ra = ZenohTransport(conf("router", [ep["a"]], []))
        closing.append(ra)
        relay.restore()
        rb = ZenohTransport(conf("router", [ep["b"]], [f"tcp/127.0.0.1:{relay.port}"]))
        closing.append(rb)
        side = {"a": ZenohTransport(conf("client", [], [ep["a"]])),
                "b": ZenohTransport(conf("client", [], [ep["b"]]))}
        closing += side.values()
        env = dict(os.environ, PD_SERVICE_LOG_LEVEL="INFO")
        env.pop("PD_SERVICE_CONFIG", None)
        for inst, r, other in (("pd-a", "a", "pd-b"), ("pd-b", "b", "pd-a")):
            procs.append(popen(
                [sys.executable, "-m", "pd_service", "--instance", inst, "--state-dir",
                 str(state / inst), "--zenoh-config", str(no_gossip), "--mode", "client",
                 "--connect", ep[r], "--peer", other,
                 "--listen", f"tcp/127.0.0.1:{free_port()}"],
                env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                stderr=open(state / f"{inst}.log", "wb")))
        for inst in INSTANCES:
            deadline = time.monotonic() + 60
            while not side["a"].get_liveliness(keys.service_token_key(inst), timeout=1.0):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{inst} not seen: {(state / f'{inst}.log').read_text()}")
        sc = paper_scenario()
        epoch = time.time_ns()
        names = [f"part{i:03d}" for i in range(args.sessions)]
        specs = {s: sc.spec(s, epoch) for s in names}
        for s in names:
            side["a"].put(keys.config_key(s), encode(specs[s]))

        def owners() -> dict[str, list[str]]:
            """session -> the instances serving it; {} unless both instances answered."""
            got: dict[str, list[str]] = defaultdict(list)
            for inst in INSTANCES:
                answers = [r for r in side["a"].get(keys.service_status_key(inst), timeout=1.0)
                           if r.ok]
                if not answers:
                    return {}
                for s in decode(answers[0].payload, ServiceStatus).sessions:
                    got[s].append(inst)
            return got

        deadline = time.monotonic() + 60
        while sorted(s for s, o in owners().items() if len(o) == 1) != names:
            if time.monotonic() > deadline:
                raise RuntimeError(f"sessions not served once each: {dict(owners())}")
            time.sleep(0.1)
        feeds = {r: Feed(side[r]) for r in side}
        shown: dict[tuple[str, str], list[int]] = defaultdict(list)
        displays = []
        for r in side:
            for s in names:
                d = Display(side[r], s)
                d.on_prediction(lambda p, r=r: shown[r, p.session].append(p.term))
                displays.append(d)
        pubs = {}
        for i, s in enumerate(names):
            t = side["a" if i % 2 == 0 else "b"]
            pubs[s] = {k: t.publisher(k, cache=64) for k in (
                keys.command_key(s), keys.sensor_key(s, "ranger"), keys.sensor_key(s, "camera"))}
        sent: dict[str, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]] = defaultdict(list)
        rng = np.random.default_rng(args.seed)
        spec0 = specs[names[0]]
        period, lead = spec0.period_ns, spec0.lead
        marks: dict[str, float] = {}

        def joined() -> int:  # pd-a's log lines saying it sees pd-b (again)
            return (state / "pd-a.log").read_text(errors="replace").count(
                "event=member_joined instance=pd-b")

        total_s = args.warm + args.partition + args.after
        k0 = (time.time_ns() - epoch) // period + 1
        k = k0
        while True:
            t_k = epoch + k * period + period // 10
            dt = (t_k - time.time_ns()) / 1e9
            if dt > 0:
                time.sleep(dt)
            el = (k - k0) * period / 1e9
            if el >= args.warm and "cut" not in marks:
                if one_way:
                    relay.one_way.set()
                else:
                    relay.cut()
                marks["cut"], marks["cut_wall"] = time.monotonic(), time.time()
            if el >= args.warm + args.partition and "heal" not in marks:
                marks["joined_before"] = joined()
                if one_way:
                    relay.one_way.clear()
                else:
                    relay.restore()
                marks["heal"] = time.monotonic()
            if el >= total_s:
                break
            for s in names:
                u, zr, zc = rng.normal(size=1), rng.normal(size=1) + 5.0, rng.normal(size=2)
                sent[s].append((k, u, zr, zc))
                p = pubs[s]
                p[keys.command_key(s)].put(encode(Command(session=s, seq=k, step=k + lead, u=u)))
                if k - 12 >= 0:
                    p[keys.sensor_key(s, "ranger")].put(encode(Measurement(
                        session=s, sensor="ranger", seq=k, step=k - 12, z=zr)))
                if k - 10 >= 0:
                    p[keys.sensor_key(s, "camera")].put(encode(Measurement(
                        session=s, sensor="camera", seq=k, step=k - 10, z=zc)))
            if "heal" in marks and "one_owner" not in marks:
                if sorted(s for s, o in owners().items() if len(o) == 1) == names:
                    marks["one_owner"] = time.monotonic()
            if "heal" in marks and "members" not in marks and \
                    joined() > marks["joined_before"]:
                marks["members"] = time.monotonic()
            k += 1
        time.sleep(0.5)
        # the uninterrupted reference: every sample sent, in order, to one estimator
        ratios_after, ratios_during, exact = [], [], 0
        inexact: list[dict[str, Any]] = []  # why a session is not exact at the end
        for s in names:
            est = build(specs[s]).est
            ref: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            for kk, u, zr, zc in sent[s]:
                est.add_command(kk + lead, u, now=kk)
                if kk - 12 >= 0:
                    est.add_measurement("ranger", kk - 12, zr, now=kk)
                if kk - 10 >= 0:
                    est.add_measurement("camera", kk - 10, zc, now=kk)
                pr = est.predict(kk)
                ref[int(pr.step)] = (np.array(pr.x), np.diag(pr.P).copy())
            with feeds["a"].lock:
                got = list(feeds["a"].preds[s])
            last = None
            for _term, step, x, P, at, counters in got:
                if step not in ref:
                    continue
                r = float(np.max(np.diag(P) / ref[step][1]))
                if "one_owner" in marks and at > marks["one_owner"]:
                    ratios_after.append(r)
                    last = (x, P, step, counters)
                elif marks["cut"] < at < marks["heal"]:
                    ratios_during.append(r)
            if last is not None and np.allclose(last[0], ref[last[2]][0], rtol=1e-9, atol=1e-9) \
                    and np.allclose(np.diag(last[1]), ref[last[2]][1], rtol=1e-9, atol=1e-9):
                exact += 1
            elif last is not None:
                now = last[2] - lead
                meas = sum((kk <= now and kk >= 12) + (kk <= now and kk >= 10)
                           for kk, *_ in sent[s])
                cmds = sum(1 for kk, *_ in sent[s] if kk <= now)
                c = last[3]
                inexact.append({"session": s, "step": last[2],
                                "x_err": float(np.max(np.abs(last[0] - ref[last[2]][0]))),
                                "P_ratio": float(np.max(np.diag(last[1]) / ref[last[2]][1])),
                                "lacks": (meas - c.get("accepted", 0),
                                          cmds - c.get("commands_accepted", 0)),
                                "counters": {k: v for k, v in c.items() if v}})
        two_owner = sum(1 for r in feeds for s in names
                        if interleaved([p[0] for p in feeds[r].preds[s]]))
        shown_bad = sum(1 for v in shown.values() if interleaved(v))
        stale = sum(d.stats().stale_term for d in displays)
        for d in displays:
            d.close()
        logs = {i: (state / f"{i}.log").read_text(errors="replace") for i in INSTANCES}
        return {
            "sessions": args.sessions, "partition_s": args.partition,
            "two_owner_keys": two_owner, "display_interleaved": shown_bad,
            "stale_dropped": stale,
            "one_owner_s": None if "one_owner" not in marks else
            round(marks["one_owner"] - marks["heal"], 3),
            "members_back_s": None if "members" not in marks else
            round(marks["members"] - marks["heal"], 3),
            "diagP_after": round(max(ratios_after), 4) if ratios_after else None,
            "diagP_during": round(max(ratios_during), 4) if ratios_during else None,
            "exact_after": exact, "inexact": inexact,
            "yielded": sum(lg.count("event=term_yielded") for lg in logs.values()),
            "kept": sum(lg.count("event=term_kept") for lg in logs.values()),
            "taken_over": sum(lg.count("taken over") for lg in logs.values()),
            "one_way": one_way,
            # what each instance saw of the other, s after the cut
            "membership": {i: membership_events(lg, marks["cut_wall"]) for i, lg in logs.items()},
        }
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        relay.cut()
        for c in closing:
            c.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sessions", type=int, default=20)
    ap.add_argument("--warm", type=float, default=4.0, help="s with the link up first")
    ap.add_argument("--partition", type=float, default=10.0, help="s with the link cut")
    ap.add_argument("--after", type=float, default=8.0, help="s after the heal")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--one-way", action="store_true",
                    help="an asymmetric partition: router-b no longer hears router-a (the "
                         "relay stops reading that direction), router-a still hears router-b")
    args = ap.parse_args()
    stop_children_on_exit()  # a SIGTERM / SIGINT or an exception stops the daemons started
    from gauge import gauge_ms

    g = gauge_ms()
    runs = [one_run(args) for _ in range(args.repeat)]
    cols = ["two_owner_keys", "display_interleaved", "stale_dropped", "one_owner_s",
            "members_back_s", "diagP_during", "diagP_after", "exact_after", "yielded",
            "kept"]
    print(f"{'one-way ' if args.one_way else ''}partition of {args.partition:g} s, 2 instances "
          f"x {args.sessions} sessions, {args.repeat} run(s); gauge {g:.1f} ms")
    for i, r in enumerate(runs):
        print(f"  run {i}: membership seen (s after the cut): " + "; ".join(
            f"{inst}: " + ", ".join(f"{ev.removeprefix('member_')} {who} {t}" for ev, who, t in evs)
            for inst, evs in r["membership"].items()))
    for c in cols:
        vals = [r[c] for r in runs if r[c] is not None]
        med = round(statistics.median(vals), 4) if vals else None
        spread = f"[{min(vals)} .. {max(vals)}]" if len(vals) > 1 else ""
        print(f"  {c:20s} {med!s:>10s} {spread}")
    print(json.dumps({"bench": "partition", "gauge_ms": g, "runs": runs}))


if __name__ == "__main__":
    main()
