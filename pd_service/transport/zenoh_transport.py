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
#: Samples a drained subscription holds before Zenoh waits for its owner (see _DrainGroup).
DRAIN_CAPACITY = 65_536
#: Most samples taken from one channel per look while emptying it at its close.
_DRAIN_BATCH = 4096
#: The armed watcher's wait between two looks at the channels (s): it doubles from the first
#: to the most; once nothing arrived for _POLL_QUIET_S, to _POLL_QUIET_MAX_S (an idle daemon
#: then looks 100 times a second).
_POLL_FIRST_S = 5e-5
_POLL_MAX_S = 1e-3
_POLL_QUIET_S = 0.5
_POLL_QUIET_MAX_S = 0.01
#: A read-back query that ended after this share of its timeout without a reply timed out.
_TIMED_OUT = 0.9
#: What the drain watcher's look found (_DrainGroup._look).
_EMPTY, _HANDED, _TAKEN_BACK, _CLOSED = 0, 1, 2, 3


class _Handle:
    def __init__(self, obj: object, owner: HandleOwner) -> None:
        self._obj, self._owner = obj, owner

    def close(self) -> None:
        obj, self._obj = self._obj, None
        if obj is not None:
            try:
                obj.undeclare()  # type: ignore[attr-defined]
            except Exception:  # already closed with the session
                pass
            self._owner._forget(self)


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


class _DrainMember:
    """One subscription of a :class:`_DrainGroup`: its FIFO channel and callback."""

    __slots__ = ("group", "keyexpr", "callback", "sub", "rx")

    def __init__(self, group: _DrainGroup, keyexpr: str, callback: Callable[[Sample], None],
                 sub: zenoh.Subscriber) -> None:
        self.group, self.keyexpr, self.callback, self.sub = group, keyexpr, callback, sub
        # the receiver itself: receiving through it does not borrow the subscriber
        self.rx = sub.handler

    def close(self) -> None:
        self.group.remove(self)


class _DrainGroup:
    """Subscriptions into FIFO channels that the owner drains on its own thread, with one
    watcher thread for all of them.

    Zenoh's threads push samples into each channel without the GIL. While the owner is busy
    it takes them in batches (``try_recv``), so a loaded daemon pays no GIL hand-off per
    sample. Before the owner waits idle it arms the group: the watcher polls every channel,
    hands the first sample found over itself, wakes the owner and parks until armed again::

        watcher:  wait(go) -> poll all: try_recv ... sleep(d), d doubling -> callback(sample)
                  -> clear(go), wake()
        owner:    drain(): clear(go), then try_recv each channel until empty
                  arm() before waiting idle: set(go)

    Taking is serialised by one lock, so each channel's samples reach its callback in the
    order Zenoh delivered them. zenoh-python cannot wait on several channels at once (and
    two subscribers cannot share one), so the armed watcher polls: the wait between two
    looks doubles from ``_POLL_FIRST_S`` to ``_POLL_MAX_S`` (the worker's round interval: a
    busy worker makes samples wait as long), and to ``_POLL_QUIET_MAX_S`` once nothing has
    arrived for ``_POLL_QUIET_S``. One thread per instance, not one per subscription:
    arming wakes one thread whatever the number of owned partitions.

    The channels are bounded (``capacity`` samples); a full channel makes Zenoh wait (it
    never drops silently), which happens only if the owner falls far behind.

    Receipt times of drained samples: ``recv_ns`` is the wall clock read by the drain (the
    sample arrived before it, so it is never judged "future" too early); ``recv_mono_ns`` is
    the monotonic time of the previous look at the queues (the last drain, or the watcher's
    previous poll), before which it had not arrived: latencies measured from it include the
    time spent in the queue (an upper bound by at most one loop of the owner or one poll).
    """

    def __init__(self, session: zenoh.Session, wake: Callable[[], None], capacity: int) -> None:
        self._session, self._wake, self._capacity = session, wake, capacity
        #: replaced, never changed in place, and read under the lock
        self._members: list[_DrainMember] = []
        self._lock = threading.Lock()
        # parked at first: the owner's first drain() takes what arrived since the
        # declarations (before anything read back is handled), then hands over to the watcher
        self._go = threading.Event()
        self._closed = False
        self._seen_mono = time.monotonic_ns()  # last look at the queues
        self._watcher = threading.Thread(target=self._watch, name="drain watcher", daemon=True)
        self._watcher.start()

    def add(self, keyexpr: str, callback: Callable[[Sample], None]) -> _DrainMember:
        sub = self._session.declare_subscriber(keyexpr, zenoh.handlers.FifoChannel(self._capacity))
        m = _DrainMember(self, keyexpr, callback, sub)
        with self._lock:
            self._members = [*self._members, m]
        return m

    def remove(self, m: _DrainMember) -> None:
        """Undeclare ``m``, then hand what its channel still holds to its callback. Zenoh
        may still push a batch routed before the undeclaration into the channel: ``m``
        stays in the group, drained as before, until its channel reports itself closed
        (Zenoh dropped its end: nothing more can arrive)."""
        try:  # outside the lock: Zenoh may wait for its own threads
            m.sub.undeclare()
        except Exception:  # already closed with the session
            pass
        with self._lock:
            if m in self._members:
                now, mono = time.time_ns(), self._seen_mono
                while self._take(m, _DRAIN_BATCH, now, mono):
                    pass

    def _gone(self, m: _DrainMember) -> None:
        """Under the lock: ``m``'s channel is closed and empty."""
        self._members = [x for x in self._members if x is not m]

    def _take(self, m: _DrainMember, limit: int, now: int, mono: int) -> int:
        try_recv, cb = m.rx.try_recv, m.callback
        n = 0
        while n < limit:
            try:
                s = try_recv()
            except Exception:  # closed and empty
                self._gone(m)
                return n
            if s is None:
                return n
            _deliver(cb, m.keyexpr, s, now, mono)
            n += 1
        return n

    def drain(self, limit: int) -> int:
        with self._lock:
            self._go.clear()  # the owner takes the queues back (order kept by the lock)
            now, mono = time.time_ns(), self._seen_mono
            self._seen_mono = time.monotonic_ns()
            n = 0
            for m in self._members:
                n += self._take(m, limit, now, mono)
            return n

    def arm(self) -> None:
        self._go.set()

    def _watch(self) -> None:
        go = self._go
        while True:
            go.wait()
            delay, cap = _POLL_FIRST_S, _POLL_MAX_S
            quiet_at = time.monotonic() + _POLL_QUIET_S
            while True:
                look = self._look()
                if look == _CLOSED:
                    return
                if look == _HANDED:
                    self._wake()
                if look != _EMPTY:
                    break
                time.sleep(delay)
                if delay < cap:
                    delay = min(delay * 2, cap)
                elif cap < _POLL_QUIET_MAX_S and time.monotonic() >= quiet_at:
                    cap = _POLL_QUIET_MAX_S

    def _look(self) -> int:
        """The watcher's look at the channels, under the lock: _CLOSED, _TAKEN_BACK (the
        owner drains again), _HANDED (a sample handed over: wake the owner) or _EMPTY."""
        with self._lock:
            if self._closed:
                return _CLOSED
            if not self._go.is_set():
                return _TAKEN_BACK
            if not self._poll():
                return _EMPTY
            self._go.clear()  # only now may the owner take the next ones
            return _HANDED

    def _poll(self) -> bool:
        """Under the lock: hand the first waiting sample of any channel over."""
        mono = time.monotonic_ns()
        for m in self._members:
            try:
                s = m.rx.try_recv()
            except Exception:  # closed and empty
                self._gone(m)
                continue
            if s is not None:
                _deliver(m.callback, m.keyexpr, s, time.time_ns(), self._seen_mono)
                self._seen_mono = mono
                return True
        self._seen_mono = mono
        return False

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            members, self._members = self._members, []
        self._go.set()
        self._watcher.join(timeout=5.0)
        for m in members:
            try:
                m.sub.undeclare()
            except Exception:  # already closed with the session
                pass


def _deliver(cb: Callable[[Sample], None], keyexpr: str, s: zenoh.Sample, now: int,
             mono: int) -> None:
    try:  # encoding and attachment not read (Transport.drain_group); the tuple built
        # directly: Sample(...) would run the NamedTuple's Python-level __new__
        cb(_new_tuple(Sample, (str(s.key_expr), s.payload.to_bytes(),
                               "delete" if s.kind == _DELETE else "put", now, mono,
                               None, None, False)))
    except Exception:
        log.exception("subscriber callback failed for %s", keyexpr)


def _collect_replies(start: Callable[[zenoh.handlers.Callback], object],
                     timeout: float) -> list[zenoh.Reply]:
    """The replies of one get, collected by a callback rather than Zenoh's default channel.

    Zenoh answers a get from the caller's own session (its tokens, its queryables) in the
    calling thread; with the default bounded channel more than its capacity (256) of such
    replies block that thread on a channel only it would drain. ``timeout`` in seconds.
    """
    out: list[zenoh.Reply] = []
    done = threading.Event()
    start(zenoh.handlers.Callback(out.append, done.set))
    done.wait(timeout + 1.0)  # Zenoh ends the get at its own timeout; the margin is slack
    return list(out)


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
        self._owner._forget(self)


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
        self._track(d)
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

    def drain_group(self, wake: Callable[[], None]) -> _DrainGroup:
        g = _DrainGroup(self.session, wake, DRAIN_CAPACITY)
        self._track(g)
        return g

    def read_back(self, keyexpr: str, callback: Callable[[Sample], None], *,
                  max_samples: int, timeout: float = 2.0,
                  answered: Callable[[str], None] | None = None) -> _Handle:
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

        def query(key: str, then: Callable[[], None] | None) -> None:
            """Query the cache whose token is ``key`` (callback form: returns at once); once
            its replies are in, ``answered`` (the cache's publisher key), then ``then``. A
            query that got nothing until its timeout is not an answer (a stalled sender: an
            empty cache answers at once)."""
            t0 = time.monotonic()
            replied = [False]

            def on_one(r: zenoh.Reply) -> None:
                replied[0] = replied[0] or r.ok is not None
                on_reply(r)

            def on_end() -> None:
                if answered is not None and (
                        replied[0] or time.monotonic() - t0 < _TIMED_OUT * timeout):
                    try:
                        answered(key.split("/@adv/", 1)[0])
                    except Exception:
                        log.exception("recovery callback failed for %s", keyexpr)
                if then is not None:
                    then()

            self.session.get(
                f"{key}?_max={max_samples}", zenoh.handlers.Callback(on_one, on_end),
                target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
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
                query(key, None)
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
            str(r.ok.key_expr) for r in _collect_replies(
                lambda h: self.session.liveliness().get(caches, handler=h, timeout=timeout),
                timeout)
            if r.ok is not None) if first_read(key)]
        left = [len(present)]
        done = threading.Condition()

        def finished() -> None:  # a query's replies are all in, or its timeout passed
            with done:
                left[0] -= 1
                done.notify_all()

        for key in present:  # all in flight at once: the wait is the slowest cache's
            try:
                query(key, finished)
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
        replies = _collect_replies(lambda h: self.session.get(selector, handler=h, **kwargs),
                                   timeout)
        for r in replies:
            if r.ok is not None:
                out.append(Reply(str(r.ok.key_expr), r.ok.payload.to_bytes(), True))
            elif r.err is not None:
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
        replies = _collect_replies(
            lambda h: self.session.liveliness().get(keyexpr, handler=h, timeout=timeout), timeout)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def session_id(self) -> str:
        return str(self.session.zid())

    def _keep(self, obj: object) -> _Handle:
        h = _Handle(obj, self)
        self._track(h)
        return h

    def _close_more(self) -> None:
        _OPEN.discard(self)
        self.session.close()
