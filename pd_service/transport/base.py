"""The transport interface: what the daemon, link emulator and SDK need from Zenoh.

Two implementations: :class:`~pd_service.transport.zenoh_transport.ZenohTransport` (real) and
:class:`~pd_service.transport.memory.InMemoryTransport` (tests; no network, deterministic).
Callbacks run on the transport's own thread and must not block: hand work to a queue.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple, Protocol, Self

from .keyexpr import check_keyexpr

#: Samples a sender keeps per key by default (``Transport.publisher(key, cache=...)``) so that
#: a restarted daemon reads back what it missed: a stream of one sample per step covers
#: 256 steps (12.8 s at 20 Hz; the paper's window is max_delay 12 + lead 10 steps). About
#: 256 x the payload (~30 KB for a 4-D measurement) per key.
DEFAULT_SENDER_CACHE = 256


class Sample(NamedTuple):
    """A received publication. ``recv_ns``: wall clock at receipt (time.time_ns());
    ``recv_mono_ns``: monotonic clock at receipt (for latency); ``encoding`` (None: the
    default, Zenoh's ``zenoh/bytes``) and ``attachment`` as the publisher set them.
    ``recovered``: True for a sample read back from a sender's cache
    (:meth:`Transport.read_back`), not received live: it may repeat one received live or be
    older than the receiver can use. (A NamedTuple: built per received message, and cheaper
    to build than a frozen dataclass.)"""

    key: str
    payload: bytes
    kind: Literal["put", "delete"]
    recv_ns: int
    recv_mono_ns: int
    encoding: str | None = None
    attachment: bytes | None = None
    recovered: bool = False


@dataclass(frozen=True, slots=True)
class Reply:
    """One answer to :meth:`Transport.get`: ``ok`` False for an error reply."""

    key: str
    payload: bytes
    ok: bool


class Query(Protocol):
    """A query received by a queryable."""

    key: str  # the key expression the query asked for
    payload: bytes | None

    def reply(self, key: str, payload: bytes, encoding: str | None = None) -> None: ...

    def reply_err(self, payload: bytes, encoding: str | None = None) -> None: ...


class Handle(Protocol):
    def close(self) -> None: ...


class DrainMember(Protocol):
    """One subscription of a :class:`DrainGroup`. ``callback`` may be replaced at any time:
    the next sample taken goes to the new one."""

    callback: Callable[[Sample], None]

    def close(self) -> None: ...


class DrainGroup(Protocol):
    """Subscriptions whose samples wait in queues until the owner drains them on its own
    thread (:meth:`Transport.drain_group`): one watcher for all of them, however many."""

    def add(self, keyexpr: str, callback: Callable[[Sample], None]) -> DrainMember:
        """Subscribe ``keyexpr`` into the group; its samples reach ``callback``. The member's
        ``close`` undeclares it and hands what its queue still holds to its callback."""
        ...

    def drain(self, limit: int) -> int:
        """On the owner's thread: take the queues back from the watcher (disarm) and hand up
        to ``limit`` waiting samples of each subscription to its callback; returns how many."""
        ...

    def arm(self) -> None:
        """The owner is going to wait idle: the watcher hands the next sample that arrives
        in any of the queues over on its own thread and wakes the owner; the owner's next
        :meth:`drain` takes the rest."""
        ...

    def close(self) -> None: ...


class Publisher(Protocol):
    """A declared publisher on one key: reliable, it waits rather than drop a message when
    the network is congested. ``encoding`` None: the default (Zenoh's ``zenoh/bytes``)."""

    def put(self, payload: bytes, *, encoding: str | None = None,
            attachment: bytes | None = None) -> None: ...

    def delete(self, *, attachment: bytes | None = None) -> None: ...

    def close(self) -> None: ...


class Transport(Protocol):
    def put(self, key: str, payload: bytes) -> None: ...

    def delete(self, key: str) -> None: ...

    def publisher(self, key: str, *, express: bool = False, cache: int = 0) -> Publisher:
        """``express``: send at once, without batching (Zenoh's express flag). ``cache`` > 0:
        the publisher keeps its last ``cache`` samples, which a receiver that was away
        (restarted, or not yet connected) reads back with :meth:`read_back` (Zenoh: a zenoh-ext
        advanced publisher with a cache, publisher detection and sequence numbers)."""
        ...

    def subscribe(self, keyexpr: str, callback: Callable[[Sample], None]) -> Handle: ...

    def drain_group(self, wake: Callable[[], None]) -> DrainGroup:
        """Drained subscriptions (:meth:`DrainGroup.add`): like :meth:`subscribe`, but the
        samples wait in queues and reach their callback on the thread that calls
        :meth:`DrainGroup.drain`, or, once armed, the first one on the group's watcher, which
        then calls ``wake``: the owner should drain soon. ``Sample.recv_ns`` is then the wall
        clock read when the sample was taken from the queue (one read per drain) and
        ``recv_mono_ns`` the monotonic time of the previous look at the queues (so latencies
        include the wait in them). ``encoding`` and ``attachment`` are not read (None):
        drained streams carry messages whose encoding the protocol fixes, and reading the
        two costs time on every sample."""
        ...

    def read_back(self, keyexpr: str, callback: Callable[[Sample], None], *,
                  max_samples: int, timeout: float = 2.0,
                  answered: Callable[[str], None] | None = None) -> Handle:
        """Read back what cached publishers (``publisher(key, cache=N)``) on keys matching
        ``keyexpr`` hold: at most ``max_samples`` of each, oldest first, as samples with
        ``recovered`` True. The caches present now are read before this returns (each
        answered, or ``timeout`` s passed); until the handle is closed, the cache of every
        cached publisher that appears later (a sender that connects or reconnects) is read
        too, its samples given to ``callback`` on a transport thread. Each cache is read
        once each time it appears, also when it appears while this call runs. A recovered sample
        may repeat one received live: the receiver must tell (the daemon refuses it as a
        duplicate, counted apart from live refusals). ``answered``, if given, is called with
        a cache's publisher key (``keyexpr``'s match, e.g. ``pd/p3/s/sensor/cam``) once that
        cache has answered, after its samples were given to ``callback`` (not for one whose
        query got no reply until ``timeout``: a stalled sender)."""
        ...

    def queryable(self, keyexpr: str, handler: Callable[[Query], None]) -> Handle: ...

    def declare_keys(self, keys: Sequence[str]) -> Handle:
        """Declare ``keys`` (exact keys, no wildcards) as busy: ones this side puts on
        (:meth:`put` then uses the declaration) or receives on, many times a second.
        Closing the handle withdraws them. On Zenoh each becomes a declared key expression:
        a message on it is routed by a cached route, where an undeclared key's route is
        computed per message by comparing its chunks with every declared resource's (Zenoh
        1.10: the cost grows with the number of sibling keys declared anywhere, e.g. every
        display's subscription to its own session, docs/service.md "Declared keys")."""
        ...

    def get(self, selector: str, payload: bytes | None = None,
            timeout: float = 2.0) -> list[Reply]: ...

    def subscribed(self, key: str, timeout: float = 1.0) -> bool:
        """Whether another party subscribes to ``key`` (waits up to ``timeout`` seconds for
        the subscription to become known). On Zenoh a publisher's matching status: a
        router's access control lets every user learn of subscriptions (it reveals key
        expressions, never data), so a client can tell "the service listens, but my put
        is refused" from "no service"."""
        ...

    def declare_token(self, key: str) -> Handle: ...

    def subscribe_liveliness(self, keyexpr: str, callback: Callable[[str, bool], None],
                             history: bool = True) -> Handle: ...

    def get_liveliness(self, keyexpr: str, timeout: float = 1.0) -> list[str]: ...

    def session_id(self) -> str:
        """The Zenoh session id (``zid``) in lowercase hex, as ``zenoh::Id::to_string`` prints
        it; the in-memory transport gives a fixed id per transport of its bus."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Transport: ...

    def __exit__(self, *exc: object) -> None: ...


def check_exact_keys(keys: Sequence[str]) -> list[str]:
    """``keys`` as a list; ValueError naming the first that is not an exact key (a key
    expression, :func:`.keyexpr.check_keyexpr`, without wildcards)."""
    out = list(keys)
    for k in out:
        try:
            check_keyexpr(k)
        except ValueError as exc:
            raise ValueError(f"declare_keys: {k!r} is not an exact key ({exc})") from None
        if "*" in k:
            raise ValueError(f"declare_keys: {k!r} is not an exact key (a wildcard)")
    return out


class HandleOwner:
    """What both transports do with the handles they declare: close them newest first, once,
    then :meth:`_close_more` (the Zenoh session, say); a context manager closing on exit."""

    def __init__(self) -> None:
        #: open handles in declaration order (a dict: a closed one forgets itself in O(1),
        #: so a long run that declares and closes per session keeps none of them)
        self._handles: dict[Handle, None] = {}
        self._closed = False

    def _track(self, h: Handle) -> None:
        """Keep ``h`` to close with the transport."""
        self._handles[h] = None

    def _forget(self, h: Handle) -> None:
        """``h`` was closed by its user (not while the transport closes them all)."""
        if not self._closed:
            self._handles.pop(h, None)

    def _close_more(self) -> None:
        """Closed after the handles; nothing by default."""

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for h in reversed(list(self._handles)):
            h.close()
        self._handles.clear()
        self._close_more()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
