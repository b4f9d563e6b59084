#!/usr/bin/env python3
"""Faults of a deployment, tried from outside: router restart, daemon restart, takeover,
host clock step, soak.

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
* ``restart``: the documented set-up from outside: the daemon as it runs with no options
  (a peer listening, here on a free port), default settings; this process the SDK's side,
  ``pd_client.connect`` to it, per session a cached direct ``Robot`` (with the spec) and an
  ``Operator`` feeding the paper run at 100 ms steps (``--max-delay``: the window in steps;
  12, the paper's 1.2 s, is shorter than every outage). After ``--before`` s the daemon is
  killed (SIGKILL) and started again on the same state directory ``--down`` s later (a list,
  cycled over ``--repeat`` runs). Printed per session: where it resumed from and how its
  wait for the senders' caches ended (SessionStatus), the first prediction's diag P over
  a mirror estimator's (every input the SDK took, each at the step it was sent: the run
  that never stopped) at the same step, largest and smallest entry, and the largest over
  the predictions after; the inputs sent (20 ms before it was made) that the first and
  the last prediction lack; the gap; a restart from the prior; the last prediction exact
  to 1e-9. Then the median and spread over all runs.
* ``takeover``: the same with two trusted instances (``--peer``), clients of a Python
  router as the SDK is; the owner of the most sessions killed (SIGKILL); the rows are
  its sessions, their first prediction the survivor's (a newer term).
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
    .venv/bin/python bench/faults.py restart --sessions 4 --repeat 8 --max-delay 12
    .venv/bin/python bench/faults.py takeover --sessions 8 --repeat 8 --max-delay 12
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
sys.path.insert(0, str(Path(__file__).resolve().parent))  # also when a test loads this file
from children import popen, stop_children_on_exit  # noqa: E402

from pd_service.scenarios.paper import UPLINK_DELAY, paper_prior  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


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
        self.proc = popen([sys.executable, __file__, "serve-router", str(self.port)],
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
        self.proc = popen([sys.executable, *args], stdout=self._log, stderr=self._log, env=env,
                          cwd=ROOT)

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
    """``python -m pd_service``, default settings: a client of the router at ``endpoint``,
    or (``listen``) a peer listening there, as it runs with no options (the SDK's clients
    connect to it); ``peers``: the other instances it shares sessions with."""

    def __init__(self, endpoint: str, state_dir: Path, instance: str = "inst-f",
                 listen: bool = False, peers: tuple[str, ...] = ()) -> None:
        self.instance = instance
        net = ["--listen", endpoint] if listen else ["--mode", "client", "--connect", endpoint]
        super().__init__(["-m", "pd_service", "--instance", instance, "--state-dir",
                          str(state_dir), *net, *(a for p in peers for a in ("--peer", p))],
                         state_dir.parent / f"{instance}.log")

    def kill9(self) -> None:
        """SIGKILL: no hand-over, no flush; the kernel closes its sockets."""
        self.proc.kill()
        self.proc.wait()
        self._log.close()

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
    and every Prediction recorded as (receipt monotonic ns, step, seq, trace P).
    ``time_scale``, ``max_delay``: the spec's (``Scenario.spec``; 0.5: 100 ms steps);
    ``listen``: receive the predictions at all (a feeder does not);
    ``record``: also keep every Prediction received (:attr:`full`) and every input sent
    (:attr:`sent`, for a mirror estimator); ``ahead``: a command is sent for the step this
    many steps ahead (default 2; the spec's ``lead`` as docs/clients.md does it)."""

    def __init__(self, t, sessions: list[str], epoch_ns: int, steps: int = 2_000,
                 direct: bool = True, time_scale: float = 1.0, max_delay: int | None = None,
                 record: bool = False, ahead: int = 2, listen: bool = True) -> None:
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
        self.time_scale, self.max_delay, self.ahead = time_scale, max_delay, ahead
        self.record = record
        #: per session, with ``record``: (receipt monotonic ns, Prediction) of every one
        self.full: dict[str, list[tuple[int, object]]] = defaultdict(list)
        #: per session, with ``record``: (wall ns sent, step k, sensor or "" for the
        #: command, sample / apply step, z or u) of every input the SDK took
        self.sent: dict[str, list[tuple[int, int, str, int, np.ndarray]]] = defaultdict(list)
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
        if listen:  # else a feeder only (10,000 decodes a second would take its GIL)
            t.subscribe(keys.ALL_PREDICTIONS, self._on)
        from pd_client import Admin
        self.admin = Admin(t)
        self._keys, self._encode = keys, encode
        for s in sessions:
            self.add(s, Robot, Operator)

    def add(self, s: str, Robot=None, Operator=None) -> None:
        if Robot is None:
            from pd_client import Operator, Robot
        spec = self.spec(s)
        # as docs/clients.md creates a session: acknowledged, re-put while rate-limited (a
        # burst of bare puts beyond config_burst_total is refused, config_rate_limited)
        self.admin.open_session(spec, exist_ok=True, serve_spec=False, timeout=30.0)
        self.robots[s] = Robot(self.t, s, spec=spec, direct=self.direct)
        self.ops[s] = Operator(self.t, s, spec=spec)

    def spec(self, s: str):
        """Session ``s``'s SessionSpec."""
        return self.scenario.spec(s, self.epoch, time_scale=self.time_scale,
                                  max_delay=self.max_delay)

    def remove(self, s: str) -> None:
        self.robots.pop(s).close()  # type: ignore[attr-defined]
        self.ops.pop(s).close()  # type: ignore[attr-defined]
        self.t.delete(self._keys.config_key(s))

    def _on(self, sample) -> None:
        p = self._decode(sample.payload, self._Prediction)
        with self.lock:
            self.preds[p.session].append((time.monotonic_ns(), p.step, p.seq,
                                          float(np.trace(p.P)), p.counters.get("accepted", 0)))
            if self.record:
                self.full[p.session].append((time.monotonic_ns(), p))

    def run(self, rate_hz: float = 20.0) -> None:
        """Each step: the ranger's reading of the step (stamped by step) and the operator's
        command for step + lead, for every session; paced on the shared clock."""
        period = int(1e9 / rate_hz)
        k = (time.time_ns() - self.epoch) // period
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
                        if self.record:
                            self.sent[s].append((time.time_ns(), k, sensor, k - delay, z))
                    u = np.array([self._command(k + self.ahead)])
                    self.ops[s].send(u, step=k + self.ahead)  # type: ignore[attr-defined]
                    if self.record:
                        self.sent[s].append((time.time_ns(), k, "", k + self.ahead, u))
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
        link: bool = False, listen: bool = True) -> Iterator[tuple[Router, Daemon, object, Traffic]]:
    """A router, the daemon behind it, this process's client and the traffic of
    ``sessions`` (fed at ``rate_hz`` on a thread; ``link``: the robots' samples through a
    pd-link process; ``listen``: see :class:`Traffic`); all stopped at the end."""
    tmp = Path(tempfile.mkdtemp(prefix="pd-faults-", dir=root))
    router = Router(free_port())
    router.start()
    daemon = Daemon(router.endpoint, tmp / "state")
    relay = Link(router.endpoint, tmp) if link else None
    t = _client(router.endpoint, daemon)
    traffic = Traffic(t, sessions, time.time_ns() - 10**9, direct=not link, listen=listen)
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


def mirror(spec, sent: list[tuple[int, int, str, int, np.ndarray]]
           ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The uninterrupted run: one estimator of ``spec`` fed every input in ``sent``
    (:attr:`Traffic.sent`), in order, each at the step it was sent; per step ``now``:
    (x, diag P) of its prediction for ``now + lead`` (what a daemon that never stopped
    publishes at the tick of ``now``)."""
    from pd_service.backends import build
    est = build(spec).est
    ref: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    k_prev = None
    for _, k, sensor, step, v in sent:
        if k_prev is not None and k != k_prev:
            pr = est.predict(k_prev)
            ref[k_prev] = (np.array(pr.x), np.diag(pr.P).copy())
        k_prev = k
        if sensor:
            est.add_measurement(sensor, step, v, now=k)
        else:
            est.add_command(step, v, now=k)
    if k_prev is not None:
        pr = est.predict(k_prev)
        ref[k_prev] = (np.array(pr.x), np.diag(pr.P).copy())
    return ref


#: A sample sent less than this before a prediction was made may still be on its way: not
#: counted as one the prediction should have (ns).
IN_FLIGHT_NS = 20_000_000


def resumed_row(traffic: Traffic, s: str, t_fault: int, status, newer_than: int = -1) -> dict:
    """Session ``s`` around a fault at ``t_fault`` (monotonic ns): its first prediction after
    it (of a term above ``newer_than``: the survivor's at a takeover) against the mirror of
    what was sent (:func:`mirror`), the inputs sent before it was made that it lacks, the
    gap, whether it restarted from the prior; ``status``: its SessionStatus afterwards."""
    spec = traffic.spec(s)
    with traffic.lock:
        got = list(traffic.full[s])
        sent = list(traffic.sent[s])
    ref = mirror(spec, sent)
    before = [p for at, p in got if at < t_fault]
    after = [(at, p) for at, p in got if at >= t_fault and p.term > newer_than]
    row: dict = {"session": s, "origin": None if status is None else status.origin,
                 "origin_step": None if status is None else status.origin_step,
                 "readback": None if status is None else status.readback,
                 "counters": {} if status is None
                 else {k: v for k, v in status.counters.items() if v}}
    if not after:
        return {**row, "first_ratio": None}

    def ratios(p) -> tuple[float, float] | None:
        r = ref.get(p.step - spec.lead)
        if r is None:
            return None
        q = np.diag(p.P) / r[1]
        return float(q.max()), float(q.min())

    def lacking(p) -> tuple[int, int]:
        """(measurements, commands) sent before ``p`` was made that it has not accepted."""
        cut = p.made_ns - IN_FLIGHT_NS
        meas = sum(1 for x in sent if x[0] < cut and x[2])
        cmds = sum(1 for x in sent if x[0] < cut and not x[2])
        return (max(0, meas - p.counters.get("accepted", 0)),
                max(0, cmds - p.counters.get("commands_accepted", 0)))

    at0, first = after[0]
    last_at = max((at for at, p in got if at < t_fault), default=t_fault)
    r0 = ratios(first)
    later = [r for r in (ratios(p) for _, p in after) if r is not None]
    # the last one of a step the mirror has (after the feed stopped the daemon goes on)
    end = next((p for _, p in reversed(after) if p.step - spec.lead in ref), first)
    r_end = ref.get(end.step - spec.lead)
    acc_before = before[-1].counters.get("accepted", 0) if before else 0
    return {**row,
            "first_ratio": None if r0 is None else round(r0[0], 4),
            "first_ratio_min": None if r0 is None else round(r0[1], 4),
            "max_ratio_after": round(max(r[0] for r in later), 4) if later else None,
            "first_lacks": lacking(first), "end_lacks": lacking(end),
            "recovered_accepted": end.counters.get("recovered_accepted", 0),
            "recovered_late": end.counters.get("recovered_late", 0),
            "gap_s": round((at0 - last_at) / 1e9, 3),
            "first_after_fault_s": round((at0 - t_fault) / 1e9, 3),
            # restarted from the prior: no state resumed (counters from a checkpoint older
            # than the last prediction before the fault may be lower: not a reset)
            "reset_to_prior": status is not None and status.origin == "prior",
            "accepted_before": acc_before,
            "exact_end": r_end is not None and bool(
                np.allclose(end.x, r_end[0], rtol=1e-9, atol=1e-9)
                and np.allclose(np.diag(end.P), r_end[1], rtol=1e-9, atol=1e-9))}


def session_status(t, s: str, tries: int = 6):
    """Session ``s``'s SessionStatus (None if no answer in ``tries`` queries of 5 s: a
    loaded machine may let one go unanswered)."""
    from pd_service.wire import SessionStatus, decode, keys
    for _ in range(tries):
        for r in t.get(keys.status_key(s), timeout=5.0):
            if r.ok:
                return decode(r.payload, SessionStatus)
    return None


def _sdk_client(endpoint: str, instances: list[str], timeout: float = 60.0):
    """``pd_client.connect(endpoint)`` (client mode, as docs/clients.md says), retried until
    something listens there, once the liveliness tokens of ``instances`` are seen."""
    from pd_client import ServiceUnavailable, connect
    from pd_service.wire import keys
    deadline = time.monotonic() + timeout
    while True:
        try:
            t = connect(endpoint)
            break
        except ServiceUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    want = {keys.service_token_key(i) for i in instances}
    if not _wait(lambda: want <= set(t.get_liveliness(keys.ALL_SERVICES)), timeout):
        raise RuntimeError(f"not up: {sorted(want)}")
    return t


@contextlib.contextmanager
def fed(t, names: list[str], max_delay: int) -> Iterator[Traffic]:
    """The paper run at 100 ms steps (``time_scale`` 0.5) fed to ``names`` through the SDK
    on ``t`` (cached direct Robot, Operator sending for now + lead), everything recorded."""
    traffic = Traffic(t, names, time.time_ns() - 10**9, time_scale=0.5, max_delay=max_delay,
                      record=True, ahead=UPLINK_DELAY)
    feeder = threading.Thread(target=traffic.run, args=(10.0,), daemon=True)
    feeder.start()
    try:
        yield traffic
    finally:
        traffic.stop.set()
        feeder.join(5)


def restart_run(sessions: int, down_s: float, max_delay: int, before_s: float = 4.0,
                after_s: float = 3.0, root: Path | None = None) -> dict:
    """One ``restart`` run (module docstring): the daemon killed with SIGKILL, started again
    ``down_s`` later on the same state directory."""
    tmp = Path(tempfile.mkdtemp(prefix="pd-restart-", dir=root))
    ep = f"tcp/127.0.0.1:{free_port()}"
    daemon = Daemon(ep, tmp / "state", "inst-r", listen=True)
    names = [f"r{i}" for i in range(sessions)]
    t = None
    try:
        t = _sdk_client(ep, [daemon.instance])
        with fed(t, names, max_delay) as traffic:
            if not _wait(lambda: all(traffic.full[s] for s in names), 60.0):
                raise RuntimeError(f"no predictions: {daemon.log_path}")
            time.sleep(before_s)
            t_kill = time.monotonic_ns()
            daemon.kill9()
            time.sleep(down_s)
            daemon = Daemon(ep, tmp / "state", "inst-r", listen=True)
            t_start = time.monotonic_ns()
            _wait(lambda: all(traffic.after(s, t_kill) for s in names), 60.0)
            time.sleep(after_s)
            statuses = {s: session_status(t, s) for s in names}
            svc = service_status(t, daemon.instance)
        rows = [resumed_row(traffic, s, t_kill, statuses[s]) for s in names]
    finally:
        daemon.stop()
        if t is not None:
            t.close()
    log = daemon.log_path.read_text(errors="replace")
    ready = [ln for ln in log.splitlines() if "event=ready" in ln]
    return {"down_s": down_s, "max_delay": max_delay, "rows": rows,
            "service_counters": {} if svc is None else {
                k: v for k, v in svc.counters.items() if k.startswith(SERVICE_COUNTERS)},
            "start_to_first_s": round(min((r["first_after_fault_s"] for r in rows
                                           if r["first_ratio"] is not None), default=-1)
                                      - down_s, 3),
            "ready": ready[-1].split("event=ready", 1)[1].strip() if ready else "",
            "t_start_s": round((t_start - t_kill) / 1e9, 3)}


def takeover_run(sessions: int, max_delay: int, before_s: float = 4.0, after_s: float = 3.0,
                 root: Path | None = None) -> dict:
    """One ``takeover`` run (module docstring): two trusted instances behind a router, the
    owner of the most sessions killed with SIGKILL."""
    tmp = Path(tempfile.mkdtemp(prefix="pd-takeover-", dir=root))
    router = Router(free_port())
    router.start()
    insts = ("inst-a", "inst-b")
    daemons = {i: Daemon(router.endpoint, tmp / i, i, peers=tuple(x for x in insts if x != i))
               for i in insts}
    names = [f"k{i}" for i in range(sessions)]
    t = None
    try:
        t = _sdk_client(router.endpoint, list(insts))
        with fed(t, names, max_delay) as traffic:
            if not _wait(lambda: all(traffic.full[s] for s in names), 60.0):
                raise RuntimeError(f"no predictions: {tmp}")
            time.sleep(before_s)
            owner: dict[str, str | None] = dict.fromkeys(names)

            def owners_known() -> bool:
                for s in names:
                    owner[s] = owner[s] or getattr(session_status(t, s), "instance", None)
                return all(owner.values())

            if not _wait(owners_known, 30.0):
                raise RuntimeError(f"sessions without an owner: {owner}")
            victim = max(insts, key=lambda i: sum(1 for o in owner.values() if o == i))
            moved = [s for s in names if owner[s] == victim]
            with traffic.lock:
                term = {s: traffic.full[s][-1][1].term for s in moved}
            t_kill = time.monotonic_ns()
            daemons[victim].kill9()

            def survivor_predicts(s: str) -> bool:
                with traffic.lock:
                    return any(at >= t_kill and p.term > term[s] for at, p in traffic.full[s])

            _wait(lambda: all(survivor_predicts(s) for s in moved), 60.0)
            time.sleep(after_s)
            statuses = {s: session_status(t, s) for s in moved}
            survivor = next(i for i in insts if i != victim)
            svc = service_status(t, survivor)
        rows = [resumed_row(traffic, s, t_kill, statuses[s], term[s]) for s in moved]
    finally:
        for d in daemons.values():
            d.stop()
        if t is not None:
            t.close()
        router.kill()
    return {"max_delay": max_delay, "victim": victim, "moved": len(moved),
            "service_counters": {} if svc is None else {
                k: v for k, v in svc.counters.items() if k.startswith(SERVICE_COUNTERS)},
            "sessions": sessions, "rows": rows}


#: The service counters a restart or takeover run reports (prefixes).
SERVICE_COUNTERS = ("resumed", "readback", "restore", "recovered", "replica", "checkpoint")


def resumed_summary(runs: list[dict]) -> dict:
    """Over the runs' sessions: the first prediction's diag P ratio (largest entry) and its
    median / spread, how many within 10 %, inputs lacking, resets, gaps."""
    rows = [r for run in runs for r in run["rows"]]
    firsts = [r["first_ratio"] for r in rows if r["first_ratio"] is not None]
    per_run = [max((r["first_ratio"] for r in run["rows"] if r["first_ratio"] is not None),
                   default=None) for run in runs]

    def spread(v: list[float]) -> dict:
        return {"median": round(statistics.median(v), 4), "min": round(min(v), 4),
                "max": round(max(v), 4)} if v else {}

    return {"sessions": len(rows), "no_prediction": len(rows) - len(firsts),
            "first_ratio": spread(firsts),
            "runs_worst_first_ratio": per_run,
            "runs_within_10pct": sum(1 for v in per_run if v is not None and v <= 1.10),
            "first_within_10pct": sum(1 for v in firsts if v <= 1.10),
            "first_lacking_inputs": sum(1 for r in rows if r.get("first_lacks", (0, 0)) != (0, 0)),
            "end_lacking_inputs": sum(1 for r in rows if r.get("end_lacks", (0, 0)) != (0, 0)),
            "resets_to_prior": sum(1 for r in rows if r.get("reset_to_prior")),
            "resumed_stale": sum(run["service_counters"].get("resumed_stale", 0)
                                 for run in runs),
            "gap_s": spread([r["gap_s"] for r in rows if r.get("gap_s") is not None]),
            "readback": {k: sum(1 for r in rows if r["readback"] == k)
                         for k in ("answered", "timeout", "", None)},
            "origin": {k: sum(1 for r in rows if r["origin"] == k)
                       for k in ("checkpoint", "replica", "prior", None)}}


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
        self.procs = [popen(
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
    traffic = Traffic(t, [f"s{i}" for i in range(first, first + count)], epoch_ns, listen=False)
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
    # listen=False: this process receives no prediction (the daemon counts those it published);
    # a client slow to take 10,000 a second had its config answers dropped by the router
    with rig([f"s{i}" for i in range(sessions - churn, sessions)], rate_hz, root,
             listen=False) as (router, daemon, t, traffic):
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
                   "feed_skipped": traffic.steps_skipped + fed["skipped"],
                   "heap_returned_mb": None if st is None else round(
                       st.counters.get("heap_returned_bytes", 0) / 2**20, 1)}
            samples.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items()), flush=True)


def soak_summary(samples: list[dict]) -> dict:
    """The issue's soak figures: RSS growth after the first 5 min (MB: the highest row after
    5 min over the row at 5 min), median p99 of the last 10 min over the first 10 min's (with
    less than 20 min: of the last half over the first half), and the ranges of the fds and
    declarations. Beside them, what tells a leak from a backlog: the RSS floor (lowest row)
    of the last 10 min over that of minutes 5-15 (a leak raises the floor; a backlog the
    daemon catches up with and returns, heap_returned_mb, raises only peaks)."""
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
    early = [r["rss_mb"] for r in samples if min(300.0, end / 2) <= r["t_s"] <= 900.0]
    late = [r["rss_mb"] for r in samples if r["t_s"] >= end - span]
    return {"rss_growth_mb": round(max(settled) - settled[0], 1) if settled else None,
            "rss_floor_growth_mb": round(min(late) - min(early), 1) if early and late else None,
            "rss_range_mb": [min(settled), max(settled)] if settled else None,
            "late_share": round((last_row["late_total"] or 0) / fed, 4) if fed else None,
            "feed_skipped_share": round(last_row["feed_skipped"] / max(
                1, last_row["feed_skipped"] + last_row["feed_steps"]), 4),
            "p99_last_over_first": None if ratio is None else round(ratio, 2),
            **{f"{k}_range": [min(r[k] for r in samples), max(r[k] for r in samples)]
               for k in ("fds", "subscribers", "queryables", "tokens")}}


def resumed_main(a: argparse.Namespace) -> dict:
    """The ``restart`` and ``takeover`` modes: the runs, a row per session, the summary."""
    sys.path.insert(0, str(ROOT / "bench"))
    from gauge import gauge_ms
    g = gauge_ms()
    runs = []
    downs = [float(x) for x in a.down.split(",")] if a.mode == "restart" else [0.0]
    print(f"{'run':>3} {'session':>7} {'down':>5} {'origin':>10} {'readback':>8} "
          f"{'P1/ref':>7} {'min':>6} {'max aft':>8} {'lacks 1st':>9} {'lacks end':>9} "
          f"{'gap s':>6} {'reset':>5} {'exact':>5}")
    for i in range(a.repeat):
        if a.mode == "restart":
            run = restart_run(a.sessions, downs[i % len(downs)], a.max_delay, a.before,
                              a.after)
        else:
            run = takeover_run(a.sessions, a.max_delay, a.before, a.after)
        runs.append(run)
        for r in run["rows"]:
            if r.get("end_lacks", (0, 0)) != (0, 0):
                print("    lacking at the end:", r["session"], r["counters"])
            print(f"{i:>3} {r['session']:>7} {run.get('down_s', 0):>5} {r['origin']!s:>10} "
                  f"{r['readback']!s:>8} {r['first_ratio']!s:>7} "
                  f"{r.get('first_ratio_min')!s:>6} {r.get('max_ratio_after')!s:>8} "
                  f"{str(r.get('first_lacks')):>9} {str(r.get('end_lacks')):>9} "
                  f"{r.get('gap_s')!s:>6} {r.get('reset_to_prior')!s:>5} "
                  f"{r.get('exact_end')!s:>5}", flush=True)
    summary = resumed_summary(runs)
    print(f"gauge {g:.2f} ms; window {a.max_delay} steps of 100 ms")
    for k, v in summary.items():
        print(f"  {k:24s} {v}")
    return {"mode": a.mode, "gauge_ms": g, "max_delay": a.max_delay, "summary": summary,
            "runs": runs}


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
    for name in ("restart", "takeover"):
        r = sub.add_parser(name)
        r.add_argument("--sessions", type=int, default=4 if name == "restart" else 8)
        r.add_argument("--repeat", type=int, default=8)
        r.add_argument("--max-delay", type=int, default=60,
                       help="the spec's window in 100 ms steps (12: the paper's 1.2 s)")
        r.add_argument("--before", type=float, default=4.0)
        r.add_argument("--after", type=float, default=3.0)
        if name == "restart":
            r.add_argument("--down", default="2,3,4,5",
                           help="s from the kill to the restart, cycled over the runs")
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
    # a SIGTERM / SIGINT or an exception stops the routers, daemons and feeders started
    stop_children_on_exit()
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
    elif a.mode in ("restart", "takeover"):
        out = resumed_main(a)
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
