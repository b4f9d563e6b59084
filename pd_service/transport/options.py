"""One Zenoh option group and one config builder for every executable.

Every executable (``pd-service``, ``pd-link`` and the client tools) takes the same flags:

=====================  ==========================================================
``--mode``             ``peer``, ``client`` or ``router``
``--listen EP``        endpoint to listen on (repeatable)
``--connect EP``       endpoint to connect to (repeatable; ``-e`` for short)
``--zenoh-config F``   Zenoh JSON5 file, read first; the flags above override it
``--multicast``        multicast scouting on (``--no-multicast``: off)
``--user``             user name for Zenoh's user/password authentication
``--password``         its password (default ``$PD_ZENOH_PASSWORD``: prefer it)
=====================  ==========================================================

Only the defaults differ, by role (:data:`DAEMON`, :data:`LINK`, :data:`TOOL`). Each of mode,
listen and connect takes the role's default when its flag is absent, and only without
``--zenoh-config`` (with a file, the file decides what the flags do not say). Multicast
scouting is off by default everywhere: an instance finds exactly the peers it is told about.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, TypeVar

if TYPE_CHECKING:
    import zenoh

Mode = Literal["peer", "client", "router"]
T = TypeVar("T")
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: The environment variable every executable reads the Zenoh password from.
PASSWORD_ENV = "PD_ZENOH_PASSWORD"


@dataclass(frozen=True)
class Role:
    """The defaults of one kind of executable (used when no ``--zenoh-config`` is given)."""

    mode: Mode
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()


#: The daemon: a peer listening on loopback, needing no router.
DAEMON = Role("peer", listen=(DEFAULT_ENDPOINT,))
#: The link emulator: a peer on an ephemeral loopback port that connects to the daemon.
LINK = Role("peer", listen=("tcp/127.0.0.1:0",), connect=(DEFAULT_ENDPOINT,))
#: Client tools and the SDK: a client of the daemon's (or a router's) endpoint.
TOOL = Role("client", connect=(DEFAULT_ENDPOINT,))


@dataclass(frozen=True)
class ZenohOptions:
    """What the option group collects; None / empty means "not given" (role default)."""

    mode: Mode | None = None
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: Path | None = None
    multicast: bool | None = None
    user: str | None = None
    password: str | None = field(default=None, repr=False)

    def resolved(self, role: Role) -> ZenohOptions:
        """The options with the role's defaults filled in (none when a file is given). A
        client listens on nothing unless told: the role's listen default is a peer's (a
        daemon made a client of a router still bound 7447, and a second on the host failed)."""
        if self.config_file is not None:
            return self
        mode = self.mode or role.mode
        listen = self.listen or (() if mode == "client" else role.listen)
        return ZenohOptions(mode, listen,
                            self.connect or role.connect, None,
                            False if self.multicast is None else self.multicast,
                            self.user, self.password)

    def config(self, role: Role) -> zenoh.Config:
        """The ``zenoh.Config`` for ``role`` (see :func:`zenoh_config`)."""
        o = self.resolved(role)
        return zenoh_config(mode=o.mode, listen=o.listen, connect=o.connect,
                            multicast=o.multicast, file=o.config_file, user=o.user,
                            password=o.password)


def add_zenoh_args(ap: argparse.ArgumentParser, role: Role) -> None:
    """Add the Zenoh option group (the module's table) with ``role``'s defaults in the help."""
    g = ap.add_argument_group("Zenoh")
    g.add_argument("--mode", choices=("peer", "client", "router"),
                   help=f"Zenoh mode (default {role.mode}, or the --zenoh-config file's)")
    g.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; default "
                        f"{', '.join(role.listen) or 'none'})")
    g.add_argument("--connect", "-e", action="append", metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. a zenohd router (repeatable; default "
                        f"{', '.join(role.connect) or 'none'})")
    g.add_argument("--zenoh-config", dest="zenoh_config", metavar="FILE",
                   help="Zenoh JSON5 config file, read first; the other Zenoh flags override it")
    g.add_argument("--multicast", action=argparse.BooleanOptionalAction, default=None,
                   help="multicast scouting (default off)")
    g.add_argument("--user", help="Zenoh user name (user/password authentication; default "
                                  "the --zenoh-config file's, else none)")
    g.add_argument("--password", help=f"Zenoh password (default ${PASSWORD_ENV}; the flag is "
                                      "visible in the process list, the variable is not)")


def options_from_args(args: argparse.Namespace) -> ZenohOptions:
    """The :class:`ZenohOptions` given on a command line built with :func:`add_zenoh_args`."""
    return ZenohOptions(
        mode=args.mode, listen=tuple(args.listen or ()), connect=tuple(args.connect or ()),
        config_file=Path(args.zenoh_config) if args.zenoh_config else None,
        multicast=args.multicast, user=args.user,
        password=args.password if args.password is not None else os.environ.get(PASSWORD_ENV))


#: How long an executable retries a router or daemon that does not answer (``--connect-wait``,
#: s), and the backoff between attempts: first pause, longest pause (s).
CONNECT_WAIT_S = 10.0
RETRY_FIRST_S, RETRY_MAX_S = 0.25, 2.0


def add_connect_wait_arg(ap: argparse.ArgumentParser) -> None:
    """``--connect-wait S`` (read by :func:`open_retrying`)."""
    ap.add_argument("--connect-wait", type=float, default=CONNECT_WAIT_S, metavar="S",
                    help="retry a router or daemon that does not answer yet for S seconds, "
                         f"with backoff (default {CONNECT_WAIT_S:g}; 0: one attempt)")


def open_retrying(open_once: Callable[[], T], wait_s: float, stop: threading.Event | None,
                  retriable: Callable[[BaseException], bool],
                  report: Callable[[BaseException, float, float], None]) -> T:
    """``open_once()``, retried while it raises a ``retriable`` error, with backoff
    (RETRY_FIRST_S doubling to RETRY_MAX_S), for up to ``wait_s`` seconds or until ``stop``
    is set; ``report(error, pause, seconds left)`` before each pause. The last error is
    raised when the time is up (or ``stop`` set)."""
    deadline = time.monotonic() + wait_s
    delay = RETRY_FIRST_S
    while True:
        try:
            return open_once()
        except Exception as exc:
            remaining = deadline - time.monotonic()
            if not retriable(exc) or remaining <= 0:
                raise
            pause = min(delay, remaining)
            report(exc, pause, remaining)
            if stop is not None:
                if stop.wait(pause):
                    raise
            else:
                time.sleep(pause)
            delay = min(2 * delay, RETRY_MAX_S)


def error_text(exc: BaseException) -> str:
    """A Zenoh error as a user reads it: without the Rust source location zenoh appends
    (`` at /root/.cargo/.../orchestrator.rs:447.``)."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()


def zenoh_config(
    mode: str | None = None,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool | None = None,
    file: str | Path | None = None,
    user: str | None = None,
    password: str | None = None,
) -> zenoh.Config:
    """Build a zenoh.Config: ``file`` (JSON5) first, then the given arguments override it.

    Without a file the defaults are peer mode and multicast scouting off (explicit endpoints
    only, which is what loopback tests and a router deployment want).
    """
    import zenoh  # here, so that `import pd_client` does not load Zenoh

    if file and not Path(file).is_file():  # zenoh's own error names a Rust source line
        raise FileNotFoundError(f"Zenoh config file not found: {file}")
    conf = zenoh.Config.from_file(str(file)) if file else zenoh.Config()
    if mode is None and not file:
        mode = "peer"
    if multicast is None and not file:
        multicast = False
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if multicast is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    if user is not None and password is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return conf
