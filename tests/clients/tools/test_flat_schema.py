"""The JSON Schemas pd-record and pd-viz give their JSON channels, run through Lichtblick's own
parser (vendored: viewers/lichtblick_parse_json_schema.js, run with node): every channel is
read, where pydantic's schemas as they are lose 7 of 9 message types."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pd_client.tools.flat_schema import Inexpressible, flat_schema, schema_of_value
from pd_service.wire.schemas import schemas

PARSER = Path(__file__).parent / "viewers" / "lichtblick_parse_json_schema.js"
needs_node = pytest.mark.skipif(shutil.which("node") is None, reason="needs node (20+)")


def lichtblick(named: dict[str, dict]) -> dict[str, dict]:
    """name -> {"fields": [...]} or {"error": "..."}: Lichtblick's verdict on each schema."""
    out = subprocess.run(["node", str(PARSER)], input=json.dumps(
        [{"name": n, "schema": s} for n, s in named.items()]), capture_output=True, text=True,
        check=True, timeout=60).stdout
    return {r.pop("name"): r for r in json.loads(out)}


@needs_node
def test_lichtblick_reads_every_flattened_message_schema() -> None:
    raw = {n.removesuffix(".json"): s for n, s in schemas().items()}
    before = lichtblick(raw)
    refused = sorted(n for n, r in before.items() if "error" in r)
    assert refused == ["CameraFrame", "Command", "CommandEcho", "ErrorReport", "Measurement",
                       "PredictedPath", "Prediction", "SessionSpec", "SessionState",
                       "SessionStatus"]  # issue 45's finding, reproduced
    after = lichtblick({n: flat_schema(s) for n, s in raw.items()})
    assert {n: r.get("error") for n, r in after.items()} == dict.fromkeys(raw)
    for n, s in raw.items():
        assert after[n]["fields"] == list(s["properties"]), n  # every field kept, in order


@needs_node
def test_lichtblick_reads_the_schemas_in_a_recorded_mcap(tmp_path) -> None:
    from mcap.reader import make_reader

    from pd_client.tools.mcap_log import McapLog
    from pd_service.scenarios import get_scenario
    from pd_service.wire import Command, Prediction, encode, keys
    from pd_service.wire.camera import CameraFrame
    from pd_service.wire.truth import Truth

    spec = get_scenario("paper").spec("s1", 0)
    log = McapLog(tmp_path / "a.mcap")
    log.write_sample(keys.config_key("s1"), encode(spec), 1)
    log.write_sample(keys.command_key("s1"), encode(Command(session="s1", seq=1, step=3,
                                                            u=np.zeros(2))), 2)
    log.write_sample(keys.prediction_key("s1"), encode(Prediction(
        session="s1", seq=1, step=3, t_ns=0, x=np.zeros(4), P=np.eye(4), newest_step=None,
        made_ns=0)), 3)
    log.write_sample(keys.truth_key("s1"), encode(Truth(session="s1", step=3, t_ns=0,
                                                        x=np.zeros(4))), 4)
    log.write_sample(keys.sensor_key("s1", "camera"), b"\xc1", 5)  # -> the raw channel
    frame = CameraFrame(session="s1", seq=1, t_ns=7, data="/9j/4AAA", width=4, height=4,
                        center_x=0.0, center_y=0.0, scale=10.0)
    log.write_sample(keys.camera_key("s1"), encode(frame), 6)  # + its foxglove image copy
    log.close()
    with open(tmp_path / "a.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    got = {summary.schemas[c.schema_id].name: json.loads(summary.schemas[c.schema_id].data)
           for c in summary.channels.values() if c.message_encoding == "json"}
    assert sorted(got) == ["CameraFrame", "Command", "Prediction", "RawSample", "SessionSpec",
                           "Truth", "foxglove.CompressedImage"]
    verdict = lichtblick(got)
    assert all("error" not in r for r in verdict.values()), verdict
    image = verdict["foxglove.CompressedImage"]
    assert dict(zip(image["fields"], image["types"], strict=True))["data"] == "uint8[]"


def test_flat_schema_rules() -> None:
    s = {"type": "object", "title": "T", "$defs": {"D": {"type": "object", "properties": {
        "a": {"type": "integer", "minimum": 0}}}},
         "properties": {
             "opt": {"anyOf": [{"type": "integer"}, {"type": "null"}], "description": "d"},
             "ref": {"$ref": "#/$defs/D"},
             "kind": {"enum": ["put", "delete"]},
             "either": {"oneOf": [{"$ref": "#/$defs/D"},
                                  {"type": "object", "properties": {"b": {"type": "string"}}}]},
             "num": {"anyOf": [{"type": "integer"}, {"type": "number"}]}}}
    f = flat_schema(s)["properties"]
    assert f["opt"] == {"type": "integer", "description": "d"}
    assert f["ref"] == {"type": "object", "properties": {"a": {"type": "integer", "minimum": 0}}}
    assert f["kind"] == {"type": "string", "enum": ["put", "delete"]}
    assert set(f["either"]["properties"]) == {"a", "b"} and f["num"] == {"type": "number"}
    with pytest.raises(Inexpressible):
        flat_schema({"type": "object", "properties": {"m": {"type": "array", "items": {
            "type": "array", "items": {"type": "number"}}}}})
    with pytest.raises(Inexpressible):
        flat_schema({"type": "object", "properties": {"m": {"anyOf": [
            {"type": "string"}, {"type": "object"}]}}})
    assert schema_of_value({"a": 1, "b": [1.5, 2], "c": {"d": "x"}, "e": None}) == {
        "type": "object", "properties": {"a": {"type": "integer"},
                                         "b": {"type": "array", "items": {"type": "number"}},
                                         "c": {"type": "object", "properties": {"d": {"type": "string"}}}}}


@needs_node
def test_lichtblick_reads_pd_viz_json_schemas() -> None:
    pytest.importorskip("foxglove")
    from pd_client.tools.pd_viz import JSON_SCHEMAS

    got = lichtblick({s["title"]: s for s in JSON_SCHEMAS.values()})
    assert all("error" not in r for r in got.values()), got
    assert got["pd_viz.Prediction"]["fields"][:3] == ["step", "seq", "newest_step"]
