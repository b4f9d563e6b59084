"""``pd-robot-sim --ros2`` on the in-memory bus: the simulated differential-drive robot
publishes its sensors as rmw_zenoh ROS 2 messages (CDR, attachment, liveliness tokens) that
decode to the simulator's samples, obeys cmd_vel Twists from the step they arrive in, and goes
through pd-link's deploy/link-ros2.toml with each topic's delay."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3 as Vector3  # noqa: E402

from pd_client import Truth  # noqa: E402
from pd_client.tools.pd_robot_sim import RobotSim, main  # noqa: E402
from pd_client.tools.ros2_robot import Ros2Options  # noqa: E402
from pd_service.link.config import load_config  # noqa: E402
from pd_service.link.relay import LinkRelay  # noqa: E402
from pd_service.ros2.attachment import decode_attachment  # noqa: E402
from pd_service.ros2.extract import decode_measurement  # noqa: E402
from pd_service.ros2.keys import parse_token, topic_keyexpr  # noqa: E402
from pd_service.ros2.messages import Twist, encode, type_hash  # noqa: E402
from pd_service.scenarios import ScenarioSim, get_scenario  # noqa: E402
from pd_service.wire import decode, keys  # noqa: E402

from ..conftest import EPOCH_NS, Collector  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
TWIST = "geometry_msgs/msg/Twist"


def twist(v: float, w: float) -> bytes:
    return encode(Twist(linear=Vector3(x=v, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=w)),
                  TWIST)


def cmd_key(domain: int = 0, ns: str = "") -> str:
    return topic_keyexpr(domain, f"{ns}/cmd_vel", TWIST, type_hash(TWIST))


def test_samples_are_ros_messages_of_the_simulated_values(bus):
    sc = get_scenario("diffdrive")
    spec = sc.spec("bot", EPOCH_NS)
    sink = Collector(bus, "robot/**")
    sim = RobotSim(bus.transport(), sc, [spec], seed=7, ros2=Ros2Options())
    ref = ScenarioSim(sc, seed=7)
    expected = []
    for k in range(25):
        sim.tick(k)
        if k:
            ref.advance(np.zeros(2))
        expected += ref.sample()
    assert sim.ros is not None
    by_key = defaultdict(list)
    for s in sink.samples:
        by_key[s.key].append(s)
    assert not [k for k in by_key if "/sensor/" in k]  # no native measurement
    truth = [decode(s.payload, Truth) for s in by_key[keys.truth_key("bot")]]
    assert [t.step for t in truth] == list(range(25))  # the truth stays native
    assert spec.ros2 is not None
    for name, binding in spec.ros2.sensors.items():
        ros_type = binding.msg_type
        key = f"robot/0/{binding.topic}/{ros_type.replace('/msg/', '::msg::dds_::')}_/" \
              f"{type_hash(ros_type)}"
        assert sim.ros.key_of(name) == key
        got = by_key[key]
        want = [d for d in expected if d.sensor == name]
        assert len(got) == len(want) > 0
        R = sc.select([name])[0].R
        gid = sim.ros.endpoints[name].gid()
        for i, (s, d) in enumerate(zip(got, want, strict=True)):
            m = decode_measurement(binding, s.payload)
            np.testing.assert_allclose(m.z, d.z, rtol=0, atol=1e-12)
            assert m.stamp_ns == spec.time_of(d.step)  # header.stamp = the sample's step
            assert m.R is not None
            np.testing.assert_allclose(m.R, R, rtol=1e-12)  # the message's covariance
            att = decode_attachment(s.attachment)
            assert att.sequence_number == i + 1 and att.gid == gid
            assert att.source_timestamp_ns > 0


def test_liveliness_tokens_announce_node_publishers_and_subscription(bus):
    sc = get_scenario("diffdrive")
    sim = RobotSim(bus.transport(), sc, [sc.spec("bot", EPOCH_NS)], seed=0,
                   ros2=Ros2Options(domain_id=3, namespace="/bot1"))
    tokens = [parse_token(t) for t in bus.transport().get_liveliness("@ros2_lv/**")]
    by_kind = defaultdict(list)
    for t in tokens:
        assert (t.domain_id, t.namespace, t.node_name) == (3, "/bot1", "robot_sim")
        by_kind[t.kind].append(t)
    assert len(by_kind["NN"]) == 1
    assert {(t.topic, t.ros_type) for t in by_kind["MP"]} == {
        ("/bot1/odom", "nav_msgs/msg/Odometry"), ("/bot1/imu", "sensor_msgs/msg/Imu"),
        ("/bot1/pose_fix", "geometry_msgs/msg/PoseWithCovarianceStamped")}
    assert [(t.topic, t.ros_type) for t in by_kind["MS"]] == [("/bot1/cmd_vel", TWIST)]
    assert len({t.entity_id for t in tokens}) == 5
    assert sim.ros is not None and sim.ros.command_key == "robot/" + cmd_key(3, "/bot1")
    assert sim.ros.key_of("imu").startswith("robot/3/bot1/imu/sensor_msgs::msg::dds_::Imu_/")
    sim.close()
    assert bus.transport().get_liveliness("@ros2_lv/**") == []


def test_cmd_vel_twist_drives_the_robot_from_the_step_it_arrives(bus):
    sc = get_scenario("diffdrive-stationary")
    spec = sc.spec("bot", EPOCH_NS)
    now = [0]  # the step the wall clock is in
    sim = RobotSim(bus.transport(), sc, [spec], seed=4, ros2=Ros2Options(),
                   clock=lambda: spec.time_of(now[0]) + 1_000)
    operator = bus.transport()
    ref = ScenarioSim(sc, seed=4)
    ref.sample()
    us = []
    for k in range(12):
        now[0] = k
        sim.tick(k)
        if k == 3:
            operator.put("robot/" + cmd_key(), twist(0.6, 0.2))  # arrives during step 3
        if k == 7:
            operator.put("robot/" + cmd_key(), b"\x00\x01\x00\x00garbage")  # refused
        if k:
            us.append(sim.last_u.copy())
    assert sim.ros is not None
    assert (sim.ros.commands_received, sim.ros.commands_invalid) == (2, 1)
    np.testing.assert_array_equal(us[:3], np.zeros((3, 2)))  # u(0..2)
    np.testing.assert_array_equal(us[3:], np.tile([0.6, 0.2], (8, 1)))  # u(3..10)
    for u in us:
        ref.advance(u)
        ref.sample()
    np.testing.assert_array_equal(sim.sim.x, ref.x)
    assert sim.sim.x[3] > 0.1  # the commanded speed took the robot's speed up
    sim.close()


def test_through_pd_link_each_topic_gets_its_delay_and_cmd_vel_the_lead(bus):
    """sim -> pd-link (deploy/link-ros2.toml, in-memory relay on a 20 ms step clock) -> the
    plain rmw_zenoh keys; a Twist on the plain cmd_vel key reaches the robot 100 ms later."""
    sc = get_scenario("diffdrive")
    spec = sc.spec("bot", EPOCH_NS)
    period_ms = spec.period_ns // 1_000_000
    now = [0]
    relay = LinkRelay(bus.transport(), load_config(ROOT / "deploy" / "link-ros2.toml"), "t",
                      clock=lambda: now[0]).attach()
    sim = RobotSim(bus.transport(), sc, [spec], seed=2, ros2=Ros2Options(),
                   clock=lambda: EPOCH_NS + now[0])
    assert sim.ros is not None and spec.ros2 is not None
    arrivals: dict[str, list[tuple[int, int]]] = defaultdict(list)  # sensor -> (step, arrival)
    sub = bus.transport()
    for name, binding in spec.ros2.sensors.items():
        plain = sim.ros.key_of(name).removeprefix("robot/")

        def on(s, name=name, binding=binding):
            m = decode_measurement(binding, s.payload)
            arrivals[name].append((spec.step_of(m.stamp_ns), now[0] // (period_ms * 1_000_000)))

        sub.subscribe(plain, on)
    operator = bus.transport()
    for k in range(60):
        now[0] = k * period_ms * 1_000_000
        relay.step()  # releases due now, before the robot's step k
        sim.tick(k)
        relay.step()  # takes in step k's samples
        if k == 10:
            operator.put(cmd_key(), twist(0.5, 0.0))  # the operator side, plain key
    delays = {name: {a - s for s, a in got} for name, got in arrivals.items()}
    assert delays == {"odom_twist": {2}, "imu": {1}, "pose": {15}}
    # the Twist sent during step 10 is released 5 steps later: it applies from step 15
    assert sim.schedule.received == 1
    assert sim.last_u.tolist() == [0.5, 0.0]
    ref = ScenarioSim(sc, seed=2)
    ref.sample()
    for k in range(1, 60):
        ref.advance([0.5, 0.0] if k - 1 >= 15 else [0.0, 0.0])
        ref.sample()
    np.testing.assert_array_equal(sim.sim.x, ref.x)
    sim.close()
    relay.close()


def test_ros2_needs_bindings_and_one_session(bus):
    paper = get_scenario("paper")
    with pytest.raises(ValueError, match="no ROS 2 bindings"):
        RobotSim(bus.transport(), paper, [paper.spec("p", EPOCH_NS)], ros2=Ros2Options())
    sc = get_scenario("diffdrive")
    with pytest.raises(ValueError, match="exactly one session"):
        RobotSim(bus.transport(), sc, [sc.spec("a", EPOCH_NS), sc.spec("b", EPOCH_NS)],
                 ros2=Ros2Options())


@pytest.mark.parametrize("argv", [["--namespace", "bot1"], ["--domain-id", "300"]])
def test_bad_ros2_flags_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--scenario", "diffdrive", "--ros2", *argv])
    assert exc.value.code == 2
    assert argv[0].removeprefix("--").split("-")[0] in capsys.readouterr().err


def test_the_ros_camera_goes_through_pd_ros2_to_frames_with_a_pinhole_view(bus):
    """``--ros2 --camera``: the spec binds the camera (placed by the pose fix), the robot
    publishes each chase-view frame as CompressedImage + CameraInfo, and pd-ros2 (on the same
    bus, no link) makes CameraFrames of them: the robot's JPEG, the chase camera's K, D and
    mount, the robot placed by the pose fix stamped nearest the image (the pose fix, 5 Hz,
    every 10th step, frames every 5th: a fix 0 or 100 ms before each frame)."""
    from pd_client.tools.camera_view import CHASE_D, CHASE_K, CHASE_MOUNT, render_chase
    from pd_client.tools.pd_robot_sim import with_ros2_camera
    from pd_service.ros2.bridge import BridgeSettings, Ros2Bridge
    from pd_service.wire.camera import CameraFrame

    sc = get_scenario("diffdrive")
    spec = with_ros2_camera(sc.spec("bot", EPOCH_NS))
    assert spec.ros2 is not None and spec.ros2.camera is not None
    assert spec.ros2.camera.pose_sensor == "pose"
    frames = Collector(bus, keys.camera_key("bot"))
    bridge = Ros2Bridge(bus.transport(), BridgeSettings(diagnostics_interval_s=0))
    bridge.attach()
    bridge.apply_spec(spec)
    sim = RobotSim(bus.transport(), sc, [spec], seed=7, camera_every=5,
                   ros2=Ros2Options(prefix=None))
    poses: dict[int, np.ndarray] = {}
    truths: dict[int, np.ndarray] = {}
    bus.transport().subscribe("0/pose_fix/**", lambda s: poses.__setitem__(
        (m := decode_measurement(spec.ros2.sensors["pose"], s.payload)).stamp_ns, m.z))
    for k in range(41):
        truths[k] = sim.tick(k)
        bridge.drain()
    c = bridge.status()["sessions"]["bot"]["counters"]
    bridge.close()
    got = [decode(s.payload, CameraFrame) for s in frames.samples]
    # a frame every 5th step, each with a pose fix at most 100 ms (5 steps) before it
    assert [f.t_ns for f in got] == [spec.time_of(k) for k in range(0, 41, 5)]
    assert c["camera_frames_received"] == c["camera_frames_forwarded"] == 9
    assert c["camera_info_applied"] == 9 and c.get("refused", 0) == 0
    for f in got:
        k = round((f.t_ns - EPOCH_NS) / spec.period_ns)
        x = truths[k]
        assert f.image() == render_chase("bot", k // 5, f.t_ns, x[0], x[1], x[2]).image()
        v = f.pinhole
        assert v is not None and v.K == CHASE_K and v.D == CHASE_D and v.mount == CHASE_MOUNT
        near = min(poses, key=lambda t: abs(t - f.t_ns))
        assert [v.body_x, v.body_y, v.body_yaw] == pytest.approx(poses[near], abs=1e-12)


def test_an_unsynchronised_ros_robot_stamps_on_its_clock_and_echoes_each_twist(bus):
    """--clock-offset-s with --ros2: header.stamp on the robot's clock; --apply-on-arrival
    echoes each Twist (its attachment's sequence number, its arrival on the robot's clock),
    not the native Command that reaches the robot by another way."""
    from pd_client.tools.robot_clock import RobotClock
    from pd_service.ros2.attachment import Attachment, encode_attachment
    from pd_service.wire import Command, CommandEcho
    from pd_service.wire import encode as wire_encode

    sc = get_scenario("diffdrive")
    spec = sc.spec("bot", EPOCH_NS)
    now = [spec.time_of(0)]
    robot_clock = RobotClock(10.0, 0.0, base=lambda: now[0], t0_ns=EPOCH_NS)
    sink = Collector(bus, "robot/**")
    echoes = Collector(bus, keys.robot_echo_key("bot"))
    sim = RobotSim(bus.transport(), sc, [spec], seed=7, ros2=Ros2Options(),
                   clock=lambda: now[0], robot_clock=robot_clock, apply_on_arrival=True)
    operator = bus.transport()
    twists = operator.publisher("robot/" + cmd_key())
    for k in range(6):
        now[0] = spec.time_of(k) + 3_000
        sim.tick(k)
        if k == 2:
            twists.put(twist(0.5, 0.1), attachment=encode_attachment(
                Attachment(sequence_number=41, source_timestamp_ns=1, gid=bytes(16))))
        if k == 4:  # the bridge's Command, by another way: not what the robot applied
            operator.put(keys.robot_command_key("bot"),
                         wire_encode(Command(session="bot", seq=41, step=2,
                                             u=np.array([0.5, 0.1]))))
    assert spec.ros2 is not None
    stamps = []
    for name, binding in spec.ros2.sensors.items():
        for s in sink.samples:
            if s.key == sim.ros.key_of(name):
                stamps.append(decode_measurement(binding, s.payload).stamp_ns)
    assert stamps and {t - 10 * 1_000_000_000 for t in stamps} <= {spec.time_of(k)
                                                                  for k in range(6)}
    (echo,) = [decode(p, CommandEcho) for p in echoes.payloads()]
    assert echo.seq == 41 and echo.applied_ns == spec.time_of(2) + 3_000 + 10 * 1_000_000_000
    np.testing.assert_array_equal(sim.last_u, [0.5, 0.1])
    sim.close()
