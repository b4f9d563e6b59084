"""In-memory transport: several :class:`InMemoryTransport` on one :class:`InMemoryBus` behave
like processes on one Zenoh network, with no sockets and synchronous delivery (deterministic
tests). Delivery happens on the caller's thread, so a test sees the effect of ``put`` at once.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from .base import HandleOwner, Reply, Sample
from .keyexpr import intersects


class _Handle:
    def __init__(self, registry: list, entry: object) -> None:
        self._registry, self._entry = registry, entry

    def close(self) -> None:
        try:
            self._registry.remove(self._entry)
        except ValueError:
            pass


class _Drain:
    """A drained subscription on the bus: delivery is synchronous, nothing ever waits."""

    pending = False

    def __init__(self, handle: _Handle) -> None:
        self._handle = handle

    def drain(self, limit: int) -> int:
        return 0

    def close(self) -> None:
        self._handle.close()


@dataclass
class _MemQuery:
    key: str
    payload: bytes | None
    replies: list[Reply] = field(default_factory=list)

    def reply(self, key: str, payload: bytes, encoding: str | None = None) -> None:
        self.replies.append(Reply(key, bytes(payload), True))

    def reply_err(self, payload: bytes, encoding: str | None = None) -> None:
        self.replies.append(Reply(self.key, bytes(payload), False))


@dataclass
class _Publisher:
    transport: InMemoryTransport
    key: str

    def put(self, payload: bytes, *, encoding: str | None = None,
            attachment: bytes | None = None) -> None:
        self.transport._deliver(self.key, bytes(payload), "put", encoding, attachment)

    def delete(self, *, attachment: bytes | None = None) -> None:
        self.transport._deliver(self.key, b"", "delete", None, attachment)

    def close(self) -> None:
        pass


class InMemoryBus:
    """Shared medium for in-memory transports."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.subs: list[tuple[str, Callable[[Sample], None]]] = []
        self.queryables: list[tuple[str, Callable]] = []
        self.tokens: list[str] = []
        self.live_subs: list[tuple[str, Callable[[str, bool], None]]] = []
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

    def session_id(self) -> str:
        return self._zid

    # pub/sub
    def put(self, key: str, payload: bytes) -> None:
        self._deliver(key, bytes(payload), "put")

    def delete(self, key: str) -> None:
        self._deliver(key, b"", "delete")

    def publisher(self, key: str, *, express: bool = False) -> _Publisher:
        return _Publisher(self, key)

    def _deliver(self, key: str, payload: bytes, kind: Literal["put", "delete"],
                 encoding: str | None = None, attachment: bytes | None = None) -> None:
        with self.bus.lock:
            targets = [cb for ke, cb in self.bus.subs if intersects(ke, key)]
        s = Sample(key, payload, kind, time.time_ns(), time.monotonic_ns(), encoding, attachment)
        for cb in targets:
            cb(s)

    def subscribe(self, keyexpr: str, callback: Callable[[Sample], None]) -> _Handle:
        return self._register(self.bus.subs, (keyexpr, callback))

    def subscribe_drained(self, keyexpr: str, callback: Callable[[Sample], None],
                          wake: Callable[[], None]) -> _Drain:
        """In memory, samples reach ``callback`` at once (as with :meth:`subscribe`): the
        drain never holds anything."""
        return _Drain(self.subscribe(keyexpr, callback))

    # queries
    def queryable(self, keyexpr: str, handler: Callable) -> _Handle:
        return self._register(self.bus.queryables, (keyexpr, handler))

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
        bus = self.bus

        class _Token:
            def close(self_inner) -> None:
                with bus.lock:
                    if key not in bus.tokens:
                        return
                    bus.tokens.remove(key)
                    subs2 = [cb for ke, cb in bus.live_subs if intersects(ke, key)]
                for cb in subs2:
                    cb(key, False)

        tok = _Token()
        self._handles.append(tok)
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
        h = _Handle(registry, entry)
        self._handles.append(h)
        return h
