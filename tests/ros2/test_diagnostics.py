"""pd-ros2's /diagnostics (pd_service.ros2.diagnostics): the checks' levels from two
SessionStatus one interval apart, and the DiagnosticArray the bridge publishes, read back
from its CDR with the rosbags typestore; pd-ros2's and pd-link's metrics parsed with
prometheus-client's own parser."""

from __future__ import annotations

import logging

import pytest
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from pd_service.metrics import registry_of
from pd_service.ros2.bridge import bridge_metrics
from pd_service.ros2.diagnostics import (
    DIAGNOSTICS_TYPE,
    ERROR,
    OK,
    WARN,
    decode_diagnostic_array,
    session_checks,
)
from pd_service.ros2.keys import topic_keyexpr
from pd_service.ros2.messages import type_hash
from pd_service.wire import SessionStatus, encode, keys

from .specs import unicycle_spec
from .test_bridge import IMU, NOW, STAMP, imu, make_rig, rmw_key

SPEC = unicycle_spec("s1")


def status(now_step: int, **counters: int) -> SessionStatus:
    return SessionStatus(session="s1", instance="a", state="active", now_step=now_step,
                         counters=counters, published=0, latency_p50_us=0.0,
                         latency_p99_us=0.0)


def levels(checks) -> dict[str, int]:
    return {c.name: c.level for c in checks}


STEP_NOW = SPEC.step_of(NOW)


@pytest.mark.parametrize("late, level", [(0, OK), (10, WARN), (50, ERROR)])
def test_late_rate_levels(late: int, level: int) -> None:
    prev = status(STEP_NOW, accepted=1000, late=7)
    cur = status(STEP_NOW, accepted=1100 - late, late=7 + late)  # 100 samples judged
    assert levels(session_checks(SPEC, prev, cur, {}, NOW, 2.0))["late rate"] == level


def test_silent_sensors_clock_and_missing_status() -> None:
    cur = status(STEP_NOW)
    heard = {"odom": NOW - 100_000_000, "imu": NOW - 10_000_000_000, "pose_fix": None}
    lv = levels(session_checks(SPEC, None, cur, heard, NOW, 2.0))
    assert lv["silent sensors"] == WARN and lv["clock"] == OK
    assert lv["NEES consistency"] == OK  # not available: said, never an alarm
    none_heard = dict.fromkeys(heard)
    assert levels(session_checks(SPEC, None, cur, none_heard, NOW, 2.0))["silent sensors"] == ERROR
    # the daemon's step 3 ahead of the bridge's: a clock offset of 3 steps
    assert levels(session_checks(SPEC, None, status(STEP_NOW + 3), {}, NOW, 2.0))["clock"] == WARN
    far = status(STEP_NOW + SPEC.max_delay + 1)
    assert levels(session_checks(SPEC, None, far, {}, NOW, 2.0))["clock"] == ERROR
    assert levels(session_checks(SPEC, None, None, {}, NOW, 2.0)) == {"status": ERROR}


def test_the_bridge_publishes_a_diagnostic_array_per_interval() -> None:
    rig = make_rig(specs=(unicycle_spec("s1"), unicycle_spec("s2", prefix="b/")))
    try:
        answers = [status(STEP_NOW, accepted=100), status(STEP_NOW, accepted=150, late=50)]

        def on_query(q) -> None:  # a stand-in daemon: s1 answers, s2 does not
            q.reply(keys.status_key("s1"), encode(answers[0]))

        rig.t.queryable(keys.status_key("s1"), on_query)
        rig.ros_put(rmw_key("/odom", "nav_msgs/msg/Odometry"), *_odom())
        rig.ros_put(rmw_key("/imu", IMU), imu(STAMP, 0.1), IMU)
        rig.bridge.publish_diagnostics()
        answers.pop(0)
        payload = rig.bridge.publish_diagnostics()
        key = topic_keyexpr(0, "/diagnostics", DIAGNOSTICS_TYPE, type_hash(DIAGNOSTICS_TYPE))
        published = rig.on(key)
        assert len(published) == 2 and published[-1].payload == payload
        arr = decode_diagnostic_array(payload)
        by_name = {s.name: s for s in arr.status}
        s1, s2 = by_name["pd_service: s1"], by_name["pd_service: s2"]
        assert s1.level == ERROR and "late rate" in s1.message  # 50 of 100 late
        values = {v.key: v.value for v in s1.values}
        assert values["late rate"] == "0.5000" and values["silent sensors"] == "pose"
        assert s2.level == ERROR and "no SessionStatus" in s2.message
    finally:
        rig.bridge.close()


def _odom():
    from .test_bridge import ODOM, odometry

    return odometry(STAMP, 1.0, -2.0, 0.3, 0.5, 0.1), ODOM


def scrape(collect) -> dict:
    text = generate_latest(registry_of(collect, logging.getLogger("test"))).decode()
    return {f.name: f for f in text_string_to_metric_families(text)}


def test_pd_ros2_metrics_sum_the_sessions() -> None:
    rig = make_rig(specs=(unicycle_spec("s1"), unicycle_spec("s2", prefix="b/")))
    try:
        rig.ros_put(rmw_key("/imu", IMU), imu(STAMP, 0.1), IMU)
        rig.ros_put(rmw_key("/b/imu", IMU), imu(0, 0.1), IMU)  # stamp 0: refused
        fams = scrape(lambda: bridge_metrics(rig.bridge))
        received = fams["pd_ros2_sessions_received"].samples
        assert [s.value for s in received if s.name.endswith("_total")] == [2.0]
        assert fams["pd_ros2_sessions"].samples[0].value == 2.0
        assert all(not s.labels for f in fams.values() for s in f.samples)  # no session label
        assert all(f.type != "counter" or s.name.endswith(("_total", "_created"))
                   for f in fams.values() for s in f.samples)
    finally:
        rig.bridge.close()
