"""One logging setup for every executable: one line per record on stderr, ``key=value``
(``kv``, the default) or JSON.

``event(log, "session_created", session="s1", state="active")`` writes::

    ts=2025-01-01T12:00:00.123Z level=info event=session_created session=s1 state=active

A plain record (``log.info("loss model", extra={"fields": {"rule": "cam"}})``) writes
``msg="loss model" rule=cam``; records of loggers outside ``pd_service`` (Zenoh's callback
errors come as ``zenoh.handlers``) also carry ``logger=NAME``.

Per-message events (a refused packet) are logged at DEBUG only; INFO carries lifecycle
events (start, ready, session created/replaced/removed/expired/taken over, member joined or
left, stop).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from typing import Any, Literal

LOGGER_NAME = "pd_service.service"
LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
LogFormat = Literal["kv", "json"]


def _fmt_value(v: Any) -> str:
    s = v if isinstance(v, str) else json.dumps(v, default=str, separators=(",", ":"))
    if s == "" or any(c in s for c in ' ="\n\t'):
        return json.dumps(s)
    return s


def _fields(record: logging.LogRecord) -> dict[str, Any]:
    """The record's fields: ``extra={"fields": {...}}``; ``msg`` unless it is an event."""
    given: dict[str, Any] = getattr(record, "fields", None) or {}
    out: dict[str, Any] = {}
    if not record.name.startswith("pd_service"):
        out["logger"] = record.name
    if "event" not in given:
        out["msg"] = record.getMessage()
    out.update(given)
    return out


class KVFormatter(logging.Formatter):
    """``ts=... level=... event=... k=v ...`` (logfmt)."""

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        ts += f".{int(record.msecs):03d}Z"
        parts = [f"ts={ts}", f"level={record.levelname.lower()}"]
        parts += [f"{k}={_fmt_value(v)}" for k, v in _fields(record).items()]
        if record.exc_info:
            parts.append("exc=" + json.dumps(self.formatException(record.exc_info)))
        return " ".join(parts)


class JSONFormatter(logging.Formatter):
    """One JSON object per line with ``ts`` (s since the epoch), ``level`` and the fields."""

    def format(self, record: logging.LogRecord) -> str:
        obj: dict[str, Any] = {"ts": record.created, "level": record.levelname.lower()}
        obj.update(_fields(record))
        if record.exc_info:
            obj["exc"] = self.formatException(record.exc_info)
        return json.dumps(obj, default=str)


def setup_logging(level: str = "INFO", fmt: str = "kv") -> None:
    """Send every log record (``pd_service`` and Zenoh's) to stderr, one line each, in the
    chosen format; ``level`` is one of :data:`LEVELS`."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JSONFormatter() if fmt == "json" else KVFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


def add_logging_args(ap: argparse.ArgumentParser, default_level: str | None = "INFO",
                     default_shown: str | None = None) -> None:
    """``--log-level``, ``--log-format``, ``-v/--verbose`` and ``--version``, the same for
    every executable (read the level with :func:`level_of`). A default of None leaves the
    value None when the flag is not given (the daemon layers settings); ``default_shown`` is
    then what the help names as the default."""
    shown = default_shown or default_level
    g = ap.add_argument_group("logs")
    g.add_argument("--log-level", dest="log_level", type=str.upper, choices=LEVELS,
                   default=default_level, help=f"least severe level logged (default {shown})")
    g.add_argument("--log-format", dest="log_format", choices=("kv", "json"),
                   default="kv" if default_level is not None else None,
                   help="kv: key=value lines (default); json: one JSON object per line")
    g.add_argument("--verbose", "-v", action="store_true", help="same as --log-level DEBUG")
    ap.add_argument("--version", action="version", version=f"%(prog)s {package_version()}",
                    help="print the version and exit")


def level_of(args: argparse.Namespace) -> str | None:
    """The log level a command line asks for: DEBUG with ``-v``, else ``--log-level``."""
    return "DEBUG" if args.verbose else args.log_level


def package_version() -> str:
    """pd-service's installed version ("unknown" when run from a source tree not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pd-service")
    except PackageNotFoundError:
        return "unknown"


def event(log: logging.Logger, name: str, level: int = logging.INFO, **fields: Any) -> None:
    """Log lifecycle event ``name`` with ``fields`` (cheap no-op when the level is off)."""
    if log.isEnabledFor(level):
        log.log(level, name, extra={"fields": {"event": name, **fields}})


def name_os_thread(name: str) -> None:
    """Give the calling thread a name that top, perf, py-spy and /proc show (Linux, at most
    15 characters; elsewhere nothing): the daemon's busy threads told apart in a profile."""
    try:
        with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as f:
            f.write(name[:15])
    except OSError:
        pass
