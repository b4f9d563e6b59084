"""Key expressions (key layout 2): building, parsing, partitions, and how Zenoh's wildcards
match them."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings

from pd_service.wire import keys
from pd_service.wire.keys import KeyError_, ParsedKey, parse_key
from tests.wire.factories import names

zenoh = pytest.importorskip("zenoh")

PROTOCOL_MD = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
K1 = keys.partition_of("s1")  # s1's partition at this process's P
SESSION_KEYS = {
    keys.config_key("s1"): ParsedKey("operator", "s1", "config", None, K1),
    keys.sensor_key("s1", "camera"): ParsedKey("operator", "s1", "sensor", "camera", K1),
    keys.command_key("s1"): ParsedKey("operator", "s1", "cmd", None, K1),
    keys.prediction_key("s1"): ParsedKey("operator", "s1", "prediction", None, K1),
    keys.error_key("s1"): ParsedKey("operator", "s1", "error", None, K1),
    keys.status_key("s1"): ParsedKey("operator", "s1", "status", None, K1),
    keys.robot_sensor_key("s1", "camera"): ParsedKey("robot", "s1", "sensor", "camera", K1),
    keys.robot_command_key("s1"): ParsedKey("robot", "s1", "cmd", None, K1),
    keys.truth_key("s1"): ParsedKey("robot", "s1", "truth", None, K1),
}
SERVICE_KEYS = [keys.service_token_key("pd-a"), keys.service_status_key("pd-a"),
                keys.link_rules_key("link-1"), keys.link_stats_key("link-1"),
                keys.ros2_status_key("r-1")]
WILDCARDS = {
    keys.ALL_CONFIGS: keys.config_key, keys.ALL_COMMANDS: keys.command_key,
    keys.ALL_PREDICTIONS: keys.prediction_key, keys.ALL_ERRORS: keys.error_key,
    keys.ALL_STATUS: keys.status_key, keys.ROBOT_ALL_COMMANDS: keys.robot_command_key,
    keys.ALL_TRUTHS: keys.truth_key,
}


@pytest.fixture
def p64() -> Iterator[None]:
    """P = 64 (the default) for the literal keys below, whatever PD_PARTITIONS says."""
    before = keys.partitions()
    keys.set_partitions(64)
    yield
    keys.set_partitions(before)


def doc_vectors() -> list[tuple[str, int, int, int]]:
    """protocol.md §3's test vectors: (name, FNV-1a-32, k for P = 64, k for P = 256)."""
    row = re.compile(r"^\| `([a-z0-9_-]+)` \| `0x([0-9a-f]{8})` \| (\d+) \| (\d+) \|$")
    found = [row.match(line) for line in PROTOCOL_MD.read_text().splitlines()]
    return [(m[1], int(m[2], 16), int(m[3]), int(m[4])) for m in found if m]


def test_layout(p64):
    assert keys.KEY_LAYOUT == 2 and keys.partition_of("s1") == 9
    assert [keys.config_key("s1"), keys.sensor_key("s1", "camera"), keys.command_key("s1"),
            keys.prediction_key("s1"), keys.error_key("s1"), keys.status_key("s1"),
            keys.robot_sensor_key("s1", "camera"), keys.robot_command_key("s1"),
            keys.truth_key("s1")] == [
        "pd/p9/s1/config", "pd/p9/s1/sensor/camera", "pd/p9/s1/cmd", "pd/p9/s1/prediction",
        "pd/p9/s1/error", "pd/p9/s1/status", "robot/p9/s1/sensor/camera", "robot/p9/s1/cmd",
        "robot/p9/s1/truth"]
    assert keys.session_prefix("s1") == "pd/p9/s1"
    assert keys.sensors_of("s1") == "pd/p9/s1/sensor/*"
    assert (keys.partition_sensors(9), keys.partition_commands(9)) == ("pd/p9/*/sensor/*",
                                                                       "pd/p9/*/cmd")
    assert SERVICE_KEYS == ["pd/@service/pd-a", "pd/@service/pd-a/status",
                            "pd/@link/link-1/rules", "pd/@link/link-1/stats",
                            "pd/@ros2/r-1/status"]
    keys.set_partitions(256)
    assert keys.config_key("s1") == "pd/p201/s1/config"


@pytest.mark.parametrize("key", list(SESSION_KEYS))
def test_parse_session_keys(key):
    assert parse_key(key) == SESSION_KEYS[key]
    assert keys.session_of(key) == "s1"


@pytest.mark.parametrize("key", list(SESSION_KEYS) + SERVICE_KEYS)
def test_keys_are_canonical_zenoh_keys(key):
    assert str(zenoh.KeyExpr(key)) == key


@settings(max_examples=200, deadline=None)
@given(session=names, sensor=names)
def test_build_parse_round_trip(session, sensor):
    k = keys.partition_of(session)
    assert parse_key(keys.sensor_key(session, sensor)) == \
        ParsedKey("operator", session, "sensor", sensor, k)
    assert parse_key(keys.robot_sensor_key(session, sensor)) == \
        ParsedKey("robot", session, "sensor", sensor, k)
    for build in WILDCARDS.values():
        p = parse_key(build(session))
        assert p.session == session and p.sensor is None and p.partition == k
    assert keys.to_robot_side(keys.sensor_key(session, sensor)) == keys.robot_sensor_key(session, sensor)
    assert keys.to_operator_side(keys.robot_command_key(session)) == keys.command_key(session)
    assert keys.session_of(keys.sensor_key(session, sensor)) == session


def test_wildcards_match_their_keys_only():
    every = list(SESSION_KEYS) + SERVICE_KEYS
    for wildcard, build in WILDCARDS.items():
        w = zenoh.KeyExpr(wildcard)
        matched = [k for k in every if w.intersects(zenoh.KeyExpr(k))]
        assert matched == [build("s1")], wildcard
    for wildcard, want in [(keys.ALL_SENSORS, keys.sensor_key("s1", "camera")),
                           (keys.ROBOT_ALL_SENSORS, keys.robot_sensor_key("s1", "camera")),
                           (keys.sensors_of("s1"), keys.sensor_key("s1", "camera"))]:
        w = zenoh.KeyExpr(wildcard)
        assert [k for k in every if w.intersects(zenoh.KeyExpr(k))] == [want]
    # '@' chunks are verbatim: session wildcards never reach service keys, and the
    # service wildcards reach only them
    svc = zenoh.KeyExpr(keys.ALL_SERVICES)
    assert [k for k in every if svc.intersects(zenoh.KeyExpr(k))] == ["pd/@service/pd-a"]
    st_all = zenoh.KeyExpr(keys.all_service_status())
    assert [k for k in every if st_all.intersects(zenoh.KeyExpr(k))] == ["pd/@service/pd-a/status"]
    assert not zenoh.KeyExpr("pd/**").intersects(zenoh.KeyExpr("pd/@service/pd-a"))


def test_partition_wildcards_match_their_partition_only(p64):
    sessions = [f"s{i}" for i in range(200)]
    by_partition: dict[int, set[str]] = {}
    for s in sessions:
        by_partition.setdefault(keys.partition_of(s), set()).add(s)
    assert len(by_partition) > 40  # 200 names spread over most of the 64 partitions
    for k in (0, 9, 63):
        sens, cmds = zenoh.KeyExpr(keys.partition_sensors(k)), zenoh.KeyExpr(keys.partition_commands(k))
        got_sens = {s for s in sessions if sens.intersects(zenoh.KeyExpr(keys.sensor_key(s, "cam")))}
        got_cmds = {s for s in sessions if cmds.intersects(zenoh.KeyExpr(keys.command_key(s)))}
        assert got_sens == got_cmds == by_partition.get(k, set())
        assert not cmds.intersects(zenoh.KeyExpr(keys.sensor_key("s1", "cam")))
        assert not sens.intersects(zenoh.KeyExpr(keys.command_key("s1")))
    # one session's sensor wildcard: its own sensors only, not a neighbour in the same partition
    same = sorted(by_partition[9] - {"s1"})[0]
    w = zenoh.KeyExpr(keys.sensors_of("s1"))
    assert w.intersects(zenoh.KeyExpr(keys.sensor_key("s1", "ranger")))
    assert not w.intersects(zenoh.KeyExpr(keys.sensor_key(same, "ranger")))


@pytest.mark.parametrize("bad", ["", "S1", "-a", "_a", "a b", "a/b", "a*", "@service", "a" * 65,
                                 "é", "a\n", None, 5])
def test_bad_names_are_refused(bad):
    with pytest.raises(KeyError_) as info:
        keys.command_key(bad)  # type: ignore[arg-type]
    assert str(info.value) == f"session {bad!r} must match [a-z0-9][a-z0-9_-]{{0,63}}"


def test_name_edge_cases_accepted():
    for ok in ["a", "0", "a" * 64, "a-b_c", "9_-"]:
        assert keys.check_name(ok) == ok
    with pytest.raises(KeyError_, match="sensor 'Cam' must match"):
        keys.sensor_key("s1", "Cam")
    with pytest.raises(KeyError_, match="instance '' must match"):
        keys.service_token_key("")


@pytest.mark.parametrize("key, text", [
    ("x/p9/s1/cmd", "is not a pd-service session key"),
    ("pd/s1", "is not a pd-service session key"),
    ("pd", "is not a pd-service session key"),
    ("pd/p9/s1", "is not a pd-service session key"),
    ("pd/p9/s1/unknown", "unknown stream 'unknown' for the operator side"),
    ("pd/p9/s1/truth", "unknown stream 'truth' for the operator side"),
    ("robot/p9/s1/prediction", "unknown stream 'prediction' for the robot side"),
    ("pd/p9/s1/cmd/extra", "unknown stream 'cmd' for the operator side"),
    ("pd/p9/s1/sensor", "a sensor key is <root>/p<k>/<session>/sensor/<name>"),
    ("pd/p9/s1/sensor/a/b", "a sensor key is <root>/p<k>/<session>/sensor/<name>"),
    ("pd/p9/s1/sensor/A", "sensor 'A' must match"),
    ("pd/p9/S1/cmd", "session 'S1' must match"),
    ("pd/p9/@service/pd-a", "session '@service' must match"),
    ("pd/p9/*/cmd", "session '*' must match"),
    ("pd/@service/pd-a/status", "'@service' is not a partition chunk p<k>"),
    ("pd/s1/sensor/camera", "'s1' is not a partition chunk p<k>"),
    ("pd/p09/s1/cmd", "'p09' is not a partition chunk p<k>"),
    ("pd/p10000/s1/cmd", "'p10000' is not a partition chunk p<k>"),
    # another P: the chunk names a partition, not the session's
    ("pd/p201/s1/config", "session 's1' is in partition p9 of 64, not p201 (is PD_PARTITIONS"),
    ("robot/p8/s1/cmd", "session 's1' is in partition p9 of 64, not p8"),
])
def test_parse_refuses(p64, key, text):
    with pytest.raises(KeyError_) as info:
        parse_key(key)
    assert text in str(info.value)


@pytest.mark.parametrize("key", ["pd/s1/config", "pd/s1/status", "pd/s1/cmd", "pd/s1/prediction",
                                 "pd/s1/error"])
def test_layout_1_keys_are_refused_with_the_new_key(p64, key):
    assert keys.is_legacy_key(key)
    with pytest.raises(KeyError_) as info:
        parse_key(key)
    assert str(info.value) == keys.legacy_reason(key)
    assert "key layout 1" in str(info.value) and "'pd/p9/s1/config'" in str(info.value)


def test_legacy_wildcards_reach_layout_1_keys_only(p64):
    for wildcard, old in [(keys.LEGACY_CONFIGS, "pd/s1/config"), (keys.LEGACY_STATUS, "pd/s1/status")]:
        w = zenoh.KeyExpr(wildcard)
        assert w.intersects(zenoh.KeyExpr(old))
        assert [k for k in list(SESSION_KEYS) + SERVICE_KEYS if w.intersects(zenoh.KeyExpr(k))] == []
    for new in (keys.config_key("s1"), keys.sensor_key("s1", "camera"), "pd/@service/pd-a/status",
                "robot/s1/cmd"):
        assert not keys.is_legacy_key(new)


def test_twins(p64):
    assert keys.to_operator_side("robot/p9/s1/sensor/camera") == "pd/p9/s1/sensor/camera"
    assert keys.to_robot_side("pd/p9/s1/cmd") == "robot/p9/s1/cmd"
    with pytest.raises(KeyError_, match="has no operator-side twin"):
        keys.to_operator_side("robot/p9/s1/truth")
    with pytest.raises(KeyError_, match="has no robot-side twin"):
        keys.to_robot_side("pd/p9/s1/prediction")


def test_partition_count_bounds():
    assert keys.DEFAULT_PARTITIONS == 64 and keys.PARTITIONS_ENV == "PD_PARTITIONS"
    assert [keys.check_partitions(v) for v in (1, "256", " 4096 ")] == [1, 256, 4096]
    for bad in (0, 4097, -1, "x", "", True, 2.5):
        with pytest.raises(KeyError_, match="PD_PARTITIONS must be an integer from 1 to 4096"):
            keys.check_partitions(bad)
    assert keys.partition_of("s1", 1) == 0
    assert keys.parse_partition(keys.partition_chunk(4095)) == 4095


def test_partition_test_vectors():
    """protocol.md's table: edge cases of the name rule, '-' and '_', and both P."""
    vectors = doc_vectors()
    assert len(vectors) >= 8
    names_ = [v[0] for v in vectors]
    assert {"a", "s1"} <= set(names_) and any(len(n) == 64 for n in names_)
    assert any("-" in n for n in names_) and any("_" in n for n in names_)
    for name, h, k64, k256 in vectors:
        assert keys.fnv1a32(name.encode()) == h, name
        assert (keys.partition_of(name, 64), keys.partition_of(name, 256)) == (k64, k256), name
    assert keys.fnv1a32(b"") == 0x811C9DC5


# FNV-1a as protocol.md §3 describes it, in another language: offset basis 2166136261, for
# each byte XOR then multiply by 16777619 modulo 2^32 (Math.imul keeps the low 32 bits).
NODE_FNV = """
const names = JSON.parse(process.argv[1]);
function fnv1a32(name) {
  let h = 2166136261;
  for (const b of Buffer.from(name, "utf8")) {
    h = Math.imul(h ^ b, 16777619) >>> 0;
  }
  return h >>> 0;
}
console.log(JSON.stringify(names.map((n) => { const h = fnv1a32(n); return [n, h, h % 64, h % 256]; })));
"""


def test_partition_test_vectors_in_node():
    """An independent implementation (JavaScript, written from the doc's text) agrees."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node (Node.js) is not installed: the cross-language check of "
                    "protocol.md's FNV-1a vectors needs it")
    vectors = doc_vectors()
    out = subprocess.run([node, "-e", NODE_FNV, json.dumps([v[0] for v in vectors])],
                         capture_output=True, text=True, timeout=60, check=True).stdout
    assert [tuple(row) for row in json.loads(out)] == vectors


def test_key_error_is_a_value_error():
    assert issubclass(KeyError_, ValueError)
