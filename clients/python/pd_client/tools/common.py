"""Shared pieces of the command-line tools: Zenoh options, logging, signals, the clock."""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence

from pd_service.transport import DEFAULT_ENDPOINT, Transport

from ._base import connect


def add_tool_args(ap: argparse.ArgumentParser) -> None:
    """The flags every tool has: --progress, --verbose and the Zenoh group."""
    ap.add_argument("--progress", type=float, default=2.0,
                    help="seconds between progress lines on stderr (0: none)")
    ap.add_argument("--verbose", "-v", action="store_true")
    add_zenoh_args(ap)


def add_zenoh_args(ap: argparse.ArgumentParser) -> None:
    g = ap.add_argument_group("Zenoh")
    g.add_argument("--connect", "-e", dest="connect", action="append", metavar="ENDPOINT",
                   help=f"Zenoh endpoint to connect to (repeatable; default {DEFAULT_ENDPOINT})")
    g.add_argument("--mode", default="client", choices=("client", "peer"),
                   help="Zenoh mode (default: client)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (peer mode; repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 configuration file, read first")
    g.add_argument("--user", help="Zenoh user name (user/password authentication)")
    g.add_argument("--password", help="Zenoh password")


def open_transport(args: argparse.Namespace) -> Transport:
    endpoints: list[str] | None = args.connect
    if endpoints is None and not args.zenoh_config:
        endpoints = [DEFAULT_ENDPOINT]
    return connect(endpoints or [], args.mode, listen=args.listen,
                   config_file=args.zenoh_config, user=args.user, password=args.password)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


@contextlib.contextmanager
def signal_stop() -> Iterator[threading.Event]:
    """An Event set by SIGINT or SIGTERM (the tools then stop cleanly); the previous
    handlers are restored on exit (so ``main()`` can be called from Python too)."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)


def run_tool(build_parser: Callable[[], argparse.ArgumentParser],
             body: Callable[[argparse.ArgumentParser, argparse.Namespace, threading.Event], int],
             argv: Sequence[str] | None) -> int:
    """A tool's main: parse the flags, set up logging, run ``body(parser, args, stop)`` with
    ``stop`` set by SIGINT / SIGTERM."""
    with signal_stop() as stop:
        ap = build_parser()
        args = ap.parse_args(argv)
        setup_logging(args.verbose)
        return body(ap, args, stop)


def wait_until(t_ns: int, stop: threading.Event) -> bool:
    """Sleep until wall-clock time ``t_ns`` (time.time_ns()); False if ``stop`` was set."""
    while True:
        remaining = (t_ns - time.time_ns()) / 1e9
        if remaining <= 0:
            return not stop.is_set()
        if stop.wait(min(remaining, 0.5)):
            return False


def progress(tool: str, text: str) -> None:
    print(f"{tool}: {text}", file=sys.stderr, flush=True)


def fail(tool: str, err: BaseException | str, code: int = 1) -> int:
    print(f"{tool}: error: {err}", file=sys.stderr, flush=True)
    return code


def parse_session_arg(value: str) -> tuple[str, list[str] | None]:
    """``NAME`` or ``NAME:sensor,sensor`` -> (name, sensors or None)."""
    name, _, rest = value.partition(":")
    sensors = [s for s in rest.split(",") if s] if rest else None
    return name, sensors


def fmt_vec(values: Sequence[float], width: int = 8, prec: int = 3) -> str:
    return "[" + " ".join(f"{v:{width}.{prec}f}" for v in values) + "]"

