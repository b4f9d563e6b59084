"""Zenoh implementation of the transport (zenoh-python 1.x).

Zenoh calls subscriber and queryable callbacks on its own threads; an exception there is only
logged by Zenoh, so every callback here is wrapped to log and swallow errors itself.
"""

from __future__ import annotations

import atexit
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Final, Literal

import zenoh
import zenoh.ext

from .base import HandleOwner, Reply, Sample, check_exact_keys
from .options import zenoh_config

log = logging.getLogger("pd_service.transport")
_DEFAULT_ENCODING: Final = zenoh.Encoding.ZENOH_BYTES
_DELETE: Final = zenoh.SampleKind.DELETE
#: Samples a drained subscription holds before Zenoh waits for its owner (see _Drain).
DRAIN_CAPACITY = 65_536


class _Handle:
    def __init__(self, obj: object) -> None:
        self._obj = obj

    def close(self) -> None:
        obj, self._obj = self._obj, None
        if obj is not None:
            try:
                obj.undeclare()  # type: ignore[attr-defined]
            except Exception:  # already closed with the session
                pass


class _Publisher:
    __slots__ = ("_pub", "_handle")

    def __init__(self, pub: zenoh.Publisher | zenoh.ext.AdvancedPublisher,
                 handle: _Handle) -> None:
        self._pub, self._handle = pub, handle

    def put(self, payload: bytes, *, encoding: str | None = None,
            attachment: bytes | None = None) -> None:
        self._pub.put(payload, encoding=encoding, attachment=attachment)

    def delete(self, *, attachment: bytes | None = None) -> None:
        self._pub.delete(attachment=attachment)

    def close(self) -> None:
        self._handle.close()


def _convert(s: zenoh.Sample, now: int, mono: int) -> Sample:
    enc, att = s.encoding, s.attachment
    return Sample(str(s.key_expr), s.payload.to_bytes(),
                  "delete" if s.kind == _DELETE else "put", now, mono,
                  None if enc == _DEFAULT_ENCODING else str(enc),
                  None if att is None else att.to_bytes())


_new_tuple: Final = tuple.__new__


class _Drain:
    """A subscription into a FIFO channel that the owner drains on its own thread.

    Zenoh's threads push samples into the channel without the GIL. While the owner is
    busy it takes them in batches (``try_recv``), so a loaded daemon pays no GIL hand-off
    per sample. Before the owner waits idle it arms the drain: a watcher thread blocks in
    ``recv`` (GIL released); the first sample that arrives is handed over by the watcher
    itself, which wakes the owner and parks until the owner arms it again::

        watcher:  wait(go) -> recv() -> callback(sample) -> clear(go), wake()
        owner:    drain(), only while go is clear: try_recv ... until empty
                  arm() before waiting idle: set(go)

    Only one of the two takes samples at a time, so they reach the callback in the order
    Zenoh delivered them. A busy owner (it comes back within its round interval) does not
    arm: no thread switch and no GIL hand-off per round.

    The channel is bounded (``capacity`` samples); a full channel makes Zenoh wait (it
    never drops silently), which happens only if the owner falls far behind.

    Receipt times of drained samples: ``recv_ns`` is the wall clock read by the drain (the
    sample arrived before it, so it is never judged "future" too early); ``recv_mono_ns`` is
    the monotonic time of the previous look at the queue (the last drain, or the watcher's
    hand-over), before which it had not arrived: latencies measured from it include the
    time spent in the queue (an upper bound by at most one loop of the owner).
    """

    def __init__(self, session: zenoh.Session, keyexpr: str,
                 callback: Callable[[Sample], None], wake: Callable[[], None],
                 capacity: int) -> None:
        self._cb, self._wake, self._keyexpr = callback, wake, keyexpr
        self._sub = session.declare_subscriber(keyexpr, zenoh.handlers.FifoChannel(capacity))
        # the receiver itself: receiving through it does not borrow the subscriber, so
        # undeclare() works while the watcher waits (and makes its recv() raise)
        self._rx = self._sub.handler
        # parked at first: the owner's first drain() takes what arrived since the
        # declaration (before anything read back is handled), then hands over to the watcher
        self._go = threading.Event()
        self._closed = False
        self._seen_mono = time.monotonic_ns()  # last look at the queue
        self._watcher = threading.Thread(target=self._watch, name=f"drain {keyexpr}",
                                        daemon=True)
        self._watcher.start()

    @property
    def pending(self) -> bool:
        return not self._go.is_set()

    def _watch(self) -> None:
        rx, go = self._rx, self._go
        while True:
            go.wait()
            if self._closed:
                return
            try:
                s = rx.recv()
            except Exception:  # the channel closed: the subscriber was undeclared
                return
            mono = time.monotonic_ns()
            self._deliver(s, time.time_ns(), mono)
            self._seen_mono = mono
            go.clear()  # only now may the owner take the next ones: the order is kept
            self._wake()

    def _deliver(self, s: zenoh.Sample, now: int, mono: int) -> None:
        try:  # encoding and attachment not read (Transport.subscribe_drained); the tuple
            # built directly: Sample(...) would run the NamedTuple's Python-level __new__
            self._cb(_new_tuple(Sample, (str(s.key_expr), s.payload.to_bytes(),
                                         "delete" if s.kind == _DELETE else "put", now, mono,
                                         None, None, False)))
        except Exception:
            log.exception("subscriber callback failed for %s", self._keyexpr)

    def drain(self, limit: int) -> int:
        if self._go.is_set():  # the watcher is receiving: it hands the next sample over
            return 0
        try_recv, deliver = self._rx.try_recv, self._deliver
        now, mono = time.time_ns(), self._seen_mono
        self._seen_mono = time.monotonic_ns()
        n = 0
        while n < limit:
            try:
                s = try_recv()
            except Exception:  # closed
                return n
            if s is None:
                return n
            deliver(s, now, mono)
            n += 1
        return n

    def arm(self) -> None:
        self._go.set()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._sub.undeclare()
        except Exception:  # already closed with the session
            pass
        self._go.set()
        self._watcher.join(timeout=5.0)


class _DeclaredKeys:
    """Key expressions declared with ``Session.declare_keyexpr`` (see
    :meth:`Transport.declare_keys`); :meth:`close` undeclares them."""

    def __init__(self, owner: ZenohTransport, keys: list[str]) -> None:
        self._owner = owner
        self._kes: list[tuple[str, zenoh.KeyExpr]] = []
        declare, declared = owner.session.declare_keyexpr, owner._declared
        try:
            for k in keys:
                ke = declare(k)
                declared[k] = ke  # the newest declaration of a key is the one put() uses
                self._kes.append((k, ke))
        except BaseException:  # none half declared
            self.close()
            raise

    def close(self) -> None:
        kes, self._kes = self._kes, []
        declared = self._owner._declared
        for k, ke in kes:
            if declared.get(k) is ke:
                del declared[k]
            try:
                self._owner.session.undeclare(ke)
            except Exception:  # already closed with the session
                pass
        handles = self._owner._handles
        if not self._owner._closed and self in handles:  # (not while the owner closes all)
            handles.remove(self)


class _ZQuery:
    __slots__ = ("_q", "key", "payload")

    def __init__(self, q: zenoh.Query) -> None:
        self._q = q
        self.key = str(q.key_expr)
        self.payload = q.payload.to_bytes() if q.payload is not None else None

    def reply(self, key: str, payload: bytes, encoding: str | None = None) -> None:
        self._q.reply(key, payload, encoding=encoding)

    def reply_err(self, payload: bytes, encoding: str | None = None) -> None:
        self._q.reply_err(payload, encoding=encoding)


#: Transports not closed yet: closed at interpreter exit (below). Held strongly (a compiled
#: class takes no weak reference); each leaves it when closed.
_OPEN: set[ZenohTransport] = set()


def _close_open_transports() -> None:
    """Close the sessions a program left open: zenoh-python runs subscriber callbacks on a
    thread that is not a daemon, which the interpreter waits for at exit while the session is
    open: a snippet that subscribes and returns would never exit."""
    for transport in list(_OPEN):
        try:
            transport.close()
        except Exception:  # exiting anyway: a failed close must not mask the exit status
            pass


# threading's exit hook runs before the interpreter joins the threads that are not daemons
# (atexit runs after: too late); the same hook concurrent.futures uses
_register = getattr(threading, "_register_atexit", None)
if _register is not None:
    _register(_close_open_transports)
else:  # pragma: no cover - Python without the hook
    atexit.register(_close_open_transports)


class ZenohTransport(HandleOwner):
    """A Zenoh session behind the :class:`~pd_service.transport.base.Transport` interface."""

    def __init__(self, conf: zenoh.Config | None = None) -> None:
        self.session = zenoh.open(conf if conf is not None else zenoh_config())
        super().__init__()
        _OPEN.add(self)
        #: key -> its declared key expression (declare_keys), which put() uses
        self._declared: dict[str, zenoh.KeyExpr] = {}

    def put(self, key: str, payload: bytes) -> None:
        # a declared key's put reuses its cached route; another key's route is computed
        # for this put
        ke = self._declared.get(key)
        self.session.put(key if ke is None else ke, payload)

    def declare_keys(self, keys: Sequence[str]) -> _DeclaredKeys:
        d = _DeclaredKeys(self, check_exact_keys(keys))
        self._handles.append(d)
        return d

    def delete(self, key: str) -> None:
        self.session.delete(key)

    def publisher(self, key: str, *, express: bool = False, cache: int = 0) -> _Publisher:
        # BLOCK: a message must not be lost by Zenoh's own queue
        block = zenoh.CongestionControl.BLOCK
        if cache <= 0:
            pub = self.session.declare_publisher(key, express=express, congestion_control=block)
            return _Publisher(pub, self._keep(pub))
        # zenoh-ext advanced publisher: a cache answering queries on <key>/@adv/pub/..., a
        # liveliness token on the same key (publisher detection: late receivers find it) and
        # sequence numbers (sample_miss_detection; unlike timestamps they need no
        # 'timestamping' in the session's config)
        adv = zenoh.ext.declare_advanced_publisher(
            self.session, key, express=express, congestion_control=block,
            cache=zenoh.ext.CacheConfig(max_samples=cache), publisher_detection=True,
            sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None))
        return _Publisher(adv, self._keep(adv))

    def subscribed(self, key: str, timeout: float = 1.0) -> bool:
        pub = self.session.declare_publisher(key)
        try:
            deadline = time.monotonic() + timeout
            # getattr: the stub says bool (compiled code would check it), 1.10 gives a
            # MatchingStatus
            while not getattr(pub, "matching_status").matching:  # noqa: B009
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.05)
            return True
        finally:
            pub.undeclare()

    def subscribe(self, keyexpr: str, callback: Callable[[Sample], None]) -> _Handle:
        def on_sample(s: zenoh.Sample) -> None:
            try:
                callback(_convert(s, time.time_ns(), time.monotonic_ns()))
            except Exception:
                log.exception("subscriber callback failed for %s", keyexpr)

        return self._keep(self.session.declare_subscriber(keyexpr, on_sample))

    def subscribe_drained(self, keyexpr: str, callback: Callable[[Sample], None],
                          wake: Callable[[], None]) -> _Drain:
        d = _Drain(self.session, keyexpr, callback, wake, DRAIN_CAPACITY)
        self._handles.append(d)
        return d

    def read_back(self, keyexpr: str, callback: Callable[[Sample], None], *,
                  max_samples: int, timeout: float = 2.0) -> _Handle:
        # zenoh-ext 1.10's layout: a cached publisher on K answers queries and holds its
        # liveliness token on K/@adv/pub/<zid>/<eid>/<meta> (the queryable's key too); "_max=N"
        # asks for its last N samples (tests/transport pins this against a real advanced
        # publisher)
        caches = f"{keyexpr}/@adv/pub/**"

        def on_reply(r: zenoh.Reply) -> None:
            ok = r.ok
            if ok is None:
                return
            try:
                kind: Literal["put", "delete"] = (
                    "delete" if ok.kind == zenoh.SampleKind.DELETE else "put")
                enc, att = ok.encoding, ok.attachment
                callback(Sample(str(ok.key_expr), ok.payload.to_bytes(), kind,
                                time.time_ns(), time.monotonic_ns(),
                                None if enc == _DEFAULT_ENCODING else str(enc),
                                None if att is None else att.to_bytes(), True))
            except Exception:
                log.exception("recovery callback failed for %s", keyexpr)

        def query(selector: str, handler: Callable[[zenoh.Reply], None]) -> None:
            self.session.get(
                f"{selector}?_max={max_samples}", handler, target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                accept_replies=zenoh.ReplyKeyExpr.ANY, timeout=timeout)

        # each cache is read once per appearance of its token: a token seen both by the
        # watch and by the read of the present ones (it appeared in between) is read once
        read: set[str] = set()
        read_lock = threading.Lock()

        def first_read(key: str) -> bool:
            with read_lock:
                new = key not in read
                read.add(key)
                return new

        def on_token(s: zenoh.Sample) -> None:  # a cached publisher appeared (again)
            key = str(s.key_expr)
            if s.kind != zenoh.SampleKind.PUT:
                with read_lock:  # gone: its next appearance is read again
                    read.discard(key)
                return
            if not first_read(key):
                return
            try:
                query(key, on_reply)  # callback form: returns at once
            except Exception:
                log.exception("recovery query failed for %s", key)

        # watch first (new tokens only), then read the present caches: a publisher that
        # appears in between is seen by both and read once, never missed.  The present caches
        # are found by their tokens and each is queried on its own key, never with one
        # wildcard query: a router's access control scoped by session (deploy/make_acl.py)
        # lets a query reach a sender only on its sessions' keys
        handle = self._keep(self.session.liveliness().declare_subscriber(
            caches, on_token, history=False))
        present = [key for key in dict.fromkeys(
            str(r.ok.key_expr) for r in self.session.liveliness().get(caches, timeout=timeout)
            if r.ok is not None) if first_read(key)]
        left = [len(present)]
        done = threading.Condition()

        def finished() -> None:  # a query's replies are all in, or its timeout passed
            with done:
                left[0] -= 1
                done.notify_all()

        for key in present:  # all in flight at once: the wait is the slowest cache's
            try:
                query(key, zenoh.handlers.Callback(on_reply, finished))
            except Exception:
                log.exception("recovery query failed for %s", key)
                finished()
        with done:  # each query ends by its own timeout; the margin only guards a lost drop
            if not done.wait_for(lambda: left[0] <= 0, timeout + 5.0):
                log.warning("recovery of %s: %d cache queries did not end", keyexpr, left[0])
        return handle

    def queryable(self, keyexpr: str, handler: Callable) -> _Handle:
        def on_query(q: zenoh.Query) -> None:
            try:
                handler(_ZQuery(q))
            except Exception:
                log.exception("queryable handler failed for %s", keyexpr)

        return self._keep(self.session.declare_queryable(keyexpr, on_query))

    def get(self, selector: str, payload: bytes | None = None, timeout: float = 2.0) -> list[Reply]:
        out: list[Reply] = []
        kwargs: dict = {"timeout": timeout}
        if payload is not None:
            kwargs["payload"] = payload
        for r in self.session.get(selector, **kwargs):
            if r.ok is not None:
                out.append(Reply(str(r.ok.key_expr), r.ok.payload.to_bytes(), True))
            else:
                out.append(Reply(selector, r.err.payload.to_bytes(), False))
        return out

    def declare_token(self, key: str) -> _Handle:
        return self._keep(self.session.liveliness().declare_token(key))

    def subscribe_liveliness(self, keyexpr: str, callback: Callable[[str, bool], None],
                             history: bool = True) -> _Handle:
        def on_sample(s: zenoh.Sample) -> None:
            try:
                callback(str(s.key_expr), s.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("liveliness callback failed for %s", keyexpr)

        return self._keep(
            self.session.liveliness().declare_subscriber(keyexpr, on_sample, history=history))

    def get_liveliness(self, keyexpr: str, timeout: float = 1.0) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get(keyexpr, timeout=timeout)
                if r.ok is not None]

    def session_id(self) -> str:
        return str(self.session.zid())

    def _keep(self, obj: object) -> _Handle:
        h = _Handle(obj)
        self._handles.append(h)
        return h

    def _close_more(self) -> None:
        _OPEN.discard(self)
        self.session.close()
