"""Recorder: predictions matched with truth by step, CSV, summary, plots."""

from __future__ import annotations

import csv
import json
import math
import sys

import numpy as np
import pytest

from pd_client import Prediction, Truth
from pd_client.tools.pd_record import Recorder, finish
from pd_client.tools.record_csv import format_summary, read_csv, summarize
from pd_service.wire import encode, keys

NAMES = ["p1", "v1"]


def _pred(seq, step, x, var=(0.04, 0.01), session="s1"):
    return encode(Prediction(session=session, seq=seq, step=step, t_ns=step, x=np.array(x, float),
                             P=np.diag(var), newest_step=None, made_ns=0, counters={}))


def _truth(step, x, session="s1"):
    return encode(Truth(session=session, step=step, t_ns=step, x=np.array(x, float),
                        names=NAMES))


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_matches_by_step_in_either_order_and_flushes_unmatched(bus, tmp_path):
    pub = bus.transport()
    rec = Recorder(bus.transport(), ["s1"], tmp_path)
    pub.put(keys.prediction_key("s1"), _pred(0, 10, [1.0, 0.5]))   # prediction first
    pub.put(keys.truth_key("s1"), _truth(10, [1.5, 0.5]))
    pub.put(keys.truth_key("s1"), _truth(11, [2.0, 0.5]))          # truth first
    pub.put(keys.prediction_key("s1"), _pred(1, 11, [2.25, 0.5]))
    pub.put(keys.prediction_key("s1"), _pred(2, 12, [3.0, 0.5]))   # never gets truth
    pub.put(keys.prediction_key("s2"), _pred(0, 10, [9.0, 9.0], session="s2"))  # not recorded
    pub.put(keys.prediction_key("s1"), b"junk")
    assert rec.poll() == 6  # s2 is not subscribed
    assert rec.invalid == 1
    rec.close()
    rows = _rows(tmp_path / "s1.csv")
    assert [r["step"] for r in rows] == ["10", "11", "12"]
    assert float(rows[0]["err_p1"]) == -0.5 and float(rows[1]["err_p1"]) == 0.25
    assert rows[2]["true_p1"] == "" and rows[2]["x_p1"] == "3.0"
    assert float(rows[0]["var_p1"]) == 0.04 and rows[0]["newest_step"] == ""
    assert not (tmp_path / "s2.csv").exists()


def test_summary_numbers(tmp_path):
    path = tmp_path / "s.csv"
    errs = {10: (0.1, 0.0), 11: (-0.3, 0.0), 12: (0.2, 0.1), 13: (5.0, 5.0)}
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["session", "step", "t_ns", "seq", "newest_step", "made_ns", "recv_ns",
                    "latency_us", "x_p1", "x_v1", "var_p1", "var_v1", "true_p1", "true_v1",
                    "err_p1", "err_v1"])
        for step, (e1, e2) in errs.items():
            truth = ("", "", "", "") if step == 13 else (0.0, 0.0, e1, e2)
            w.writerow(["s", step, 0, step, "", 0, 0, 0, e1, e2, 0.04, 0.01, *truth])
        w.writerow(["s", 5, 0, 0, "", 0, 0, 0, 9, 9, 9, 9, 0, 0, 9, 9])  # before the warm-up
    s = summarize(path, warmup=10)
    assert s["rows"] == 3 and (s["first_step"], s["last_step"]) == (10, 12)
    assert s["rms_p1"] == pytest.approx(math.sqrt((0.01 + 0.09 + 0.04) / 3))
    assert s["rms_v1"] == pytest.approx(math.sqrt(0.01 / 3))
    assert s["mean_var_p1"] == pytest.approx(0.04) and s["max_abs_err_p1"] == pytest.approx(0.3)
    assert s["within_3sigma"] == 1.0
    empty = summarize(path, warmup=100)
    assert empty["rows"] == 0 and math.isnan(empty["rms_p1"])
    table = format_summary({"with-ranger": s, "camera-only": empty}, ["p1"])
    assert "RMS error p1" in table and "with-ranger" in table and "0.2160" in table
    names, cols = read_csv(path)
    assert names == ["p1", "v1"] and np.isnan(cols["true_p1"][3])


def test_not_a_record_csv(tmp_path):
    bad = tmp_path / "x.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="not a pd-record CSV"):
        summarize(bad)


def _record_some(bus, tmp_path, sessions=("s1",)):
    pub = bus.transport()
    rec = Recorder(bus.transport(), list(sessions), tmp_path)
    rng = np.random.default_rng(0)
    for k in range(60):
        for s in sessions:
            x = np.array([0.1 * k, 0.1])
            pub.put(keys.truth_key(s), _truth(k, x, session=s))
            pub.put(keys.prediction_key(s), _pred(k, k, x + 0.1 * rng.standard_normal(2),
                                                  session=s))
    rec.poll()
    rec.close()
    return rec


def test_finish_without_matplotlib_still_writes_csv_and_summary(bus, tmp_path, capsys,
                                                                monkeypatch):
    rec = _record_some(bus, tmp_path)
    monkeypatch.setitem(sys.modules, "pd_client.tools.plots", None)  # import fails
    assert finish(rec.paths, tmp_path, warmup=20) == 0
    out = capsys.readouterr().out
    assert "PNG plots skipped" in out and "RMS error p1" in out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["s1"]["rows"] == 40
    assert not list(tmp_path.glob("*.png"))


def test_plots_are_rendered(bus, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    rec = _record_some(bus, tmp_path, sessions=("a", "b"))
    assert finish(rec.paths, tmp_path, warmup=20) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == ["a-error.png", "a-states.png", "a-variance.png", "b-error.png",
                    "b-states.png", "b-variance.png", "compare-variance.png"]
    assert all((tmp_path / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)


def test_angle_errors_are_wrapped(bus, tmp_path):
    """A heading of +3.13 rad predicted against a true -3.13 rad is 0.023 rad off, not 6.26."""
    pub = bus.transport()
    rec = Recorder(bus.transport(), ["s1"], tmp_path)
    pub.put(keys.prediction_key("s1"), _pred(0, 5, [3.13, 1.0]))
    pub.put(keys.truth_key("s1"), encode(Truth(session="s1", step=5, t_ns=5,
                                               x=np.array([-3.13, 1.5]), names=["theta", "w"],
                                               angles=[0])))
    rec.poll()
    rec.close()
    [row] = _rows(tmp_path / "s1.csv")
    assert float(row["err_theta"]) == pytest.approx(6.26 - 2 * math.pi, abs=1e-12)
    assert float(row["err_w"]) == -0.5  # not an angle: not wrapped
