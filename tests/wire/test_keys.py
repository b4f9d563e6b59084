"""Key expressions: building, parsing, and how Zenoh's wildcards match them."""

from __future__ import annotations

import pytest
from hypothesis import given, settings

from pd_service.wire import keys
from pd_service.wire.keys import KeyError_, ParsedKey, parse_key
from tests.wire.factories import names

zenoh = pytest.importorskip("zenoh")

SESSION_KEYS = {
    keys.config_key("s1"): ParsedKey("operator", "s1", "config"),
    keys.sensor_key("s1", "camera"): ParsedKey("operator", "s1", "sensor", "camera"),
    keys.command_key("s1"): ParsedKey("operator", "s1", "cmd"),
    keys.prediction_key("s1"): ParsedKey("operator", "s1", "prediction"),
    keys.error_key("s1"): ParsedKey("operator", "s1", "error"),
    keys.status_key("s1"): ParsedKey("operator", "s1", "status"),
    keys.robot_sensor_key("s1", "camera"): ParsedKey("robot", "s1", "sensor", "camera"),
    keys.robot_command_key("s1"): ParsedKey("robot", "s1", "cmd"),
    keys.truth_key("s1"): ParsedKey("robot", "s1", "truth"),
}
SERVICE_KEYS = [keys.service_token_key("pd-a"), keys.service_status_key("pd-a"),
                keys.link_rules_key("link-1"), keys.link_stats_key("link-1"),
                keys.ros2_status_key("r-1")]
WILDCARDS = {
    keys.ALL_CONFIGS: keys.config_key, keys.ALL_COMMANDS: keys.command_key,
    keys.ALL_PREDICTIONS: keys.prediction_key, keys.ALL_ERRORS: keys.error_key,
    keys.ALL_STATUS: keys.status_key, keys.ROBOT_ALL_COMMANDS: keys.robot_command_key,
}


def test_layout():
    assert list(SESSION_KEYS) == [
        "pd/s1/config", "pd/s1/sensor/camera", "pd/s1/cmd", "pd/s1/prediction", "pd/s1/error",
        "pd/s1/status", "robot/s1/sensor/camera", "robot/s1/cmd", "robot/s1/truth"]
    assert SERVICE_KEYS == ["pd/@service/pd-a", "pd/@service/pd-a/status",
                            "pd/@link/link-1/rules", "pd/@link/link-1/stats",
                            "pd/@ros2/r-1/status"]


@pytest.mark.parametrize("key", list(SESSION_KEYS))
def test_parse_session_keys(key):
    assert parse_key(key) == SESSION_KEYS[key]


@pytest.mark.parametrize("key", list(SESSION_KEYS) + SERVICE_KEYS)
def test_keys_are_canonical_zenoh_keys(key):
    assert str(zenoh.KeyExpr(key)) == key


@settings(max_examples=200, deadline=None)
@given(session=names, sensor=names)
def test_build_parse_round_trip(session, sensor):
    assert parse_key(keys.sensor_key(session, sensor)) == ParsedKey("operator", session, "sensor", sensor)
    assert parse_key(keys.robot_sensor_key(session, sensor)) == ParsedKey("robot", session, "sensor", sensor)
    for build in WILDCARDS.values():
        p = parse_key(build(session))
        assert p.session == session and p.sensor is None
    assert keys.to_robot_side(keys.sensor_key(session, sensor)) == keys.robot_sensor_key(session, sensor)
    assert keys.to_operator_side(keys.robot_command_key(session)) == keys.command_key(session)


def test_wildcards_match_their_keys_only():
    every = list(SESSION_KEYS) + SERVICE_KEYS
    for wildcard, build in WILDCARDS.items():
        w = zenoh.KeyExpr(wildcard)
        matched = [k for k in every if w.intersects(zenoh.KeyExpr(k))]
        assert matched == [build("s1")], wildcard
    for wildcard, want in [(keys.ALL_SENSORS, "pd/s1/sensor/camera"),
                           (keys.ROBOT_ALL_SENSORS, "robot/s1/sensor/camera")]:
        w = zenoh.KeyExpr(wildcard)
        assert [k for k in every if w.intersects(zenoh.KeyExpr(k))] == [want]
    # '@' chunks are verbatim: session wildcards never reach service keys, and the
    # service wildcards reach only them
    svc = zenoh.KeyExpr(keys.ALL_SERVICES)
    assert [k for k in every if svc.intersects(zenoh.KeyExpr(k))] == ["pd/@service/pd-a"]
    st_all = zenoh.KeyExpr(keys.all_service_status())
    assert [k for k in every if st_all.intersects(zenoh.KeyExpr(k))] == ["pd/@service/pd-a/status"]
    assert not zenoh.KeyExpr("pd/**").intersects(zenoh.KeyExpr("pd/@service/pd-a"))


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
    ("x/s1/cmd", "is not a pd-service session key"),
    ("pd/s1", "is not a pd-service session key"),
    ("pd", "is not a pd-service session key"),
    ("pd/s1/unknown", "unknown stream 'unknown' for the operator side"),
    ("pd/s1/truth", "unknown stream 'truth' for the operator side"),
    ("robot/s1/prediction", "unknown stream 'prediction' for the robot side"),
    ("pd/s1/cmd/extra", "unknown stream 'cmd' for the operator side"),
    ("pd/s1/sensor", "a sensor key is <root>/<session>/sensor/<name>"),
    ("pd/s1/sensor/a/b", "a sensor key is <root>/<session>/sensor/<name>"),
    ("pd/s1/sensor/A", "sensor 'A' must match"),
    ("pd/S1/cmd", "session 'S1' must match"),
    ("pd/@service/pd-a", "session '@service' must match"),
    ("pd/*/cmd", "session '*' must match"),
])
def test_parse_refuses(key, text):
    with pytest.raises(KeyError_) as info:
        parse_key(key)
    assert text in str(info.value)


def test_twins():
    assert keys.to_operator_side("robot/s1/sensor/camera") == "pd/s1/sensor/camera"
    assert keys.to_robot_side("pd/s1/cmd") == "robot/s1/cmd"
    with pytest.raises(KeyError_, match="has no operator-side twin"):
        keys.to_operator_side("robot/s1/truth")
    with pytest.raises(KeyError_, match="has no robot-side twin"):
        keys.to_robot_side("pd/s1/prediction")


def test_key_error_is_a_value_error():
    assert issubclass(KeyError_, ValueError)
