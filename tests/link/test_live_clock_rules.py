"""bench/robot_clock_live.py's link: its pd-link rules, run through the relay on the in-memory
bus with an injected clock, give every stream the processes use the issue's delay (up 500 ms,
down 600 ms, the paper's camera 500 ms, each +- 50 ms), the keys the daemon and the robot
read, and the loopback variant no delay."""

from __future__ import annotations

import tomllib
from collections import defaultdict

import pytest

from pd_service.link.config import parse_config
from pd_service.link.relay import LinkRelay
from pd_service.transport import InMemoryBus, Sample
from pd_service.wire import keys
from tests.scripts import load_script

live = load_script("bench/robot_clock_live.py", "bench_robot_clock_live")

MS = 1_000_000
ROS = "0/{}/some_msgs::msg::dds_::T_/RIHS01_0"


def released(rules: str, sent: dict[str, str], count: int = 200
             ) -> dict[str, tuple[list[int], set[str]]]:
    """``count`` messages on each key of ``sent``, one a millisecond from t = 0; per key: the
    delays (ms) of those released and the keys they came out on."""
    bus = InMemoryBus()
    now = [0]
    relay = LinkRelay(bus.transport(), parse_config(tomllib.loads(rules)), "t",
                      clock=lambda: now[0]).attach()
    out: dict[str, tuple[list[int], set[str]]] = defaultdict(lambda: ([], set()))
    sub = bus.transport()
    for key, want in sent.items():
        def on(s: Sample, key: str = key) -> None:
            i = int(s.payload.decode())
            out[key][0].append(now[0] // MS - i)
            out[key][1].add(s.key)

        sub.subscribe(want, on)
    pub = bus.transport()
    for t in range(800):
        now[0] = t * MS
        if t < count:
            for key in sent:
                pub.put(key, str(t).encode())
        relay.step()
    relay.close()
    return out


@pytest.mark.parametrize("scenario", ["paper", "diffdrive"])
def test_every_stream_gets_the_issues_delay_on_the_keys_its_reader_uses(scenario: str) -> None:
    s = live.SESSION[scenario]
    sensors = ["camera", "ranger"] if scenario == "paper" else ["odom_twist", "imu", "pose"]
    sent = {keys.robot_sensor_key(s, n): keys.sensor_key(s, n) for n in sensors}
    sent[keys.robot_echo_key(s)] = keys.echo_key(s)
    sent[keys.command_key(s)] = keys.robot_command_key(s)
    if scenario == "diffdrive":
        for topic in live.ROS_TOPICS:
            sent["robot/" + ROS.format(topic)] = ROS.format(topic)
        sent[ROS.format("cmd_vel")] = "robot/" + ROS.format("cmd_vel")
    rules = live.link_rules(scenario, 50.0 if scenario == "paper" else 20.0, delays=True)
    got = released(rules, sent)
    for key, want in sent.items():
        delays, out_keys = got[key]
        assert out_keys == {want}, key
        assert len(delays) >= 150, key  # the demo's loss: a few per cent
        up = key.startswith("pd/") or "cmd_vel" in key
        base = 500 if up or key.endswith("/camera") else 600
        assert base - 50 <= min(delays) and max(delays) <= base + 50, key
        assert max(delays) - min(delays) >= 60, key  # the jitter is there
    flat = released(live.link_rules(scenario, 50.0, delays=False), sent, count=50)
    assert all(set(flat[k][0]) == {0} for k in sent)
