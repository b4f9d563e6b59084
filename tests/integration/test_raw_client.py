"""examples/raw_client.py, a client written from docs/protocol.md with raw zenoh + msgpack,
against a real daemon process over Zenoh on loopback: its predictions equal an offline
ObserverPredictor fed the packets the daemon accepted, and it imports nothing of the project."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pd_service.backends import build
from pd_service.estimation import ObserverPredictor
from pd_service.wire import Command, Measurement, Prediction, SessionSpec
from tests.service.procs import Daemon

pytestmark = pytest.mark.integration

CLIENT = Path(__file__).resolve().parents[2] / "examples" / "raw_client.py"
STEPS = 60


def test_raw_client_imports_only_zenoh_msgpack_and_the_standard_library() -> None:
    tree = ast.parse(CLIENT.read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "relative import"
            roots.add((node.module or "").split(".")[0])
    assert "zenoh" in roots and "msgpack" in roots
    assert roots - {"zenoh", "msgpack", "__future__"} <= set(sys.stdlib_module_names), roots


def _offline(spec: SessionSpec, packets: list[tuple[int, Measurement | Command]]
             ) -> ObserverPredictor:
    op = build(spec).est
    assert isinstance(op, ObserverPredictor)
    for k, msg in packets:
        if isinstance(msg, Measurement):
            assert msg.step is not None
            assert op.add_measurement(msg.sensor, msg.step, msg.z, now=k)
        else:
            assert msg.step is not None
            assert op.add_command(msg.step, msg.u, now=k)
    return op


def test_raw_client_against_the_daemon_equals_the_offline_observer(tmp_path: Path) -> None:
    d = Daemon("raw", tmp_path / "state", []).start()
    try:
        out = subprocess.run(
            [sys.executable, str(CLIENT), "--connect", d.endpoint, "--session", "raw",
             "--steps", str(STEPS), "--period-ms", "20"],
            capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr + d.log()
    finally:
        d.stop()
    records = [json.loads(line) for line in out.stdout.splitlines()]
    assert records[0] == {"ready": "raw"} and records[-1] == {"done": STEPS}
    spec = next(SessionSpec.model_validate(r["msg"]) for r in records if r.get("sent") == "spec")
    sent = [(r["at_step"], (Measurement if r["sent"] == "measurement" else Command)
             .model_validate(r["msg"])) for r in records if r.get("sent") in ("measurement",
                                                                              "command")]
    errors = [r["msg"] for r in records if r.get("got") == "error"]
    preds = [Prediction.model_validate(r["msg"]) for r in records if r.get("got") == "prediction"]

    # the three refusals it provokes: each reported, seq echoed, reason naming the field
    heads = sorted((e["seq"], e["reason"].split(": ", 1)[0]) for e in errors)
    assert len(heads) == 3, errors
    assert [h for _, h in heads] == ["Measurement.step", "Measurement.step", "Measurement.t_ns"]
    assert any("already has a sample" in e["reason"] for e in errors)
    assert any("older than the window" in e["reason"] for e in errors)
    refused = {e["seq"] for e in errors}
    accepted = [(k, m) for k, m in sent if m.seq not in refused]

    # the packets are sent in bursts, one per step: a prediction whose counters equal the
    # totals at the end of a burst was made from exactly the bursts up to it
    bounds: dict[tuple[int, int], int] = {}
    a = c = 0
    for i, (_, msg) in enumerate(accepted):
        a, c = (a + 1, c) if isinstance(msg, Measurement) else (a, c + 1)
        if i + 1 == len(accepted) or accepted[i + 1][0] != accepted[i][0]:
            bounds[(a, c)] = i + 1
    assert len(preds) >= STEPS
    checked = 0
    ops: dict[int, ObserverPredictor] = {}
    for p in preds:
        n = bounds.get((p.counters["accepted"], p.counters.get("commands_accepted", 0)))
        if n is None:
            continue
        op = ops.get(n) or ops.setdefault(n, _offline(spec, accepted[:n]))
        ref = op.predict(now=p.step - spec.lead)
        np.testing.assert_allclose(p.x, ref.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(p.P, ref.P, rtol=1e-9, atol=1e-9)
        checked += 1
    print(f"raw client: {checked} of {len(preds)} predictions checked")
    assert checked >= len(preds) // 2, (checked, len(preds))
    last = preds[-1]
    assert (last.counters["accepted"], last.counters["commands_accepted"]) == (a, c)
    assert last.counters["refused"] == 3
