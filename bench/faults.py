#!/usr/bin/env python3
"""Faults of a deployment, tried from outside: router restart, host clock step, soak.

One daemon (``python -m pd_service``, default settings, ``--mode client``) behind a Python
Zenoh router on loopback (a separate process, so that it can be killed). This process is the
SDK's side, a client of the same router: per session a ``Robot`` (direct, cached senders)
and an ``Operator`` feed the paper scenario at its 50 ms step, and a subscriber records every
Prediction (step, seq, trace P). Modes:

* ``router``: ``--before`` s of traffic, the router killed (SIGKILL) and restarted on the
  same port after ``--down`` s, ``--after`` s more. Printed per session: the gap from the
  router's return to the first new prediction, whether the first one after it is a reset to
  the prior (trace P over the prior's), duplicate predictions (a seq seen twice or going
  back), and the declarations the router holds (its admin space: subscribers, queryables,
  tokens) before the kill and after the return. What the senders published while the
  router was down reaches the daemon only through their caches (read back when their
  tokens reappear).
* ``clock``: the host clock step, faked through the injected clocks (the OS clock cannot be
  stepped here): the in-memory core with a :class:`StepClock` on a wall clock stepped by
  ±1 s and +1 h; printed: the re-anchors, the refusals counted as ``clock_step``, the
  predictions after the step.
* ``soak``: ``--sessions`` sessions at ``--rate`` Hz (each a ranger sample per step) with
  one session created and one deleted per second, for ``--minutes``; printed each
  ``--every`` s: the daemon's RSS and open file descriptors (from /proc), its p99 latency
  (ServiceStatus), the router's declarations, predictions published, the samples accepted
  and refused as late (a soak whose samples are refused measures nothing) and the steps
  the feeding thread skipped because it fell behind.

The last line is one JSON object. Quote ``bench/gauge.py`` beside any figure.

    .venv/bin/python bench/faults.py router --sessions 20 --down 5
    .venv/bin/python bench/faults.py clock
    .venv/bin/python bench/faults.py soak --sessions 500 --rate 20 --minutes 60 --every 60
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pd_service.scenarios.paper import paper_prior  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STEP_NS = 50_000_000


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_router(port: int) -> None:
    """The router process: a Zenoh router on loopback with its admin space readable."""
    import zenoh
    c = zenoh.Config()
    c.insert_json5("mode", '"router"')
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("adminspace/enabled", "true")
    c.insert_json5("adminspace/permissions/read", "true")
    s = zenoh.open(c)
    print("router up", flush=True)
    try:
        while True:
            time.sleep(3600)
    finally:
        s.close()


class Router:
    """A router process on a fixed port; killed and started again on the same one."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.proc: subprocess.Popen | None = None

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__, "serve-router", str(self.port)],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        assert self.proc.stdout is not None
        self.proc.stdout.readline()  # "router up": listening

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


#: Liveliness tokens, by name (``**`` never matches a verbatim chunk: the daemons'
#: ``@service`` tokens, the senders' caches' ``@adv`` ones; the router's admin space does not
#: list keys with such chunks either).
TOKEN_SELECTORS = ("pd/@service/*", "pd/@link/*", "pd/*/*/sensor/*/@adv/pub/**",
                   "pd/*/*/cmd/@adv/pub/**", "robot/*/*/sensor/*/@adv/pub/**")


def declarations(t) -> dict[str, set[str]]:
    """The declarations the router holds: subscribers and queryables from its admin space
    (those on keys without a verbatim chunk), liveliness tokens by name."""
    out: dict[str, set[str]] = {"subscriber": set(), "queryable": set(), "token": set()}
    for r in t.get("@/*/router/**", timeout=3.0):
        if not r.ok:
            continue
        parts = r.key.split("/", 4)
        if len(parts) == 5 and parts[3] in ("subscriber", "queryable"):
            out[parts[3]].add(parts[4])
    for sel in TOKEN_SELECTORS:
        out["token"].update(t.get_liveliness(sel, timeout=3.0))
    return out


class Process:
    """One of the project's executables, its output in ``log_path``; stopped with SIGTERM."""

    def __init__(self, args: list[str], log_path: Path) -> None:
        self.log_path = log_path
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("PD_SERVICE_CONFIG", None)
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen([sys.executable, *args], stdout=self._log,
                                     stderr=self._log, env=env, cwd=ROOT)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


class Daemon(Process):
    """``python -m pd_service`` as a client of the router, default settings."""

    def __init__(self, endpoint: str, state_dir: Path, instance: str = "inst-f") -> None:
        self.instance = instance
        super().__init__(["-m", "pd_service", "--instance", instance, "--state-dir",
                          str(state_dir), "--mode", "client", "--connect", endpoint],
                         state_dir.parent / f"{instance}.log")

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/fd"))


#: pd-link's rules in ``--link`` runs: every sensor stream carried at once, nothing lost (the
#: link is there to be restarted around, not to delay).
LINK_RULES = """step_ms = 50
[[downlink]]
name = "sensors"
match = "robot/*/*/sensor/*"
delay = "0 steps"
"""


class Link(Process):
    """``pd-link`` as a client of the router, its publishers cached (the daemon reads them
    back, as the robot's own caches without it)."""

    def __init__(self, endpoint: str, tmp: Path) -> None:
        rules = tmp / "link.toml"
        rules.write_text(LINK_RULES)
        super().__init__(["-m", "pd_service.link", "--config", str(rules), "--mode", "client",
                          "--connect", endpoint, "--cache", "256"], tmp / "link.log")


class Traffic:
    """The SDK's side: per session a cached Robot and an Operator feeding the paper run,
    and every Prediction recorded as (receipt monotonic ns, step, seq, trace P)."""

    def __init__(self, t, sessions: list[str], epoch_ns: int, steps: int = 2_000,
                 direct: bool = True, record: bool = True) -> None:
        from pd_client import Operator, Robot
        from pd_service.scenarios.paper import paper_command, paper_scenario
        from pd_service.wire import Prediction, decode, encode, keys

        self.t, self.epoch = t, epoch_ns
        self._command, self._decode, self._Prediction = paper_command, decode, Prediction
        #: per session: (receipt monotonic ns, step, seq, trace P, counters["accepted"])
        self.preds: dict[str, list[tuple[int, int, int, float, int]]] = defaultdict(list)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.scenario = paper_scenario()
        self.robots: dict[str, object] = {}
        self.ops: dict[str, object] = {}
        self.steps = steps
        self.direct = direct
        self.send_errors = 0
        #: steps fed, and steps skipped because the feeding thread fell a step behind
        self.steps_sent = self.steps_skipped = 0
        self.last_error = ""
        from pd_service.scenarios.paper import simulate_paper
        run = simulate_paper(steps, np.random.default_rng(1), loss=0.0)
        #: per step of the run (mod ``steps``): (sensor, delay in steps, z) arriving then
        self.arrivals: dict[int, list[tuple[str, int, np.ndarray]]] = defaultdict(list)
        for smp in run.samples:
            if smp.arrival is not None and smp.arrival < steps:
                self.arrivals[smp.arrival].append((smp.sensor, smp.arrival - smp.step, smp.z))
        if record:  # else a feeder only (10,000 decodes a second would take its GIL)
            t.subscribe(keys.ALL_PREDICTIONS, self._on)
        from pd_client import Admin
        self.admin = Admin(t)
        self._keys, self._encode = keys, encode
        for s in sessions:
            self.add(s, Robot, Operator)

    def add(self, s: str, Robot=None, Operator=None) -> None:
        if Robot is None:
            from pd_client import Operator, Robot
        spec = self.scenario.spec(s, self.epoch)
        # as docs/clients.md creates a session: acknowledged, re-put while rate-limited (a
        # burst of bare puts beyond config_burst_total is refused, config_rate_limited)
        self.admin.open_session(spec, exist_ok=True, serve_spec=False, timeout=30.0)
        self.robots[s] = Robot(self.t, s, spec=spec, direct=self.direct)
        self.ops[s] = Operator(self.t, s, spec=spec)

    def remove(self, s: str) -> None:
        self.robots.pop(s).close()  # type: ignore[attr-defined]
        self.ops.pop(s).close()  # type: ignore[attr-defined]
        self.t.delete(self._keys.config_key(s))

    def _on(self, sample) -> None:
        p = self._decode(sample.payload, self._Prediction)
        with self.lock:
            self.preds[p.session].append((time.monotonic_ns(), p.step, p.seq,
                                          float(np.trace(p.P)), p.counters.get("accepted", 0)))

    def run(self, rate_hz: float = 20.0) -> None:
        """Each step: the ranger's reading of the step (stamped by step) and the operator's
        command for step + lead, for every session; paced on the shared clock."""
        period = int(1e9 / rate_hz)
        k = (time.time_ns() - self.epoch) // STEP_NS
        while not self.stop.is_set():
            k += 1
            due = self.epoch + k * period
            behind = (time.time_ns() - due) // period
            if behind > 0:  # this thread fell behind (CPU): on to the current step, counted
                self.steps_skipped += behind
                k += behind
                due += behind * period
            self.steps_sent += 1
            dt = (due - time.time_ns()) / 1e9
            if dt > 0:
                time.sleep(dt)
            for s in list(self.robots):
                try:
                    for sensor, delay, z in self.arrivals.get(k % self.steps, ()):
                        self.robots[s].publish(sensor, z, step=k - delay)  # type: ignore[attr-defined]
                    self.ops[s].send(self._command(k + 2), step=k + 2)  # type: ignore[attr-defined]
                except KeyError:
                    pass  # removed meanwhile (soak churn)
                except Exception as exc:  # a send failing while the router is down
                    self.send_errors += 1
                    self.last_error = repr(exc)

    def after(self, s: str, t_mono: int) -> list[tuple[int, int, int, float, int]]:
        with self.lock:
            return [p for p in self.preds[s] if p[0] >= t_mono]


def service_status(t, instance: str):
    from pd_service.wire import ServiceStatus, decode, keys
    for r in t.get(keys.service_status_key(instance), timeout=5.0):
        if r.ok:
            return decode(r.payload, ServiceStatus)
    return None


def _client(endpoint: str, daemon: Daemon):
    """This process's client of the router, once the daemon's liveliness token is seen (a
    spec put before the daemon subscribed would be lost)."""
    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire import keys
    t = ZenohTransport(zenoh_config(mode="client", connect=[endpoint], multicast=False))
    token = keys.service_token_key(daemon.instance)
    if not _wait(lambda: token in t.get_liveliness(keys.ALL_SERVICES), 60.0):
        raise RuntimeError(f"the daemon did not come up: {daemon.log_path}")
    return t


@contextlib.contextmanager
def rig(sessions: list[str], rate_hz: float = 20.0, root: Path | None = None,
        link: bool = False, record: bool = True) -> Iterator[tuple[Router, Daemon, object, Traffic]]:
    """A router, the daemon behind it, this process's client and the traffic of
    ``sessions`` (fed at ``rate_hz`` on a thread; ``link``: the robots' samples through a
    pd-link process; ``record``: see :class:`Traffic`); all stopped at the end."""
    tmp = Path(tempfile.mkdtemp(prefix="pd-faults-", dir=root))
    router = Router(free_port())
    router.start()
    daemon = Daemon(router.endpoint, tmp / "state")
    relay = Link(router.endpoint, tmp) if link else None
    t = _client(router.endpoint, daemon)
    traffic = Traffic(t, sessions, time.time_ns() - 10**9, direct=not link, record=record)
    feeder = threading.Thread(target=traffic.run, args=(rate_hz,), daemon=True)
    try:
        feeder.start()
        yield router, daemon, t, traffic
    finally:
        traffic.stop.set()
        feeder.join(5)
        if relay is not None:
            relay.stop()
        daemon.stop()
        t.close()  # type: ignore[attr-defined]
        router.kill()


def router_restart(sessions: int = 4, down_s: float = 5.0, before_s: float = 3.0,
                   after_s: float = 4.0, root: Path | None = None, link: bool = False) -> dict:
    """The ``router`` mode (module docstring); returns its figures."""
    from pd_client import Display
    names = [f"f{i}" for i in range(sessions)]
    with rig(names, root=root, link=link) as (router, daemon, t, traffic):
        displays = {s: Display(t, s) for s in names}  # the SDK's display, beside the recorder
        _wait(lambda: all(traffic.preds[s] for s in names), 60.0)
        time.sleep(before_s)
        before = declarations(t)
        st0 = service_status(t, daemon.instance)
        steady = {s: max(p[3] for p in traffic.preds[s][-20:]) for s in names}
        router.kill()
        t_down = time.monotonic_ns()
        time.sleep(down_s)
        router.start()
        t_back = time.monotonic_ns()
        shown = {s: d.stats().received for s, d in displays.items()}
        _wait(lambda: all(traffic.after(s, t_back) for s in names), 30.0 + after_s)
        time.sleep(after_s)
        after = declarations(t)
        status = service_status(t, daemon.instance)
        # predictions a Display received after the return, and those it counts as missed
        # (the gap's: the daemon published them into the void)
        display_rows = {s: (d.stats().received - shown[s], d.stats().missed)
                        for s, d in displays.items()}
    prior = float(np.trace(paper_prior()[1]))  # for scale: the prior's trace
    rows = []
    for s in names:
        got = traffic.preds[s]
        new = [p for p in got if p[0] >= t_back]
        seqs = [p[2] for p in got]
        rows.append({
            "session": s,
            "gap_s": (new[0][0] - t_back) / 1e9 if new else None,
            "silent_s": ((new[0][0] - max([p[0] for p in got if p[0] < t_down], default=t_down))
                         / 1e9 if new else None),
            "first_trace_P": new[0][3] if new else None,
            # the first prediction after the return with a measurement accepted since
            "data_back_s": next(((b[0] - t_back) / 1e9 for a, b in zip(new, new[1:],
                                 strict=False) if b[4] > a[4]), None),
            "steady_trace_P": steady[s],
            # a session restarted from the prior: its counters start again from 0
            "reset_to_prior": any(b[4] < a[4] for a, b in zip(got, got[1:], strict=False)),
            "max_trace_P_after": max((p[3] for p in new), default=None),
            # from the return until trace P is back within 1.5x the steady state's
            "settled_s": next(((p[0] - t_back) / 1e9 for p in new
                               if p[3] <= 1.5 * steady[s] and p[0] > t_back), None),
            "duplicates": sum(1 for a, b in zip(seqs, seqs[1:], strict=False) if b <= a),
            "display_received_after": display_rows[s][0],
            "display_missed": display_rows[s][1],
        })
    return {"mode": "router", "sessions": sessions, "down_s": down_s, "link": link,
            "prior_trace_P": prior,
            "rows": rows,
            "declarations_before": {k: len(v) for k, v in before.items()},
            "declarations_after": {k: len(v) for k, v in after.items()},
            "declarations_missing": {k: sorted(before[k] - after[k]) for k in before},
            "send_errors": traffic.send_errors, "last_send_error": traffic.last_error,
            "daemon_counters_before": {} if st0 is None else st0.counters,
            "daemon_counters": {} if status is None else status.counters}


def _wait(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def clock_steps(steps_ns=(1_000_000_000, -1_000_000_000, 3_600_000_000_000)) -> dict:
    """The ``clock`` mode: per step, an in-memory core on a StepClock whose wall clock steps
    away from the senders' by it mid-run; what it counted and whether it kept predicting."""
    sys.path.insert(0, str(ROOT))
    from tests.reliability.test_clock_step import HostClock, Mirror

    rows = []
    for step in steps_ns:
        with tempfile.TemporaryDirectory() as d:
            host = HostClock(0)
            m = Mirror(Path(d), host)
            m.configure()
            for k in range(40):
                m.step(k)
            host.off = step
            n = len(m.col.predictions["s1"])
            for k in range(40, 100):
                m.step(k)
            c = m.service().counters
            rows.append({"step_s": step / 1e9, "clock_steps": c.get("clock_steps", 0),
                         "clock_step_refusals": c.get("clock_step", 0)
                         + c.get("commands_clock_step", 0),
                         "late_future": sum(c.get(r, 0) for r in (
                             "late", "future", "commands_late", "commands_future")),
                         "predictions_after": len(m.col.predictions["s1"]) - n,
                         "compared_with_mirror": m.compared})
    return {"mode": "clock", "rows": rows}


#: Sessions of the soak's churn alive at once: each lives this many seconds (one created and
#: one deleted per second); the others are fed by feeder processes for the whole run.
CHURN_LIVE = 20


class Feeders:
    """``n`` processes (``faults.py feed``), each a client of the router feeding its share of
    the sessions ``s<first>..`` as the SDK's senders (one Python process's GIL cannot feed
    500 sessions at 20 Hz); each writes its counters to a JSON file every 2 s."""

    def __init__(self, endpoint: str, tmp: Path, epoch_ns: int, rate_hz: float, first: int,
                 count: int, n: int) -> None:
        self.stats = [tmp / f"feed{i}.json" for i in range(n)]
        bounds = [first + count * i // n for i in range(n + 1)]
        self.procs = [subprocess.Popen(
            [sys.executable, __file__, "feed", endpoint, str(epoch_ns), str(rate_hz),
             str(bounds[i]), str(bounds[i + 1] - bounds[i]), str(self.stats[i])],
            stdout=subprocess.DEVNULL, stderr=open(tmp / f"feed{i}.log", "ab"))
            for i in range(n)]

    def counters(self) -> dict[str, int]:
        out = {"steps": 0, "skipped": 0, "send_errors": 0}
        for path in self.stats:
            with contextlib.suppress(OSError, ValueError):
                for k, v in json.loads(path.read_text()).items():
                    out[k] += v
        return out

    def stop(self) -> None:
        for p in self.procs:
            p.send_signal(signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def feed(endpoint: str, epoch_ns: int, rate_hz: float, first: int, count: int,
         stats: Path) -> None:
    """The ``feed`` mode: one feeder process of :class:`Feeders`, until SIGTERM."""
    from pd_service.transport import ZenohTransport, zenoh_config
    t = ZenohTransport(zenoh_config(mode="client", connect=[endpoint], multicast=False))
    traffic = Traffic(t, [f"s{i}" for i in range(first, first + count)], epoch_ns, record=False)
    signal.signal(signal.SIGTERM, lambda *_: traffic.stop.set())

    def report() -> None:
        while not traffic.stop.wait(2.0):
            tmp = stats.with_suffix(".tmp")
            tmp.write_text(json.dumps({"steps": traffic.steps_sent,
                                       "skipped": traffic.steps_skipped,
                                       "send_errors": traffic.send_errors}))
            tmp.replace(stats)

    threading.Thread(target=report, daemon=True).start()
    try:
        traffic.run(rate_hz)
    finally:
        t.close()


def soak(sessions: int, rate_hz: float, minutes: float, every_s: float, feeders: int = 2,
         root: Path | None = None) -> dict:
    """The ``soak`` mode (module docstring); returns its samples."""
    samples = []
    churn = min(CHURN_LIVE, sessions)
    next_id = sessions
    # record=False: this process receives no prediction (the daemon counts those it published);
    # a client slow to take 10,000 a second had its config answers dropped by the router
    with rig([f"s{i}" for i in range(sessions - churn, sessions)], rate_hz, root,
             record=False) as (router, daemon, t, traffic):
        feed_procs = Feeders(router.endpoint, daemon.log_path.parent, traffic.epoch, rate_hz,
                             0, sessions - churn, feeders)
        try:
            # the feeders open theirs at config_rate_total
            if not _wait(lambda: len(getattr(service_status(t, daemon.instance), "sessions",
                                              ())) >= sessions, 180.0):
                raise RuntimeError(f"the daemon does not serve {sessions} sessions")
            _soak_rows(daemon, t, traffic, feed_procs, minutes, every_s, samples, next_id)
        finally:
            feed_procs.stop()
    return {"mode": "soak", "sessions": sessions, "rate_hz": rate_hz, "minutes": minutes,
            "feeders": feeders, "summary": soak_summary(samples), "samples": samples}


def _soak_rows(daemon, t, traffic, feed_procs: Feeders, minutes: float, every_s: float,
               samples: list[dict], next_id: int) -> None:
    """The soak's loop: the churn each second, a row every ``every_s`` s."""
    t0 = time.monotonic()
    next_print = t0 + every_s
    while time.monotonic() - t0 < minutes * 60:
        time.sleep(1.0)
        traffic.add(f"s{next_id}")  # churn: one created, one deleted per second
        traffic.remove(sorted(traffic.robots, key=lambda n: int(n[1:]))[0])  # oldest
        next_id += 1
        if time.monotonic() >= next_print:
            next_print += every_s
            st = service_status(t, daemon.instance)
            dec = declarations(t)
            fed = feed_procs.counters()
            row = {"t_s": round(time.monotonic() - t0, 1), "rss_mb": round(daemon.rss_mb(), 1),
                   "fds": daemon.fds(),
                   "p99_us": None if st is None else round(st.latency_p99_us, 1),
                   "sessions_served": None if st is None else len(st.sessions),
                   "subscribers": len(dec["subscriber"]), "queryables": len(dec["queryable"]),
                   "tokens": len(dec["token"]),
                   "published": None if st is None else st.counters.get("published", 0),
                   "send_errors": traffic.send_errors + fed["send_errors"],
                   "accepted": None if st is None else st.counters.get("accepted", 0),
                   "late_total": None if st is None else st.counters.get("late_total", 0),
                   "feed_steps": traffic.steps_sent + fed["steps"],
                   "feed_skipped": traffic.steps_skipped + fed["skipped"]}
            samples.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items()), flush=True)


def soak_summary(samples: list[dict]) -> dict:
    """The issue's soak figures: RSS growth after the first 5 min (MB), median p99 of the
    last 10 min over the first 10 min's (with less than 20 min: of the last half over the
    first half), and the ranges of the fds and declarations."""
    if not samples:
        return {}
    end = samples[-1]["t_s"]
    settled = [r["rss_mb"] for r in samples if r["t_s"] >= min(300.0, end / 2)]
    span = min(600.0, end / 2)
    first = [r["p99_us"] for r in samples if r["t_s"] <= span and r["p99_us"] is not None]
    last = [r["p99_us"] for r in samples if r["t_s"] >= end - span and r["p99_us"] is not None]
    ratio = (statistics.median(last) / statistics.median(first)) if first and last else None
    last_row = samples[-1]
    fed = (last_row["accepted"] or 0) + (last_row["late_total"] or 0)
    return {"rss_growth_mb": round(max(settled) - settled[0], 1) if settled else None,
            "late_share": round((last_row["late_total"] or 0) / fed, 4) if fed else None,
            "feed_skipped_share": round(last_row["feed_skipped"] / max(
                1, last_row["feed_skipped"] + last_row["feed_steps"]), 4),
            "p99_last_over_first": None if ratio is None else round(ratio, 2),
            **{f"{k}_range": [min(r[k] for r in samples), max(r[k] for r in samples)]
               for k in ("fds", "subscribers", "queryables", "tokens")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="mode", required=True)
    r = sub.add_parser("router")
    r.add_argument("--sessions", type=int, default=20)
    r.add_argument("--down", type=float, default=5.0)
    r.add_argument("--before", type=float, default=3.0)
    r.add_argument("--after", type=float, default=4.0)
    r.add_argument("--link", action="store_true",
                   help="the robots' samples through a pd-link process")
    sub.add_parser("clock")
    s = sub.add_parser("soak")
    s.add_argument("--sessions", type=int, default=500)
    s.add_argument("--rate", type=float, default=20.0)
    s.add_argument("--minutes", type=float, default=60.0)
    s.add_argument("--every", type=float, default=60.0)
    s.add_argument("--feeders", type=int, default=2,
                   help="processes feeding all but the churning sessions")
    f = sub.add_parser("feed")
    for name, typ in (("endpoint", str), ("epoch_ns", int), ("rate", float), ("first", int),
                      ("count", int), ("stats", Path)):
        f.add_argument(name, type=typ)
    sr = sub.add_parser("serve-router")
    sr.add_argument("port", type=int)
    a = ap.parse_args()
    if a.mode == "serve-router":
        serve_router(a.port)
        return
    if a.mode == "feed":
        feed(a.endpoint, a.epoch_ns, a.rate, a.first, a.count, a.stats)
        return
    if a.mode == "router":
        out = router_restart(a.sessions, a.down, a.before, a.after, link=a.link)
        print(f"{'session':>8} {'gap s':>7} {'silent s':>9} {'data s':>7} {'tr P first':>10} "
              f"{'max':>8} {'steady':>8} {'settle s':>8} {'reset':>6} {'dup':>4}")
        for row in out["rows"]:
            print(f"{row['session']:>8} {row['gap_s']!s:>7.5} {row['silent_s']!s:>9.5} "
                  f"{row['data_back_s']!s:>7.5} {row['first_trace_P']!s:>10.6} "
                  f"{row['max_trace_P_after']!s:>8.6} {row['steady_trace_P']:>8.4g} "
                  f"{row['settled_s']!s:>8.5} "
                  f"{row['reset_to_prior']!s:>6} {row['duplicates']:>4}")
        print("declarations before", out["declarations_before"], "after",
              out["declarations_after"], "missing", out["declarations_missing"])
    elif a.mode == "clock":
        out = clock_steps()
        for row in out["rows"]:
            print("  ".join(f"{k}={v}" for k, v in row.items()))
    else:
        out = soak(a.sessions, a.rate, a.minutes, a.every, a.feeders)
        print("summary", out["summary"])
    print(json.dumps(out))


if __name__ == "__main__":
    main()
