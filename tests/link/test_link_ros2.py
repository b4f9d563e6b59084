"""deploy/link-ros2.toml: the ROS 2 robot's rmw_zenoh keys (under ``robot/``) are mapped to the
plain keys and back for cmd_vel, without loops, and each topic gets its rule's delay and loss,
on the in-memory relay with an injected clock (exact times)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pd_service.link.config import load_config
from pd_service.link.relay import LinkRelay
from pd_service.transport import InMemoryBus, Sample
from pd_service.transport.keyexpr import intersects
from pd_service.wire import keys

ros2_keys = pytest.importorskip("pd_service.ros2.keys")
messages = pytest.importorskip("pd_service.ros2.messages")

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "deploy" / "link-ros2.toml"
MS = 1_000_000
#: topic -> (message type, direction, delay ms) as the file's comments state them
TOPICS = {
    "odom": ("nav_msgs/msg/Odometry", "downlink", 40),
    "imu": ("sensor_msgs/msg/Imu", "downlink", 20),
    "pose_fix": ("geometry_msgs/msg/PoseWithCovarianceStamped", "downlink", 300),
    "cmd_vel": ("geometry_msgs/msg/Twist", "uplink", 100),
}


def plain_key(topic: str, domain: int = 0) -> str:
    ros_type = TOPICS[topic][0]
    return ros2_keys.topic_keyexpr(domain, f"/{topic}", ros_type, messages.type_hash(ros_type))


def test_topics_map_between_robot_prefix_and_plain_keys_without_loops():
    cfg = load_config(CONFIG)
    subscriptions = [m.subscribe for m in cfg.mappings]
    for topic, (_, direction, _) in TOPICS.items():
        for domain in (0, 7):
            plain = plain_key(topic, domain)
            robot = f"robot/{plain}"
            src, dst = (robot, plain) if direction == "downlink" else (plain, robot)
            [mapping] = [m for m in cfg.mappings if intersects(m.subscribe, src)]
            assert mapping.direction == direction
            assert mapping.map_key(src) == dst
            assert not any(intersects(s, dst) for s in subscriptions), dst  # no loop
    # the native keys keep their default mapping
    native = {m.map_key(k) for m in cfg.mappings for k in
              (keys.robot_sensor_key("s", "x"), keys.command_key("s"))
              if intersects(m.subscribe, k)}
    assert native == {keys.sensor_key("s", "x"), keys.robot_command_key("s")}


class Clock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def test_each_topic_gets_its_delay_and_keeps_payload_and_attachment():
    bus = InMemoryBus()
    clock = Clock()
    relay = LinkRelay(bus.transport(), load_config(CONFIG), "ros2", clock=clock).attach()
    client = bus.transport()
    out: list[tuple[int, Sample]] = []
    for topic in TOPICS:
        for ke in (plain_key(topic), f"robot/{plain_key(topic)}"):
            client.subscribe(ke, lambda s: out.append((clock.now, s)))
    sent = {}
    for i, (topic, (_, direction, _)) in enumerate(TOPICS.items()):
        src = f"robot/{plain_key(topic)}" if direction == "downlink" else plain_key(topic)
        sent[topic] = (f"cdr-{i}".encode(), bytes([i]) * 33)
        client.publisher(src).put(sent[topic][0], attachment=sent[topic][1])
    out.clear()  # the client's own puts
    due = sorted((d, t) for t, (_, _, d) in TOPICS.items())
    for t_ms in range(0, 301):
        clock.now = t_ms * MS
        relay.step()
    got = {s.key: (t // MS, s.payload, s.attachment) for t, s in out}
    for delay, topic in due:
        direction = TOPICS[topic][1]
        dst = plain_key(topic) if direction == "downlink" else f"robot/{plain_key(topic)}"
        assert got[dst] == (delay, *sent[topic]), topic
    assert len(out) == 4
    stats = {r["name"]: r for r in relay.stats()["rules"]}
    assert {n: stats[n]["delay_ms"]["p50"] for n in TOPICS} == {
        n: float(d) for n, (_, _, d) in TOPICS.items()}


def test_sensor_streams_lose_some_samples_the_uplink_none():
    bus = InMemoryBus()
    clock = Clock()
    relay = LinkRelay(bus.transport(), load_config(CONFIG), "ros2", clock=clock).attach()
    client = bus.transport()
    pubs = {t: client.publisher(f"robot/{plain_key(t)}" if TOPICS[t][1] == "downlink"
                                else plain_key(t)) for t in TOPICS}
    for k in range(2000):
        clock.now = k * 20 * MS
        for pub in pubs.values():
            pub.put(b"x")
        relay.step()
    stats = {r["name"]: r for r in relay.stats()["rules"]}
    assert all(stats[t]["received"] == 2000 for t in TOPICS)
    assert 0.002 < stats["imu"]["dropped_loss"] / 2000 < 0.03      # 1 %
    assert 0.002 < stats["odom"]["dropped_loss"] / 2000 < 0.03     # 1 %
    assert 0.015 < stats["pose_fix"]["dropped_loss"] / 2000 < 0.07  # Gilbert-Elliott ~3.8 %
    assert stats["cmd_vel"]["dropped"] == 0
