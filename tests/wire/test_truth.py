"""The Truth message from its documentation alone: the bytes a simulator in another language
would write (msgpack of the map in docs/protocol.md section 4) decode, and the committed
schema (docs/schemas/Truth.json) describes the same fields and rules."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest

from pd_service.wire import WireError, decode, encode, keys
from pd_service.wire.truth import Truth

SCHEMA = Path(__file__).resolve().parents[2] / "docs" / "schemas" / "Truth.json"
DOC_EXAMPLE = {"v": 1, "session": "s1", "step": 40, "t_ns": 1700000002000000000,
               "x": {"shape": [2], "data": [1.25, 0.5]}, "names": ["p1", "v1"], "angles": []}


def test_documented_map_decodes() -> None:
    t = decode(msgpack.packb(DOC_EXAMPLE), Truth)
    assert (t.session, t.step, t.t_ns, t.names) == ("s1", 40, 1700000002000000000, ["p1", "v1"])
    assert np.array_equal(t.x, [1.25, 0.5])
    assert keys.truth_key("s1").endswith("/s1/truth") and keys.truth_key("s1").startswith("robot/p")
    # defaults may be omitted; what Python writes decodes to the same message
    short = {k: v for k, v in DOC_EXAMPLE.items() if k not in ("names", "angles")}
    assert decode(msgpack.packb(short), Truth).names == []
    assert decode(encode(t), Truth) == t


@pytest.mark.parametrize("bad", [{"extra": 1}, {"step": -1}, {"names": ["a b"]},
                                 {"x": {"shape": [2], "data": [1.0, float("nan")]}}, {"v": 2}])
def test_documented_rules_refuse(bad: dict) -> None:
    with pytest.raises(WireError):
        decode(msgpack.packb({**DOC_EXAMPLE, **bad}), Truth)


def test_schema_lists_the_documented_fields() -> None:
    schema = json.loads(SCHEMA.read_text())
    assert schema["$id"] == "pd-service/v1/Truth.json" and schema["additionalProperties"] is False
    assert set(schema["properties"]) == set(DOC_EXAMPLE)
    assert set(schema["required"]) == {"session", "step", "t_ns", "x"}
    names = schema["properties"]["names"]
    assert names["items"]["pattern"] == "^[A-Za-z0-9_.-]{1,32}$" and names["maxItems"] == 64
