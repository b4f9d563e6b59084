"""The relay in-process, through real Zenoh on loopback (two peer sessions, no router)."""

from __future__ import annotations

import json
import struct
import time

import numpy as np
import pytest

from pd_service.link.config import parse_config
from pd_service.link.relay import LinkRelay
from pd_service.wire import keys

MS = 1_000_000


def query(session, key: str, payload: bytes | None = None):
    replies = list(session.get(key, payload=payload, timeout=5.0))
    for _ in range(20):  # a read: asked again while the new queryable is not routed yet
        if replies or payload is not None:
            break
        time.sleep(0.1)
        replies = list(session.get(key, timeout=5.0))
    assert len(replies) == 1, f"expected one reply from {key}, got {len(replies)}"
    r = replies[0]
    if r.ok is not None:
        return True, json.loads(r.ok.payload.to_bytes())
    return False, json.loads(r.err.payload.to_bytes())


def prime(pub, collector, probe: bytes = b"probe") -> None:
    """Send probes until one comes out of the relay (all declarations have propagated), then
    ignore probes from then on (earlier ones may still be on their way)."""
    deadline = time.monotonic() + 10
    while not pub.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)
    for i in range(100):
        pub.put(probe + b"-%d" % i)
        if collector.wait_for(lambda items: any(p.startswith(probe) for _, _, p in items), 0.1):
            collector.ignore_prefix = probe
            collector.clear()
            return
    raise AssertionError("nothing came through the relay")


def wait_rule_stats(relay, name: str, pred, timeout: float = 5.0) -> dict:
    """Poll the relay's stats until rule ``name`` satisfies ``pred``; return its entry."""
    deadline = time.monotonic() + timeout
    while True:
        rule = next(r for r in relay.stats()["rules"] if r["name"] == name)
        if pred(rule) or time.monotonic() > deadline:
            return rule
        time.sleep(0.01)


@pytest.fixture
def relay_env(zenoh_pair, collector_factory):
    """Factory: start a relay with given rules; yields helpers; closes everything after."""
    test_s, relay_s, _ = zenoh_pair
    made = []

    def make(doc: dict, instance: str, out_key: str):
        got = collector_factory()
        sub = test_s.declare_subscriber(out_key, got)
        relay = LinkRelay(relay_s, parse_config(doc), instance).start()
        made.append((relay, sub))
        return relay, got

    yield test_s, make
    for relay, sub in made:
        relay.close()
        sub.undeclare()


def test_downlink_delay_is_applied(relay_env):
    test_s, make = relay_env
    doc = {"downlink": [
        {"name": "cam", "match": "robot/*/*/sensor/camera", "delay": 120},
        {"name": "rng", "match": "robot/*/*/sensor/ranger", "delay": 40},
    ]}  # fmt: skip
    relay, got = make(doc, "t-delay", keys.sensors_of("rd"))
    cam = test_s.declare_publisher(keys.robot_sensor_key("rd", "camera"))
    rng = test_s.declare_publisher(keys.robot_sensor_key("rd", "ranger"))
    prime(cam, got)
    got.clear()
    sent = {}
    for i in range(20):
        for name, pub in (("camera", cam), ("ranger", rng)):
            payload = f"{name}-{i}".encode()
            sent[payload] = time.monotonic_ns()
            pub.put(payload)
        time.sleep(0.005)
    assert got.wait_for(lambda items: len(items) >= 40, 10.0)
    delays: dict[str, list[float]] = {"camera": [], "ranger": []}
    for t, key, payload in got.items:
        name = key.rsplit("/", 1)[1]
        assert key == keys.sensor_key("rd", name)
        assert payload.startswith(name.encode())
        delays[name].append((t - sent[payload]) / MS)
    cam_med, rng_med = np.median(delays["camera"]), np.median(delays["ranger"])
    print(f"measured delay: camera median {cam_med:.2f} ms (configured 120), "
          f"ranger median {rng_med:.2f} ms (configured 40)")  # fmt: skip
    # loose bounds: never early, not absurdly late on a loaded 2-core machine
    assert min(delays["camera"]) >= 119.0 and cam_med < 170
    assert min(delays["ranger"]) >= 39.0 and rng_med < 90
    # the counter moves just after put() returns, so it may trail the subscriber a little
    cam_stats = wait_rule_stats(relay, "cam", lambda r: r["forwarded"] >= 21)  # + 1 probe
    assert cam_stats["delay_ms"]["p50"] >= 120


def test_uplink_maps_commands_to_robot_side(relay_env):
    test_s, make = relay_env
    relay, got = make({"uplink": [{"name": "cmd", "delay": 30}]}, "t-up", keys.robot_command_key("ru"))
    pub = test_s.declare_publisher(keys.command_key("ru"))
    prime(pub, got)
    t0 = time.monotonic_ns()
    pub.put(b"\x01\x02cmd")
    assert got.wait_for(lambda items: len(items) == 1)
    t, key, payload = got.items[0]
    assert key == keys.robot_command_key("ru") and payload == b"\x01\x02cmd"
    assert (t - t0) / MS >= 29.0


def test_payload_bytes_are_relayed_verbatim_and_corrupt_flips_bits(relay_env):
    test_s, make = relay_env
    doc = {"downlink": [{"name": "bad", "match": "robot/*/*/sensor/bad", "corrupt": 100},
                        {"name": "good", "match": "robot/*/*/sensor/good"}]}  # fmt: skip
    relay, got = make(doc, "t-bytes", keys.sensors_of("rb"))
    good = test_s.declare_publisher(keys.robot_sensor_key("rb", "good"))
    bad = test_s.declare_publisher(keys.robot_sensor_key("rb", "bad"))
    prime(good, got)
    blob = bytes(range(256)) * 4
    good.put(blob)
    bad.put(blob)
    assert got.wait_for(lambda items: len(items) == 2)
    by_key = {k.rsplit("/", 1)[1]: p for _, k, p in got.items}
    assert by_key["good"] == blob
    flipped = sum(bin(a ^ b).count("1") for a, b in zip(by_key["bad"], blob, strict=True))
    assert flipped == 1
    assert next(r for r in relay.stats()["rules"] if r["name"] == "bad")["corrupted"] == 1


def test_unmatched_keys_pass_through_and_are_counted(relay_env):
    test_s, make = relay_env
    doc = {"downlink": [{"name": "probes", "match": "robot/*/*/sensor/probe"},
                        {"name": "cam-only", "match": "robot/*/*/sensor/camera", "loss": 100}]}
    relay, got = make(doc, "t-pass", keys.sensors_of("rp"))
    prime(test_s.declare_publisher(keys.robot_sensor_key("rp", "probe")), got)
    imu = test_s.declare_publisher(keys.robot_sensor_key("rp", "imu"))
    cam = test_s.declare_publisher(keys.robot_sensor_key("rp", "camera"))
    for i in range(5):
        cam.put(b"c%d" % i)
        imu.put(b"i%d" % i)
    assert got.wait_for(lambda items: len(items) >= 5)
    assert got.wait_for(lambda items: False, 0.2) is False  # nothing else arrives
    assert sorted(p for _, _, p in got.items) == [b"i%d" % i for i in range(5)]
    assert wait_rule_stats(relay, "(unmatched)", lambda r: r["forwarded"] >= 5)["forwarded"] == 5
    rules = {r["name"]: r for r in relay.stats()["rules"] if r["direction"] == "downlink"}
    assert rules["cam-only"]["dropped"] == 5 and rules["cam-only"]["forwarded"] == 0


def test_rules_queryable_get_replace_and_refuse(relay_env):
    test_s, make = relay_env
    relay, got = make({"downlink": [{"name": "slow", "delay": 300}]}, "t-rules",
                      f"{keys.session_prefix('rq')}/**")
    rules_key = keys.link_rules_key("t-rules")
    ok, doc = query(test_s, rules_key)
    assert ok and doc["generation"] == 1 and doc["downlink"][0]["delay"] == "300ms"

    # a bad replacement is refused with a readable error and changes nothing
    ok, err = query(test_s, rules_key, b'{"downlink": [{"delay": "soon"}]}')
    assert not ok and "delay" in err["error"]
    ok, err = query(test_s, rules_key, b"[[downlink]]\nloss = 150\n")
    assert not ok and "percentage" in err["error"]
    assert relay.generation == 1

    # a TOML replacement takes effect for the next message
    ok, doc = query(test_s, rules_key, b'[[downlink]]\nname = "fast"\ndelay = 10\n')
    assert ok and doc["generation"] == 2 and doc["downlink"][0]["name"] == "fast"
    pub = test_s.declare_publisher(keys.robot_sensor_key("rq", "camera"))
    prime(pub, got)
    t0 = time.monotonic_ns()
    pub.put(b"x")
    assert got.wait_for(lambda items: len(items) == 1, 5.0)
    assert 9.0 <= (got.items[0][0] - t0) / MS < 250  # the 300 ms rule is gone

    # JSON replacement; the GET answers the normalised rules
    new = {"downlink": [{"name": "lossy", "loss": {"model": "gemodel", "p": 5, "r": 50}}]}
    ok, doc = query(test_s, rules_key, json.dumps(new).encode())
    assert ok and doc["downlink"][0]["loss"]["model"] == "gemodel"
    assert query(test_s, rules_key)[1]["generation"] == 3


def test_stats_queryable_counts(relay_env):
    test_s, make = relay_env
    doc = {"seed": 4, "downlink": [{"name": "lossy", "match": "robot/*/*/sensor/x",
                                    "loss": 30, "duplicate": 10, "delay": 5}]}  # fmt: skip
    relay, got = make(doc, "t-stats", keys.sensors_of("rs"))
    prime(test_s.declare_publisher(keys.robot_sensor_key("rs", "probe")), got)  # unmatched
    pub = test_s.declare_publisher(keys.robot_sensor_key("rs", "x"))
    n = 400
    for i in range(n):
        pub.put(struct.pack("<I", i))
    ok, stats = query(test_s, keys.link_stats_key("t-stats"))
    assert ok
    deadline = time.monotonic() + 10
    while True:
        ok, stats = query(test_s, keys.link_stats_key("t-stats"))
        rule = next(r for r in stats["rules"] if r["name"] == "lossy")
        if rule["received"] == n and stats["pending"] == 0 or time.monotonic() > deadline:
            break
        got.wait_for(lambda items: False, 0.05)
    assert rule["received"] == n
    assert rule["forwarded"] == n - rule["dropped"] + rule["duplicated"]
    assert 0.2 * n < rule["dropped"] < 0.4 * n
    assert 0 < rule["duplicated"] < 0.2 * n
    assert rule["delay_ms"]["p50"] >= 5.0 and rule["lateness_ms"]["p99"] is not None
    assert stats["instance"] == "t-stats" and stats["generation"] == 1


def test_outage_stall_over_zenoh(relay_env):
    test_s, make = relay_env
    doc = {"downlink": [{"name": "flaky", "match": "robot/*/*/sensor/x",
                         "outage": {"at": 0, "for": "300ms"}, "outage_mode": "stall"}]}
    relay, got = make({}, "t-stall", keys.sensors_of("ro"))
    prime(test_s.declare_publisher(keys.robot_sensor_key("ro", "probe")), got)
    pub = test_s.declare_publisher(keys.robot_sensor_key("ro", "x"))
    t0 = time.monotonic_ns()
    relay.replace_rules(parse_config(doc))  # the outage starts now
    for i in range(10):
        pub.put(b"m%d" % i)
    assert got.wait_for(lambda items: len(items) == 10, 5.0)
    arrivals = [(t - t0) / MS for t, _, _ in got.items]
    assert min(arrivals) >= 290  # held until the outage ended ...
    assert max(arrivals) - min(arrivals) < 50  # ... then released in one burst
    rule = relay.stats()["rules"][0]
    assert rule["stalled"] == 10 and rule["dropped"] == 0


@pytest.mark.parametrize("shared", [False, True])
def test_shared_rule_state_spans_keys(relay_env, shared):
    """A rate-limited rule: per-key state lets two keys go in parallel; shared state queues
    them behind each other on one link."""
    test_s, make = relay_env
    doc = {"downlink": [{"name": "probes", "match": "robot/*/*/sensor/probe"},
                        {"name": "slow", "match": "robot/*/*/sensor/*", "rate": "5msg/s",
                         "shared": shared}]}  # fmt: skip
    relay, got = make(doc, f"t-shared-{int(shared)}", keys.sensors_of("rh"))
    prime(test_s.declare_publisher(keys.robot_sensor_key("rh", "probe")), got)
    a = test_s.declare_publisher(keys.robot_sensor_key("rh", "a"))
    b = test_s.declare_publisher(keys.robot_sensor_key("rh", "b"))
    t0 = time.monotonic_ns()
    a.put(b"a")
    b.put(b"b")
    assert got.wait_for(lambda items: len(items) == 2, 5.0)
    arrivals = sorted((t - t0) / MS for t, _, _ in got.items)
    assert arrivals[0] >= 199  # 1 / (5 msg/s) on the link
    if shared:
        assert arrivals[1] - arrivals[0] >= 195  # the second waits for the first
    else:
        assert arrivals[1] - arrivals[0] < 100  # two independent links
