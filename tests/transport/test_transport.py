"""The in-memory and Zenoh transports behave alike (Zenoh over loopback, free ports)."""

from __future__ import annotations

import contextlib
import re
import socket
import threading
import time
from collections.abc import Iterator

import pytest

from pd_service.transport import InMemoryBus, Sample, ZenohTransport, zenoh_config
from pd_service.transport.keyexpr import intersects


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    ("a", "b", "want"),
    [
        ("pd/*/*/sensor/*", "pd/p9/s1/sensor/camera", True),
        ("pd/*/*/cmd", "pd/p9/s1/sensor/camera", False),
        ("pd/*/*/cmd", "pd/@service/x", False),  # verbatim chunks never match wildcards
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

    sub = t1.subscribe("pd/*/*/sensor/*", on)
    t1.queryable("pd/*/*/status", lambda q: q.reply(q.key, b"status:" + (q.payload or b"")))
    t1.declare_token("pd/@service/a")
    live: list = []
    seen = threading.Event()

    def on_live(k: str, alive: bool) -> None:
        live.append((k, alive))
        seen.set()

    t2.subscribe_liveliness("pd/@service/*", on_live)
    wait()
    t2.put("pd/p9/s1/sensor/cam", b"abc")
    assert ev.wait(5.0)
    assert got == [("pd/p9/s1/sensor/cam", b"abc", "put")]
    replies = t2.get("pd/p9/s1/status", payload=b"q", timeout=2.0)
    assert [(r.key, r.payload, r.ok) for r in replies] == [("pd/p9/s1/status", b"status:q", True)]
    # the token's declaration travels on its own: once t2's liveliness subscriber has seen
    # it, a liveliness query from t2 must find it
    assert seen.wait(5.0)
    assert t2.get_liveliness("pd/@service/*", timeout=5.0) == ["pd/@service/a"]
    assert ("pd/@service/a", True) in live
    # declared keys: the receiver's and the sender's; puts on them arrive as any put,
    # also once the declarations are withdrawn (closing twice is harmless)
    mine = t1.declare_keys(["pd/p9/s1/sensor/cam", "pd/p16/s2/sensor/cam"])
    theirs = t2.declare_keys(["pd/p16/s2/sensor/cam"])
    for key, payload in (("pd/p16/s2/sensor/cam", b"declared"), ("pd/p9/s1/sensor/cam", b"half")):
        ev.clear()
        t2.put(key, payload)
        assert ev.wait(5.0) and got[-1] == (key, payload, "put")
    theirs.close()
    mine.close()
    mine.close()
    ev.clear()
    t2.put("pd/p16/s2/sensor/cam", b"undeclared")
    assert ev.wait(5.0) and got[-1] == ("pd/p16/s2/sensor/cam", b"undeclared", "put")
    for bad in (["pd/p9/*/sensor/cam"], ["pd/p9/s1/**"], ["pd//x"], [""], ["pd/$*x"]):
        with pytest.raises(ValueError, match="not an exact key"):
            t1.declare_keys(bad)
    sub.close()
    ev.clear()
    t2.put("pd/p9/s1/sensor/cam", b"again")
    assert not ev.wait(0.2)


def test_in_memory_transport() -> None:
    bus = InMemoryBus()
    with bus.transport() as t1, bus.transport() as t2:
        exercise(t1, t2, lambda: None)
        kept = t1.declare_keys(["pd/p35/s3/cmd"])
        assert t1.declared == [("pd/p35/s3/cmd",)] and t2.declared == []
        kept.close()
        assert t1.declared == []
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
        assert t1._declared == {} and t2._declared == {}  # withdrawn: put() no longer uses them


@contextlib.contextmanager
def listener_and_client() -> Iterator[tuple[ZenohTransport, ZenohTransport]]:
    """A listening transport and a client connected to it, once the client sees the
    listener's declarations (an event, not a sleep)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohTransport(zenoh_config(listen=[ep])) as t1, \
            ZenohTransport(zenoh_config(mode="client", connect=[ep])) as t2:
        t1.declare_token("pd/@service/a")
        for _ in range(100):
            if t2.get_liveliness("pd/@service/*", timeout=0.2):
                break
        yield t1, t2


def drain_watchers() -> int:
    """Drain watcher threads alive in this process."""
    return sum(th.name == "drain watcher" for th in threading.enumerate())


@pytest.mark.integration
def test_zenoh_drain_group_keeps_order_and_closes_while_waiting() -> None:
    """Samples reach their callback in order, whether the watcher hands one over (owner idle,
    armed) or the owner drains them in batches; nothing is lost; an owner that does not arm
    gets no hand-over; a member closed hands what it holds over first; close() returns
    while the watcher polls; one watcher thread however many members."""
    with listener_and_client() as (t1, t2):
        got: list[bytes] = []
        woke = threading.Event()
        before = drain_watchers()
        g = t1.drain_group(woke.set)
        m = g.add("pd/*/*/sensor/*", lambda s: got.append(s.payload))
        others = [g.add(f"pd/p{k}/*/sensor/*", lambda s: None) for k in range(16)]
        assert drain_watchers() == before + 1
        assert g.drain(10) == 0  # parked at first: the owner looks once
        t2.put("pd/p2/s/sensor/-1", b"-1")
        for _ in range(500):  # not armed: nobody hands it over, it waits for the owner
            if got:
                break
            g.drain(10)
            assert not woke.wait(0.01)
        assert got == [b"-1"]
        got.clear()
        # the drain builds its Sample as a plain tuple: every field, defaults included
        whole: list[Sample] = []
        m2 = g.add("pd/*/*/cmd", whole.append)
        t2.put("pd/p2/s/cmd", b"c")
        for _ in range(500):
            if g.drain(10) and whole:
                break
            time.sleep(0.01)
        (s,) = whole
        assert type(s) is Sample and len(s) == len(Sample._fields)
        assert s._replace(recv_ns=0, recv_mono_ns=0) == Sample("pd/p2/s/cmd", b"c", "put", 0, 0)
        seen = threading.Event()  # a plain subscriber: once it has the sample, so has m2
        t1.subscribe("pd/*/*/cmd", lambda s: seen.set() if s.payload == b"held" else None)
        t2.put("pd/p2/s/cmd", b"held")
        assert seen.wait(5.0)
        m2.close()  # closing a member hands over what its queue holds
        assert whole[1].payload == b"held"
        for o in others[8:]:
            o.close()
        g.arm()
        t2.put("pd/p2/s/sensor/x", b"0")
        assert woke.wait(5.0)  # the watcher handed the first one over
        assert got == [b"0"]
        for i in range(1, 2001):
            t2.put("pd/p2/s/sensor/x", str(i).encode())
        for _ in range(10_000):  # bounded: a broken drain fails instead of hanging
            if len(got) == 2001:
                break
            if not g.drain(64):  # small batches; empty: the watcher takes a turn
                woke.clear()
                g.arm()
                woke.wait(0.05)
        assert got == [str(i).encode() for i in range(2001)]
        assert g.drain(64) == 0
        g.arm()
        g.close()  # while the watcher polls: it must return, not hang
        assert g.drain(10) == 0
        assert m is not None


# ---------------------------------------------------------------- sender caches ----------

def test_in_memory_cached_publisher_is_recovered() -> None:
    bus = InMemoryBus()
    snd, rcv = bus.transport(), bus.transport()
    cam = snd.publisher("pd/p2/s/sensor/cam", cache=3)
    plain = snd.publisher("pd/p2/s/sensor/ranger")
    for i in range(5):
        cam.put(f"c{i}".encode())
        plain.put(f"r{i}".encode())
    snd.put("pd/p2/s/cmd", b"not cached")
    got: list = []
    h = rcv.read_back("pd/*/*/sensor/*", got.append, max_samples=2)
    # the last max_samples of each cached publisher, oldest first; plain puts keep nothing
    assert [(s.key, s.payload, s.recovered) for s in got] == \
        [("pd/p2/s/sensor/cam", b"c3", True), ("pd/p2/s/sensor/cam", b"c4", True)]
    got.clear()
    cam2 = snd.publisher("pd/p35/t/sensor/cam", cache=3)  # a later one is watched
    cam2.put(b"x")
    assert got == []  # declared with an empty cache, and live samples are not recovered
    cam.close()  # a closed publisher's cache is gone
    got2: list = []
    rcv.read_back("pd/*/*/sensor/*", got2.append, max_samples=10)
    assert [s.payload for s in got2] == [b"x"]
    h.close()


@pytest.mark.integration
def test_zenoh_cached_publisher_is_recovered_at_once_and_when_it_joins_late() -> None:
    """Pins zenoh-ext 1.10's cache layout (<key>/@adv/pub/..., '_max'): read at once from a
    connected sender, and from one that connects only after ``read_back`` was declared; each
    cache read is reported by ``answered``, a cache that never replies (a stalled sender) is
    not."""
    p1, p2 = free_port(), free_port()
    a = b = c = None
    try:
        a = ZenohTransport(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{p1}"],
                                        multicast=False))
        pub = a.publisher("pd/p2/s/sensor/cam", cache=4)
        for i in range(6):
            pub.put(f"m{i}".encode())
        # a stalled sender's cache: its token and queryable are there, no reply ever comes
        stalled = f"pd/p3/q/sensor/x/@adv/pub/{a.session.info.zid()}/99/_"
        held_queries: list = []  # kept: a query dropped would end at once
        silent = [a.session.declare_queryable(stalled, held_queries.append),
                  a.session.liveliness().declare_token(stalled)]
        # c: a sender whose peer (b, on p2) is not there yet; it keeps retrying
        c = ZenohTransport(zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{p2}"],
                                        multicast=False, listen=[]))
        pub_c = c.publisher("pd/p16/u/sensor/ranger", cache=4)
        other = c.publisher("pd/p16/u/cmd", cache=4)  # not matched by pd/*/*/sensor/*
        for i in range(2):
            pub_c.put(f"r{i}".encode())
            other.put(b"no")
        b = ZenohTransport(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{p2}"],
                                        connect=[f"tcp/127.0.0.1:{p1}"], multicast=False))
        got: list = []
        cond = threading.Condition()

        def on(s) -> None:
            with cond:
                got.append((s.key, s.payload, s.recovered))
                cond.notify_all()

        for _ in range(100):  # the routes to a's cache: wait on its token (an event)
            if b.get_liveliness("pd/p2/s/sensor/*/@adv/pub/**", timeout=0.5):
                break
        answered: list[str] = []

        def on_answered(key: str) -> None:
            with cond:
                answered.append(key)
                cond.notify_all()

        h = b.read_back("pd/*/*/sensor/*", on, max_samples=3, timeout=1.0, answered=on_answered)
        at_once = list(got)
        assert "pd/p2/s/sensor/cam" in answered  # before read_back returned
        # a's cache was read before read_back returned: its last 3, oldest first (c's may come
        # before or after them, depending on when c reached b)
        assert [x for x in at_once if x[0] == "pd/p2/s/sensor/cam"] == \
            [("pd/p2/s/sensor/cam", f"m{i}".encode(), True) for i in (3, 4, 5)]
        with cond:
            assert cond.wait_for(lambda: len(got) >= 5, timeout=30), got
        rest = sorted(x for x in got if x[0] != "pd/p2/s/sensor/cam")
        assert rest == [("pd/p16/u/sensor/ranger", b"r0", True), ("pd/p16/u/sensor/ranger", b"r1", True)]
        with cond:
            assert cond.wait_for(lambda: "pd/p16/u/sensor/ranger" in answered, timeout=30)
        assert sorted(answered) == ["pd/p16/u/sensor/ranger", "pd/p2/s/sensor/cam"]
        assert held_queries  # the stalled cache was asked, and its query timed out
        del silent
        print(f"\nlate sender read {'after' if len(at_once) == 3 else 'before'} read_back returned")
        h.close()
    finally:
        for t in (c, b, a):
            if t is not None:
                t.close()


@pytest.mark.integration
def test_zenoh_cache_appearing_while_recover_starts_is_read_once() -> None:
    """A sender whose cache appears after ``read_back`` began watching for new caches and
    before it read the present ones is seen by both, and read once (CI caught it read twice,
    its samples given twice)."""
    port = free_port()
    b = ZenohTransport(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"],
                                    multicast=False))
    c = ZenohTransport(zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"],
                                    multicast=False, listen=[]))
    real = b.session
    appeared = threading.Event()

    class Liveliness:  # the read of the present caches waits until c's token was watched
        def __init__(self, inner) -> None:
            self.inner = inner

        def declare_subscriber(self, *args, **kwargs):
            return self.inner.declare_subscriber(*args, **kwargs)

        def get(self, *args, **kwargs):
            pub = c.publisher("pd/p16/u/sensor/ranger", cache=4)
            pub.put(b"r0")
            assert appeared.wait(10.0), "the late cache's token never reached the watch"
            return self.inner.get(*args, **kwargs)

    class Session:
        def __getattr__(self, name: str):
            return getattr(real, name)

        def liveliness(self):
            return Liveliness(real.liveliness())

    watch = b.subscribe_liveliness("pd/*/*/sensor/*/@adv/pub/**",
                                   lambda key, alive: alive and appeared.set(), history=False)
    got: list = []
    try:
        b.session = Session()  # type: ignore[assignment]
        h = b.read_back("pd/*/*/sensor/*", lambda s: got.append(s.payload), max_samples=3)
        b.session = real
        time.sleep(0.5)  # room for a second read (the watch's), which answers in ms here
        assert got == [b"r0"]
        h.close()
    finally:
        b.session = real
        watch.close()
        c.close()
        b.close()


def test_zenoh_gets_answered_by_the_own_session_beyond_a_channel_capacity() -> None:
    """More than 256 of a get's replies from the caller's own session (its tokens, its
    queryables) all arrive: Zenoh answers those in the calling thread, which a bounded
    channel would block for good."""
    n = 600
    result: dict[str, int] = {}
    with ZenohTransport(zenoh_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as t:
        for i in range(n):
            t.declare_token(f"pd/@test/tok{i}")

        def answer(q) -> None:  # one queryable, one reply per key (as a router's admin space)
            for i in range(n):
                q.reply(f"pd/test/q{i}", b"x")

        t.queryable("pd/test/**", answer)

        def run() -> None:
            result["tokens"] = len(t.get_liveliness("pd/@test/*", timeout=2.0))
            result["replies"] = len(t.get("pd/test/*", timeout=2.0))

        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        worker.join(30.0)  # a bound on a hang, not a timing assertion: the gets end by 2 s
        assert not worker.is_alive(), "a get blocked on its own replies"
    assert result == {"tokens": n, "replies": n}


def _declare_and_close_per_session(t, n: int) -> None:
    """What the daemon declares for each session it serves, and closes when the session goes
    (the soak's churn: one created and one deleted per second)."""
    for i in range(n):
        handles = [t.declare_keys([f"pd/p1/s{i}/cmd", f"pd/p1/s{i}/prediction"]),
                   t.publisher(f"pd/p1/s{i}/prediction"),
                   t.publisher(f"pd/p1/s{i}/path", cache=4),
                   t.subscribe(f"pd/p1/s{i}/echo", lambda s: None),
                   t.declare_token(f"pd/@robot/s{i}")]
        for h in handles:
            h.close()


def test_in_memory_transport_keeps_no_closed_handle() -> None:
    with InMemoryBus().transport() as t:
        _declare_and_close_per_session(t, 3)
        kept = len(t._handles)
        _declare_and_close_per_session(t, 200)
        assert len(t._handles) == kept


@pytest.mark.integration
def test_zenoh_transport_keeps_no_closed_handle() -> None:
    with ZenohTransport(zenoh_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as t:
        _declare_and_close_per_session(t, 3)
        kept = len(t._handles)
        _declare_and_close_per_session(t, 200)
        assert len(t._handles) == kept
