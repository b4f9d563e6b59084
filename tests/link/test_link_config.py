"""Configuration: parsing, units, netem defaults, first match, mapping, errors, round trip."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pd_service.errors import ConfigError
from pd_service.link.config import (
    DEFAULT_MAPPINGS,
    KeyMapping,
    decode_document,
    load_config,
    parse_config,
    parse_percent,
    parse_rate,
    parse_time_ns,
)
from pd_service.link.model import FourStateLoss, GilbertElliott, RandomLoss
from pd_service.transport.keyexpr import intersects
from pd_service.wire import keys

MS = 1_000_000
ROOT = Path(__file__).resolve().parents[2]

TOML = """
seed = 11
step_ms = 50

[[downlink]]
name = "camera"
match = "robot/*/*/sensor/camera"
delay = "10 steps"
jitter = "2ms"
distribution = "normal"
delay_correlation = "25%"
loss = { model = "gemodel", p = "1%", r = "30%" }
outage = [{ at = "5s", for = "2s", every = "30s" }]
outage_mode = "stall"

[[downlink]]
name = "everything-else"
delay = 30
loss = 2
loss_correlation = "25%"
reorder = "10%"
gap = 5
corrupt = "0.5%"
rate = "1mbit"
packet_overhead = 28

[[uplink]]
name = "cmd"
delay = "10 steps"
duplicate = 1
"""


def test_toml_example_parses_with_units():
    cfg = parse_config(decode_document(TOML))
    assert cfg.seed == 11 and cfg.step_ms == 50.0
    cam, rest = cfg.downlink
    assert cam.params.delay.delay_ns == 500 * MS
    assert cam.params.delay.jitter_ns == 2 * MS
    assert cam.params.delay.correlation == pytest.approx(0.25)
    assert cam.params.loss == GilbertElliott(0.01, 0.3, 1.0, 0.0)
    (w,) = cam.params.outages
    assert (w.start_ns, w.duration_ns, w.every_ns) == (5000 * MS, 2000 * MS, 30000 * MS)
    assert cam.params.outage_mode == "stall"
    assert rest.match == "**"
    assert rest.params.loss == RandomLoss(0.02, 0.25)
    assert rest.params.rate.bytes_per_s == 125_000 and rest.params.rate.overhead_bytes == 28
    assert (rest.params.reorder, rest.params.gap, rest.params.corrupt) == (0.1, 5, 0.005)
    assert cfg.uplink[0].params.duplicate == pytest.approx(0.01)


def test_json_is_accepted_too():
    doc = {"seed": 3, "downlink": [{"delay": "0.5s", "loss": "3%"}]}
    cfg = parse_config(decode_document(json.dumps(doc)))
    assert cfg.downlink[0].params.delay.delay_ns == 500 * MS
    assert cfg.downlink[0].params.loss == RandomLoss(0.03)
    assert cfg.downlink[0].name == "downlink-0"


def test_round_trip_through_normalised_json():
    cfg = parse_config(decode_document(TOML))
    again = parse_config(json.loads(cfg.to_json()))
    assert again == cfg


def test_first_match_wins_and_unmatched_is_none():
    cfg = parse_config({
        "downlink": [
            {"name": "cam", "match": "robot/*/*/sensor/camera", "delay": 1},
            {"name": "s1", "match": "robot/*/s1/**", "delay": 2},
        ],
        "uplink": [{"name": "only-a", "match": "pd/*/a/cmd"}],
    })  # fmt: skip
    assert cfg.rule_for("downlink", keys.robot_sensor_key("s1", "camera"))[1].name == "cam"
    assert cfg.rule_for("downlink", keys.robot_sensor_key("s1", "ranger")) == (1, cfg.downlink[1])
    assert cfg.rule_for("downlink", keys.robot_sensor_key("s2", "ranger")) is None
    assert cfg.rule_for("uplink", keys.command_key("a"))[1].name == "only-a"
    assert cfg.rule_for("uplink", keys.command_key("b")) is None


@pytest.mark.parametrize("pattern,key,expected", [
    ("robot/*/*/sensor/*", "robot/p9/s1/sensor/camera", True),
    ("robot/*/*/sensor/*", "robot/p9/s1/sensor/camera/x", False),
    ("robot/**", "robot/p9/s1/sensor/camera", True),
    ("robot/**/camera", "robot/camera", True),
    ("**", "pd/p1/s/cmd", True),
    ("pd/*/*/cmd", "pd/@service/x/cmd", False),  # '@' chunks are verbatim
    ("**", "pd/@link/x/rules", False),
    ("robot/*/*/sensor/cam$*", "robot/p1/s/sensor/camera2", True),
    ("robot/*/*/sensor/cam$*", "robot/p1/s/sensor/ranger", False),
    ("robot/p9/s1/sensor/camera", "robot/p9/s1/sensor/camera", True),
])  # fmt: skip
def test_keyexpr_matching(pattern, key, expected):
    assert intersects(pattern, key) is expected
    assert intersects(key, pattern) is expected


def test_default_mapping_uses_keys_module():
    down, echo, video, up = DEFAULT_MAPPINGS
    assert (down.subscribe, echo.subscribe, video.subscribe, up.subscribe) == (
        "robot/*/*/sensor/*", "robot/*/*/echo", "robot/*/*/camera", "pd/*/*/cmd")
    assert echo.direction == "downlink"
    assert echo.map_key(keys.robot_echo_key("s1")) == keys.echo_key("s1")
    assert down.map_key(keys.robot_sensor_key("s1", "camera")) == keys.sensor_key("s1", "camera")
    assert video.map_key(keys.robot_camera_key("s1")) == keys.camera_key("s1")
    assert up.map_key(keys.command_key("s1")) == keys.robot_command_key("s1")
    with pytest.raises(ValueError):
        down.map_key("robot/p9/BAD KEY/sensor/camera")


def test_template_mapping():
    cfg = parse_config({"mapping": [
        {"direction": "downlink", "subscribe": "lab/*/imu/*", "publish": "pd/{p1}/{1}/sensor/imu-{2}"},
        {"direction": "uplink", "subscribe": "pd/*/*/cmd", "publish": "robot"},
        {"direction": "downlink", "subscribe": "raw/*/*", "publish": "x/{1}/{2}"},
    ]})  # fmt: skip
    assert cfg.mappings[0].map_key("lab/r2/imu/front") == keys.sensor_key("r2", "imu-front")
    assert cfg.mappings[0] == KeyMapping(direction="downlink", subscribe="lab/*/imu/*",
                                        publish="pd/{p1}/{1}/sensor/imu-{2}")
    assert cfg.mappings[2].map_key("raw/R2/p") == "x/R2/p"  # {n}: the chunk as it is
    with pytest.raises(ValueError, match="session 'R2' must match"):  # {p<n>}: a session name
        cfg.mappings[0].map_key("lab/R2/imu/front")


@pytest.mark.parametrize("mapping,match", [
    ({"direction": "sideways", "subscribe": "a/*", "publish": "b/{1}"}, "direction"),
    ({"direction": "uplink", "subscribe": "a/*", "publish": "b/{2}"}, "has 1"),
    ({"direction": "uplink", "subscribe": "a/*", "publish": "b/{p2}/{1}"}, r"\{p2\} but 'a/\*' has 1"),
    ({"direction": "uplink", "subscribe": "a/**", "publish": "b/{1}"}, r"\*\*"),
    ({"direction": "uplink", "subscribe": "a/*", "publish": "b/*"}, "wildcards"),
    ({"direction": "uplink", "subscribe": "a//b", "publish": "robot"}, "empty chunk"),
    ({"direction": "uplink", "subscribe": "a/*", "publish": "robot", "x": 1}, "unknown"),
])  # fmt: skip
def test_bad_mapping(mapping, match):
    with pytest.raises(ConfigError, match=match):
        parse_config({"mapping": [mapping]})


def test_netem_loss_defaults():
    ge = parse_config({"downlink": [{"loss": {"model": "gemodel", "p": 5}}]}).downlink[0]
    assert ge.params.loss == GilbertElliott(0.05, 0.95, 1.0, 0.0)  # r = 1 - p, 1-h = 1, 1-k = 0
    st = parse_config({"downlink": [{"loss": {"model": "state", "p13": 5}}]}).downlink[0]
    assert st.params.loss == FourStateLoss(0.05, 0.95, 0.0, 1.0, 0.0)
    full = parse_config({"downlink": [{"loss": {
        "model": "state", "p13": "2%", "p31": "30%", "p32": "40%", "p23": "10%", "p14": "1%"}}]})
    assert full.downlink[0].params.loss == FourStateLoss(0.02, 0.3, 0.4, 0.1, 0.01)


@pytest.mark.parametrize("value,ns", [
    (50, 50 * MS), (0.5, 500_000), ("2s", 2_000 * MS), ("250us", 250_000), ("7ns", 7),
    ("1.5 ms", 1_500_000), ("3 steps", 150 * MS), ("1step", 50 * MS),
])  # fmt: skip
def test_time_units(value, ns):
    assert parse_time_ns(value, step_ms=50) == ns


@pytest.mark.parametrize("value", ["-5ms", "5 parsecs", "fast", True, None, [1], float("inf")])
def test_bad_times(value):
    with pytest.raises(ConfigError, match="t"):
        parse_time_ns(value, step_ms=50)


def test_steps_need_step_ms():
    with pytest.raises(ConfigError, match="step_ms"):
        parse_config({"downlink": [{"delay": "10 steps"}]})


@pytest.mark.parametrize("value,p", [(5, 0.05), ("5%", 0.05), ("0.5%", 0.005), (100, 1.0)])
def test_percent(value, p):
    assert parse_percent(value) == pytest.approx(p)


@pytest.mark.parametrize("value", [101, -1, "5 percent", True, "nan%"])
def test_bad_percent(value):
    with pytest.raises(ConfigError):
        parse_percent(value)


@pytest.mark.parametrize("text,bps,mps", [
    ("1mbit", 125_000, None), ("8kbit", 1000, None), ("125kbps", 125_000, None),
    ("100msg/s", None, 100), ("20pps", None, 20), ("1Gbit", 125_000_000, None),
])  # fmt: skip
def test_rates(text, bps, mps):
    r = parse_rate(text)
    assert (r.bytes_per_s, r.msgs_per_s) == (bps, mps)


@pytest.mark.parametrize("value", [1000, "1000", "10 furlongs", "0mbit"])
def test_bad_rates(value):
    with pytest.raises(ConfigError, match="rate"):
        parse_rate(value)


@pytest.mark.parametrize("doc,match", [
    ({"downlink": [{"dealy": 5}]}, "unknown field.*dealy"),
    ({"uplinks": []}, "unknown field"),
    ({"downlink": [{"jitter": 0, "distribution": "normal"}]}, "without jitter"),
    ({"downlink": [{"jitter": 5, "distribution": "cauchy"}]}, "distribution"),
    ({"downlink": [{"reorder": 5}]}, "delay"),
    ({"downlink": [{"delay": 5, "gap": 3}]}, "gap given without reorder"),
    ({"downlink": [{"loss_correlation": 5}]}, "without loss"),
    ({"downlink": [{"loss": {"model": "bernoulli", "p": 1}}]}, "model"),
    ({"downlink": [{"loss": {"model": "gemodel"}}]}, "needs 'p'"),
    ({"downlink": [{"loss": {"model": "gemodel", "p": 1, "q": 2}}]}, "unknown"),
    ({"downlink": [{"loss": {"model": "state", "p13": 60, "p14": 50}}]}, "p13 \\+ p14"),
    ({"downlink": [{"outage": {"at": 0}}]}, "'for'"),
    ({"downlink": [{"outage": [{"for": "1s", "every": "1s"}]}]}, "period"),
    ({"downlink": [{"outage_mode": "freeze"}]}, "outage_mode"),
    ({"downlink": [{"packet_overhead": 10}]}, "without rate"),
    ({"downlink": [{"shared": "yes"}]}, "true or false"),
    ({"downlink": [{"gap": 1.5, "reorder": 1, "delay": 1}]}, "integer"),
    ({"downlink": [{"name": "a"}, {"name": "a"}]}, "unique"),
    ({"downlink": [{"match": "robot/**x"}]}, "whole chunk"),
    ({"downlink": "camera"}, "list of rule tables"),
    ({"seed": "x"}, "seed"),
    ({"step_ms": 0}, "step_ms"),
    ([1, 2], "table"),
])  # fmt: skip
def test_errors_name_the_field(doc, match):
    with pytest.raises(ConfigError, match=match):
        parse_config(doc)


def test_decode_errors():
    with pytest.raises(ConfigError, match="JSON"):
        decode_document(b"{not json")
    with pytest.raises(ConfigError, match="TOML"):
        decode_document(b"[[downlink]\n")
    with pytest.raises(ConfigError, match="UTF-8"):
        decode_document(b"\xff\xfe")


def test_replacement_keeps_seed_and_refuses_new_mapping():
    base = parse_config({"seed": 5, "step_ms": 20})
    new = parse_config({"downlink": [{"delay": "2 steps"}]}, base=base)
    assert new.seed == 5 and new.downlink[0].params.delay.delay_ns == 40 * MS
    with pytest.raises(ConfigError, match="mapping"):
        parse_config({"mapping": [{"direction": "uplink", "subscribe": "x/*",
                                   "publish": "robot"}]}, base=base)  # fmt: skip
    same = parse_config({"mapping": [m.to_dict() for m in base.mappings]}, base=base)
    assert same.mappings == base.mappings


def test_load_config_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")


def test_paper_link_file():
    cfg = load_config(ROOT / "deploy" / "link-paper.toml")
    assert cfg.step_ms == 50
    cam = cfg.rule_for("downlink", keys.robot_sensor_key("paper", "camera"))[1]
    rng = cfg.rule_for("downlink", keys.robot_sensor_key("paper", "ranger"))[1]
    other = cfg.rule_for("downlink", keys.robot_sensor_key("paper", "imu"))[1]
    cmd = cfg.rule_for("uplink", keys.command_key("paper"))[1]
    assert cam.params.delay.delay_ns == 10 * 50 * MS
    assert rng.params.delay.delay_ns == 12 * 50 * MS
    assert cmd.params.delay.delay_ns == 10 * 50 * MS
    assert other.params.delay.delay_ns == 0
    # some loss on the sensor streams (the demo's link), none on the uplink or other streams
    assert cam.params.loss is not None and rng.params.loss is not None
    assert other.params.loss is None and cmd.params.loss is None
