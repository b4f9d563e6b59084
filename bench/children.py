"""The child processes of a benchmark (routers, daemons, feeders, load generators): stopped
when the benchmark ends, however it ends.

A benchmark starts its children with :func:`popen` and calls :func:`stop_children_on_exit`
once in its ``main``: then SIGTERM and SIGINT raise SystemExit in the main thread (the
benchmark's ``finally`` blocks run: children stopped the orderly way), and at exit, after
an exception as after a normal end, every child still running gets SIGTERM, and SIGKILL
after ``STOP_WAIT_S``. (A SIGKILL of the benchmark itself cannot be caught: its children
then have to be stopped by hand.)
"""

from __future__ import annotations

import atexit
import contextlib
import signal
import subprocess
import time
from typing import Any

#: How long a child has after SIGTERM before it gets SIGKILL (s).
STOP_WAIT_S = 10.0

_children: list[subprocess.Popen] = []


def popen(args: list[str], **kw: Any) -> subprocess.Popen:
    """``subprocess.Popen(args, **kw)``, remembered: stopped at exit if still running."""
    p = subprocess.Popen(args, **kw)
    _children.append(p)
    return p


def stop_all(wait_s: float = STOP_WAIT_S) -> int:
    """SIGTERM to every child still running, then SIGKILL to those still running after
    ``wait_s``; returns how many were running."""
    alive = [p for p in _children if p.poll() is None]
    for p in alive:
        with contextlib.suppress(OSError):
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + wait_s
    for p in alive:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                p.kill()
            p.wait()
    _children[:] = [p for p in _children if p.poll() is None]
    return len(alive)


def _exit_on_signal(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def stop_children_on_exit() -> None:
    """In the benchmark's main thread, once: SIGTERM / SIGINT end it through SystemExit
    (its ``finally`` blocks run), and :func:`stop_all` runs at exit."""
    signal.signal(signal.SIGTERM, _exit_on_signal)
    signal.signal(signal.SIGINT, _exit_on_signal)
    atexit.register(stop_all)
