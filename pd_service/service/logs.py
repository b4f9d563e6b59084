"""Structured logs: one line per lifecycle event, ``key=value`` (default) or JSON.

``event(log, "session_created", session="s1", state="active")`` writes::

    ts=2025-01-01T12:00:00.123Z level=info event=session_created session=s1 state=active

Per-message events (a refused packet) are logged at DEBUG only; INFO carries lifecycle
events (start, ready, session created/replaced/removed/expired/taken over, member joined or
left, stop).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any

LOGGER_NAME = "pd_service.service"


def _fmt_value(v: Any) -> str:
    s = str(v)
    if s == "" or any(c in s for c in ' ="\n\t'):
        return json.dumps(s)
    return s


class KVFormatter(logging.Formatter):
    """``ts=... level=... event=... k=v ...``; fields come from ``record.fields``."""

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        ts += f".{int(record.msecs):03d}Z"
        fields: dict[str, Any] = getattr(record, "fields", None) or {"msg": record.getMessage()}
        parts = [f"ts={ts}", f"level={record.levelname.lower()}"]
        parts += [f"{k}={_fmt_value(v)}" for k, v in fields.items()]
        if record.exc_info:
            parts.append("exc=" + json.dumps(self.formatException(record.exc_info)))
        return " ".join(parts)


class JSONFormatter(logging.Formatter):
    """One JSON object per line with ``ts``, ``level`` and the event's fields."""

    def format(self, record: logging.LogRecord) -> str:
        obj: dict[str, Any] = {"ts": record.created, "level": record.levelname.lower()}
        obj.update(getattr(record, "fields", None) or {"msg": record.getMessage()})
        if record.exc_info:
            obj["exc"] = self.formatException(record.exc_info)
        return json.dumps(obj, default=str)


def setup_logging(level: str = "INFO", fmt: str = "kv") -> None:
    """Send ``pd_service`` logs to stderr, one line per record, in the chosen format."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JSONFormatter() if fmt == "json" else KVFormatter())
    root = logging.getLogger("pd_service")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def event(log: logging.Logger, name: str, level: int = logging.INFO, **fields: Any) -> None:
    """Log lifecycle event ``name`` with ``fields`` (cheap no-op when the level is off)."""
    if log.isEnabledFor(level):
        log.log(level, name, extra={"fields": {"event": name, **fields}})
