"""The in-memory and Zenoh transports behave alike (Zenoh over loopback, free ports)."""

from __future__ import annotations

import re
import socket
import threading

import pytest

from pd_service.transport import InMemoryBus, ZenohTransport, zenoh_config
from pd_service.transport.keyexpr import intersects


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    ("a", "b", "want"),
    [
        ("pd/*/sensor/*", "pd/s1/sensor/camera", True),
        ("pd/*/cmd", "pd/s1/sensor/camera", False),
        ("pd/*/cmd", "pd/@service/x", False),  # verbatim chunks never match wildcards
        ("pd/**", "pd/@service/x", False),
        ("pd/@service/*", "pd/@service/inst", True),
        ("pd/**", "pd", True),
        ("a/**/c", "a/b/b/c", True),
        ("a/*", "a/b/c", False),
    ],
)
def test_keyexpr_intersection(a: str, b: str, want: bool) -> None:
    assert intersects(a, b) is want
    assert intersects(b, a) is want


def exercise(t1, t2, wait) -> None:
    ids = (t1.session_id(), t2.session_id())  # Zenoh ids: lowercase hex, one per session
    assert ids[0] != ids[1] and all(re.fullmatch(r"[0-9a-f]{1,32}", i) for i in ids)
    got: list = []
    ev = threading.Event()

    def on(s):
        got.append((s.key, s.payload, s.kind))
        ev.set()

    sub = t1.subscribe("pd/*/sensor/*", on)
    t1.queryable("pd/*/status", lambda q: q.reply(q.key, b"status:" + (q.payload or b"")))
    t1.declare_token("pd/@service/a")
    live: list = []
    seen = threading.Event()

    def on_live(k: str, alive: bool) -> None:
        live.append((k, alive))
        seen.set()

    t2.subscribe_liveliness("pd/@service/*", on_live)
    wait()
    t2.put("pd/s1/sensor/cam", b"abc")
    assert ev.wait(5.0)
    assert got == [("pd/s1/sensor/cam", b"abc", "put")]
    replies = t2.get("pd/s1/status", payload=b"q", timeout=2.0)
    assert [(r.key, r.payload, r.ok) for r in replies] == [("pd/s1/status", b"status:q", True)]
    assert t2.get_liveliness("pd/@service/*", timeout=5.0) == ["pd/@service/a"]
    assert seen.wait(5.0)  # the subscriber's callback may come after the get's reply
    assert ("pd/@service/a", True) in live
    sub.close()
    ev.clear()
    t2.put("pd/s1/sensor/cam", b"again")
    assert not ev.wait(0.2)


def test_in_memory_transport() -> None:
    bus = InMemoryBus()
    with bus.transport() as t1, bus.transport() as t2:
        exercise(t1, t2, lambda: None)
    assert bus.subs == [] and bus.tokens == []


@pytest.mark.integration
def test_zenoh_transport_loopback() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohTransport(zenoh_config(listen=[ep])) as t1, \
            ZenohTransport(zenoh_config(mode="client", connect=[ep])) as t2:
        ready = threading.Event()
        # wait until t2 sees t1's declarations, by polling liveliness (an event, not a sleep)
        def wait():
            for _ in range(100):
                if t2.get_liveliness("pd/@service/*", timeout=0.2):
                    ready.set()
                    return
            raise AssertionError("peer never became visible")
        exercise(t1, t2, wait)


@pytest.mark.integration
def test_zenoh_drained_subscription_keeps_order_and_closes_while_waiting() -> None:
    """Samples reach the callback in order, whether the watcher hands one over (owner idle)
    or the owner drains them in batches; nothing is lost; close() returns while the watcher
    is blocked in recv."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohTransport(zenoh_config(listen=[ep])) as t1, \
            ZenohTransport(zenoh_config(mode="client", connect=[ep])) as t2:
        got: list[bytes] = []
        woke = threading.Event()
        d = t1.subscribe_drained("pd/*/sensor/*", lambda s: got.append(s.payload), woke.set)
        t1.declare_token("pd/@service/a")
        for _ in range(100):  # t2 sees t1's declarations (an event, not a sleep)
            if t2.get_liveliness("pd/@service/*", timeout=0.2):
                break
        t2.put("pd/s/sensor/x", b"0")
        assert woke.wait(5.0)  # the watcher handed the first one over
        assert got == [b"0"] and d.pending
        for i in range(1, 2001):
            t2.put("pd/s/sensor/x", str(i).encode())
        for _ in range(10_000):  # bounded: a broken drain fails instead of hanging
            if len(got) == 2001:
                break
            if d.pending:
                d.drain(64)  # small batches: the watcher takes turns with the owner
            else:
                woke.wait(0.05)
                woke.clear()
        assert got == [str(i).encode() for i in range(2001)]
        while d.pending:
            assert d.drain(64) == 0
        assert not d.pending  # the queue is empty: the watcher waits in recv
        d.close()  # undeclares while the watcher waits: it must return, not hang
        assert not d.pending or d.drain(10) == 0
