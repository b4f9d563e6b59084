"""pd-admin: manage the sessions of a pd-service deployment from the shell.

    pd-admin create paper.toml            # create the session(s) of a spec file
    pd-admin create fleet.yaml --replace  # ... replacing those that run already
    pd-admin replace paper.json           # create or replace
    pd-admin list                         # sessions per instance
    pd-admin show paper                   # status, counters, origin of one session
    pd-admin watch paper --interval 1     # ... again every second (Ctrl-C stops)
    pd-admin export paper > paper.json    # the spec a session runs (--format toml, yaml)
    pd-admin delete paper

A spec file is JSON (.json), TOML (.toml) or YAML (.yaml, .yml) and holds one SessionSpec
as its fields (docs/protocol.md, "SessionSpec"; arrays in the wire form
{"shape": [rows, cols], "data": [...]}: what `pd-admin export` writes), or several under
`sessions` (a list of them: a fleet). `expire_s` in a spec sets its lifetime without traffic
(0: never expires). A spec without `epoch_ns` starts its step 0 when the file is read (a
fixed epoch long past would make the service propagate the prior over every step since).
A field that breaks a rule is named: `paper.toml: session 1: SessionSpec.x0: ...`. Creating
many sessions goes at the service's config rate (40 at once, then 20 a second
by default): refused changes are sent again after a pause, up to --timeout per session.

Exit codes (a script can rely on them):
  0  done
  1  other error (e.g. Zenoh could not be opened)
  2  bad command line or spec file (the field is named)
  3  no pd-service instance reachable (none runs, or none connected)
  4  no such session
  5  the service refused the spec (the reason is printed: a budget, a rule)
  6  the router's access control refused this user (it may not change or see the session)
  7  no answer within --timeout
  8  create: the session runs already (use --replace)

Flags before COMMAND: the Zenoh group (--connect, --zenoh-config, ...), --timeout, logging.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from pd_service.transport import Transport
from pd_service.wire import SessionSpec, SessionStatus
from pd_service.wire.codec import validation_reason

from ..admin import Admin
from ..errors import (
    AccessDenied,
    PdClientError,
    ServiceUnavailable,
    SessionExists,
    SessionNotFound,
    SessionRefused,
    Timeout,
)
from . import common

TOOL = "pd-admin"

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_UNAVAILABLE = 0, 1, 2, 3
EXIT_NOT_FOUND, EXIT_REFUSED, EXIT_DENIED, EXIT_TIMEOUT, EXIT_EXISTS = 4, 5, 6, 7, 8

#: Exit code of each SDK error (the most specific class first).
_CODES: tuple[tuple[type[PdClientError], int], ...] = (
    (AccessDenied, EXIT_DENIED), (SessionRefused, EXIT_REFUSED),
    (SessionNotFound, EXIT_NOT_FOUND), (ServiceUnavailable, EXIT_UNAVAILABLE),
    (Timeout, EXIT_TIMEOUT), (SessionExists, EXIT_EXISTS))


class SpecFileError(ValueError):
    """A spec file that cannot be read or breaks a rule; the message names the field."""


def load_specs(path: Path, now_ns: int | None = None) -> list[SessionSpec]:
    """The SessionSpecs of a JSON, TOML or YAML file (one spec, or a list under
    ``sessions``); a spec without ``epoch_ns`` gets ``now_ns`` (default: the current time).
    Raises SpecFileError naming the file, the spec and the field."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SpecFileError(f"{path}: cannot read ({exc.strerror})") from None
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            doc: Any = tomllib.loads(text)
        elif suffix in (".yaml", ".yml"):
            doc = yaml.safe_load(text)
        elif suffix == ".json":
            doc = json.loads(text)
        else:
            raise SpecFileError(f"{path}: unknown format {suffix!r} (use .json, .toml, "
                                ".yaml or .yml)")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, yaml.YAMLError) as exc:
        raise SpecFileError(f"{path}: not valid {suffix[1:].upper()}: {exc}") from None
    if not isinstance(doc, dict):
        raise SpecFileError(f"{path}: expected a table of SessionSpec fields, or 'sessions'")
    items = doc["sessions"] if set(doc) == {"sessions"} else [doc]
    if not isinstance(items, list) or not items:
        raise SpecFileError(f"{path}: 'sessions' must be a non-empty list of specs")
    specs = []
    for i, item in enumerate(items):
        where = f"{path}: session {i + 1}" if len(items) > 1 else str(path)
        if not isinstance(item, dict):
            raise SpecFileError(f"{where}: expected a table of SessionSpec fields")
        try:
            specs.append(SessionSpec.model_validate({"epoch_ns": now_ns, **item}))
        except ValidationError as exc:
            raise SpecFileError(f"{where}: {validation_reason('SessionSpec', exc)}") from None
    names = [s.session for s in specs]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise SpecFileError(f"{path}: session {dupes[0]!r} is given twice")
    return specs


def _toml_value(v: Any) -> str:
    """One TOML value; tables inline (a spec's fields nest only a few levels)."""
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()
                               if x is not None) + "}"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return json.dumps(str(v))  # a JSON string is a TOML basic string


def spec_text(spec: SessionSpec, fmt: str) -> str:
    """``spec`` as a spec file of format ``fmt`` ("json", "toml" or "yaml") that
    load_specs reads back to the same spec."""
    doc = spec.model_dump(mode="json")
    if fmt == "yaml":
        return str(yaml.safe_dump(doc, sort_keys=False))
    if fmt == "toml":  # null has no TOML form: an absent optional field is the same
        return "".join(f"{k} = {_toml_value(v)}\n" for k, v in doc.items() if v is not None)
    return json.dumps(doc, indent=2) + "\n"


def status_lines(st: SessionStatus) -> list[str]:
    """A SessionStatus as ``field: value`` lines, counters sorted, one per line."""
    origin = st.origin if st.origin_step is None else f"{st.origin} (step {st.origin_step})"
    out = [f"session:   {st.session}", f"state:     {st.state}", f"instance:  {st.instance}",
           f"origin:    {origin}", f"now_step:  {st.now_step}", f"published: {st.published}",
           f"latency:   p50 {st.latency_p50_us:.0f} µs, p99 {st.latency_p99_us:.0f} µs"]
    if st.detail:
        out.append(f"detail:    {st.detail}")
    out.append("counters:")
    out += [f"  {k}: {v}" for k, v in sorted(st.counters.items())]
    return out


def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--timeout", type=float, default=10.0,
                    help="seconds to wait for the service (per session for create, replace "
                         "and delete; default 10)")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, what in (("create", "create the sessions of spec files (refused if one runs, "
                                  "unless --replace)"),
                       ("replace", "create or replace the sessions of spec files")):
        p = sub.add_parser(name, help=what, description=what)
        p.add_argument("files", nargs="+", type=Path, metavar="FILE",
                       help="spec file (.json, .toml, .yaml, .yml)")
        if name == "create":
            p.add_argument("--replace", action="store_true",
                           help="replace a session that runs already")
    sub.add_parser("list", help="the sessions every instance runs",
                   description="the sessions every instance runs")
    p = sub.add_parser("show", help="a session's status, counters and origin",
                       description="a session's status, counters and origin")
    p.add_argument("session")
    p.add_argument("--json", action="store_true", help="the SessionStatus as JSON")
    p = sub.add_parser("watch", help="show a session's status again and again",
                       description="show a session's status every --interval s until Ctrl-C")
    p.add_argument("session")
    p.add_argument("--interval", type=float, default=2.0, help="seconds between two (default 2)")
    p.add_argument("--count", type=int, default=0, help="stop after this many (default 0: never)")
    p = sub.add_parser("delete", help="remove sessions", description="remove sessions")
    p.add_argument("sessions", nargs="+", metavar="SESSION")
    p = sub.add_parser("export", help="print the spec a session runs (a spec file)",
                       description="print the spec a running session runs, as a spec file")
    p.add_argument("session")
    p.add_argument("--format", choices=("json", "toml", "yaml"), default="json",
                   help="output format (default json)")


def _create(admin: Admin, args: argparse.Namespace, stop: threading.Event) -> int:
    specs = [s for f in args.files for s in load_specs(f)]
    replace = args.command == "replace" or args.replace
    for spec in specs:
        if stop.is_set():
            return EXIT_ERROR
        if replace:
            st = admin.replace_session(spec, timeout=args.timeout, serve_spec=False)
        else:
            st = admin.open_session(spec, timeout=args.timeout, serve_spec=False)
        assert st is not None
        print(f"{spec.session}: {st.state} on {st.instance}", flush=True)
    return EXIT_OK


def _list(admin: Admin, args: argparse.Namespace, stop: threading.Event) -> int:
    admin.wait_for_service(timeout=args.timeout)
    for inst in sorted(admin.service_status(timeout=min(args.timeout, 2.0)),
                       key=lambda s: s.instance):
        for name in inst.sessions:
            print(f"{name}\t{inst.instance}")
    return EXIT_OK


def _show(admin: Admin, args: argparse.Namespace, stop: threading.Event) -> int:
    count = 0
    while True:
        st = admin.status(args.session, timeout=args.timeout)
        if getattr(args, "json", False):
            print(json.dumps(st.model_dump(mode="json")), flush=True)
        else:
            print("\n".join(status_lines(st)), flush=True)
        count += 1
        if args.command == "show" or count == args.count or stop.wait(args.interval):
            return EXIT_OK
        print(flush=True)


def _delete(admin: Admin, args: argparse.Namespace, stop: threading.Event) -> int:
    for name in args.sessions:
        admin.status(name, timeout=args.timeout)  # SessionNotFound: nothing to delete
        admin.close_session(name, timeout=args.timeout)
        print(f"{name}: removed", flush=True)
    return EXIT_OK


def _export(admin: Admin, args: argparse.Namespace, stop: threading.Event) -> int:
    spec = admin.get_spec(args.session, timeout=args.timeout)
    if spec is None:
        admin.status(args.session, timeout=args.timeout)  # the reason: not found, no service
        raise SessionNotFound(f"session {args.session!r} runs, but nobody answered for its spec")
    sys.stdout.write(spec_text(spec, args.format))
    return EXIT_OK


_COMMANDS: dict[str, Callable[[Admin, argparse.Namespace, threading.Event], int]] = {
    "create": _create, "replace": _create, "list": _list, "show": _show, "watch": _show,
    "delete": _delete, "export": _export}


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    if args.command in ("create", "replace"):  # a bad file fails before connecting
        try:
            for f in args.files:
                load_specs(f)
        except SpecFileError as exc:
            return common.fail(TOOL, exc, EXIT_USAGE)

    def body(transport: Transport) -> int:
        with Admin(transport) as admin:
            try:
                return _COMMANDS[args.command](admin, args, stop)
            except PdClientError as exc:
                code = next((c for cls, c in _CODES if isinstance(exc, cls)), EXIT_ERROR)
                return common.fail(TOOL, exc, code)

    return common.run_on_transport(TOOL, args, body)


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main

if __name__ == "__main__":
    sys.exit(main())
