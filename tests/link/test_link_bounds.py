"""pd-link's bounds on the in-memory bus (injected clock, ``step()``): held messages and bytes,
the configured delay, and the LRU of per-key routes, models and publishers."""

from __future__ import annotations

import pytest
from test_link_memory import MS, Link  # tests/link is on sys.path (no package)

from pd_service.errors import ConfigError
from pd_service.link.config import HELD_OVERHEAD_BYTES, Limits, load_config, parse_config
from pd_service.link.relay import LinkRelay
from pd_service.transport import InMemoryBus, InMemoryTransport
from pd_service.wire import keys

HOUR = "3600s"


class CountingTransport(InMemoryTransport):
    """The in-memory transport, counting the publishers declared and not yet closed."""

    def __init__(self, bus: InMemoryBus) -> None:
        super().__init__(bus)
        self.open_publishers = 0
        self.most_open = 0

    def publisher(self, key: str, *, express: bool = False,  # type: ignore[no-untyped-def]
                  cache: int = 0):
        pub = super().publisher(key, express=express, cache=cache)
        owner = self
        self.open_publishers += 1
        self.most_open = max(self.most_open, self.open_publishers)

        class Counted:
            def put(self, payload, **kw):  # type: ignore[no-untyped-def]
                pub.put(payload, **kw)

            def delete(self, **kw):  # type: ignore[no-untyped-def]
                pub.delete(**kw)

            def close(self) -> None:
                owner.open_publishers -= 1

        return Counted()


def rule_stats(relay: LinkRelay, name: str) -> dict:
    return next(r for r in relay.stats()["rules"] if r["name"] == name)


def test_limits_parse_with_defaults_and_units():
    assert parse_config({}).limits == Limits()
    cfg = parse_config({"limits": {"max_held_messages": 10, "max_held_bytes": "1MiB",
                                   "max_delay": "7200s", "max_keys": 5}})
    assert cfg.limits == Limits(10, 1024 * 1024, 2 * 3600 * 1_000_000_000, 5)
    assert parse_config(cfg.to_dict()) == cfg
    for bad in ({"max_held_bytes": "5 parsecs"}, {"max_keys": 0}, {"max_held_bytes": 0},
                {"what": 1}):
        with pytest.raises(ConfigError, match="limits"):
            parse_config({"limits": bad})


def test_delay_over_the_cap_is_refused_unless_raised():
    with pytest.raises(ConfigError, match=r"downlink\[0\] \(slow\)\.delay: .*limits.max_delay"):
        parse_config({"downlink": [{"name": "slow", "delay": HOUR}]})
    # a jitter table can draw up to ~4x the jitter: 20 s + 4 * 11 s > 60 s
    with pytest.raises(ConfigError, match="max_delay"):
        parse_config({"uplink": [{"name": "j", "delay": "20s", "jitter": "11s",
                                  "distribution": "normal"}]})
    assert parse_config({"uplink": [{"name": "j", "delay": "20s", "jitter": "11s"}]})
    cfg = parse_config({"limits": {"max_delay": "7200s"}, "downlink": [{"name": "slow",
                                                                     "delay": HOUR}]})
    assert cfg.downlink[0].params.delay.delay_ns == 3600 * 10**9


def test_limits_cannot_be_raised_by_a_rules_query():
    link = Link({"limits": {"max_delay": "2s"}, "downlink": [{"name": "d", "delay": "1s"}]}, "q")
    ok, err = link.query(keys.link_rules_key("q"), b'{"downlink": [{"delay": "10s"}]}')
    assert not ok and "max_delay" in err["error"]
    ok, err = link.query(keys.link_rules_key("q"),
                         b'{"limits": {"max_delay": "3600s"}, "downlink": [{"delay": "10s"}]}')
    assert not ok and "limits cannot be changed at runtime" in err["error"]
    ok, doc = link.query(keys.link_rules_key("q"), b'{"downlink": [{"delay": "1500ms"}]}')
    assert ok and doc["limits"]["max_delay"] == "2000ms" and link.relay.generation == 2


def test_hour_delay_flood_stays_under_the_caps_and_drops_are_counted(caplog):
    # 2 rules + 2 unmatched: each rule may hold a quarter of the limits
    limits = {"max_held_messages": 4000, "max_held_bytes": 4000 * (100 + HELD_OVERHEAD_BYTES),
              "max_delay": "7200s"}
    link = Link({"limits": limits,
                 "downlink": [{"name": "slow", "match": "robot/*/flood/sensor/*", "delay": HOUR}],
                 "uplink": [{"name": "cmd", "delay": 20}]})  # fmt: skip
    relay = link.relay
    payload = b"x" * 100
    for i in range(5000):
        link.client.put(keys.robot_sensor_key("flood", "cam"), payload)
        if i % 500 == 0:
            link.client.put(keys.command_key("ok"), b"u%d" % i)
        link.at(i * 0.1)
        if i % 50 == 0:
            st, slow = relay.stats(), rule_stats(relay, "slow")
            assert st["pending"] <= 4000 and st["pending_bytes"] <= limits["max_held_bytes"]
            assert slow["held"] <= 1000 and slow["held_bytes"] <= 1000 * (100 + HELD_OVERHEAD_BYTES)
    st = relay.stats()
    slow = rule_stats(relay, "slow")
    assert st["pending"] == 1000 and slow["held"] == 1000  # its share, full of the flood
    assert slow["received"] == 5000 and slow["dropped_capacity"] == 4000
    assert slow["dropped"] == 4000 and st["dropped_capacity"] == 4000
    # another stream keeps its delay (it never hit the cap: each command went out at +20 ms)
    cmd = rule_stats(relay, "cmd")
    assert cmd["received"] == 10 and cmd["forwarded"] == 10 and cmd["dropped_capacity"] == 0
    assert cmd["delay_ms"]["p99"] == pytest.approx(20.0, abs=0.01)
    # the periodic stats log carries the counters
    relay._stats_interval_ns = 0
    with caplog.at_level("INFO", logger="pd_service.link"):
        relay._maybe_log_stats()
    fields = [getattr(r, "fields", {}) for r in caplog.records]
    assert any(f.get("rule") == "slow" and f.get("dropped_capacity") == 4000 for f in fields)
    assert any(f.get("dropped_capacity") == 4000 and "held" in f for f in fields)
    # an hour later everything held goes out and the heap is empty again
    link.at(3600_000 + 100)
    assert relay.stats()["pending"] == 0 and relay.stats()["pending_bytes"] == 0
    assert rule_stats(relay, "slow")["forwarded"] == 1000


def test_byte_cap_counts_payload_and_attachment():
    size = 1000 + 24 + HELD_OVERHEAD_BYTES  # 1 rule + 2 unmatched: a third of the limit each
    link = Link({"limits": {"max_held_bytes": 3 * 3 * size}, "downlink": [{"name": "d",
                                                                        "delay": 50}]})
    pub = link.client.publisher(keys.robot_sensor_key("m", "x"))
    for _ in range(5):
        pub.put(b"p" * 1000, attachment=b"a" * 24)
    link.at(0)
    assert link.relay.stats()["pending"] == 3 and link.relay.stats()["pending_bytes"] == 3 * size
    assert rule_stats(link.relay, "d")["dropped_capacity"] == 2
    link.at(50)
    assert len(link.out) == 3


def test_many_keys_keep_publishers_at_the_lru_size_and_other_streams_their_delay():
    bus = InMemoryBus()
    transport = CountingTransport(bus)
    now = [0]
    relay = LinkRelay(transport, parse_config({
        "limits": {"max_keys": 16},
        "downlink": [{"name": "victim", "match": "robot/*/good/sensor/*", "delay": 30},
                     {"name": "many", "match": "robot/*/*/sensor/*", "delay": 10}]}),
        "lru", clock=lambda: now[0]).attach()  # fmt: skip
    client = bus.transport()
    got: list[tuple[int, str]] = []
    client.subscribe(keys.ALL_SENSORS, lambda s: got.append((now[0], s.key)))
    victim_sent: list[int] = []
    for i in range(2000):
        now[0] = i * MS
        client.put(keys.robot_sensor_key(f"k{i}", "cam"), b"x")
        if i % 10 == 0:
            client.put(keys.robot_sensor_key("good", "cam"), b"v")
            victim_sent.append(now[0])
        relay.step()
        assert transport.open_publishers <= 16
        assert len(relay._gen.routes) <= 16 and len(relay._gen.models) <= 16
    for t in range(2000, 2100):
        now[0] = t * MS
        relay.step()
    st = relay.stats()
    assert st["publishers"] <= 16 and transport.most_open == 16
    assert st["keys"] <= 16 and st["keys_evicted"] > 1900 and st["publishers_evicted"] > 1900
    assert rule_stats(relay, "many")["forwarded"] == 2000  # evicted keys still relayed
    victim_out = [t for t, k in got if k == keys.sensor_key("good", "cam")]
    assert [t - s for t, s in zip(victim_out, victim_sent, strict=True)] == [30 * MS] * len(
        victim_sent)  # every victim release exactly on time
    assert rule_stats(relay, "victim")["delay_ms"]["p50"] == 30.0


def test_shipped_link_configs_fit_the_default_limits():
    from pathlib import Path

    deploy = Path(__file__).resolve().parents[2] / "deploy"
    for name in ("link-paper.toml", "link-ros2.toml"):
        assert load_config(deploy / name).limits == Limits()


def test_outputs_to_the_service_keep_their_last_samples():
    """Sensor outputs (pd/p<k>/<s>/sensor/<name>) keep a cache a restarted service reads back;
    outputs the service does not read (robot/p<k>/<s>/cmd) keep none."""
    bus = InMemoryBus()
    now = [0]
    relay = LinkRelay(bus.transport(), parse_config({"downlink": [{"name": "d", "delay": 0}],
                                                     "uplink": [{"name": "u", "delay": 0}]}),
                      "cache", cache=3, clock=lambda: now[0]).attach()
    client = bus.transport()
    for i in range(5):
        now[0] = i * MS
        client.put(keys.robot_sensor_key("s", "cam"), f"z{i}".encode())
        client.put(keys.command_key("s"), f"u{i}".encode())
        relay.step()
    got: list = []
    client.read_back(keys.ALL_SENSORS, got.append, max_samples=10)
    assert [s.payload for s in got] == [b"z2", b"z3", b"z4"] and all(s.recovered for s in got)
    got.clear()
    client.read_back(keys.ROBOT_ALL_COMMANDS, got.append, max_samples=10)
    assert got == []
    relay.close()
