"""``pd-record``: record predictions and truth to CSV, plot them, summarise the accuracy.

    pd-record --session paper --session paper-cam --out out/demo --idle-timeout 3

One CSV per session, ``<out>/<session>.csv``, one row per prediction, matched by step: a
prediction's target step k against the simulator's truth x(k) (columns empty when no truth
for k arrived). Columns::

    session, step, t_ns, seq, newest_step, made_ns, recv_ns, latency_us,
    x_<name>..., var_<name>... (diagonal of P), true_<name>..., err_<name>... (x - truth)

State names come from the truth messages (``p1, v1, p2, v2`` for the paper scenario), else
``x0, x1, ...``. On exit it prints a summary per session (RMS prediction error and mean
predicted variance per state, after a warm-up; :func:`summarize`), writes
``<out>/summary.json`` and, if matplotlib is installed (``pip install 'pd-client[plots]'``),
PNG plots like the paper's figures: ``<session>-states.png`` (predicted vs true state),
``<session>-error.png`` (prediction error with the predicted 2-sigma band),
``<session>-variance.png`` (predicted variance) and, with several sessions,
``compare-variance.png``. It stops on SIGINT/SIGTERM, after ``--duration`` seconds,
once every session has a matched row at step >= ``--until-step``, or after
``--idle-timeout`` seconds without data (once data has arrived).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pd_service.transport import Sample, Transport
from pd_service.wire import Prediction, keys

from .._base import try_decode
from .._queue import Inbox
from ..errors import InvalidMessage, PdClientError
from ..pairing import TruthPairs, prediction_error
from ..truth import Truth
from . import common
from .record_csv import DEFAULT_WARMUP, META_COLUMNS, format_summary, summarize

if TYPE_CHECKING:
    from .mcap_log import McapRecorder

TOOL = "pd-record"


@dataclass(frozen=True, slots=True)
class _Pred:
    msg: Prediction
    recv_ns: int


class _SessionLog:
    """Matches one session's predictions with truth by step and writes the CSV rows."""

    def __init__(self, session: str, path: Path, keep: int = 8192) -> None:
        self.session = session
        self.path = path
        self.keep = keep
        self.pairs = TruthPairs(keep)
        self.waiting: OrderedDict[int, _Pred] = OrderedDict()  # rows waiting for their truth
        self.names: list[str] | None = None
        self.rows = 0
        self.matched = 0
        self.last_matched_step: int | None = None
        self._file: io.TextIOWrapper | None = None
        self._writer: Any = None

    def add_prediction(self, p: _Pred) -> None:
        t = self.pairs.add_prediction(p.msg)
        if t is not None:
            self._write(p, t)
            return
        self.waiting[p.msg.step] = p
        self.waiting.move_to_end(p.msg.step)
        while len(self.waiting) > self.keep:
            self._write(self.waiting.popitem(last=False)[1], None)

    def add_truth(self, t: Truth) -> None:
        if self.names is None and t.names and len(t.names) == t.x.shape[0]:
            self.names = list(t.names)
        self.pairs.add_truth(t)
        p = self.waiting.pop(t.step, None)
        if p is not None:
            self._write(p, t)

    def _open(self, n: int) -> None:
        if self.names is None or len(self.names) != n:
            self.names = [f"x{i}" for i in range(n)]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        cols = list(META_COLUMNS)
        for prefix in ("x_", "var_", "true_", "err_"):
            cols += [prefix + name for name in self.names]
        self._writer.writerow(cols)

    def _write(self, p: _Pred, t: Truth | None) -> None:
        m = p.msg
        n = m.x.shape[0]
        if self._writer is None:
            self._open(n)
        var = np.diag(m.P)
        row: list[Any] = [self.session, m.step, m.t_ns, m.seq,
                          "" if m.newest_step is None else m.newest_step, m.made_ns, p.recv_ns,
                          f"{(p.recv_ns - m.made_ns) / 1e3:.1f}"]
        row += [repr(float(v)) for v in m.x] + [repr(float(v)) for v in var]
        err = None if t is None else prediction_error(m, t)
        if t is not None and err is not None:
            row += [repr(float(v)) for v in t.x] + [repr(float(v)) for v in err]
            self.matched += 1
            self.last_matched_step = max(self.last_matched_step or m.step, m.step)
        else:
            row += [""] * (2 * n)
        self._writer.writerow(row)
        self.rows += 1

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        """Write the predictions still waiting for truth (truth columns empty)."""
        for p in list(self.waiting.values()):
            self._write(p, None)
        self.waiting.clear()
        if self._file is not None:
            self._file.close()
            self._file = None


class Recorder:
    """Records the predictions and truth of one or more sessions to CSV files in ``out_dir``.

    Transport callbacks only queue what arrives; :meth:`poll` (call it in a loop, or let
    :meth:`run` do it) matches and writes rows. :meth:`close` flushes everything.
    """

    def __init__(self, transport: Transport, sessions: Sequence[str],
                 out_dir: str | Path) -> None:
        if not sessions:
            raise InvalidMessage("sessions: at least one session is required")
        self.transport = transport
        self.out_dir = Path(out_dir)
        self.logs: dict[str, _SessionLog] = {}
        for s in sessions:
            try:
                keys.check_name(s, "session")
            except keys.KeyError_ as exc:
                raise InvalidMessage(str(exc)) from None
            self.logs[s] = _SessionLog(s, self.out_dir / f"{s}.csv")
        self._inbox: Inbox[tuple[str, Sample]] = Inbox(100_000)
        self.last_receipt: float | None = None
        self.invalid = 0
        self._handles = []
        for s in sessions:
            self._handles.append(transport.subscribe(
                keys.prediction_key(s), lambda sample: self._inbox.push(("p", sample))))
            self._handles.append(transport.subscribe(
                keys.truth_key(s), lambda sample: self._inbox.push(("t", sample))))
        self._closed = False

    @property
    def paths(self) -> dict[str, Path]:
        return {s: log.path for s, log in self.logs.items()}

    def poll(self, timeout: float = 0.0) -> int:
        """Process what has arrived (waiting up to ``timeout`` s for the first item);
        returns the number of messages processed."""
        first = self._inbox.pop(timeout) if timeout > 0 else None
        items = ([first] if first is not None else []) + self._inbox.drain()
        for kind, sample in items:
            if sample.kind != "put":
                continue
            self.last_receipt = time.monotonic()
            session = keys.parse_key(sample.key).session
            log = self.logs.get(session)
            if log is None:
                continue
            if kind == "p":
                msg = try_decode(sample, Prediction)
                if msg is None or msg.session != session:
                    self.invalid += 1
                    continue
                log.add_prediction(_Pred(msg, sample.recv_ns))
            else:
                truth = try_decode(sample, Truth)
                if truth is None or truth.session != session:
                    self.invalid += 1
                    continue
                log.add_truth(truth)
        for log in self.logs.values():
            log.flush()
        return len(items)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for h in self._handles:
            h.close()
        self.poll()
        for log in self.logs.values():
            log.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- command line ----------------------------------------------------------------------------

def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--session", action="append", metavar="NAME",
                    help="session to record (repeatable; default: paper)")
    ap.add_argument("--out", default="out/record", help="output directory (default out/record)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")
    ap.add_argument("--until-step", type=int,
                    help="stop once every session has a matched row at this target step")
    ap.add_argument("--idle-timeout", type=float,
                    help="stop after this many seconds without data (once data arrived)")
    ap.add_argument("--warmup", type=int, default=DEFAULT_WARMUP,
                    help=f"target steps left out of the summary (default {DEFAULT_WARMUP})")
    ap.add_argument("--states", help="states in the printed summary, e.g. p1,p2 (default all)")
    ap.add_argument("--no-plots", action="store_true", help="do not render PNGs")
    ap.add_argument("--mcap", metavar="FILE",
                    help="also record every input and output of the sessions to this MCAP "
                         "file (pip install 'pd-client[viz]'; see pd_client.tools.mcap_log)")
    common.add_progress_arg(ap)


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    sessions = args.session or ["paper"]
    recorded: list[Recorder] = []

    def body(transport: Transport) -> int:
        try:
            recorder = Recorder(transport, sessions, args.out)
        except PdClientError as exc:
            return common.fail(TOOL, exc, 2)
        try:
            mcap = _open_mcap(transport, sessions, args.mcap) if args.mcap else None
        except ImportError:
            return common.fail(TOOL, "--mcap needs the mcap package: "
                                     "pip install 'pd-client[viz]'", 2)
        common.progress(TOOL, f"recording {', '.join(sessions)} to {args.out}")
        _record(recorder, args, stop)
        recorder.close()
        if mcap is not None:
            mcap.close()
            print(f"mcap: {mcap.path} ({mcap.log.messages} messages)")
        recorded.append(recorder)
        return 0

    code = common.run_on_transport(TOOL, args, body, stop=stop)
    if not recorded:
        return code
    recorder = recorded[0]
    return finish(recorder.paths, args.out, args.warmup,
                  args.states.split(",") if args.states else None, plots=not args.no_plots)


def _open_mcap(transport: Transport, sessions: Sequence[str], path: str) -> McapRecorder:
    from .mcap_log import McapRecorder

    return McapRecorder(transport, sessions, path)


def _record(recorder: Recorder, args: argparse.Namespace, stop: threading.Event) -> None:
    start = last_report = time.monotonic()
    while not stop.is_set():
        recorder.poll(timeout=0.1)
        now = time.monotonic()
        if args.duration is not None and now - start >= args.duration:
            break
        if args.until_step is not None and all(
                (lg.last_matched_step or -1) >= args.until_step for lg in recorder.logs.values()):
            break
        if (args.idle_timeout is not None and recorder.last_receipt is not None
                and now - recorder.last_receipt >= args.idle_timeout):
            common.progress(TOOL, f"no data for {args.idle_timeout:g} s: stopping")
            break
        if args.progress and now - last_report >= args.progress:
            last_report = now
            common.progress(TOOL, "rows " + ", ".join(
                f"{s} {lg.rows} ({lg.matched} with truth)" for s, lg in recorder.logs.items()))


def finish(paths: dict[str, Path], out_dir: str | Path, warmup: int = DEFAULT_WARMUP,
           states: Sequence[str] | None = None, plots: bool = True) -> int:
    """Summarise the CSVs, print the table, write summary.json and (optionally) PNGs."""
    summaries: dict[str, dict[str, Any]] = {}
    for session, path in paths.items():
        if not path.exists():
            common.progress(TOOL, f"session {session}: nothing recorded")
            continue
        summaries[session] = summarize(path, warmup)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summaries, indent=2, allow_nan=True) + "\n")
    print(f"summary (target steps >= {warmup}):")
    print(format_summary(summaries, states))
    for session, path in paths.items():
        if path.exists():
            print(f"csv {session}: {path}")
    if plots and summaries:
        try:
            from .plots import render
        except ImportError:
            print("PNG plots skipped: matplotlib is not installed "
                  "(pip install 'pd-client[plots]')")
        else:
            for png in render({s: paths[s] for s in summaries}, out):
                print(f"png: {png}")
    return 0 if summaries else 1


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
