"""docs/schemas/ is exactly what `python -m pd_service.wire.schemas` writes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from pd_service.wire import MESSAGE_TYPES, SessionState
from pd_service.wire.camera import CameraFrame
from pd_service.wire.path import PredictedPath
from pd_service.wire.schemas import export, schemas, stale
from pd_service.wire.truth import Truth

REPO = Path(__file__).resolve().parents[2]
SCHEMA_DIR = REPO / "docs" / "schemas"


def test_committed_schemas_are_up_to_date():
    problems = stale(SCHEMA_DIR)
    assert problems == [], (
        f"stale JSON Schemas {problems}: run `python -m pd_service.wire.schemas` "
        "from the repository root")


def test_one_schema_per_message():
    assert sorted(schemas()) == sorted(f"{t.__name__}.json"
                                       for t in (*MESSAGE_TYPES, PredictedPath, SessionState, Truth,
                                                          CameraFrame))
    for name, schema in schemas().items():
        assert schema["additionalProperties"] is False, name
        assert schema["properties"]["v"]["const"] == 1, name


def test_export_and_check(tmp_path):
    (tmp_path / "Gone.json").write_text("{}")
    written = export(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in written)
    assert stale(tmp_path) == []
    path = tmp_path / "Measurement.json"
    data = json.loads(path.read_text())
    data["properties"].pop("z")
    path.write_text(json.dumps(data))
    (tmp_path / "Extra.json").write_text("{}")
    assert stale(tmp_path) == ["Measurement.json", "Extra.json"]


def test_command_line_check(tmp_path):
    cmd = [sys.executable, "-m", "pd_service.wire.schemas"]
    assert subprocess.run(cmd + ["--check", str(SCHEMA_DIR)]).returncode == 0
    assert subprocess.run(cmd + ["--check", str(tmp_path)], capture_output=True).returncode == 1
    assert subprocess.run(cmd + [str(tmp_path)], capture_output=True).returncode == 0
    assert stale(tmp_path) == []
