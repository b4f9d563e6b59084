"""In-memory transport: several :class:`InMemoryTransport` on one :class:`InMemoryBus` behave
like processes on one Zenoh network, with no sockets and synchronous delivery (deterministic
tests). Delivery happens on the caller's thread, so a test sees the effect of ``put`` at once.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from .base import HandleOwner, Reply, Sample, check_exact_keys
from .keyexpr import intersects


class _Handle:
    def __init__(self, registry: list, entry: object, owner: HandleOwner) -> None:
        self._registry, self._entry, self._owner = registry, entry, owner

    def close(self) -> None:
        try:
            self._registry.remove(self._entry)
        except ValueError:
            pass
        self._owner._forget(self)


class _DrainMember:
    """One subscription of a :class:`_DrainGroup`; ``callback`` may be replaced."""

    def __init__(self, callback: Callable[[Sample], None]) -> None:
        self.callback = callback
        self.handle: _Handle | None = None

    def deliver(self, s: Sample) -> None:  # encoding and attachment dropped, as on Zenoh
        self.callback(s if s.encoding is None and s.attachment is None
                      else s._replace(encoding=None, attachment=None))

    def close(self) -> None:
        if self.handle is not None:
            self.handle.close()


class _DrainGroup:
    """Drained subscriptions on the bus: delivery is synchronous, nothing ever waits."""

    def __init__(self, transport: InMemoryTransport) -> None:
        self._t = transport
        self._members: list[_DrainMember] = []

    def add(self, keyexpr: str, callback: Callable[[Sample], None]) -> _DrainMember:
        """Samples reach ``callback`` at once (as with :meth:`InMemoryTransport.subscribe`)."""
        m = _DrainMember(callback)
        m.handle = self._t.subscribe(keyexpr, m.deliver)
        self._members.append(m)
        return m

    def drain(self, limit: int) -> int:
        return 0

    def arm(self) -> None:
        pass

    def close(self) -> None:
        for m in self._members:
            m.close()
        self._members.clear()


@dataclass
class _MemQuery:
    key: str
    payload: bytes | None
    replies: list[Reply] = field(default_factory=list)

    def reply(self, key: str, payload: bytes, encoding: str | None = None) -> None:
        self.replies.append(Reply(key, bytes(payload), True))

    def reply_err(self, payload: bytes, encoding: str | None = None) -> None:
        self.replies.append(Reply(self.key, bytes(payload), False))


@dataclass(eq=False)
class _Publisher:
    """``cache`` set: the publisher's last samples, readable by ``read_back`` while it is open
    (like a zenoh-ext advanced publisher's cache)."""

    transport: InMemoryTransport
    key: str
    cache: deque[Sample] | None = None

    def put(self, payload: bytes, *, encoding: str | None = None,
            attachment: bytes | None = None) -> None:
        s = self.transport._deliver(self.key, bytes(payload), "put", encoding, attachment)
        if self.cache is not None:
            with self.transport.bus.lock:
                self.cache.append(s)

    def delete(self, *, attachment: bytes | None = None) -> None:
        s = self.transport._deliver(self.key, b"", "delete", None, attachment)
        if self.cache is not None:
            with self.transport.bus.lock:
                self.cache.append(s)

    def close(self) -> None:
        bus = self.transport.bus
        with bus.lock:
            if self in bus.cached:
                bus.cached.remove(self)
        self.transport._forget(self)


def _recovered(pub: _Publisher, n: int) -> list[Sample]:
    """The last ``n`` samples of ``pub``'s cache, oldest first, marked recovered, with the
    time they are read back as their receipt time."""
    assert pub.cache is not None
    now, mono = time.time_ns(), time.monotonic_ns()
    return [s._replace(recv_ns=now, recv_mono_ns=mono, recovered=True)
            for s in list(pub.cache)[-n:]] if n > 0 else []


class InMemoryBus:
    """Shared medium for in-memory transports."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.subs: list[tuple[str, Callable[[Sample], None]]] = []
        self.queryables: list[tuple[str, Callable]] = []
        self.tokens: list[str] = []
        self.live_subs: list[tuple[str, Callable[[str, bool], None]]] = []
        #: open publishers with a cache, and who reads the caches of new ones (read_back)
        self.cached: list[_Publisher] = []
        self.recoverers: list[tuple[str, Callable[[Sample], None], int,
                                    Callable[[str], None] | None]] = []
        self.transports = 0  # how many transports were made on this bus (their session ids)

    def transport(self) -> InMemoryTransport:
        return InMemoryTransport(self)


class InMemoryTransport(HandleOwner):
    def __init__(self, bus: InMemoryBus) -> None:
        super().__init__()
        self.bus = bus
        with bus.lock:
            bus.transports += 1
            # a fixed Zenoh-like id per transport of the bus: 1st -> "a1", 2nd -> "a2", ...
            self._zid = f"a{bus.transports:x}"
        #: What :meth:`declare_keys` declared and is not withdrawn: one tuple per call.
        self.declared: list[tuple[str, ...]] = []

    def session_id(self) -> str:
        return self._zid

    # pub/sub
    def put(self, key: str, payload: bytes) -> None:
        self._deliver(key, bytes(payload), "put")

    def delete(self, key: str) -> None:
        self._deliver(key, b"", "delete")

    def publisher(self, key: str, *, express: bool = False, cache: int = 0) -> _Publisher:
        if cache <= 0:
            return _Publisher(self, key)
        pub = _Publisher(self, key, deque(maxlen=cache))
        with self.bus.lock:
            self.bus.cached.append(pub)
            watchers = [(cb, n, done) for ke, cb, n, done in self.bus.recoverers
                        if intersects(ke, key)]
        self._track(pub)
        for cb, n, done in watchers:  # a new cached publisher: its (empty) cache is read
            for s in _recovered(pub, n):
                cb(s)
            if done is not None:
                done(key)
        return pub

    def _deliver(self, key: str, payload: bytes, kind: Literal["put", "delete"],
                 encoding: str | None = None, attachment: bytes | None = None) -> Sample:
        with self.bus.lock:
            targets = [cb for ke, cb in self.bus.subs if intersects(ke, key)]
        s = Sample(key, payload, kind, time.time_ns(), time.monotonic_ns(), encoding, attachment)
        for cb in targets:
            cb(s)
        return s

    def subscribed(self, key: str, timeout: float = 1.0) -> bool:
        with self.bus.lock:
            return any(intersects(ke, key) for ke, _ in self.bus.subs)

    def subscribe(self, keyexpr: str, callback: Callable[[Sample], None]) -> _Handle:
        return self._register(self.bus.subs, (keyexpr, callback))

    def drain_group(self, wake: Callable[[], None]) -> _DrainGroup:
        return _DrainGroup(self)

    def read_back(self, keyexpr: str, callback: Callable[[Sample], None], *,
                  max_samples: int, timeout: float = 2.0,
                  answered: Callable[[str], None] | None = None) -> _Handle:
        """The caches of the open cached publishers matching ``keyexpr`` (last
        ``max_samples`` of each, oldest first), at once; later ones when declared."""
        with self.bus.lock:
            h = self._register(self.bus.recoverers, (keyexpr, callback, max_samples, answered))
            pubs = [p for p in self.bus.cached if intersects(keyexpr, p.key)]
            held = [(p.key, _recovered(p, max_samples)) for p in pubs]
        for key, samples in held:
            for s in samples:
                callback(s)
            if answered is not None:
                answered(key)
        return h

    # queries
    def queryable(self, keyexpr: str, handler: Callable) -> _Handle:
        return self._register(self.bus.queryables, (keyexpr, handler))

    def declare_keys(self, keys: Sequence[str]) -> _Handle:
        """Recorded in :attr:`declared` (key, ...) until closed: no routing to speed up."""
        return self._register(self.declared, tuple(check_exact_keys(keys)))

    def get(self, selector: str, payload: bytes | None = None, timeout: float = 2.0) -> list[Reply]:
        with self.bus.lock:
            targets = [h for ke, h in self.bus.queryables if intersects(ke, selector)]
        q = _MemQuery(selector, payload)
        for h in targets:
            h(q)
        return q.replies

    # liveliness
    def declare_token(self, key: str) -> _Handle:
        with self.bus.lock:
            self.bus.tokens.append(key)
            subs = [cb for ke, cb in self.bus.live_subs if intersects(ke, key)]
        for cb in subs:
            cb(key, True)
        bus, owner = self.bus, self

        class _Token:
            def close(self_inner) -> None:
                owner._forget(self_inner)
                with bus.lock:
                    if key not in bus.tokens:
                        return
                    bus.tokens.remove(key)
                    subs2 = [cb for ke, cb in bus.live_subs if intersects(ke, key)]
                for cb in subs2:
                    cb(key, False)

        tok = _Token()
        self._track(tok)
        return tok  # type: ignore[return-value]

    def subscribe_liveliness(self, keyexpr: str, callback: Callable[[str, bool], None],
                             history: bool = True) -> _Handle:
        h = self._register(self.bus.live_subs, (keyexpr, callback))
        if history:
            with self.bus.lock:
                present = [k for k in self.bus.tokens if intersects(keyexpr, k)]
            for k in present:
                callback(k, True)
        return h

    def get_liveliness(self, keyexpr: str, timeout: float = 1.0) -> list[str]:
        with self.bus.lock:
            return [k for k in self.bus.tokens if intersects(keyexpr, k)]

    # lifecycle
    def _register(self, registry: list, entry: object) -> _Handle:
        with self.bus.lock:
            registry.append(entry)
        h = _Handle(registry, entry, self)
        self._track(h)
        return h
