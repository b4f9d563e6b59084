"""The pd-ros2 bridge end to end on the in-memory bus (no network): specs in, CDR sensors ->
native Measurements, Twist -> Command, native Prediction -> CDR Odometry / Pose / TF with the
rmw_zenoh attachment, refusals with ErrorReports and counters, liveliness tokens, status."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest

from pd_service.errors import ConfigError
from pd_service.ros2.__main__ import build_parser, main, settings_from_args
from pd_service.ros2.attachment import Attachment, decode_attachment, encode_attachment
from pd_service.ros2.bridge import REFUSAL_REASONS, BridgeSettings, Ros2Bridge
from pd_service.ros2.extract import yaw_of
from pd_service.ros2.keys import NodeIdentity, TopicEndpoint, bridge_keyexpr, dds_type_name, topic_keyexpr
from pd_service.ros2.messages import RosMessage, TFMessage, decode, encode, type_hash
from pd_service.transport import InMemoryBus, InMemoryTransport, Sample
from pd_service.wire import (
    Command,
    ErrorReport,
    Measurement,
    Prediction,
    SessionSpec,
    keys,
)
from pd_service.wire import decode as wire_decode
from pd_service.wire import encode as wire_encode
from tests.ros2.specs import (
    IMU,
    ODOM,
    POSE,
    TF,
    imu,
    odometry,
    pose_fix,
    twist,
    twist_stamped,
    unicycle_spec,
)

NOW = 1_700_000_001_000_000_000
STAMP = NOW - 30_000_000
GID = bytes(range(16))


@dataclass
class Clock:
    t: int = NOW

    def __call__(self) -> int:
        return self.t


@dataclass
class Rig:
    """The bus, the bridge (no worker thread: ``pump`` drains it), and a test transport that
    records everything put on ``pd/**`` and on the ROS keys."""

    bus: InMemoryBus
    bridge: Ros2Bridge
    t: InMemoryTransport
    clock: Clock
    seen: list[Sample] = field(default_factory=list)

    def pump(self) -> None:
        self.bridge.drain()

    def put_spec(self, spec: SessionSpec) -> None:
        self.t.put(keys.config_key(spec.session), wire_encode(spec))
        self.pump()

    def ros_put(self, key: str, msg: RosMessage, msg_type: str, attachment: bytes | None = None,
                payload: bytes | None = None) -> None:
        data = encode(msg, msg_type) if payload is None else payload
        self.t.publisher(key).put(data, attachment=attachment)
        self.pump()

    def on(self, key: str) -> list[Sample]:
        return [s for s in self.seen if s.key == key and s.kind == "put"]

    def measurements(self, session: str, sensor: str) -> list[Measurement]:
        return [wire_decode(s.payload, Measurement) for s in self.on(keys.sensor_key(session, sensor))]

    def errors(self, session: str) -> list[ErrorReport]:
        return [wire_decode(s.payload, ErrorReport) for s in self.on(keys.error_key(session))]

    def counters(self, session: str) -> dict[str, int]:
        return dict(self.bridge.sessions[session].counters)


def rmw_key(topic: str, msg_type: str, domain: int = 0) -> str:
    return topic_keyexpr(domain, topic, msg_type, type_hash(msg_type))


def make_rig(settings: BridgeSettings | None = None, specs: tuple[SessionSpec, ...] = ()) -> Rig:
    bus = InMemoryBus()
    t = bus.transport()
    clock = Clock()
    seen: list[Sample] = []
    t.subscribe("**", seen.append)
    bridge = Ros2Bridge(bus.transport(), settings, now_ns=clock)
    bridge.attach()
    rig = Rig(bus, bridge, t, clock, seen)
    for spec in specs:
        rig.put_spec(spec)
    return rig


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = make_rig(specs=(unicycle_spec("s1"), unicycle_spec("s2", prefix="b/")))
    yield r
    r.bridge.close()


# --------------------------------------------------------------------------------- inputs ---


def test_odometry_becomes_a_measurement_with_r_stamp_and_attachment_seq(rig: Rig) -> None:
    att = encode_attachment(Attachment(41, NOW, GID))
    rig.ros_put(rmw_key("/odom", ODOM), odometry(STAMP, 1.0, -2.0, 0.3, 0.5, 0.1), ODOM, att)
    (m,) = rig.measurements("s1", "odom")
    np.testing.assert_allclose(m.z, [1.0, -2.0, 0.3, 0.5, 0.1], atol=1e-15)
    assert m.t_ns == STAMP and m.step is None and m.seq == 41 and m.sensor == "odom"
    assert m.R is not None
    np.testing.assert_allclose(np.diag(m.R), [1e-4, 1e-4, 1e-4, 4e-4, 4e-4])
    assert rig.counters("s1")["forwarded"] == 1 and not rig.measurements("s2", "odom")


def test_imu_and_pose_fix_become_measurements(rig: Rig) -> None:
    rig.ros_put(rmw_key("/imu", IMU), imu(STAMP, -0.25, var=2e-4), IMU)
    rig.ros_put(rmw_key("/pose_fix", POSE), pose_fix(STAMP + 1, 3.0, 4.0, -1.0), POSE)
    (mi,) = rig.measurements("s1", "imu")
    assert mi.z.tolist() == [-0.25] and mi.R is not None and mi.R.tolist() == [[2e-4]]
    assert mi.t_ns == STAMP and mi.seq == 1  # no attachment: the bridge's own count
    (mp,) = rig.measurements("s1", "pose")
    np.testing.assert_allclose(mp.z, [3.0, 4.0, -1.0], atol=1e-15)
    assert mp.R is None  # all-zero covariance = unknown: the spec's R applies
    assert mp.t_ns == STAMP + 1
    cov = np.diag([0.01, 0.02, 1.0, 1.0, 1.0, 0.003])
    rig.ros_put(rmw_key("/pose_fix", POSE), pose_fix(STAMP + 2, 3.0, 4.0, -1.0, cov), POSE)
    mp2 = rig.measurements("s1", "pose")[1]
    assert mp2.seq == 2 and mp2.R is not None
    np.testing.assert_allclose(mp2.R, np.diag([0.01, 0.02, 0.003]))


def test_namespace_and_domain_resolve_relative_topics() -> None:
    r = make_rig(BridgeSettings(domain_id=7, namespace="/robot1"), (unicycle_spec("s1"),))
    r.ros_put(rmw_key("/robot1/imu", IMU, domain=7), imu(STAMP, 0.5), IMU)
    r.ros_put(rmw_key("/imu", IMU, domain=7), imu(STAMP, 0.6), IMU)  # not the bound topic
    r.ros_put(rmw_key("/robot1/imu", IMU, domain=0), imu(STAMP, 0.7), IMU)  # other domain
    assert [m.z[0] for m in r.measurements("s1", "imu")] == [0.5]
    # the absolute pose topic is not resolved under the namespace
    r.ros_put(rmw_key("/pose_fix", POSE, domain=7), pose_fix(STAMP, 1.0, 1.0, 0.0), POSE)
    assert len(r.measurements("s1", "pose")) == 1


def test_bridge_ros2dds_key_format() -> None:
    r = make_rig(BridgeSettings(key_format="bridge_ros2dds", namespace="/bot1"),
                 (unicycle_spec("s1"),))
    assert bridge_keyexpr("/bot1/odom") == "bot1/odom"
    r.ros_put("bot1/odom", odometry(STAMP, 1.0, 2.0, 0.0, 0.0, 0.0), ODOM)
    assert len(r.measurements("s1", "odom")) == 1
    assert r.bus.tokens == []  # no rmw_zenoh graph tokens in this format
    r.t.put(keys.prediction_key("s1"), wire_encode(prediction("s1", np.zeros(5), 1)))
    r.pump()
    (odom,) = r.on("bot1/predicted/odom")
    assert odom.attachment is None
    assert isinstance(decode(odom.payload, ODOM), type(odometry(1, 0, 0, 0, 0, 0)))


def test_twist_applies_at_arrival_and_twist_stamped_at_its_stamp() -> None:
    r = make_rig(specs=(unicycle_spec("s1"),
                        unicycle_spec("s2", prefix="b/", cmd_type="geometry_msgs/msg/TwistStamped")))
    r.clock.t = NOW + 123
    r.ros_put(rmw_key("/cmd_vel", "geometry_msgs/msg/Twist"), twist(0.4, -0.2),
              "geometry_msgs/msg/Twist", encode_attachment(Attachment(9, NOW, GID)))
    r.ros_put(rmw_key("/b/cmd_vel", "geometry_msgs/msg/TwistStamped"), twist_stamped(STAMP, 0.3, 0.1),
              "geometry_msgs/msg/TwistStamped")
    (c1,) = [wire_decode(s.payload, Command) for s in r.on(keys.command_key("s1"))]
    assert c1.u.tolist() == [0.4, -0.2] and c1.issued_ns == NOW + 123 and c1.step is None
    assert c1.seq == 9
    (c2,) = [wire_decode(s.payload, Command) for s in r.on(keys.command_key("s2"))]
    assert c2.u.tolist() == [0.3, 0.1] and c2.issued_ns == STAMP and c2.seq == 1
    assert r.counters("s1")["commands_forwarded"] == 1 == r.counters("s2")["commands_forwarded"]


def test_twist_is_stamped_at_receipt_not_when_the_worker_gets_to_it() -> None:
    r = make_rig(specs=(unicycle_spec("s1"),))
    key, tw = rmw_key("/cmd_vel", "geometry_msgs/msg/Twist"), "geometry_msgs/msg/Twist"
    for i, lag in enumerate((2_000_000, 140_000_000)):  # the worker lags 2 ms, then 140 ms
        r.clock.t = NOW + i * 100_000_000
        r.t.publisher(key).put(encode(twist(0.1 * i, 0.0), tw))  # the callback: receipt
        r.clock.t += lag
        r.pump()
    issued = [wire_decode(s.payload, Command).issued_ns for s in r.on(keys.command_key("s1"))]
    assert issued == [NOW, NOW + 100_000_000]


def test_the_robot_role_echoes_twists_on_arrival_and_answers_probes() -> None:
    from pd_service.wire import ClockProbe, ClockProbeReply, CommandEcho

    r = make_rig(BridgeSettings(role="robot"), specs=(unicycle_spec("s1"),))
    key, tw = rmw_key("/cmd_vel", "geometry_msgs/msg/Twist"), "geometry_msgs/msg/Twist"
    r.clock.t = NOW + 5
    r.t.publisher(key).put(encode(twist(0.4, 0.0), tw),
                           attachment=encode_attachment(Attachment(9, NOW, GID)))
    r.clock.t = NOW + 2_000_000  # the worker gets to it later: the echo keeps the receipt
    r.pump()
    (echo,) = [wire_decode(x.payload, CommandEcho) for x in r.on(keys.echo_key("s1"))]
    assert (echo.seq, echo.applied_ns, echo.sent_ns) == (9, NOW + 5, NOW + 2_000_000)
    assert not r.on(keys.command_key("s1"))  # the operator-side bridge sends the Command
    (rep,) = r.t.get(keys.robot_clock_key("s1"),
                     payload=wire_encode(ClockProbe(session="s1", probe=2, t1_ns=7)))
    got = wire_decode(rep.payload, ClockProbeReply)
    assert (got.probe, got.t1_ns, got.t2_ns) == (2, 7, NOW + 2_000_000)
    (bad,) = r.t.get(keys.robot_clock_key("s1"), payload=b"\x01")
    assert not bad.ok
    c = r.counters("s1")
    assert (c["echoes_sent"], c["probes_answered"], c["probes_invalid"]) == (1, 1, 1)
    r.bridge.close()


# -------------------------------------------------------------------------------- outputs ---


def prediction(session: str, x: np.ndarray, seq: int, step: int = 500) -> Prediction:
    spec = unicycle_spec(session)
    P = np.diag([0.04, 0.09, 0.01, 0.0025, 0.0016])
    P[0, 1] = P[1, 0] = 0.01
    return Prediction(session=session, seq=seq, step=step, t_ns=spec.time_of(step), x=x, P=P,
                      newest_step=step - 5, made_ns=NOW)


def test_prediction_becomes_odometry_pose_and_tf_with_attachment(rig: Rig) -> None:
    x = np.array([1.5, -0.5, 2.9, 0.7, -0.3])
    pred = prediction("s1", x, 7)
    rig.clock.t = NOW + 55
    rig.t.put(keys.prediction_key("s1"), wire_encode(pred))
    rig.pump()
    node = rig.bridge.node
    assert node is not None
    outs = {"odom": ("/predicted/odom", ODOM), "pose": ("/predicted/pose", POSE), "tf": ("/tf", TF)}
    decoded: dict[str, RosMessage] = {}
    for what, (topic, msg_type) in outs.items():
        (s,) = rig.on(rmw_key(topic, msg_type))
        decoded[what] = decode(s.payload, msg_type)
        assert s.attachment is not None
        att = decode_attachment(s.attachment)
        assert att.sequence_number == 1 and att.source_timestamp_ns == NOW + 55
        (ep,) = [e for e in endpoints(rig.bridge) if e.topic == topic and e.node.name == "pd_service"
                 and e.kind == "MP" and e.ros_type == msg_type and "s1" in session_of(rig, e)]
        assert att.gid == ep.gid()
    odom, pose, tf = decoded["odom"], decoded["pose"], decoded["tf"]
    assert odom.header.stamp.sec * 10**9 + odom.header.stamp.nanosec == pred.t_ns
    assert odom.header.frame_id == "odom" and odom.child_frame_id == "base_link_predicted"
    p = odom.pose.pose
    assert (p.position.x, p.position.y) == (1.5, -0.5)
    assert abs(yaw_of(p.orientation) - 2.9) < 1e-12
    assert (odom.twist.twist.linear.x, odom.twist.twist.angular.z) == (0.7, -0.3)
    cov = np.asarray(odom.pose.covariance).reshape(6, 6)
    assert (cov[0, 0], cov[1, 1], cov[0, 1], cov[5, 5]) == (0.04, 0.09, 0.01, 0.01)
    assert pose.pose.pose.position.x == 1.5
    assert isinstance(tf, TFMessage) and tf.transforms[0].transform.translation.y == -0.5
    assert tf.transforms[0].child_frame_id == "base_link_predicted"
    # the second prediction: sequence numbers count per publisher
    rig.t.put(keys.prediction_key("s1"), wire_encode(prediction("s1", x, 8, step=501)))
    rig.pump()
    atts = [decode_attachment(s.attachment or b"") for s in rig.on(rmw_key("/predicted/odom", ODOM))]
    assert [a.sequence_number for a in atts] == [1, 2]
    c = rig.counters("s1")
    assert c["predictions_republished"] == 2 and c["outputs_published"] == 6
    assert not rig.on(rmw_key("/b/predicted/odom", ODOM))


def test_an_older_owners_prediction_is_not_republished(rig: Rig) -> None:
    """Two owners of one session (a partition between instances): the bridge republishes
    the newest term's predictions only and counts the others."""
    x = np.zeros(5)
    for seq, term in ((1, 5), (2, 9), (3, 5), (4, 9)):
        pred = prediction("s1", x, seq).model_copy(update={"term": term})
        rig.t.put(keys.prediction_key("s1"), wire_encode(pred))
    rig.pump()
    c = rig.counters("s1")
    assert c["predictions_republished"] == 3 and c["predictions_stale_term"] == 1
    assert len(rig.on(rmw_key("/predicted/odom", ODOM))) == 3


def test_keyed_attachment_layout_on_outputs() -> None:
    r = make_rig(BridgeSettings(attachment_layout="keyed"), (unicycle_spec("s1"),))
    r.t.put(keys.prediction_key("s1"), wire_encode(prediction("s1", np.zeros(5), 1)))
    r.pump()
    (s,) = r.on(rmw_key("/predicted/odom", ODOM))
    assert s.attachment is not None and len(s.attachment) == 77
    assert decode_attachment(s.attachment).sequence_number == 1


def test_a_prediction_that_does_not_fit_the_layout_is_reported(rig: Rig) -> None:
    bad = Prediction(session="s1", seq=3, step=10, t_ns=NOW, x=np.zeros(2), P=np.eye(2),
                     made_ns=NOW)
    rig.t.put(keys.prediction_key("s1"), wire_encode(bad))
    rig.t.put(keys.prediction_key("s1"), b"\x00not msgpack")
    rig.pump()
    assert rig.counters("s1")["output_errors"] == 1
    assert rig.counters("s1")["predictions_invalid"] == 1
    (err,) = rig.errors("s1")
    assert err.key == keys.prediction_key("s1") and err.seq == 3 and "layout" in err.reason
    assert not rig.on(rmw_key("/predicted/odom", ODOM))


# ------------------------------------------------------------------------------ refusals ---


def _cov_not_psd() -> np.ndarray:
    c = np.diag([0.01, 0.01, 1.0, 1.0, 1.0, 0.01])
    c[0, 1] = c[1, 0] = 0.5  # |corr| > 1
    return c


def _bad_inputs() -> dict[str, tuple[str, bytes, bytes | None, str]]:
    """reason -> (key, payload, attachment, text the ErrorReport's reason must contain)."""
    good = encode(pose_fix(STAMP, 1.0, 2.0, 0.0), POSE)
    key = rmw_key("/pose_fix", POSE)
    wrong_hash = key.rsplit("/", 1)[0] + "/RIHS01_" + "0" * 64
    wrong_type = key.replace(dds_type_name(POSE), dds_type_name("geometry_msgs/msg/PoseStamped"))
    return {
        "cdr": (key, good[:-9], None, "not valid CDR"),
        "type_hash": (wrong_hash, good, None, "type hash"),
        "type": (wrong_type, good, None, "PoseStamped"),
        "attachment": (key, good, b"\x01\x02\x03", "attachment"),
        "stamp": (key, encode(pose_fix(0, 1.0, 2.0, 0.0), POSE), None, "header.stamp is 0"),
        "not_finite": (key, encode(pose_fix(STAMP, math.nan, 2.0, 0.0), POSE), None, "x not finite"),
        "covariance": (key, encode(pose_fix(STAMP, 1.0, 2.0, 0.0, _cov_not_psd()), POSE), None,
                       "positive semi-definite"),
        "frame": (key, encode(pose_fix(STAMP, 1.0, 2.0, 0.0, frame="odom"), POSE), None,
                  "frame_id 'odom'"),
    }


@pytest.mark.parametrize("reason", list(_bad_inputs()))
def test_bad_input_is_refused_and_other_sessions_keep_flowing(rig: Rig, reason: str) -> None:
    key, payload, attachment, text = _bad_inputs()[reason]
    rig.t.publisher(key).put(payload, attachment=attachment)
    # the other session's traffic, interleaved, still goes through
    rig.t.publisher(rmw_key("/b/odom", ODOM)).put(encode(odometry(STAMP, 1, 2, 0, 0, 0), ODOM))
    rig.pump()
    c = rig.counters("s1")
    assert c["refused"] == 1 and c[f"refused_{reason}"] == 1 and c.get("forwarded", 0) == 0
    (err,) = rig.errors("s1")
    assert err.key == key and "/pose_fix" in err.reason and text in err.reason
    assert err.reason.startswith(f"ros2 {reason}:") and err.t_ns == NOW
    assert not rig.measurements("s1", "pose")
    assert len(rig.measurements("s2", "odom")) == 1 and rig.counters("s2").get("refused", 0) == 0
    assert not rig.errors("s2")
    # and the good message on the same topic still goes through afterwards
    rig.ros_put(rmw_key("/pose_fix", POSE), pose_fix(STAMP, 1.0, 2.0, 0.0), POSE)
    assert len(rig.measurements("s1", "pose")) == 1


def test_every_refusal_reason_is_exercised() -> None:
    from tests.ros2.test_bridge_camera import _bad_camera_inputs

    camera = {case.strip() for case in _bad_camera_inputs()}  # tests/ros2/test_bridge_camera.py
    assert set(_bad_inputs()) | camera | {"invalid"} == set(REFUSAL_REASONS)


def test_invalid_commands_are_refused(rig: Rig) -> None:
    key = rmw_key("/cmd_vel", "geometry_msgs/msg/Twist")
    rig.ros_put(key, twist(math.inf, 0.0), "geometry_msgs/msg/Twist")
    rig.ros_put(key, twist(0.0, 0.0), "geometry_msgs/msg/Twist", payload=b"\x00\x01\x00\x00\x01")
    c = rig.counters("s1")
    assert c["refused_not_finite"] == 1 and c["refused_cdr"] == 1
    assert c["commands_received"] == 2 and c.get("commands_forwarded", 0) == 0
    assert len(rig.errors("s1")) == 2 and not rig.on(keys.command_key("s1"))


def test_error_reports_are_rate_limited_not_the_counters() -> None:
    r = make_rig(BridgeSettings(error_rate=1.0, error_burst=3), (unicycle_spec("s1"),))
    key = rmw_key("/imu", IMU)
    for _ in range(10):
        r.ros_put(key, imu(0, 0.1), IMU)
    c = r.counters("s1")
    assert c["refused_stamp"] == 10 and c["error_reports"] == 3
    assert c["error_reports_suppressed"] == 7 and len(r.errors("s1")) == 3
    r.clock.t += 2_000_000_000  # two more tokens
    for _ in range(3):
        r.ros_put(key, imu(0, 0.1), IMU)
    assert len(r.errors("s1")) == 5


def test_full_inbox_drops_the_oldest_and_counts() -> None:
    r = make_rig(BridgeSettings(inbox_size=4), (unicycle_spec("s1"),))
    pub = r.t.publisher(rmw_key("/imu", IMU))
    for i in range(10):
        pub.put(encode(imu(STAMP + i, float(i)), IMU))
    r.pump()
    assert r.bridge.counters["inbox_dropped"] == 6
    assert [m.z[0] for m in r.measurements("s1", "imu")] == [6.0, 7.0, 8.0, 9.0]


# ------------------------------------------------------------------------- specs and graph ---


def endpoints(bridge: Ros2Bridge) -> list[TopicEndpoint]:
    out = []
    for sess in bridge.sessions.values():
        out += [i.endpoint for i in sess.inputs if i.endpoint is not None]
        out += [o.endpoint for o in sess.outputs if o.endpoint is not None]
    return out


def session_of(rig: Rig, ep: TopicEndpoint) -> str:
    for name, sess in rig.bridge.sessions.items():
        if any(o.endpoint is ep for o in sess.outputs) or any(i.endpoint is ep for i in sess.inputs):
            return name
    return ""


def test_liveliness_tokens_name_the_node_and_every_endpoint() -> None:
    r = make_rig(specs=(unicycle_spec("s1"),))
    zid = r.bridge.t.session_id()
    assert zid == "a2"  # the bridge's transport is the bus's second
    h = type_hash(IMU)
    assert r.bus.tokens[0] == f"@ros2_lv/0/{zid}/0/0/NN/%/%/pd_service"
    assert (f"@ros2_lv/0/{zid}/0/2/MS/%/%/pd_service/%imu/sensor_msgs::msg::dds_::Imu_/{h}/"
            "2::,:,:,:,,") in r.bus.tokens
    ho = type_hash(ODOM)
    assert (f"@ros2_lv/0/{zid}/0/5/MP/%/%/pd_service/%predicted%odom/"
            f"nav_msgs::msg::dds_::Odometry_/{ho}/::,:,:,:,,") in r.bus.tokens
    node = NodeIdentity(0, zid, 0, "pd_service")
    kinds = sorted((e.kind, e.topic) for e in endpoints(r.bridge))
    assert kinds == [("MP", "/predicted/odom"), ("MP", "/predicted/pose"), ("MP", "/tf"),
                     ("MS", "/cmd_vel"), ("MS", "/imu"), ("MS", "/odom"), ("MS", "/pose_fix")]
    assert sorted(r.bus.tokens) == sorted([node.token()] + [e.token() for e in endpoints(r.bridge)])
    assert r.bridge.tokens() == r.bus.tokens
    r.bridge.close()
    assert r.bus.tokens == []


def test_config_delete_and_spec_without_bindings_undeclare(rig: Rig) -> None:
    n_tokens = len(rig.bus.tokens)
    assert n_tokens == 1 + 2 * 7
    rig.t.delete(keys.config_key("s1"))
    rig.pump()
    assert "s1" not in rig.bridge.sessions and len(rig.bus.tokens) == 1 + 7
    rig.ros_put(rmw_key("/imu", IMU), imu(STAMP, 0.1), IMU)
    assert not rig.measurements("s1", "imu")
    rig.put_spec(unicycle_spec("s2", prefix="b/").model_copy(update={"ros2": None}))
    assert rig.bridge.sessions == {} and len(rig.bus.tokens) == 1


def test_replacing_a_spec_redeclares_only_when_the_bindings_change(rig: Rig) -> None:
    before = list(rig.bus.tokens)
    rig.put_spec(unicycle_spec("s1", lead=9))  # same bindings: nothing redeclared
    assert rig.bus.tokens == before and rig.bridge.sessions["s1"].spec.lead == 9
    rig.put_spec(unicycle_spec("s1", prefix="new/"))
    assert rig.bus.tokens != before and len(rig.bus.tokens) == len(before)
    rig.ros_put(rmw_key("/imu", IMU), imu(STAMP, 0.1), IMU)
    rig.ros_put(rmw_key("/new/imu", IMU), imu(STAMP, 0.2), IMU)
    assert [m.z[0] for m in rig.measurements("s1", "imu")] == [0.2]


def test_specs_are_learnt_from_the_daemon_at_start_and_filtered() -> None:
    bus = InMemoryBus()
    daemon = bus.transport()
    specs = {s.session: s for s in (unicycle_spec("s1"), unicycle_spec("s2", prefix="b/"),
                                    unicycle_spec("s3", prefix="c/"))}
    specs["s3"] = specs["s3"].model_copy(update={"ros2": None})

    def answer(q) -> None:  # type: ignore[no-untyped-def]
        for name, spec in specs.items():
            q.reply(keys.config_key(name), wire_encode(spec))
        q.reply(keys.config_key("junk"), b"junk")

    daemon.queryable(keys.ALL_CONFIGS, answer)
    bridge = Ros2Bridge(bus.transport(), now_ns=Clock())
    bridge.attach()
    assert sorted(bridge.sessions) == ["s1", "s2"] and bridge.counters["configs_invalid"] == 1
    only = Ros2Bridge(bus.transport(), BridgeSettings(sessions=frozenset({"s2"}), node_name="b2"))
    only.attach()
    assert sorted(only.sessions) == ["s2"]
    bridge.close()
    only.close()


def test_status_queryable_answers_json_counters(rig: Rig) -> None:
    rig.ros_put(rmw_key("/imu", IMU), imu(STAMP, 0.1), IMU)
    rig.ros_put(rmw_key("/imu", IMU), imu(0, 0.1), IMU)
    (reply,) = rig.t.get(keys.ros2_status_key("default"))
    assert reply.ok and reply.key == "pd/@ros2/default/status"
    doc = json.loads(reply.payload)
    s1 = doc["sessions"]["s1"]["counters"]
    assert s1["received"] == 2 and s1["forwarded"] == 1 and s1["refused_stamp"] == 1
    assert doc["sessions"]["s1"]["inputs"]["imu"]["topic"] == "/imu"
    assert doc["zid"] == rig.bridge.t.session_id() and doc["counters"]["configs_applied"] == 2


def test_worker_thread_processes_the_inbox() -> None:
    bus = InMemoryBus()
    t = bus.transport()
    got: list[Sample] = []
    t.subscribe(keys.sensor_key("s1", "imu"), got.append)
    with Ros2Bridge(bus.transport()) as bridge:
        bridge.start()
        t.put(keys.config_key("s1"), wire_encode(unicycle_spec("s1")))
        import time

        deadline = time.monotonic() + 10
        while "s1" not in bridge.sessions and time.monotonic() < deadline:
            time.sleep(0.005)
        t.publisher(rmw_key("/imu", IMU)).put(encode(imu(STAMP, 0.1), IMU))
        while not got and time.monotonic() < deadline:
            time.sleep(0.005)
    assert len(got) == 1


# ------------------------------------------------------------------------------------ CLI ---


def test_cli_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "12")
    s = settings_from_args(build_parser().parse_args(["--session", "a", "--session", "b"]))
    assert s.domain_id == 12 and s.sessions == frozenset({"a", "b"}) and s.namespace == "/"
    s = settings_from_args(build_parser().parse_args(
        ["--domain-id", "3", "--namespace", "/r1", "--key-format", "bridge_ros2dds",
         "--node-name", "pd2", "--instance", "x"]))
    assert (s.domain_id, s.namespace, s.key_format, s.node_name, s.instance) == \
        (3, "/r1", "bridge_ros2dds", "pd2", "x")
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID"):
        settings_from_args(build_parser().parse_args([]))


@pytest.mark.parametrize("argv", [["--namespace", "robot"], ["--domain-id", "300"],
                                  ["--node-name", "a-b"], ["--session", "Bad!"]])
def test_cli_refuses_bad_settings(argv: list[str]) -> None:
    assert main([*argv, "--log-level", "ERROR"]) == 2


def test_settings_are_checked() -> None:
    with pytest.raises(ConfigError):
        BridgeSettings(error_rate=0.0)


def test_the_daemons_path_becomes_a_nav_msgs_path(tmp_path) -> None:
    """The daemon core (in-process, same bus) serves a unicycle session whose spec asks for
    the path; the bridge publishes each PredictedPath as nav_msgs/Path on predicted/path:
    one pose per point, at its step's time, x, y, yaw as the daemon's (decoded with the
    rosbags typestore)."""
    from pd_service.wire.path import PredictedPath
    from tests.service.helpers import Clock as CoreClock
    from tests.service.test_core import make_core

    spec = unicycle_spec("s1")
    spec = SessionSpec.model_validate({**spec.model_dump(), "path": {"indices": [0, 1, 2]}})
    r = make_rig(specs=(spec,))
    paths: list[PredictedPath] = []
    r.t.subscribe(keys.path_key("s1"), lambda s: paths.append(wire_decode(s.payload, PredictedPath)))
    clock = CoreClock(spec.epoch_ns - 1)
    core = make_core(r.bus, clock, tmp_path)
    try:
        r.t.put(keys.config_key("s1"), wire_encode(spec))
        core.run_once()
        for k in range(6):
            r.t.put(keys.command_key("s1"), wire_encode(Command(
                session="s1", seq=k, issued_ns=spec.time_of(k), u=np.array([0.5, 0.2]))))
            clock.t = spec.time_of(k) + spec.period_ns // 2
            core.run_once()
        r.pump()
    finally:
        core.close()
    assert len(paths) >= 5
    got = [decode(s.payload, "nav_msgs/msg/Path") for s in r.on(rmw_key("/predicted/path",
                                                                          "nav_msgs/msg/Path"))]
    assert len(got) == len(paths)
    for msg, path in zip(got, paths, strict=True):
        assert msg.header.frame_id == "odom" and len(msg.poses) == len(path.steps)
        for i, ps in enumerate(msg.poses):
            assert ps.header.stamp.sec * 10**9 + ps.header.stamp.nanosec == path.t_ns(i)
            assert (ps.pose.position.x, ps.pose.position.y) == (path.X[i, 0], path.X[i, 1])
            assert abs(yaw_of(ps.pose.orientation) - path.X[i, 2]) < 1e-12
    assert r.counters("s1")["paths_republished"] == len(paths)
    # moved: the path follows the commands
    assert paths[-1].X[-1, 0] > 0.0


def test_a_path_without_the_layouts_x_y_is_refused_at_validation() -> None:
    spec = unicycle_spec("s1")
    with pytest.raises(Exception, match="path.indices"):
        SessionSpec.model_validate({**spec.model_dump(), "path": {"indices": [0, 2]}})
    off = spec.model_dump()
    off["ros2"]["outputs"]["path_topic"] = None
    assert SessionSpec.model_validate({**off, "path": {"indices": [0, 2]}}).path is not None
