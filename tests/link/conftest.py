"""Fixtures for pd-link tests over real Zenoh on loopback (router-less, peer mode)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator

import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Collector:
    """Subscriber callback that records (receive ns, key, payload) and signals waiters."""

    def __init__(self) -> None:
        self.items: list[tuple[int, str, bytes]] = []
        self.ignore_prefix: bytes | None = None  # e.g. probes that may still straggle in
        self._cond = threading.Condition()

    def __call__(self, sample) -> None:
        item = (time.monotonic_ns(), str(sample.key_expr), sample.payload.to_bytes())
        if self.ignore_prefix is not None and item[2].startswith(self.ignore_prefix):
            return
        with self._cond:
            self.items.append(item)
            self._cond.notify_all()

    def wait_for(self, pred: Callable[[list], bool], timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not pred(self.items):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def clear(self) -> None:
        with self._cond:
            self.items.clear()


@pytest.fixture
def collector_factory() -> type[Collector]:
    return Collector


@pytest.fixture(scope="module")
def zenoh_pair() -> Iterator[tuple[object, object, str]]:
    """(test session listening on a free loopback port, relay transport connected to it,
    endpoint)."""
    zenoh = pytest.importorskip("zenoh")
    from pd_service.transport import zenoh_config
    from pd_service.transport.zenoh_transport import ZenohTransport

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    test_session = zenoh.open(zenoh_config(listen=[endpoint]))
    relay_transport = ZenohTransport(zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[endpoint]))
    try:
        yield test_session, relay_transport, endpoint
    finally:
        relay_transport.close()
        test_session.close()
