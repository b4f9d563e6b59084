"""``pd-replay``: feed a recorded run (``pd-record --mcap``) into the estimator offline.

    pd-replay out/demo/run.mcap                          # same spec: must equal the daemon
    pd-replay run.mcap --spec tuned.json --out tuned.csv # another R / max_delay / backend
    pd-replay run.mcap --out replay.mcap                 # predictions as MCAP (+ CSV beside)

The recorded sensor packets and commands are given, in the order they arrived, to an
estimator built from the recorded SessionSpec (or ``--spec``, a SessionSpec JSON file: the
wire form, as in docs/schemas/SessionSpec.json; ``--session`` picks the session when a
recording holds several) by :func:`pd_service.backends.build`, with the daemon's
per-message handling: a Measurement's ``step`` (or ``floor((t_ns - epoch) / period)``) is its
sample step, it is windowed at the daemon's current step, a Command applies at its ``step``
(or ``step_of(issued_ns) + lead``).

When did the daemon handle each message, and when did it predict? Every recorded
Prediction says both: its ``step`` minus the recorded spec's ``lead`` is the daemon's current
step at that publish, and its ``counters`` count the sensor packets and commands the session
had handled (accepted or refused, by reason) until then. So the replay feeds, before the
n-th recorded prediction, exactly as many packets and commands as that prediction counts,
at that prediction's step, and then predicts at that step. An accepted packet is handled at
exactly that step (the daemon publishes in the same round); a refused one at that step or
slightly earlier, which gives the same refusal except for a packet stamped in the future
within the same interval (counted: ``diverged``).

With the recorded spec the replay reproduces each published x and P (the daemon batches
its linear arithmetic, equal to rounding): ``max |dx|`` and ``max |dP|`` are printed, and
the exit code is 3 if either exceeds ``--tolerance`` (default 1e-9). With another spec
the differences are the point: the printed summary (RMS error against the recorded truth,
mean variance) is the recorder's, for comparing filter settings on real data.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pd_service.backends import build
from pd_service.estimation import Estimator, PredictedState
from pd_service.intake import COMMAND_OUTCOMES, MAX_ABS_INPUT, MEASUREMENT_OUTCOMES, Intake
from pd_service.wire import (
    Prediction,
    SessionSpec,
    WireError,
    decode,
    encode,
)

from ..truth import Truth
from . import common
from .mcap_log import McapLog, Record, read_records, to_json
from .pd_record import _Pred, _SessionLog, finish
from .record_csv import DEFAULT_WARMUP

TOOL = "pd-replay"

#: The daemon's per-session counters of handled sensor packets / commands, by outcome.
SENSOR_REASONS = MEASUREMENT_OUTCOMES
COMMAND_REASONS = COMMAND_OUTCOMES


def handled(counters: dict[str, int], reasons: Iterable[str]) -> int:
    return sum(int(counters.get(r, 0)) for r in reasons)


class OfflineSession:
    """One session's estimator behind the daemon's own per-message rules
    (:class:`pd_service.intake.Intake`: decode, checks, step mapping, window at ``now``),
    outcomes counted by the daemon's reason names."""

    def __init__(self, spec: SessionSpec, max_abs: float = MAX_ABS_INPUT) -> None:
        self.spec = spec
        built = build(spec)
        self.est: Estimator = built.est
        self.intake = Intake(spec, self.est, built.nu, max_abs)
        self.counters: Counter[str] = Counter()

    def measurement(self, rec: Record, now: int) -> str:
        """Handle one sensor packet at the daemon's step ``now``; returns the outcome."""
        if rec.kind != "put":
            reason = "malformed"
        else:
            refusal = self.intake.measurement(rec.key, rec.payload, now)
            reason = "accepted" if refusal is None else refusal.reason
        self.counters[reason] += 1
        return reason

    def command(self, rec: Record, now: int) -> str:
        """Handle one command at the daemon's step ``now``; returns the outcome."""
        if rec.kind != "put":
            reason = "commands_malformed"
        else:
            refusal = self.intake.command(rec.key, rec.payload, now)
            reason = "commands_accepted" if refusal is None else refusal.reason
        self.counters[reason] += 1
        return reason

    def predict(self, now: int) -> PredictedState:
        return self.est.predict(now)


@dataclass
class SessionRecording:
    """One session's part of a recording, in arrival order."""

    session: str
    specs: list[SessionSpec] = field(default_factory=list)
    sensors: list[Record] = field(default_factory=list)
    commands: list[Record] = field(default_factory=list)
    predictions: list[tuple[Prediction, int]] = field(default_factory=list)  # (msg, log_ns)
    truth: list[Truth] = field(default_factory=list)


def load(path: str | Path) -> dict[str, SessionRecording]:
    """Group the records of an MCAP log by session (undecodable outputs are skipped)."""
    out: dict[str, SessionRecording] = {}
    for rec in read_records(path):
        sr = out.setdefault(rec.session, SessionRecording(rec.session))
        if rec.stream == "sensor":
            sr.sensors.append(rec)
        elif rec.stream == "cmd" and rec.key.startswith("pd/"):
            sr.commands.append(rec)
        elif rec.stream == "prediction":
            try:
                sr.predictions.append((decode(rec.payload, Prediction), rec.log_ns))
            except WireError:
                pass
        elif rec.stream == "truth":
            try:
                sr.truth.append(decode(rec.payload, Truth))
            except WireError:
                pass
        elif rec.stream == "config" and rec.kind == "put":
            try:
                spec = decode(rec.payload, SessionSpec)
            except WireError:
                continue
            if not sr.specs or sr.specs[-1] != spec:
                sr.specs.append(spec)
    return out


@dataclass
class ReplayResult:
    session: str
    spec: SessionSpec
    recorded: list[tuple[Prediction, int]]
    replayed: list[PredictedState]
    counters: dict[str, int]
    #: predictions at which the replay's counters differ from the daemon's (recorded spec)
    diverged: int = 0
    #: inputs the daemon had handled that the recording lacks (started late, or lost)
    missing_inputs: int = 0
    spec_changes: int = 0

    def max_abs_diff(self) -> tuple[float, float]:
        """max |x_replay - x_recorded| and max |P_replay - P_recorded| over the predictions
        with the same target step and dimension (nan if none)."""
        dx = dp = math.nan
        for (p, _), q in zip(self.recorded, self.replayed, strict=True):
            if p.step != q.step or p.x.shape != q.x.shape:
                continue
            ex = float(np.max(np.abs(np.asarray(q.x) - p.x)))
            ep = float(np.max(np.abs(np.asarray(q.P) - p.P)))
            dx = ex if math.isnan(dx) else max(dx, ex)
            dp = ep if math.isnan(dp) else max(dp, ep)
        return dx, dp


def replay(rec: SessionRecording, spec: SessionSpec | None = None) -> ReplayResult:
    """Replay one session (see the module docstring). ``spec``: an override (its session
    name is replaced by the recorded one); default the recorded spec."""
    if not rec.specs:
        raise WireError(f"session {rec.session!r}: the recording holds no SessionSpec "
                        "(pass --spec)")
    recorded_spec = rec.specs[0]
    use = (spec or recorded_spec).model_copy(update={"session": rec.session})
    off = OfflineSession(use)
    lead = recorded_spec.lead
    exact = spec is None
    # Predictions of the first spec only: a new spec restarts the daemon's session (seq 0).
    preds: list[tuple[Prediction, int]] = []
    for p, t in rec.predictions:
        if preds and p.seq <= preds[-1][0].seq:
            break
        preds.append((p, t))
    result = ReplayResult(rec.session, use, preds, [], {}, spec_changes=len(rec.specs) - 1)
    sensors, commands = rec.sensors, rec.commands
    fed_s = fed_c = 0
    for p, _ in preds:
        now = p.step - lead
        want_s = handled(p.counters, SENSOR_REASONS)
        want_c = handled(p.counters, COMMAND_REASONS)
        while fed_s < min(want_s, len(sensors)):
            off.measurement(sensors[fed_s], now)
            fed_s += 1
        while fed_c < min(want_c, len(commands)):
            off.command(commands[fed_c], now)
            fed_c += 1
        if fed_s < want_s or fed_c < want_c:  # the daemon handled more than was recorded
            result.missing_inputs = (want_s - fed_s) + (want_c - fed_c)
        result.replayed.append(off.predict(now))
        if exact and any(off.counters.get(r, 0) != p.counters.get(r, 0)
                         for r in SENSOR_REASONS + COMMAND_REASONS):
            result.diverged += 1
    result.counters = dict(off.counters)
    return result


def _prediction(res: ReplayResult, i: int) -> Prediction:
    q = res.replayed[i]
    rec = res.recorded[i][0]
    return Prediction(session=res.session, seq=i, step=q.step, t_ns=res.spec.time_of(q.step),
                      x=np.asarray(q.x, dtype=float), P=np.asarray(q.P, dtype=float),
                      newest_step=q.newest_step, made_ns=rec.made_ns, counters=res.counters)


def write_outputs(results: Sequence[ReplayResult], recs: dict[str, SessionRecording],
                  out: Path) -> dict[str, Path]:
    """CSV per session (pd-record's columns, truth matched by step) and, for an ``.mcap``
    ``out``, the replayed predictions on ``/replay/<s>/prediction``. Returns the CSVs."""
    mcap = McapLog(out) if out.suffix == ".mcap" else None
    csv_dir = out.parent
    paths: dict[str, Path] = {}
    for res in results:
        if out.suffix == ".csv" and len(results) == 1:
            path = out
        else:
            path = csv_dir / f"{out.stem}.{res.session}.csv"
        log = _SessionLog(res.session, path)
        for t in recs[res.session].truth:
            log.add_truth(t)
        for i, (_, log_ns) in enumerate(res.recorded):
            msg = _prediction(res, i)
            log.add_prediction(_Pred(msg, log_ns))
            if mcap is not None:
                data = to_json(encode(msg))
                if data is not None:
                    mcap.write(f"/replay/{res.session}/prediction", "Prediction", data, log_ns)
        log.close()
        paths[res.session] = path
    if mcap is not None:
        mcap.close()
    return paths


# --- command line ----------------------------------------------------------------------------

def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("mcap", help="recording written by pd-record --mcap")
    ap.add_argument("--spec", help="SessionSpec JSON file to replay with instead")
    ap.add_argument("--session", action="append", metavar="NAME",
                    help="session(s) to replay (default: every session in the file)")
    ap.add_argument("--out", help="output: FILE.csv or FILE.mcap (default: <mcap>.replay.csv "
                                  "beside the input)")
    ap.add_argument("--tolerance", type=float, default=1e-9,
                    help="with the recorded spec: largest |dx|, |dP| accepted (default 1e-9)")
    ap.add_argument("--warmup", type=int, default=DEFAULT_WARMUP,
                    help=f"target steps left out of the summary (default {DEFAULT_WARMUP})")
    ap.add_argument("--no-plots", action="store_true", help="do not render PNGs")


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    src = Path(args.mcap)
    if not src.exists():
        return common.fail(TOOL, f"{src}: no such file", 2)
    override = None
    if args.spec:
        try:
            override = SessionSpec.model_validate(json.loads(Path(args.spec).read_text()))
        except Exception as exc:
            return common.fail(TOOL, f"--spec {args.spec}: {exc}", 2)
    try:
        recs = load(src)
    except Exception as exc:
        return common.fail(TOOL, f"{src}: not a readable MCAP recording: {exc}", 2)
    names = args.session or sorted(recs)
    results = []
    worst = 0.0
    for name in names:
        rec = recs.get(name)
        if rec is None or not rec.predictions:
            common.progress(TOOL, f"session {name}: no recorded predictions")
            continue
        try:
            res = replay(rec, override)
        except WireError as exc:
            return common.fail(TOOL, exc, 2)
        results.append(res)
        dx, dp = res.max_abs_diff()
        worst = max(worst, dx if not math.isnan(dx) else 0.0, dp if not math.isnan(dp) else 0.0)
        print(f"{name}: {len(res.replayed)} predictions replayed; vs the daemon's: "
              f"max |dx| {dx:.3g}, max |dP| {dp:.3g}"
              + (f"; counters differ at {res.diverged} of them" if res.diverged else "")
              + (f"; {res.missing_inputs} inputs handled by the daemon not in the recording"
                 if res.missing_inputs else "")
              + (f"; {res.spec_changes} later spec change(s) not replayed"
                 if res.spec_changes else ""))
    if not results:
        return common.fail(TOOL, "nothing to replay")
    out = Path(args.out) if args.out else src.with_suffix(".replay.csv")
    paths = write_outputs(results, recs, out)
    if out.suffix == ".mcap":
        print(f"mcap: {out}")
    code = finish(paths, out.parent / f"{out.stem}-summary", args.warmup, plots=not args.no_plots)
    if override is None and worst > args.tolerance:
        return common.fail(TOOL, f"replay differs from the recording by {worst:.3g} "
                                 f"(> {args.tolerance:g})", 3)
    return code


CLI = common.Tool(TOOL, __doc__, _add_flags, _main, zenoh=False)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
