"""What every command-line tool shares: its skeleton (:class:`Tool`: parser, logging, stop
signal, main), the Zenoh option group with the TOOL role's defaults, progress lines and the
clock."""

from __future__ import annotations

import argparse
import contextlib
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from pd_service.logs import add_logging_args, level_of, setup_logging
from pd_service.transport import TOOL, Transport, add_zenoh_args, options_from_args
from pd_service.transport.options import add_connect_wait_arg, open_retrying

from .._base import connect_options
from ..errors import PdClientError, ServiceUnavailable

#: What a tool runs once its flags are read: ``body(parser, args, stop)`` -> exit code.
ToolBody = Callable[[argparse.ArgumentParser, argparse.Namespace, threading.Event], int]


@dataclass(frozen=True, slots=True)
class Tool:
    """A command-line tool's skeleton. Its parser: ``doc``'s first paragraph as the
    description and the rest (kept as written) as the epilog; the tool's own flags
    (``add_flags``); then the flags every tool has: ``--log-level`` / ``--log-format``
    (default WARNING), ``-v/--verbose`` (short for ``--log-level DEBUG``) and, with
    ``zenoh``, the Zenoh group (TOOL role: client mode, connect to tcp/127.0.0.1:7447) and
    ``--connect-wait`` (see :func:`open_transport`).
    Its :meth:`main` parses them, sets up logging and returns ``body(parser, args, stop)``,
    ``stop`` set by SIGINT / SIGTERM. A tool's module ends with::

        CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
        build_parser, main = CLI.build_parser, CLI.main
    """

    name: str
    doc: str
    add_flags: Callable[[argparse.ArgumentParser], None]
    body: ToolBody
    zenoh: bool = True

    def build_parser(self) -> argparse.ArgumentParser:
        doc = plain_text(self.doc)
        ap = argparse.ArgumentParser(prog=self.name, description=doc.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=doc.split("\n\n", 1)[1])
        self.add_flags(ap)
        add_logging_args(ap, default_level="WARNING")
        if self.zenoh:
            add_zenoh_args(ap, TOOL)
            add_connect_wait_arg(ap)
        return ap

    def main(self, argv: Sequence[str] | None = None) -> int:
        with signal_stop() as stop:
            ap = self.build_parser()
            args = ap.parse_args(argv)
            setup_logging(level_of(args) or "WARNING", args.log_format)
            return self.body(ap, args, stop)


def plain_text(doc: str) -> str:
    """A docstring as a terminal shows it: reStructuredText roles (:func:`x`), literals
    (``x``) and literal-block markers (``::``) made plain."""
    doc = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc)
    doc = re.sub(r"``([^`]+)``", r"\1", doc)
    return re.sub(r"::$", ":", doc, flags=re.M)


def add_ros2_args(ap: argparse.ArgumentParser, ros2_help: str) -> None:
    """``--ros2`` (described by ``ros2_help``), ``--domain-id`` and ``--namespace``: a tool
    that can speak ROS 2 in rmw_zenoh's format (read with ``pd_robot_sim.ros2_options``)."""
    ap.add_argument("--ros2", action="store_true", help=ros2_help)
    ap.add_argument("--domain-id", type=int, default=None,
                    help="with --ros2: ROS domain id (default: $ROS_DOMAIN_ID or 0)")
    ap.add_argument("--namespace", default="/",
                    help="with --ros2: the node's ROS namespace (default /)")


def add_progress_arg(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--progress", type=float, default=2.0,
                    help="seconds between progress lines on stderr (0: none)")


def open_transport(args: argparse.Namespace, stop: threading.Event | None = None,
                   tool: str = "pd-client") -> Transport:
    """The Zenoh transport of a :class:`Tool`'s command line. A router or daemon that does not
    answer yet (a tool started right after it) is retried with backoff for ``--connect-wait``
    seconds, each retry said on stderr; a bad configuration (a missing --zenoh-config file)
    is not retried. Raises :class:`ServiceUnavailable` (also when ``stop`` is set)."""
    wait_s = getattr(args, "connect_wait", 0.0)

    def report(exc: BaseException, pause: float, remaining: float) -> None:
        progress(tool, f"no answer yet ({exc}); retrying in {pause:.1f} s, for up to "
                       f"{remaining:.0f} s more (--connect-wait)")

    try:
        return open_retrying(lambda: connect_options(options_from_args(args)), wait_s, stop,
                             lambda exc: not isinstance(exc.__cause__, (OSError, ValueError)),
                             report)
    except ServiceUnavailable as exc:
        if wait_s > 0 and not isinstance(exc.__cause__, (OSError, ValueError)):
            raise ServiceUnavailable(f"{exc} (retried for {wait_s:g} s)") from exc
        raise


def run_on_transport(tool: str, args: argparse.Namespace, body: Callable[[Transport], int],
                     error_code: int = 1, stop: threading.Event | None = None) -> int:
    """Open the transport of the command line (:func:`open_transport`), return
    ``body(transport)`` and close it.

    A PdClientError opening it is reported and gives exit code 1; one raised by ``body``
    gives ``error_code``."""
    try:
        transport = open_transport(args, stop, tool)
    except PdClientError as exc:
        return fail(tool, exc)
    try:
        return body(transport)
    except PdClientError as exc:
        return fail(tool, exc, error_code)
    finally:
        transport.close()


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


def fmt_vec(values: Sequence[float] | np.ndarray, width: int = 8, prec: int = 3) -> str:
    """``[   1.000   -2.500]``: a vector on one line, fixed width."""
    return "[" + " ".join(f"{v:{width}.{prec}f}" for v in values) + "]"

