"""``pd-display``: a live terminal view of one session's predictions.

    pd-display --session paper                 # refreshes in place (ANSI), Ctrl-C to stop
    pd-display --session paper --once          # one frame after the first prediction
    pd-display --session paper --count 50      # stop after 50 predictions

Shows the newest prediction (target step, state, standard deviations from the covariance
diagonal), the newest prediction that can be checked against a simulator's truth (error and
error / sigma), latency (receipt time - made_ns), the display's counters and the service's
counters. Exit codes: 0 done, 1 no prediction within ``--timeout`` (with --once/--count;
the message says why, from the session's status: not running, e.g. expired, or running
but nothing reached this display), 2 bad command line.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time

import numpy as np

from pd_service.transport import Transport

from ..admin import Admin
from ..display import Display
from ..errors import PdClientError, SessionNotFound
from . import common

TOOL = "pd-display"
CLEAR = "\x1b[H\x1b[2J"


def _names(display: Display, n: int) -> list[str]:
    t = display.latest_truth()
    if t is not None and len(t.names) == n:
        return list(t.names)
    return [f"x{i}" for i in range(n)]


def _ms(us: float | None) -> str:
    return "-" if us is None else f"{us / 1e3:.1f} ms"


def render_frame(display: Display) -> str:
    """One text frame of the display's current state (no ANSI codes)."""
    st = display.stats()
    lines = [f"{TOOL} · session {display.session} · {time.strftime('%H:%M:%S')}",
             f"predictions {st.received}  missed {st.missed}  invalid {st.invalid}  "
             f"truth {st.truth_received}  service errors {st.errors}"]
    pred = display.latest()
    if pred is None:
        lines.append("waiting for predictions ...")
        return "\n".join(lines)
    n = pred.x.shape[0]
    names = _names(display, n)
    sd = np.sqrt(np.maximum(np.diag(pred.P), 0.0))
    newest = "-" if pred.newest_step is None else str(pred.newest_step)
    lines.append(f"latency last {_ms(st.latency_us_last)}  p50 {_ms(st.latency_us_p50)}  "
                 f"max {_ms(st.latency_us_max)}")
    lines.append("")
    lines.append(f"newest prediction: x(step {pred.step}), newest sample used: step {newest}")
    lines.append(f"  {'state':8}{'predicted':>12}{'sigma':>10}")
    for i, name in enumerate(names):
        lines.append(f"  {name:8}{pred.x[i]:12.4f}{sd[i]:10.4f}")
    pair = display.latest_pair()
    lines.append("")
    if pair is None:
        lines.append("checked against truth: (no truth yet for a predicted step)")
    else:
        p, t = pair
        psd = np.sqrt(np.maximum(np.diag(p.P), 0.0))
        err = p.x - t.x
        lines.append(f"checked against truth at step {p.step}:")
        lines.append(f"  {'state':8}{'predicted':>12}{'truth':>12}{'error':>10}{'error/σ':>9}")
        for i, name in enumerate(names):
            z = err[i] / psd[i] if psd[i] > 0 else math.inf
            lines.append(f"  {name:8}{p.x[i]:12.4f}{t.x[i]:12.4f}{err[i]:10.4f}{z:9.2f}")
    lines.append("")
    lines.append("covariance diagonal: " + " ".join(f"{v:.3g}" for v in np.diag(pred.P)))
    if pred.counters:
        lines.append("service counters: " + "  ".join(
            f"{k} {v}" for k, v in sorted(pred.counters.items())))
    if st.last_error:
        lines.append(f"last service error: {st.last_error}")
    return "\n".join(lines)


def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--session", default="paper", help="the session to show (default paper)")
    ap.add_argument("--no-truth", action="store_true", help="do not read the truth key")
    ap.add_argument("--once", action="store_true",
                    help="print one frame after the first prediction, then exit")
    ap.add_argument("--count", type=int, help="exit after this many predictions")
    ap.add_argument("--timeout", type=float, default=15.0,
                    help="with --once/--count: seconds to wait (default 15)")
    ap.add_argument("--interval", type=float, default=0.25, help="refresh period, s")
    ap.add_argument("--plain", action="store_true",
                    help="no ANSI screen clearing (default when stdout is not a terminal)")


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    if args.count is not None and args.count < 1:
        ap.error("--count must be >= 1")
    plain = args.plain or args.once or not sys.stdout.isatty()
    return common.run_on_transport(
        TOOL, args, lambda transport: _show(transport, args, plain, stop), error_code=2,
        stop=stop)


def why_silent(transport: Transport, session: str) -> str:
    """Why a session gave no prediction, as its status says: not running (never created,
    removed, expired), no service, or running (then the predictions were lost on the way)."""
    try:
        with Admin(transport) as admin:
            st = admin.status(session, timeout=2.0)
    except SessionNotFound:
        return (f"no instance runs session {session!r}: never created, deleted, or expired "
                "without traffic (create it: pd-admin create SPEC; a spec's expire_s = 0 "
                "never expires)")
    except PdClientError as exc:
        return str(exc)
    if st.state in ("expired", "removed"):
        return f"session {session!r} is {st.state} ({st.detail})"
    return (f"session {session!r} runs on {st.instance} ({st.state}, {st.published} "
            "predictions published): none reached this display (its connection, or the "
            "router's access control)")


def _show(transport: Transport, args: argparse.Namespace, plain: bool,
          stop: threading.Event) -> int:
    with Display(transport, args.session, truth=not args.no_truth) as display:
        if args.once:
            try:
                display.wait(1, timeout=args.timeout)
            except PdClientError as exc:
                return common.fail(TOOL, f"{exc}: {why_silent(transport, args.session)}")
            print(render_frame(display), flush=True)
            return 0
        deadline = time.monotonic() + args.timeout if args.count else None
        while not stop.is_set():
            frame = render_frame(display)
            print((frame if plain else CLEAR + frame) + ("\n" if plain else ""), flush=True)
            if args.count and display.stats().received >= args.count:
                return 0
            if deadline is not None and time.monotonic() > deadline:
                why = why_silent(transport, args.session) \
                    if not display.stats().received else "some were lost"
                return common.fail(TOOL, f"{display.stats().received} of {args.count} "
                                       f"predictions within {args.timeout} s: {why}")
            stop.wait(args.interval)
        return 0


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
