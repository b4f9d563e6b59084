"""The pd-record CSV format: its columns, reading a file back, summarising its accuracy.

One file per session, one row per prediction; columns::

    session, step, t_ns, seq, newest_step, made_ns, recv_ns, latency_us,
    x_<name>..., var_<name>... (diagonal of P), true_<name>..., err_<name>... (x - truth)

(:mod:`pd_client.tools.pd_record` writes them; :mod:`pd_client.tools.plots` draws them.)
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidMessage

#: Target steps skipped by :func:`summarize` by default (the estimate's start-up transient).
DEFAULT_WARMUP = 40
META_COLUMNS = ("session", "step", "t_ns", "seq", "newest_step", "made_ns", "recv_ns",
                "latency_us")


def read_csv(path: str | Path) -> tuple[list[str], dict[str, np.ndarray]]:
    """(state names, columns as float arrays; empty cells are NaN) of a pd-record CSV."""
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        try:
            header = next(reader)
        except StopIteration:
            raise InvalidMessage(f"{path}: empty file (no header)") from None
        rows = list(reader)
    if header[: len(META_COLUMNS)] != list(META_COLUMNS):
        raise InvalidMessage(f"{path}: not a pd-record CSV (header starts {header[:3]})")
    names = [c[2:] for c in header if c.startswith("x_")]
    cols: dict[str, np.ndarray] = {}
    for i, c in enumerate(header):
        if c == "session":
            continue
        cols[c] = np.array([float(r[i]) if i < len(r) and r[i] != "" else math.nan
                            for r in rows], dtype=np.float64)
    return names, cols


def summarize(csv_path: str | Path, warmup: int = DEFAULT_WARMUP) -> dict[str, Any]:
    """Accuracy of a recorded session, over the rows with truth and target step >= warmup.

    Returns a dict with ``rows`` (rows used), ``first_step``, ``last_step``, ``warmup``,
    ``states`` (names), and per state name s: ``rms_<s>`` (root mean square of prediction -
    truth), ``mean_var_<s>`` (mean predicted variance P[s, s]), ``max_abs_err_<s>``, and
    ``within_3sigma`` (fraction of all state errors with |err| <= 3 sqrt(var)). When a step
    was recorded twice the last row counts. Values are NaN when no row qualifies.
    """
    names, cols = read_csv(csv_path)
    steps = cols["step"]
    keep: dict[int, int] = {}
    for i, s in enumerate(steps):
        if not math.isnan(s):
            keep[int(s)] = i
    idx = np.array(sorted(i for s, i in keep.items() if s >= warmup), dtype=int)
    if names and idx.size:
        has_truth = ~np.isnan(cols[f"true_{names[0]}"][idx])
        idx = idx[has_truth]
    out: dict[str, Any] = {"rows": int(idx.size), "warmup": int(warmup), "states": names,
                           "first_step": int(steps[idx].min()) if idx.size else None,
                           "last_step": int(steps[idx].max()) if idx.size else None}
    inside = total = 0
    for name in names:
        err = cols[f"err_{name}"][idx]
        var = cols[f"var_{name}"][idx]
        if idx.size:
            out[f"rms_{name}"] = float(np.sqrt(np.mean(err**2)))
            out[f"mean_var_{name}"] = float(np.mean(var))
            out[f"max_abs_err_{name}"] = float(np.max(np.abs(err)))
            inside += int(np.sum(np.abs(err) <= 3 * np.sqrt(np.maximum(var, 0.0))))
            total += err.size
        else:
            out[f"rms_{name}"] = out[f"mean_var_{name}"] = out[f"max_abs_err_{name}"] = math.nan
    out["within_3sigma"] = inside / total if total else math.nan
    return out


def format_summary(summaries: dict[str, dict[str, Any]], states: Sequence[str] | None = None) -> str:
    """A side-by-side table: one column per session, RMS error and mean variance per state."""
    sessions = list(summaries)
    if not sessions:
        return "(no sessions)"
    if states is None:
        states = summaries[sessions[0]].get("states", [])
    width = max(14, *(len(s) + 2 for s in sessions))
    lines = [f"{'':22}" + "".join(f"{s:>{width}}" for s in sessions)]

    def row(label: str, key: str, fmt: str) -> None:
        cells = []
        for s in sessions:
            v = summaries[s].get(key)
            cells.append(f"{'-':>{width}}" if v is None or (isinstance(v, float) and math.isnan(v))
                         else f"{v:>{width}{fmt}}")
        lines.append(f"{label:22}" + "".join(cells))

    for name in states:
        row(f"RMS error {name}", f"rms_{name}", ".4f")
    for name in states:
        row(f"mean variance {name}", f"mean_var_{name}", ".4f")
    row("rows (after warm-up)", "rows", "d")
    return "\n".join(lines)
