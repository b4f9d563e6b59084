"""Run ``python -m pd_service`` subprocesses on loopback for the integration tests.

Topology: the test process is a Zenoh peer listening on a free port; every daemon listens
on its own free port and connects to the test peer and to the daemons started before it.
Readiness and takeover are observed through liveliness tokens (events, not sleeps).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from pd_service.transport import ZenohTransport, zenoh_config
from pd_service.wire import ServiceStatus, SessionStatus, decode, keys

#: How long a query that must be answered may take: a loaded machine's daemon answers late,
#: not never (a get returns as soon as every queryable answered; only a lost answer waits it out).
ANSWER_TIMEOUT_S = 10.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Presence:
    """Tracks live daemon instances through their liveliness tokens."""

    def __init__(self, t: ZenohTransport) -> None:
        self.alive: set[str] = set()
        self.cond = threading.Condition()
        t.subscribe_liveliness(keys.ALL_SERVICES, self._on, history=True)

    def _on(self, key: str, alive: bool) -> None:
        inst = key.rsplit("/", 1)[-1]
        with self.cond:
            (self.alive.add if alive else self.alive.discard)(inst)
            self.cond.notify_all()

    def wait(self, instance: str, alive: bool = True, timeout: float = 20.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: (instance in self.alive) == alive, timeout)


class Daemon:
    """One ``python -m pd_service`` process; stderr goes to a log file in its state dir."""

    def __init__(self, instance: str, state_dir: Path, connect: list[str],
                 extra: list[str] | None = None) -> None:
        self.instance = instance
        self.state_dir = state_dir
        self.port = free_port()
        self.connect = connect
        self.extra = extra or []
        self.proc: subprocess.Popen | None = None
        self.log_path = state_dir.parent / f"{instance}.log"

    @property
    def endpoint(self) -> str:
        return endpoint(self.port)

    def start(self) -> Daemon:
        args = [sys.executable, "-m", "pd_service", "--instance", self.instance,
                "--state-dir", str(self.state_dir), "--listen", self.endpoint]
        for ep in self.connect:
            args += ["--connect", ep]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.pop("PD_SERVICE_CONFIG", None)
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(args + self.extra, stdout=self._log, stderr=self._log,
                                     env=env)
        return self

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int | None:
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else None
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(5)
        finally:
            self._log.close()

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def client(port: int) -> ZenohTransport:
    """The test's own Zenoh peer, listening on ``port``."""
    return ZenohTransport(zenoh_config(mode="peer", listen=[endpoint(port)], multicast=False))


def query_session_status(t: ZenohTransport, session: str) -> SessionStatus | None:
    for r in t.get(keys.status_key(session), timeout=ANSWER_TIMEOUT_S):
        if r.ok:
            return decode(r.payload, SessionStatus)
    return None


def query_service_status(t: ZenohTransport, instance: str) -> ServiceStatus | None:
    for r in t.get(keys.service_status_key(instance), timeout=ANSWER_TIMEOUT_S):
        if r.ok:
            return decode(r.payload, ServiceStatus)
    return None


def await_service_status(t: ZenohTransport, instance: str,
                         pred: Callable[[ServiceStatus], bool],
                         timeout: float = 10.0) -> ServiceStatus | None:
    """The instance's status once ``pred`` holds for it (asked again until ``timeout``: an
    instance applies a config the others already answered a moment later), else the last
    one it gave."""
    deadline = time.monotonic() + timeout
    while True:
        st = query_service_status(t, instance)
        if (st is not None and pred(st)) or time.monotonic() > deadline:
            return st
        time.sleep(0.05)


def sleep_until(t_ns: int) -> None:
    """Pace a publisher on the shared clock (the scenario's timeline, not a wait for an event)."""
    dt = (t_ns - time.time_ns()) / 1e9
    if dt > 0:
        time.sleep(dt)


@contextlib.contextmanager
def watched_daemon(instance: str, state_dir: Path) -> Iterator[Daemon]:
    """A started daemon, yielded once its liveliness token is seen by a peer of this
    process (which it connects to); stopped (SIGTERM) at the end."""
    port = free_port()
    with client(port) as peer:
        d = Daemon(instance, state_dir, [endpoint(port)]).start()
        try:
            assert Presence(peer).wait(instance, timeout=60.0), d.log()
            yield d
        finally:
            d.stop()
