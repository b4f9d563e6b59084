"""The whole system as separate processes over real Zenoh on loopback.

daemon (pd-service) <- pd-link <- simulator (pd-robot-sim) ; operator (pd-operator) -> daemon
and -> pd-link -> simulator. The test is one more Zenoh client of the daemon: it sees exactly
the operator-side packets the daemon sees, the predictions and the simulator's truth.

Restart (kill -9), malformed storms and two instances sharing sessions are exercised against
the daemon in tests/service/test_integration.py.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pd_client.truth import Truth
from pd_service.backends import build
from pd_service.transport import ZenohTransport, zenoh_config
from pd_service.wire import (
    Command,
    ErrorReport,
    Measurement,
    Prediction,
    SessionSpec,
    decode,
    keys,
)
from pd_service.wire.convert import command_time, measurement_step, measurement_time
from tests.service.procs import Daemon, query_service_status, query_session_status

pytestmark = pytest.mark.integration

SESSION = "paper"


class Watcher:
    """Records what the daemon sees (operator side), what it publishes and the truth."""

    def __init__(self, t: ZenohTransport) -> None:
        self.lock = threading.Condition()
        self.meas: list[tuple[int, Measurement]] = []
        self.cmds: list[tuple[int, Command]] = []
        self.preds: list[Prediction] = []
        self.errors: list[ErrorReport] = []
        self.truth: dict[int, np.ndarray] = {}
        self.last_packet = time.monotonic()
        t.subscribe(keys.sensors_of(SESSION), self._meas)
        t.subscribe(keys.command_key(SESSION), self._cmd)
        t.subscribe(keys.prediction_key(SESSION), self._pred)
        t.subscribe(keys.error_key(SESSION), self._err)
        t.subscribe(keys.truth_key(SESSION), self._truth)

    def _meas(self, s) -> None:
        with self.lock:
            self.meas.append((s.recv_ns, decode(s.payload, Measurement)))
            self.last_packet = time.monotonic()

    def _cmd(self, s) -> None:
        with self.lock:
            self.cmds.append((s.recv_ns, decode(s.payload, Command)))

    def _pred(self, s) -> None:
        with self.lock:
            self.preds.append(decode(s.payload, Prediction))
            self.lock.notify_all()

    def _err(self, s) -> None:
        with self.lock:
            self.errors.append(decode(s.payload, ErrorReport))

    def _truth(self, s) -> None:
        tr = decode(s.payload, Truth)
        with self.lock:
            self.truth[tr.step] = tr.x

    def wait(self, pred, timeout: float) -> bool:
        with self.lock:
            return self.lock.wait_for(lambda: pred(self), timeout)


def run_tool(args: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *args], stdout=log.open("ab"),
                            stderr=subprocess.STDOUT)


def open_client(endpoint: str, timeout: float = 20.0) -> ZenohTransport:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return ZenohTransport(zenoh_config(mode="client", connect=[endpoint]))
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


LINK_PAPER = """
seed = 11
step_ms = 50
[[downlink]]
name = "camera"
match = "robot/*/*/sensor/camera"
delay = "10 steps"
loss = "5%"
[[downlink]]
name = "ranger"
match = "robot/*/*/sensor/ranger"
delay = "12 steps"
loss = "5%"
[[uplink]]
name = "commands"
match = "pd/*/*/cmd"
delay = "9 steps"     # one step of slack before the apply step (lead 10), as a deployment would
"""

# 30 % Gilbert-Elliott loss (p / (p + r) = 0.3, mean burst 1 / r = 2.9), jitter, reordering.
LINK_HARSH = """
seed = 5
step_ms = 50
[[downlink]]
name = "sensors"
match = "robot/*/*/sensor/*"
delay = "10 steps"
jitter = "60ms"
distribution = "normal"
loss = { model = "gemodel", p = "15%", r = "35%" }
reorder = "10%"
gap = 3
[[uplink]]
name = "commands"
match = "pd/*/*/cmd"
delay = "10 steps"
"""


def start_system(tmp_path: Path, link_config: str, steps: int, extra_sim: list[str]):
    d = Daemon("sys", tmp_path / "state", []).start()
    t = open_client(d.endpoint)
    deadline = time.monotonic() + 20
    while not t.get_liveliness(keys.service_token_key("sys"), timeout=0.5):
        assert time.monotonic() < deadline and d.proc.poll() is None, d.log()
    w = Watcher(t)
    cfg = tmp_path / "link.toml"
    cfg.write_text(link_config)
    z = ["--connect", d.endpoint]
    procs = {
        "link": run_tool(["-m", "pd_service.link", "--config", str(cfg), "--instance", "sys", *z],
                         tmp_path / "link.log"),
    }
    deadline = time.monotonic() + 20
    while not any(r.ok for r in t.get(keys.link_stats_key("sys"), timeout=0.5)):
        assert time.monotonic() < deadline, (tmp_path / "link.log").read_text()
    procs["operator"] = run_tool(["-m", "pd_client.tools", "operator", "--session", SESSION,
                                  "--steps", str(steps), *z], tmp_path / "operator.log")
    procs["sim"] = run_tool(["-m", "pd_client.tools", "sim", "--session", SESSION, "--create-session",
                             "--steps", str(steps), "--seed", "3", *extra_sim, *z],
                            tmp_path / "sim.log")
    return d, t, w, procs


def stop_all(d: Daemon, t: ZenohTransport, procs: dict) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.terminate()
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
    t.close()
    d.stop()


def wait_quiet(w: Watcher, quiet_s: float, timeout: float) -> None:
    """Wait until no operator-side packet has arrived for ``quiet_s`` (longer than the
    link's largest delay plus jitter), bounded by ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() - w.last_packet < quiet_s:
        assert time.monotonic() < deadline, "packets kept arriving"
        time.sleep(0.05)


def fetch_spec(t: ZenohTransport) -> SessionSpec:
    for r in t.get(keys.config_key(SESSION), timeout=10.0):
        if r.ok:
            return decode(r.payload, SessionSpec)
    raise AssertionError("nobody answered the session's config query")


def test_paper_scenario_through_the_link_equals_offline(tmp_path: Path) -> None:
    steps = 200
    # max_delay 40: a machine loaded by other tests may hold the simulator back by a few
    # steps; this test is about equality with the offline filter, not about the window.
    d, t, w, procs = start_system(tmp_path, LINK_PAPER, steps, ["--max-delay", "40"])
    try:
        assert procs["sim"].wait(60) == 0, (tmp_path / "sim.log").read_text()
        wait_quiet(w, quiet_s=1.5, timeout=20)
        spec = fetch_spec(t)
        with w.lock:
            meas, cmds = list(w.meas), list(w.cmds)
        newest = max(measurement_step(m, spec) for _, m in meas)
        # a prediction made after the last packet: its newest_step is the newest stamp
        assert w.wait(lambda w: w.preds and w.preds[-1].newest_step == newest
                      and w.preds[-1].step - spec.lead > newest, 10), w.preds[-1:]
        last = w.preds[-1]
        status = query_session_status(t, SESSION)
        # every packet that crossed the link was accepted (delays 10/12 << max_delay)
        assert status.counters["accepted"] == len(meas), status.counters
        assert w.errors == []

        # Offline: the same accepted packets and commands, in the order they were received.
        op = build(spec).est
        events = [(r, 0, m) for r, m in meas] + [(r, 1, c) for r, c in cmds]
        for recv_ns, kind, msg in sorted(events, key=lambda e: e[0]):
            now = spec.step_of(recv_ns)
            if kind == 0:
                s, off = measurement_time(msg, spec)
                assert op.add_measurement(msg.sensor, s, msg.z, now=now, offset=off)
            else:
                j, off = command_time(msg, spec)
                op.add_command(j, msg.u, now=now, offset=off)
        ref = op.predict(now=last.step - spec.lead)
        np.testing.assert_allclose(last.x, ref.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(last.P, ref.P, rtol=1e-9, atol=1e-12)
        assert op.counters["commands_accepted"] == status.counters.get("commands_accepted")

        # Accuracy: predictions of x(k + lead) against the simulator's truth.
        err, sig = [], []
        for p in w.preds:
            x = w.truth.get(p.step)
            if x is not None and p.step >= 60:
                err.append(x - p.x)
                sig.append(np.sqrt(np.diag(p.P)))
        err, sig = np.array(err), np.array(sig)
        assert len(err) > 100
        rms = np.sqrt(np.mean(err**2, axis=0))
        assert rms[0] < 0.5 and rms[2] < 0.5, rms  # p1, p2 in metres
        assert np.mean(np.abs(err) <= 3 * sig) > 0.95
    finally:
        stop_all(d, t, procs)
    assert d.proc.returncode == 0, d.log()


def test_harsh_link_keeps_publishing_and_counts_refusals(tmp_path: Path) -> None:
    steps = 200
    d, t, w, procs = start_system(tmp_path, LINK_HARSH, steps, ["--max-delay", "12"])
    try:
        t0 = time.monotonic()
        assert procs["sim"].wait(60) == 0, (tmp_path / "sim.log").read_text()
        elapsed = time.monotonic() - t0
        wait_quiet(w, quiet_s=1.5, timeout=20)
        stats = [r for r in t.get(keys.link_stats_key("sys"), timeout=10.0) if r.ok]
        assert stats
        with w.lock:
            preds = list(w.preds)
        # one prediction per step at least (plus packet-triggered ones), over the whole run
        steps_seen = {p.step for p in preds}
        span = max(steps_seen) - min(steps_seen) + 1
        assert len(steps_seen) >= 0.95 * span, (len(steps_seen), span)
        assert len(preds) / elapsed >= 0.9 * 20
        status = query_session_status(t, SESSION)
        c = status.counters
        # jitter of 60 ms (normal) on a 10-step delay, max_delay 12: some samples arrive too late
        assert c.get("late", 0) > 0, c
        assert c["accepted"] + c.get("refused", 0) == len(w.meas), c
        assert len(w.errors) > 0 and all("older than the window" in e.reason for e in w.errors), w.errors[:3]
        svc = query_service_status(t, "sys")
        assert svc.counters.get("published", 0) >= len(preds)
        assert d.proc.poll() is None  # never crashed
        # reordering and loss happened on the link (its own counters)
        text = stats[0].payload.decode()
        assert '"reordered"' in text and '"dropped"' in text
    finally:
        stop_all(d, t, procs)
    assert d.proc.returncode == 0, d.log()
