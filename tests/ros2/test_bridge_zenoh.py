"""pd-ros2 as a separate process over real Zenoh on loopback.

daemon (``python -m pd_service``) + bridge (``python -m pd_service.ros2``) + this test as a raw
Zenoh peer that publishes CDR Odometry / Imu / PoseWithCovarianceStamped / Twist on rmw_zenoh
keys (with rmw_zenoh attachments) and subscribes to both the daemon's native Prediction and the
bridge's CDR Odometry of it. Checks: the decoded predicted pose equals the native Prediction of
the same step to 1e-12; the daemon accepted the bridged measurements; a malformed payload is
refused by the bridge with an ErrorReport and a counter.

Measured and printed, not asserted: the bridge hop (native Prediction received here -> the ROS
Odometry of it received here, p50 / p99) and the bridge's CPU per message from /proc.
Run: ``.venv/bin/python -m pytest -q -s -m integration tests/ros2/test_bridge_zenoh.py``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pd_client import Admin
from pd_service.ros2.attachment import Attachment, decode_attachment, encode_attachment
from pd_service.ros2.extract import yaw_of
from pd_service.ros2.keys import topic_keyexpr
from pd_service.ros2.messages import Odometry, decode, encode, stamp_ns, type_hash
from pd_service.transport import Sample, ZenohTransport
from pd_service.wire import ErrorReport, Prediction, keys
from pd_service.wire import decode as wire_decode
from tests.ros2.specs import IMU, ODOM, PERIOD_NS, POSE, imu, odometry, pose_fix, twist, unicycle_spec
from tests.service.procs import (
    ANSWER_TIMEOUT_S,
    Daemon,
    Presence,
    client,
    endpoint,
    free_port,
    query_session_status,
    sleep_until,
)

pytestmark = pytest.mark.integration

SESSION = "ros"
TWIST = "geometry_msgs/msg/Twist"
V, W = 0.5, 0.2  # the robot drives a circle: m/s, rad/s
STEPS = 200  # 4 s at 50 Hz


def key(topic: str, msg_type: str) -> str:
    return topic_keyexpr(0, topic, msg_type, type_hash(msg_type))


def truth(t_s: float) -> tuple[float, float, float]:
    """Pose on the circle at t_s seconds after the start (x, y, yaw)."""
    return V / W * math.sin(W * t_s), V / W * (1.0 - math.cos(W * t_s)), W * t_s


class Recorder:
    """Arrival (monotonic ns) of each native Prediction and each bridged Odometry."""

    def __init__(self, t: ZenohTransport) -> None:
        self.cond = threading.Condition()
        self.preds: list[tuple[int, Prediction]] = []
        self.odoms: list[tuple[int, Odometry, bytes | None]] = []
        self.errors: list[ErrorReport] = []
        t.subscribe(keys.prediction_key(SESSION), self._pred)
        t.subscribe(key("/predicted/odom", ODOM), self._odom)
        t.subscribe(keys.error_key(SESSION), self._err)

    def _pred(self, s: Sample) -> None:
        p = wire_decode(s.payload, Prediction)
        with self.cond:
            self.preds.append((s.recv_mono_ns, p))
            self.cond.notify_all()

    def _odom(self, s: Sample) -> None:
        msg = decode(s.payload, ODOM)
        assert isinstance(msg, Odometry)
        with self.cond:
            self.odoms.append((s.recv_mono_ns, msg, s.attachment))
            self.cond.notify_all()

    def _err(self, s: Sample) -> None:
        with self.cond:
            self.errors.append(wire_decode(s.payload, ErrorReport))
            self.cond.notify_all()

    def wait(self, pred, timeout: float = 20.0) -> bool:  # type: ignore[no-untyped-def]
        with self.cond:
            return self.cond.wait_for(pred, timeout)


def cpu_ticks(pid: int) -> int:
    """utime + stime of a process, clock ticks (/proc/<pid>/stat fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def bridge_status(t: ZenohTransport) -> dict:
    for r in t.get(keys.ros2_status_key("it"), timeout=ANSWER_TIMEOUT_S):
        if r.ok:
            return json.loads(r.payload)
    raise AssertionError("no status reply from pd-ros2")


def test_bridge_process_over_zenoh(tmp_path: Path) -> None:
    port = free_port()
    t = client(port)
    presence = Presence(t)
    daemon = Daemon("d1", tmp_path / "state", [endpoint(port)]).start()
    bridge_port = free_port()
    log_path = tmp_path / "pd-ros2.log"
    bridge_log = open(log_path, "ab")
    bridge: subprocess.Popen | None = None
    try:
        assert presence.wait("d1"), daemon.log()
        epoch = (time.time_ns() // PERIOD_NS) * PERIOD_NS
        spec = unicycle_spec(SESSION, epoch_ns=epoch, tf=False)
        admin = Admin(t)
        admin.open_session(spec, timeout=20.0)
        # the bridge learns the spec by querying pd/*/*/config at start
        tokens: set[str] = set()
        tok_cond = threading.Condition()

        def on_token(k: str, alive: bool) -> None:
            with tok_cond:
                (tokens.add if alive else tokens.discard)(k)
                tok_cond.notify_all()

        t.subscribe_liveliness("@ros2_lv/**", on_token, history=True)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        bridge = subprocess.Popen(
            [sys.executable, "-m", "pd_service.ros2", "--instance", "it", "--mode", "peer",
             "--listen", endpoint(bridge_port), "--connect", endpoint(port),
             "--connect", daemon.endpoint], stdout=bridge_log, stderr=bridge_log, env=env)
        with tok_cond:
            assert tok_cond.wait_for(lambda: any("%predicted%odom" in k for k in tokens), 30.0), \
                log_path.read_text()
        assert any("/NN/%/%/pd_service" in k for k in tokens)
        assert any("/MS/%/%/pd_service/%odom/nav_msgs::msg::dds_::Odometry_/" in k for k in tokens)

        rec = Recorder(t)
        gid = bytes(range(16))
        pubs = {name: t.publisher(key(topic, mt)) for name, topic, mt in (
            ("odom", "/odom", ODOM), ("imu", "/imu", IMU), ("pose", "/pose_fix", POSE),
            ("cmd", "/cmd_vel", TWIST))}
        idle0, idle_t0 = cpu_ticks(bridge.pid), time.monotonic()
        time.sleep(1.0)  # the bridge's CPU with only the daemon's predictions flowing
        idle1, idle_t1 = cpu_ticks(bridge.pid), time.monotonic()
        status0 = bridge_status(t)["sessions"][SESSION]["counters"]
        cpu0, run_t0 = cpu_ticks(bridge.pid), time.monotonic()
        start = spec.time_of(spec.step_of(time.time_ns()) + 2)
        sent = 0
        for k in range(STEPS):
            t_ns = start + k * PERIOD_NS
            sleep_until(t_ns)
            x, y, yaw = truth(k * PERIOD_NS / 1e9)
            att = encode_attachment(Attachment(k + 1, time.time_ns(), gid))
            pubs["cmd"].put(encode(twist(V, W), TWIST), attachment=att)
            pubs["odom"].put(encode(odometry(t_ns, x, y, yaw, V, W), ODOM), attachment=att)
            pubs["imu"].put(encode(imu(t_ns, W), IMU), attachment=att)
            sent += 3
            if k % 5 == 0:
                fix = pose_fix(t_ns, x, y, yaw, np.diag([0.0025, 0.0025, 1.0, 1.0, 1.0, 4e-4]))
                pubs["pose"].put(encode(fix, POSE), attachment=att)
                sent += 1
        pubs["imu"].put(b"\x00\x01\x00\x00garbage")  # refused by the bridge
        assert rec.wait(lambda: any("not valid CDR" in e.reason for e in rec.errors)), rec.errors
        time.sleep(0.3)  # let the last predictions of the run through (the tail is trimmed below)
        cpu1, run_t1 = cpu_ticks(bridge.pid), time.monotonic()
        status = bridge_status(t)["sessions"][SESSION]["counters"]
        sess = query_session_status(t, SESSION)
    finally:
        if bridge is not None:
            bridge.terminate()
            try:
                bridge.wait(15)
            except subprocess.TimeoutExpired:
                bridge.kill()
        bridge_log.close()
        daemon.stop()
        t.close()

    # --- the bridge forwarded everything and refused the garbage --------------------------
    assert status["sensor_forwarded"] - status0.get("sensor_forwarded", 0) == sent - STEPS
    assert status["commands_forwarded"] - status0.get("commands_forwarded", 0) == STEPS
    assert status["refused_cdr"] == 1 and status["refused"] == 1
    assert sess is not None and sess.counters.get("accepted", 0) > 0, sess

    # --- every bridged Odometry equals the native Prediction of its step -------------------
    with rec.cond:
        preds, odoms = list(rec.preds), list(rec.odoms)
    by_stamp: dict[int, list[tuple[int, Prediction]]] = {}
    for arrival, p in preds:
        by_stamp.setdefault(p.t_ns, []).append((arrival, p))
    odom_by_stamp: dict[int, list[tuple[int, Odometry, bytes | None]]] = {}
    for arrival, o, att in odoms:
        odom_by_stamp.setdefault(stamp_ns(o.header.stamp), []).append((arrival, o, att))
    pairs: list[tuple[int, Prediction, int, Odometry]] = []
    for stamp, group in odom_by_stamp.items():
        native = by_stamp.get(stamp, [])
        if len(native) != len(group):  # the test's subscription missed some of that step
            continue
        for (ta, p), (tb, o, _) in zip(native, group, strict=True):
            pairs.append((ta, p, tb, o))
    assert len(pairs) >= STEPS // 2, (len(preds), len(odoms), len(pairs))
    moved = 0
    for _, p, _, o in pairs:
        pose = o.pose.pose
        assert abs(pose.position.x - p.x[0]) <= 1e-12 and abs(pose.position.y - p.x[1]) <= 1e-12
        dyaw = math.remainder(yaw_of(pose.orientation) - p.x[2], 2 * math.pi)
        assert abs(dyaw) <= 1e-12
        assert o.twist.twist.linear.x == p.x[3] and o.twist.twist.angular.z == p.x[4]
        cov = np.asarray(o.pose.covariance).reshape(6, 6)
        assert abs(cov[0, 0] - p.P[0, 0]) <= 1e-12 and abs(cov[5, 5] - p.P[2, 2]) <= 1e-12
        moved += abs(p.x[0]) > 0.1
    assert moved > 0  # the robot drove: the compared poses are not all the prior's zeros
    seqs = [decode_attachment(att).sequence_number for _, _, att in odoms if att is not None]
    assert len(seqs) == len(odoms) and seqs == sorted(seqs) and len(set(seqs)) == len(seqs)

    # --- measured, not asserted ------------------------------------------------------------
    hop_us = np.array([(tb - ta) / 1e3 for ta, _, tb, _ in pairs])
    handled = (status["received"] - status0.get("received", 0)
               + status["predictions_received"] - status0.get("predictions_received", 0))
    tck = os.sysconf("SC_CLK_TCK")
    cpu_s = (cpu1 - cpu0) / tck
    print(f"\npd-ros2 hop (native Prediction -> ROS Odometry, both received by this test): "
          f"n={len(hop_us)} p50={np.percentile(hop_us, 50):.0f} us "
          f"p99={np.percentile(hop_us, 99):.0f} us; "
          f"bridge CPU {cpu_s * 1e3:.0f} ms for {handled} messages "
          f"({status['received'] - status0.get('received', 0)} ROS inputs, "
          f"{status['predictions_received'] - status0.get('predictions_received', 0)} "
          f"predictions -> {status['outputs_published'] - status0.get('outputs_published', 0)} "
          f"ROS outputs) in {run_t1 - run_t0:.1f} s = {cpu_s * 1e6 / max(handled, 1):.0f} "
          f"us/message; before the run (only the daemon's predictions flowing) "
          f"{(idle1 - idle0) / tck * 1e3 / (idle_t1 - idle_t0):.0f} ms CPU per s")
