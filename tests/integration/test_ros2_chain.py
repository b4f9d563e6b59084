"""The ROS 2 chain as separate processes over real Zenoh on loopback:

    pd-robot-sim --ros2 (rmw_zenoh CDR on robot/<key>) -> pd-link (deploy/link-ros2.toml)
      -> <key> -> pd-ros2 -> pd/p<k>/<s>/sensor/*, pd/p<k>/<s>/cmd -> daemon -> pd/p<k>/<s>/prediction
      -> pd-ros2 -> 0/predicted/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_... -> this test
    pd-operator --ros2 (Twist on 0/cmd_vel/...) -> pd-ros2 -> daemon, and -> pd-link -> robot

The test is one more Zenoh client of the daemon (every process is a client of the daemon's
router): it records the native packets the bridge gives the daemon, in their arrival order,
the native Predictions, the simulator's truth and the bridge's CDR Odometry.

Checks: (a) each decoded predicted Odometry (x, y, yaw and their covariance block) equals an
offline estimator (``build(spec).est``, the one the daemon builds) fed the same packets
up to the Prediction's counters, to 1e-9; (b) driving: RMS error against the truth is printed;
stationary (``diffdrive-stationary``): the pose NEES (x, y, yaw; 3 dof) sampled once per second
has its mean inside the 99.9 % chi-square band of that many independent samples; (c) the
bridge's and the daemon's refusal counters are printed (the bridge refuses nothing here).
Run: ``.venv/bin/python -m pytest -q -s -m integration tests/integration/test_ros2_chain.py``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from pd_client.truth import Truth  # noqa: E402
from pd_service.backends import build  # noqa: E402
from pd_service.ros2.extract import yaw_of  # noqa: E402
from pd_service.ros2.keys import topic_keyexpr  # noqa: E402
from pd_service.ros2.messages import Odometry, decode, stamp_ns, type_hash  # noqa: E402
from pd_service.transport import Sample, ZenohTransport, zenoh_config  # noqa: E402
from pd_service.wire import (  # noqa: E402
    Command,
    ErrorReport,
    Measurement,
    Prediction,
    SessionSpec,
    keys,
)
from pd_service.wire import decode as wire_decode  # noqa: E402
from pd_service.wire.convert import command_time, measurement_time  # noqa: E402
from tests.service.procs import Daemon, query_session_status  # noqa: E402

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
LINK_CONFIG = ROOT / "deploy" / "link-ros2.toml"
SESSION = "bot"
ODOM = "nav_msgs/msg/Odometry"
ODOM_KEY = topic_keyexpr(0, "/predicted/odom", ODOM, type_hash(ODOM))
MAX_DELAY = 40  # steps: a loaded machine may hold the simulator back (as in test_system.py)
NEES_SPACING = 50  # steps (1 s) between the NEES samples


class Watcher:
    """What the daemon is given (arrival order), what it and the bridge publish, the truth."""

    def __init__(self, t: ZenohTransport) -> None:
        self.lock = threading.Condition()
        self.events: list[tuple[int, Measurement | Command]] = []
        self.preds: list[Prediction] = []
        self.odoms: list[Odometry] = []
        self.errors: list[ErrorReport] = []
        self.truth: dict[int, np.ndarray] = {}
        self.last_packet = time.monotonic()
        t.subscribe(keys.sensors_of(SESSION), self._meas)
        t.subscribe(keys.command_key(SESSION), self._cmd)
        t.subscribe(keys.prediction_key(SESSION), self._pred)
        t.subscribe(keys.error_key(SESSION), self._err)
        t.subscribe(keys.truth_key(SESSION), self._truth)
        t.subscribe(ODOM_KEY, self._odom)

    def _meas(self, s: Sample) -> None:
        with self.lock:
            self.events.append((s.recv_ns, wire_decode(s.payload, Measurement)))
            self.last_packet = time.monotonic()

    def _cmd(self, s: Sample) -> None:
        with self.lock:
            self.events.append((s.recv_ns, wire_decode(s.payload, Command)))
            self.last_packet = time.monotonic()

    def _pred(self, s: Sample) -> None:
        with self.lock:
            self.preds.append(wire_decode(s.payload, Prediction))
            self.lock.notify_all()

    def _err(self, s: Sample) -> None:
        with self.lock:
            self.errors.append(wire_decode(s.payload, ErrorReport))

    def _truth(self, s: Sample) -> None:
        tr = wire_decode(s.payload, Truth)
        with self.lock:
            self.truth[tr.step] = tr.x

    def _odom(self, s: Sample) -> None:
        msg = decode(s.payload, ODOM)
        assert isinstance(msg, Odometry)
        with self.lock:
            self.odoms.append(msg)


def open_client(endpoint: str, timeout: float = 20.0) -> ZenohTransport:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return ZenohTransport(zenoh_config(mode="client", connect=[endpoint]))
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def query_json(t: ZenohTransport, key: str, timeout: float = 3.0) -> dict | None:
    for r in t.get(key, timeout=timeout):
        if r.ok:
            return json.loads(r.payload)
    return None


def wait_until(what: str, check, timeout: float, log: Path | None = None) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, f"timed out waiting for {what}" + (
            f":\n{log.read_text(errors='replace')}" if log is not None and log.exists() else "")
        time.sleep(0.1)


def chi2_band(dof: int, level: float) -> tuple[float, float]:
    """Two-sided ``level`` band of a chi-square variable with ``dof`` degrees of freedom
    (Wilson-Hilferty: chi2 ~ dof (1 - 2/(9 dof) + z sqrt(2/(9 dof)))^3, accurate to < 1 %
    for dof >= 10)."""
    from statistics import NormalDist

    z = NormalDist().inv_cdf(0.5 + level / 2)
    a = 2.0 / (9.0 * dof)
    return (dof * (1 - a - z * math.sqrt(a)) ** 3, dof * (1 - a + z * math.sqrt(a)) ** 3)


def run_chain(tmp_path: Path, scenario: str, steps: int) -> dict:
    """Run the chain for ``steps`` simulated steps; returns what was recorded and queried."""
    d = Daemon("chain", tmp_path / "state", []).start()
    t = open_client(d.endpoint)
    procs: dict[str, subprocess.Popen] = {}
    logs: dict[str, Path] = {}

    def start(name: str, args: list[str]) -> None:
        logs[name] = tmp_path / f"{name}.log"
        procs[name] = subprocess.Popen([sys.executable, *args, "--connect", d.endpoint],
                                       stdout=logs[name].open("ab"), stderr=subprocess.STDOUT)

    try:
        wait_until("the daemon", lambda: bool(
            t.get_liveliness(keys.service_token_key("chain"), timeout=0.5))
            or d.proc.poll() is not None, 20)
        assert d.proc.poll() is None, d.log()
        w = Watcher(t)
        start("link", ["-m", "pd_service.link", "--config", str(LINK_CONFIG),
                       "--instance", "chain"])
        start("bridge", ["-m", "pd_service.ros2", "--instance", "chain", "--session", SESSION])
        wait_until("pd-link", lambda: any(r.ok for r in t.get(keys.link_stats_key("chain"),
                                                               timeout=0.5)), 30, logs["link"])
        wait_until("pd-ros2", lambda: query_json(t, keys.ros2_status_key("chain"), 0.5)
                   is not None, 30, logs["bridge"])
        start("operator", ["-m", "pd_client.tools", "operator", "--scenario", scenario,
                           "--session", SESSION, "--ros2", "--steps", str(steps)])
        start("sim", ["-m", "pd_client.tools", "sim", "--scenario", scenario, "--session",
                      SESSION, "--create-session", "--ros2", "--steps", str(steps),
                      "--seed", "3", "--max-delay", str(MAX_DELAY)])
        assert procs["sim"].wait(120) == 0, logs["sim"].read_text()
        assert procs["operator"].wait(30) == 0, logs["operator"].read_text()
        # quiet: longer than the link's largest delay (300 ms)
        deadline = time.monotonic() + 20
        while time.monotonic() - w.last_packet < 1.5:
            assert time.monotonic() < deadline, "packets kept arriving"
            time.sleep(0.05)
        spec = next(wire_decode(r.payload, SessionSpec)
                    for r in t.get(keys.config_key(SESSION), timeout=10.0) if r.ok)
        with w.lock:
            n_events, n_preds = len(w.events), len(w.preds)
            # a few predictions made after the last packet, republished by the bridge
            assert w.lock.wait_for(lambda: len(w.preds) >= n_preds + 10, 10), n_preds
        time.sleep(0.3)
        session = query_session_status(t, SESSION)
        bridge = query_json(t, keys.ros2_status_key("chain"))
        with w.lock:
            out = {"spec": spec, "events": list(w.events), "preds": list(w.preds),
                   "odoms": list(w.odoms), "errors": list(w.errors), "truth": dict(w.truth),
                   "session": session, "bridge": bridge, "n_events": n_events}
    finally:
        for name in ("operator", "sim", "bridge", "link"):
            p = procs.get(name)
            if p is None:
                continue
            if p.poll() is None:
                p.terminate()
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
        t.close()
        d.stop()
    assert procs["bridge"].returncode == 0, logs["bridge"].read_text()
    assert d.proc is not None and d.proc.returncode == 0, d.log()
    return out


def offline_references(spec: SessionSpec, events: list[tuple[int, Measurement | Command]],
                       preds: list[Prediction]) -> tuple[dict[int, tuple[np.ndarray, np.ndarray]],
                                                          dict[str, int]]:
    """Feed ``build(spec).est`` the packets in arrival order and, at each Prediction
    whose counters (accepted, commands_accepted) the offline estimator reaches, predict as
    the daemon did. Returns {prediction index: (x, P)} and the offline counters.

    ``now`` of a packet: the step of its arrival here, but no later than the step of the
    next Prediction that counts it (the daemon's step when it took the packet is between the
    sample's step and that one; ``now`` only decides refusals, which the windows here, of
    MAX_DELAY steps, do not make)."""
    est = build(spec).est
    ordered = sorted(range(len(events)), key=lambda i: events[i][0])
    evs = [events[i] for i in ordered]
    refs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    i = 0
    acc = cmd = 0
    for pi, p in enumerate(preds):
        want = (p.counters.get("accepted", 0), p.counters.get("commands_accepted", 0))
        p_now = p.step - spec.lead
        while i < len(evs):
            recv_ns, msg = evs[i]
            is_meas = isinstance(msg, Measurement)
            if acc >= want[0] if is_meas else cmd >= want[1]:
                break  # the daemon took this one after the Prediction
            now = min(spec.step_of(recv_ns), p_now)
            if est.now is not None:
                now = max(now, est.now)
            if isinstance(msg, Measurement):
                s, off = measurement_time(msg, spec)  # the daemon's instant: step and offset
                acc += est.add_measurement(msg.sensor, s, msg.z, now=now, R=msg.R, offset=off)
            else:
                j, off = command_time(msg, spec)
                cmd += est.add_command(j, msg.u, now=now, offset=off)
            i += 1
        if (acc, cmd) != want or (est.now is not None and p_now < est.now):
            continue
        ref = est.predict(now=p_now)
        refs[pi] = (np.asarray(ref.x), np.asarray(ref.P))
    while i < len(evs):  # the rest, for the counters
        recv_ns, msg = evs[i]
        now = max(spec.step_of(recv_ns), est.now or 0)
        if isinstance(msg, Measurement):
            s, off = measurement_time(msg, spec)
            est.add_measurement(msg.sensor, s, msg.z, now=now, R=msg.R, offset=off)
        else:
            j, off = command_time(msg, spec)
            est.add_command(j, msg.u, now=now, offset=off)
        i += 1
    return refs, dict(est.counters)


def compare_odometry(out: dict) -> tuple[int, float]:
    """(a): every bridged Odometry whose Prediction has an offline reference equals it.
    Returns (Odometry compared, largest difference)."""
    spec: SessionSpec = out["spec"]
    preds: list[Prediction] = out["preds"]
    refs, counters = offline_references(spec, out["events"], preds)
    by_stamp: dict[int, list[int]] = {}
    for pi, p in enumerate(preds):
        by_stamp.setdefault(p.t_ns, []).append(pi)
    compared, worst = 0, 0.0
    for o in out["odoms"]:
        pose = o.pose.pose
        z = np.array([pose.position.x, pose.position.y, yaw_of(pose.orientation)])
        cands = by_stamp.get(stamp_ns(o.header.stamp), [])
        if not cands:
            continue
        pi = min(cands, key=lambda c: float(np.abs(preds[c].x[:2] - z[:2]).sum()))
        if pi not in refs:
            continue
        x, P = refs[pi]
        diff = z - x[:3]
        diff[2] = math.remainder(diff[2], 2 * math.pi)
        cov = np.asarray(o.pose.covariance).reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])]
        np.testing.assert_allclose(diff, 0.0, atol=1e-9)
        np.testing.assert_allclose(cov, P[:3, :3], rtol=1e-9, atol=1e-12)
        worst = max(worst, float(np.abs(diff).max()), float(np.abs(cov - P[:3, :3]).max()))
        compared += 1
    session = out["session"]
    assert session is not None
    c = session.counters
    # the offline estimator accepted what the daemon accepted
    assert counters.get("accepted", 0) == c.get("accepted", 0), (counters, c)
    assert counters.get("commands_accepted", 0) == c.get("commands_accepted", 0), (counters, c)
    return compared, worst


def pose_errors(out: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per Prediction with a truth, after 2 s of warm-up: error (x, y, yaw) and P's pose block."""
    errs, covs = [], []
    for p in out["preds"]:
        tr = out["truth"].get(p.step)
        if tr is None or p.step < 100:
            continue
        e = np.asarray(tr[:3]) - p.x[:3]
        e[2] = math.remainder(e[2], 2 * math.pi)
        errs.append(e)
        covs.append(p.P[:3, :3])
    return np.array(errs), np.array(covs)


def report_counters(label: str, out: dict) -> None:
    """(c): the refusal counters of the bridge and of the daemon."""
    b = out["bridge"]["sessions"][SESSION]["counters"]
    s = out["session"].counters
    refusals = {k: v for k, v in s.items() if k in ("late", "future", "duplicate", "invalid")
                or k.startswith(("refused", "commands_")) and k != "commands_accepted"}
    print(f"\n{label}: bridge received {b.get('received', 0)} forwarded {b.get('forwarded', 0)} "
          f"refused {b.get('refused', 0)} "
          f"{ {k: v for k, v in b.items() if k.startswith('refused_')} }, predictions "
          f"{b.get('predictions_received', 0)} republished {b.get('predictions_republished', 0)}"
          f"; daemon accepted {s.get('accepted', 0)} commands_accepted "
          f"{s.get('commands_accepted', 0)} refusals "
          f"{refusals}"
          f"; ErrorReports {len(out['errors'])}")
    assert b.get("refused", 0) == 0, b
    assert out["bridge"]["counters"].get("internal_errors", 0) == 0, out["bridge"]["counters"]
    assert b.get("forwarded", 0) == out["n_events"], (b, out["n_events"])


def test_driving_robot_chain_equals_offline(tmp_path: Path) -> None:
    out = run_chain(tmp_path, "diffdrive", steps=400)
    report_counters("diffdrive", out)
    compared, worst = compare_odometry(out)
    print(f"diffdrive: {compared} of {len(out['odoms'])} predicted Odometry equal the offline "
          f"estimator (largest difference {worst:.1e}); {len(out['preds'])} Predictions")
    assert compared >= len(out["odoms"]) // 2 and compared >= 200, (compared, len(out["odoms"]))
    errs, _ = pose_errors(out)
    assert len(errs) > 150
    rms = np.sqrt(np.mean(errs**2, axis=0))
    moved = max(float(np.hypot(*x[:2])) for x in out["truth"].values())
    print(f"diffdrive: RMS error of x(k + lead) over {len(errs)} predictions: x {rms[0]:.4f} m, "
          f"y {rms[1]:.4f} m, yaw {rms[2]:.4f} rad; the robot drove {moved:.2f} m from the start")
    assert moved > 1.0  # the compared poses are not all at the origin


def test_stationary_robot_chain_covariance_is_consistent(tmp_path: Path) -> None:
    out = run_chain(tmp_path, "diffdrive-stationary", steps=550)
    report_counters("diffdrive-stationary", out)
    compared, worst = compare_odometry(out)
    print(f"diffdrive-stationary: {compared} of {len(out['odoms'])} predicted Odometry equal "
          f"the offline estimator (largest difference {worst:.1e})")
    assert compared >= len(out["odoms"]) // 2, (compared, len(out["odoms"]))
    # one Prediction per sampled step (the first of that step), a step every NEES_SPACING
    first: dict[int, Prediction] = {}
    for p in out["preds"]:
        first.setdefault(p.step, p)
    nees = []
    for step in range(100, 100 + 20 * NEES_SPACING, NEES_SPACING):
        p, tr = first.get(step), out["truth"].get(step)
        if p is None or tr is None:
            continue
        e = np.asarray(tr[:3]) - p.x[:3]
        e[2] = math.remainder(e[2], 2 * math.pi)
        nees.append(float(e @ np.linalg.solve(p.P[:3, :3], e)))
    n = len(nees)
    assert n >= 6, n
    lo, hi = chi2_band(3 * n, 0.999)
    mean = float(np.mean(nees))
    print(f"diffdrive-stationary: pose NEES (x, y, yaw) at {n} steps 1 s apart: mean {mean:.2f} "
          f"(3 expected), 99.9 % band of the mean [{lo / n:.2f}, {hi / n:.2f}]")
    assert lo / n <= mean <= hi / n, (mean, nees)
