"""The relay on the in-memory bus, driven by an injected clock and ``step()``: no threads, no
sleeps, so every time is exact and every run the same."""

from __future__ import annotations

import json

import pytest

from pd_service.link.config import parse_config
from pd_service.link.relay import LinkRelay
from pd_service.transport import InMemoryBus, Sample
from pd_service.wire import keys

MS = 1_000_000


class Clock:
    """Integer ns; the test moves it."""

    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


class Link:
    """A relay and a test client on one bus; ``out`` records (clock, sample) of the outputs."""

    def __init__(self, doc: dict, instance: str = "mem") -> None:
        bus = InMemoryBus()
        self.clock = Clock()
        self.relay = LinkRelay(bus.transport(), parse_config(doc), instance,
                               clock=self.clock).attach()
        self.client = bus.transport()
        self.out: list[tuple[int, Sample]] = []
        for ke in (keys.ALL_SENSORS, keys.ROBOT_ALL_COMMANDS):
            self.client.subscribe(ke, lambda s: self.out.append((self.clock.now, s)))

    def at(self, t_ms: float) -> int:
        """Move the clock to ``t_ms`` and let the relay work; returns how many it published."""
        self.clock.now = round(t_ms * MS)
        return self.relay.step()

    def query(self, key: str, payload: bytes | None = None) -> tuple[bool, dict]:
        (reply,) = self.client.get(key, payload)
        return reply.ok, json.loads(reply.payload)


def test_delays_are_exact_and_keys_are_mapped():
    link = Link({"downlink": [
        {"name": "cam", "match": "robot/*/*/sensor/camera", "delay": 120},
        {"name": "rng", "match": "robot/*/*/sensor/ranger", "delay": "40ms"},
    ], "uplink": [{"name": "cmd", "delay": 30}]})  # fmt: skip
    link.client.put(keys.robot_sensor_key("m", "camera"), b"c0")
    link.client.put(keys.robot_sensor_key("m", "ranger"), b"r0")
    link.client.put(keys.command_key("m"), b"u0")
    assert link.at(0) == 0 and link.out == []
    assert link.at(29.999) == 0
    assert link.at(30) == 1
    assert link.at(40) == 1
    assert link.at(119) == 0
    assert link.at(500) == 1
    got = [(t / MS, s.key, s.payload) for t, s in link.out]
    assert got == [(30, keys.robot_command_key("m"), b"u0"), (40, keys.sensor_key("m", "ranger"), b"r0"),
                   (500, keys.sensor_key("m", "camera"), b"c0")]  # fmt: skip
    rules = {r["name"]: r for r in link.relay.stats()["rules"]}
    assert rules["cam"]["forwarded"] == 1 and rules["cam"]["delay_ms"]["p50"] == 500.0
    assert rules["cam"]["lateness_ms"]["p50"] == 380.0  # due at 120 ms, stepped at 500 ms
    assert rules["rng"]["delay_ms"]["p50"] == 40.0 and rules["rng"]["lateness_ms"]["p50"] == 0


def test_encoding_attachment_and_deletes_are_kept():
    link = Link({"downlink": [{"name": "d", "delay": 5}]})
    pub = link.client.publisher(keys.robot_sensor_key("m", "x"))
    pub.put(b"\x00\x01", encoding="application/json", attachment=b"meta")
    pub.delete(attachment=b"gone")
    link.at(5)
    (_, put), (_, deleted) = link.out
    assert (put.kind, put.payload, put.encoding, put.attachment) == (
        "put", b"\x00\x01", "application/json", b"meta")
    assert (deleted.kind, deleted.key, deleted.attachment) == ("delete", keys.sensor_key("m", "x"), b"gone")


def test_same_seed_same_run():
    doc = {"seed": 9, "downlink": [{"name": "lossy", "loss": {"model": "gemodel", "p": 10,
                                                              "r": 40},
                                    "delay": 10, "jitter": 8, "duplicate": 5}]}  # fmt: skip

    def run() -> list[tuple[int, bytes]]:
        link = Link(doc)
        for i in range(300):
            link.at(i)
            link.client.put(keys.robot_sensor_key("m", "x"), b"%d" % i)
        link.at(1000)
        return [(t, s.payload) for t, s in link.out]

    first = run()
    assert first == run()
    assert 200 < len(first) < 300  # some lost, some duplicated


def test_unmatched_passes_at_once_and_unmapped_is_counted():
    link = Link({"downlink": [{"name": "cam", "match": "robot/*/*/sensor/camera", "loss": 100}]})
    link.client.put(keys.robot_sensor_key("m", "camera"), b"lost")
    link.client.put(keys.robot_sensor_key("m", "imu"), b"imu")
    link.client.put("robot/p56/m/sensor/bad key", b"unmapped")
    assert link.at(0) == 1
    assert [s.payload for _, s in link.out] == [b"imu"]
    stats = link.relay.stats()
    assert stats["unmapped"] == 1
    rules = {r["name"]: r for r in stats["rules"] if r["direction"] == "downlink"}
    assert rules["cam"]["dropped_loss"] == 1 and rules["(unmatched)"]["forwarded"] == 1


def test_rules_and_stats_queryables():
    link = Link({"step_ms": 10, "downlink": [{"name": "slow", "delay": "3 steps"}]}, "q")
    ok, doc = link.query(keys.link_rules_key("q"))
    assert ok and doc["generation"] == 1 and doc["downlink"][0]["delay"] == "30ms"

    ok, err = link.query(keys.link_rules_key("q"), b'{"downlink": [{"delay": "soon"}]}')
    assert not ok and err["error"].startswith("downlink[0] (downlink-0).delay:")
    assert link.relay.generation == 1

    ok, doc = link.query(keys.link_rules_key("q"), b'[[downlink]]\nname = "fast"\ndelay = "1 step"\n')
    assert ok and doc["generation"] == 2 and doc["downlink"][0]["delay"] == "10ms"
    link.client.put(keys.robot_sensor_key("m", "x"), b"x")
    link.at(0)
    assert link.at(10) == 1

    ok, stats = link.query(keys.link_stats_key("q"))
    assert ok and stats["generation"] == 2 and stats["pending"] == 0
    assert next(r for r in stats["rules"] if r["name"] == "fast")["forwarded"] == 1


@pytest.mark.parametrize("shared", [False, True])
def test_shared_rule_queues_keys_on_one_link(shared):
    link = Link({"downlink": [{"name": "slow", "rate": "5msg/s", "shared": shared}]})
    link.client.put(keys.robot_sensor_key("m", "a"), b"a")
    link.client.put(keys.robot_sensor_key("m", "b"), b"b")
    link.at(0)
    assert link.at(200) == (1 if shared else 2)
    assert link.at(400) == (1 if shared else 0)
