"""ServiceCore: everything the daemon does, minus threads and Zenoh.

The core owns the sessions and talks to the world only through a
:class:`~pd_service.transport.Transport` (Zenoh in the daemon, :class:`InMemoryBus` in unit
tests) and reads time only through two injected clocks (``now_ns``: shared wall clock for
steps; ``mono_ns``: monotonic clock for latencies), so tests drive it deterministically.

Data path::

    transport thread(s)                         worker (run_once, one thread)
    -------------------                         ------------------------------------------
    pd/*/sensor/*  --\\                          control inbox: configs, presence  (all)
    pd/*/cmd       ---+-> parse session (split)  unknown inbox: unknown sessions   (all)
    pd/*/config    --/   append to an inbox,    ready sessions, round-robin: <= batch_budget
                         wake the worker           messages each per round
                                                after each round: publish a Prediction for
                                                   every session that accepted a measurement
                                                ticks due; idle expiry; send the outbox

Callbacks never block and never take the core's lock: they append ``(stream, key, payload,
recv_mono_ns, kind)`` to a bounded deque (the oldest entry is dropped when full and counted
as ``flood``). A session's inbox is bounded, so a flooding session loses its own oldest
messages; the round-robin budget keeps it from delaying the others by more than one budget.

Queries (status, specs) run on the transport's thread and take ``lock``; the worker holds
it while processing one round, so replies never see a half-updated session.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pd_service.logs import LOGGER_NAME, event
from pd_service.transport import Query, Sample
from pd_service.transport.keyexpr import intersects
from pd_service.wire import (
    ErrorReport,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
    WireError,
    decode,
    encode,
    keys,
)
from pd_service.wire.keys import KeyError_, check_name

from .config import Settings
from .ownership import Ownership
from .persist import SpecStore
from .session import COMMAND, SENSOR, Refusal, Session
from .stacked import Node, resolve
from .stats import LatencyWindow, TokenBucket

log = logging.getLogger(LOGGER_NAME)

CONFIG = 2
_EXPIRY_CHECK_NS = 1_000_000_000
_GONE_MEMO_NS = 10_000_000_000
#: A single run_once() call returns after this long even if work remains (ns).
_RUN_BUDGET_NS = 50_000_000


def _spawn_thread(fn: Callable[[], None]) -> None:
    threading.Thread(target=fn, name="pd-service-sync", daemon=True).start()


@dataclass(eq=False, slots=True)
class _Route:
    """Where a session's messages go. ``inbox`` None: known, but served by another instance."""

    session: str
    inbox: deque | None = None
    sess: Session | None = None
    ready: bool = False
    flood: int = 0  # written by callbacks only
    flood_seen: int = 0  # written by the worker only


@dataclass(slots=True)
class _Out:
    """One pending publication: put (payload) or delete (payload None)."""

    key: str
    payload: bytes | None
    sess: Session | None = None
    recv: list[int] = field(default_factory=list)


class ServiceCore:
    """Sessions, dispatch, validation, estimators, counters, errors, persistence, expiry,
    ownership and publish decisions. Thread model: callbacks from any thread; ``run_once``
    from one worker thread; queries from any thread."""

    def __init__(
        self,
        transport: Any,
        settings: Settings,
        *,
        store: SpecStore | None = None,
        now_ns: Callable[[], int] = time.time_ns,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        spawn: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        self.t = transport
        self.settings = settings
        self.instance = settings.instance
        self.store = store
        self.now_ns = now_ns
        self.mono_ns = mono_ns
        self._spawn = spawn or _spawn_thread
        self.lock = threading.RLock()
        self.wake = threading.Event()
        self.ownership = Ownership(self.instance, settings.shard_tuple)
        self.counters: Counter[str] = Counter()
        self.latency = LatencyWindow(settings.latency_window)
        self._specs: dict[str, SessionSpec] = {}
        self._routes: dict[str, _Route] = {}
        self._ready: deque[_Route] = deque()
        self._control: deque[tuple] = deque(maxlen=settings.control_inbox_size)
        self._unknown: deque[tuple] = deque(maxlen=settings.unknown_inbox_size)
        self._control_drops = 0
        self._unknown_drops = 0
        self._ticks: list[tuple[int, int, int, Session]] = []
        self._tick_seq = itertools.count()
        self._outbox: list[_Out] = []
        self._gone: dict[str, int] = {}
        self._unknown_limiter = TokenBucket(settings.error_rate, settings.error_burst, now_ns())
        self._total_limiter = TokenBucket(settings.error_rate_total,
                                          max(1, int(settings.error_rate_total)), now_ns())
        self._next_expiry_ns = 0
        self._handles: list[Any] = []
        self._token: Any = None
        self._started_mono = mono_ns()
        self._closed = False

    # ================================================================== lifecycle ======

    def start(self) -> None:
        """Restore specs, sync with live peers, declare everything, announce presence.

        Order matters: configs are subscribed first (queued until the initial install, so
        none is lost between the peers' snapshot and the subscription), the sessions are
        installed before sensors are subscribed (no spurious "unknown session" at restart),
        and the liveliness token comes last (peers hand sessions over only once we serve).
        """
        t, s = self.t, self.settings
        event(log, "starting", instance=self.instance, shard=s.shard or "rendezvous",
              state_dir=str(self.store.dir) if self.store else "")
        self._handles.append(t.subscribe(keys.ALL_CONFIGS, self._on_config_sample))
        disk: dict[str, SessionSpec] = {}
        if self.store is not None:
            disk, bad = self.store.load_all()
            if bad:
                event(log, "specs_unreadable", logging.WARNING, files=",".join(bad))
        peers = [k.rsplit("/", 1)[-1] for k in t.get_liveliness(keys.ALL_SERVICES,
                                                                 timeout=s.sync_timeout_s)]
        peers = [p for p in peers if p != self.instance]
        specs = dict(disk)
        origin = dict.fromkeys(disk, "restored")
        if peers:
            # Union of disk and peers; the peers' version wins (a change made while we were
            # down reached them, not us). A spec deleted while we were down comes back and
            # expires after expire_s without traffic (we cannot tell it from a spec the
            # peers never had, e.g. when they started with an empty state directory).
            from_peers = self._fetch_peer_specs()
            for name, spec in from_peers.items():
                if disk.get(name) != spec:
                    specs[name], origin[name] = spec, "active"
                    self._persist(spec)
        for p in peers:
            self.ownership.join(p)
        now = self.now_ns()
        with self.lock:
            for name, spec in specs.items():
                self._specs[name] = spec
                detail = "restored from the state directory" if origin[name] == "restored" \
                    else "synced from peers"
                self._install(name, origin[name], detail, now, answer=False)
        self._handles.append(t.subscribe(keys.ALL_SENSORS, self._on_sensor_sample))
        self._handles.append(t.subscribe(keys.ALL_COMMANDS, self._on_command_sample))
        self._handles.append(t.queryable(keys.ALL_STATUS, self._on_status_query))
        self._handles.append(t.queryable(keys.ALL_CONFIGS, self._on_config_query))
        self._handles.append(t.queryable(keys.service_status_key(self.instance),
                                         self._on_service_query))
        self._handles.append(t.subscribe_liveliness(keys.ALL_SERVICES, self._on_liveliness,
                                                    history=True))
        self._token = t.declare_token(keys.service_token_key(self.instance))
        with self.lock:
            served = sum(1 for r in self._routes.values() if r.sess is not None)
        event(log, "ready", instance=self.instance, sessions_known=len(specs),
              sessions_served=served, restored=sum(1 for o in origin.values() if o == "restored"),
              peers=",".join(sorted(peers)))
        self.wake.set()

    def close(self) -> None:
        """Withdraw presence first (peers take over at once), then undeclare everything."""
        if self._closed:
            return
        self._closed = True
        if self._token is not None:
            self._token.close()
        for h in reversed(self._handles):
            try:
                h.close()
            except Exception:  # pragma: no cover - transport already gone
                pass
        self._handles.clear()
        with self.lock:
            served = sum(1 for r in self._routes.values() if r.sess is not None)
        event(log, "stopped", instance=self.instance, sessions_served=served,
              published=self.counters["published"])

    def _fetch_peer_specs(self) -> dict[str, SessionSpec]:
        out: dict[str, SessionSpec] = {}
        try:
            replies = self.t.get(keys.ALL_CONFIGS, timeout=self.settings.sync_timeout_s)
        except Exception as exc:  # a failed sync is not fatal: disk state is used
            event(log, "sync_failed", logging.WARNING, reason=str(exc))
            return out
        for r in replies:
            if not r.ok:
                continue
            try:
                spec = decode(r.payload, SessionSpec)
            except WireError:
                continue
            out.setdefault(spec.session, spec)
        event(log, "synced", specs=len(out), replies=len(replies))
        return out

    # ================================================================== callbacks ======
    # Transport threads. No lock, no decoding, no blocking: split the key, append, wake.

    def _on_sensor_sample(self, sample: Sample) -> None:
        self._enqueue(SENSOR, sample)

    def _on_command_sample(self, sample: Sample) -> None:
        self._enqueue(COMMAND, sample)

    def _enqueue(self, stream: int, sample: Sample) -> None:
        key = sample.key
        parts = key.split("/", 2)
        if len(parts) < 3:
            return
        route = self._routes.get(parts[1])
        item = (stream, key, sample.payload, sample.recv_mono_ns, sample.kind)
        if route is None:
            q = self._unknown
            if len(q) == q.maxlen:
                self._unknown_drops += 1
            q.append((parts[1], item))
            self.wake.set()
            return
        inbox = route.inbox
        if inbox is None:  # served by another instance
            return
        if len(inbox) == inbox.maxlen:
            route.flood += 1
        inbox.append(item)
        if not route.ready:
            route.ready = True
            self._ready.append(route)
            self.wake.set()

    def _on_config_sample(self, sample: Sample) -> None:
        q = self._control
        if len(q) == q.maxlen:
            self._control_drops += 1
        q.append((CONFIG, sample))
        self.wake.set()

    def _on_liveliness(self, key: str, alive: bool) -> None:
        self._control.append(("member", key, alive))
        self.wake.set()

    # ================================================================== worker ========

    def has_work(self) -> bool:
        return bool(self._ready or self._control or self._unknown)

    def run_once(self) -> int:
        """Process what is pending: control, unknown sessions, rounds of session inboxes
        (each followed by its coalesced publications), due ticks and idle expiry, until
        nothing is left or ~50 ms have passed. Returns the number of messages handled."""
        handled = 0
        t_end = self.mono_ns() + _RUN_BUDGET_NS
        while True:
            with self.lock:
                now = self.now_ns()
                if self._control:
                    self._process_control(now)
                touched: list[Session] = []
                if self._unknown:
                    handled += self._process_unknown(now, touched)
                handled += self._round(now, touched)
                if touched:
                    self._publish_many([s for s in touched if s.alive], now)
                self._run_ticks(now)
                if now >= self._next_expiry_ns:
                    self._expire_idle(now)
                    self._next_expiry_ns = now + _EXPIRY_CHECK_NS
                self._flush()
            if not self.has_work() or self.mono_ns() >= t_end:
                return handled

    def next_deadline_ns(self) -> int:
        """Wall-clock time (ns) at which run_once has timed work (next tick or expiry check)."""
        with self.lock:
            d = self._next_expiry_ns
            if self._ticks:
                d = min(d, self._ticks[0][0])
            return d

    # --- rounds -------------------------------------------------------------------------

    def _round(self, now: int, touched: list[Session]) -> int:
        """One round-robin pass over the sessions that were ready when it began."""
        ready = self._ready
        budget = self.settings.batch_budget
        handled = 0
        for _ in range(len(ready)):
            route = ready.popleft()
            route.ready = False
            sess, inbox = route.sess, route.inbox
            if sess is None or inbox is None:
                continue
            if route.flood != route.flood_seen:
                self._note_flood(route, sess, now)
            now_step = sess.step_now(now)
            n = 0
            had_pending = bool(sess.pending_recv)
            while n < budget and inbox:
                item = inbox.popleft()
                n += 1
                self._handle(sess, item, now_step, now)
            handled += n
            if inbox and not route.ready:
                route.ready = True
                ready.append(route)
            if sess.pending_recv and not had_pending:
                touched.append(sess)
        return handled

    def _handle(self, sess: Session, item: tuple, now_step: int, now: int) -> None:
        stream, key, payload, recv_mono, kind = item
        try:
            if kind != "put":
                refusal: Refusal | None = Refusal(
                    "malformed" if stream == SENSOR else "commands_malformed",
                    f"{kind} is not supported on {key!r}: publish a message with put")
            elif stream == SENSOR:
                refusal = sess.on_measurement(key, payload, now_step, now)
                if refusal is None:
                    self.counters["accepted"] += 1
                    sess.pending_recv.append(recv_mono)
                    return
            else:
                refusal = sess.on_command(key, payload, now_step, now)
                if refusal is None:
                    self.counters["commands_accepted"] += 1
                    return
        except Exception as exc:  # isolation: nothing one session sends escapes the worker
            log.debug("internal error in session %s", sess.name, exc_info=True)
            refusal = Refusal("internal_error", f"internal error: {type(exc).__name__}: {exc}")
        self._refuse(sess, key, refusal, now)

    def _refuse(self, sess: Session, key: str, r: Refusal, now: int) -> None:
        sess.counters[r.reason] += 1
        sess.counters["refused"] += 1
        self.counters[r.reason] += 1
        self.counters["refused"] += 1
        if log.isEnabledFor(logging.DEBUG):
            event(log, "refused", logging.DEBUG, session=sess.name, key=key, reason=r.reason,
                  text=r.text)
        if sess.limiter.allow(now) and self._total_limiter.allow(now):
            self._error(sess.error_key, sess.name, key, r.text, r.seq, now)
        else:
            sess.counters["errors_suppressed"] += 1
            self.counters["errors_suppressed"] += 1

    def _error(self, err_key: str, session: str, key: str, text: str, seq: int | None,
               now: int) -> None:
        rep = ErrorReport(session=session, key=key[:512], seq=seq, reason=text[:1024], t_ns=now)
        self._outbox.append(_Out(err_key, encode(rep)))
        self.counters["errors_sent"] += 1

    def _note_flood(self, route: _Route, sess: Session, now: int) -> None:
        seen = route.flood
        dropped = seen - route.flood_seen
        route.flood_seen = seen
        sess.counters["flood"] += dropped
        sess.counters["refused"] += dropped
        self.counters["flood"] += dropped
        self.counters["refused"] += dropped
        if sess.limiter.allow(now) and self._total_limiter.allow(now):
            self._error(sess.error_key, sess.name, keys.ALL_SENSORS.replace("*", sess.name, 1),
                        f"inbox full: dropped {dropped} oldest unread message(s) "
                        f"(more than {self.settings.inbox_size} waiting)", None, now)

    def _process_unknown(self, now: int, touched: list[Session]) -> int:
        q = self._unknown
        n = 0
        if self._unknown_drops:
            self.counters["unknown_flood"] += self._unknown_drops
            self._unknown_drops = 0
        while q:
            session, item = q.popleft()
            n += 1
            route = self._routes.get(session)
            if route is not None:
                sess = route.sess
                if sess is not None:  # configured since the message arrived
                    had = bool(sess.pending_recv)
                    self._handle(sess, item, sess.step_now(now), now)
                    if sess.pending_recv and not had:
                        touched.append(sess)
                continue
            self.counters["unknown_session"] += 1
            self.counters["refused"] += 1
            try:
                check_name(session, "session")
            except KeyError_:
                self.counters["bad_key"] += 1
                continue
            # Every instance knows every spec, so the rendezvous owner of the name reports.
            if self.ownership.owns(session):
                if self._unknown_limiter.allow(now) and self._total_limiter.allow(now):
                    self._error(keys.error_key(session), session, item[1],
                                f"unknown session {session!r}: put a SessionSpec on "
                                f"{keys.config_key(session)!r} first", None, now)
                else:
                    self.counters["errors_suppressed"] += 1
        return n

    # --- publishing ---------------------------------------------------------------------

    def _publish_many(self, sessions: list[Session], now: int) -> None:
        """Publish a Prediction of now + lead for each session: the estimators' pending
        arithmetic is resolved together (stacked), then each message is packed."""
        items = []
        for sess in sessions:
            k = sess.step_now(now)
            if k < 0:  # before the session's epoch: nothing to predict yet
                sess.pending_recv.clear()
                continue
            try:
                items.append((sess, k, sess.predict(k)))
            except Exception as exc:
                self._publish_failed(sess, exc, now)
        nodes = [p.x for _, _, p in items if isinstance(p.x, Node)]
        if nodes:
            try:
                resolve(nodes)
            except Exception:  # isolation: fall back to one session at a time (in pack)
                log.debug("stacked resolve failed; resolving one by one", exc_info=True)
        for sess, k, pred in items:
            try:
                data = sess.pack(pred, k, now)
            except Exception as exc:  # e.g. a non-finite estimate: report, never crash
                self._publish_failed(sess, exc, now)
                continue
            self.counters["published"] += 1
            recv, sess.pending_recv = sess.pending_recv, []
            self._outbox.append(_Out(sess.pred_key, data, sess, recv))

    def _publish_failed(self, sess: Session, exc: Exception, now: int) -> None:
        sess.pending_recv.clear()
        self._refuse(sess, sess.pred_key, Refusal(
            "internal_error", f"prediction failed: {type(exc).__name__}: {exc}"), now)

    def _flush(self) -> None:
        out, self._outbox = self._outbox, []
        put, mono = self.t.put, self.mono_ns
        for o in out:
            try:
                if o.payload is None:
                    self.t.delete(o.key)
                else:
                    put(o.key, o.payload)
            except Exception as exc:
                self.counters["publish_failed"] += 1
                log.debug("publish on %s failed: %s", o.key, exc)
                continue
            if o.recv:
                t = mono()
                for r in o.recv:
                    us = (t - r) / 1000.0
                    o.sess.latency.add(us)  # type: ignore[union-attr]
                    self.latency.add(us)

    # --- ticks --------------------------------------------------------------------------

    def _schedule(self, sess: Session, after_step: int) -> None:
        """Queue the session's next tick: the first step k > after_step with
        k % publish_every == 0, at time epoch + k * period + tick_phase * period."""
        spec = sess.spec
        pe = spec.publish_every
        k = max(0, (after_step // pe + 1) * pe)
        deadline = spec.time_of(k) + int(self.settings.tick_phase * spec.period_ns)
        heapq.heappush(self._ticks, (deadline, next(self._tick_seq), k, sess))

    def _run_ticks(self, now: int) -> None:
        heap = self._ticks
        due: list[Session] = []
        while heap and heap[0][0] <= now:
            _, _, k, sess = heapq.heappop(heap)
            if not sess.alive:
                continue
            cur = sess.step_now(now)
            if cur > k:
                sess.counters["tick_overruns"] += 1
                self.counters["tick_overruns"] += 1
            if cur >= 0 and sess.last_pub_step != cur:
                due.append(sess)
            self._schedule(sess, max(cur, k))
        if due:
            self._publish_many(due, now)

    # ================================================================== control =======

    def _process_control(self, now: int) -> None:
        if self._control_drops:
            self.counters["control_flood"] += self._control_drops
            self._control_drops = 0
        q = self._control
        membership_changed = False
        while q:
            item = q.popleft()
            if item[0] == CONFIG:
                try:
                    self._apply_config(item[1], now)
                except Exception:  # pragma: no cover - defensive
                    log.exception("config handling failed")
                    self.counters["internal_error"] += 1
            elif item[0] == "sync":
                self._apply_sync(item[1], now)
            else:
                _, key, alive = item
                inst = key.rsplit("/", 1)[-1]
                changed = self.ownership.join(inst) if alive else self.ownership.leave(inst)
                if changed:
                    membership_changed = True
                    event(log, "member_joined" if alive else "member_left", instance=inst,
                          members=len(self.ownership.members))
                    if alive and not self._closed:
                        # It may know specs we missed (e.g. it was not reachable yet when
                        # we started): fetch them off the worker thread.
                        self._spawn(self._sync_in_background)
        if membership_changed and self.ownership.shard is None:
            self._reassign(now)

    def _apply_config(self, sample: Sample, now: int) -> None:
        parts = sample.key.split("/")
        try:
            if len(parts) != 3:
                raise KeyError_(sample.key)
            session = check_name(parts[1], "session")
        except KeyError_:
            self.counters["bad_key"] += 1
            return
        if sample.kind == "delete":
            self._remove(session, "removed", "config deleted", now, answer=True)
            return
        try:
            spec = decode(sample.payload, SessionSpec)
            if spec.session != session:
                raise WireError(f"SessionSpec.session: {spec.session!r} does not match the "
                                f"key {sample.key!r}")
            min_ns = int(self.settings.min_period_ms * 1e6)
            if spec.period_ns < min_ns:
                raise WireError(f"SessionSpec.period_ns: {spec.period_ns} is below this "
                                f"service's minimum {min_ns} ns")
            if session not in self._specs and len(self._specs) >= self.settings.max_sessions:
                raise WireError(f"SessionSpec: this service already holds "
                                f"{self.settings.max_sessions} sessions (max_sessions)")
            if self.ownership.owns(session):
                # Let the estimator check the spec before anything changes.
                Session(spec, "active", "", now, 1.0, 1)
        except WireError as exc:
            event(log, "config_refused", session=session, reason=exc.reason)
            route = self._routes.get(session)
            owns = self.ownership.owns(session)
            if owns and route is not None and route.sess is not None:
                # counted (per session and service-wide) and reported by _refuse
                self._refuse(route.sess, sample.key, Refusal("config_refused", exc.reason), now)
            else:
                self.counters["config_refused"] += 1
                if owns and self._unknown_limiter.allow(now):
                    self._error(keys.error_key(session), session, sample.key, exc.reason,
                                None, now)
            return
        old = self._specs.get(session)
        self._gone.pop(session, None)
        if old is not None and old == spec:
            route = self._routes.get(session)
            if route is not None and route.sess is not None:
                self._answer(route.sess, route.sess.state, "unchanged (same spec)", now)
            return
        self._specs[session] = spec
        self._persist(spec)
        detail = "created" if old is None else "replaced (estimator restarted from the prior)"
        self._install(session, "active", detail, now, answer=True)

    def _sync_in_background(self) -> None:
        specs = self._fetch_peer_specs()
        if specs:
            self._control.append(("sync", specs))
            self.wake.set()

    def _apply_sync(self, specs: dict[str, SessionSpec], now: int) -> None:
        """Specs fetched from peers: add the ones we do not know (a known one is kept: a
        newer version of it would have come as a config put)."""
        for name, spec in specs.items():
            if name in self._specs or name in self._gone:
                continue
            self._specs[name] = spec
            self._persist(spec)
            self._install(name, "active", "synced from peers", now,
                          answer=self.ownership.owns(name))

    def _persist(self, spec: SessionSpec) -> None:
        if self.store is None:
            return
        try:
            self.store.save(spec)
        except OSError as exc:
            self.counters["persist_failed"] += 1
            event(log, "persist_failed", logging.ERROR, session=spec.session, reason=str(exc))

    def _install(self, session: str, state: str, detail: str, now: int, answer: bool) -> None:
        """(Re)start ``session`` from its spec if we own it, else route it elsewhere."""
        route = self._routes.get(session)
        if route is None:
            route = _Route(session)
        old = route.sess
        if old is not None:
            old.alive = False
        if not self.ownership.owns(session):
            route.sess, route.inbox = None, None
            self._routes[session] = route
            if old is not None:
                event(log, "session_handed_over", session=session,
                      owner=self.ownership.owner(session) or "")
            return
        try:
            sess = Session(self._specs[session], state, detail, now,
                           self.settings.error_rate, self.settings.error_burst)
        except WireError as exc:  # a persisted or synced spec the estimator refuses
            route.sess, route.inbox = None, None
            self._routes[session] = route
            event(log, "session_failed", logging.ERROR, session=session, reason=exc.reason)
            return
        if route.inbox is None:
            route.inbox = deque(maxlen=self.settings.inbox_size)
        route.sess = sess
        self._routes[session] = route
        if route.inbox and not route.ready:
            route.ready = True
            self._ready.append(route)
        self._schedule(sess, sess.step_now(now) - 1)
        event(log, "session_" + ("restored" if state == "restored" else
                                 "replaced" if old is not None else "started"),
              session=session, state=state, detail=detail, n=sess.spec.n,
              sensors=len(sess.spec.sensors), period_ns=sess.spec.period_ns)
        if answer:
            self._answer(sess, state, detail, now)

    def _remove(self, session: str, state: str, detail: str, now: int, answer: bool) -> None:
        spec = self._specs.pop(session, None)
        route = self._routes.pop(session, None)
        owned = self.ownership.owns(session)
        if spec is None:
            if answer and owned and session not in self._gone:
                self._answer_gone(session, state, "no such session", now, None)
            self._gone[session] = now
            return
        if self.store is not None:
            self.store.remove(session)
        sess = route.sess if route is not None else None
        if sess is not None:
            sess.alive = False
        self._gone[session] = now
        if owned:
            event(log, "session_" + state, session=session, detail=detail)
            if answer:
                self._answer_gone(session, state, detail, now, sess)

    def _expire_idle(self, now: int) -> None:
        limit = int(self.settings.expire_s * 1e9)
        for name, route in list(self._routes.items()):
            sess = route.sess
            if sess is not None and now - sess.last_activity_ns > limit:
                self._remove(name, "expired", f"idle for more than {self.settings.expire_s:g} s",
                             now, answer=True)
                # Tell the other instances (they keep every spec) that it is gone.
                self._outbox.append(_Out(keys.config_key(name), None))
        for name in [n for n, t in self._gone.items() if now - t > _GONE_MEMO_NS]:
            del self._gone[name]

    def _reassign(self, now: int) -> None:
        """Membership changed: start the sessions we now own, stop those we no longer own."""
        members = ",".join(sorted(self.ownership.members))
        for name in self._specs:
            route = self._routes.get(name)
            running = route is not None and route.sess is not None
            owns = self.ownership.owns(name)
            if owns and not running:
                self._install(name, "active", f"taken over (members {members}); estimator "
                              "restarted from the spec's prior", now, answer=True)
            elif running and not owns:
                self._install(name, "active", "", now, answer=False)

    # ================================================================== status ========

    def _session_status(self, sess: Session, state: str, detail: str, now: int) -> SessionStatus:
        p50, p99 = sess.latency.percentiles()
        return SessionStatus(session=sess.name, instance=self.instance, state=state,
                             now_step=sess.spec.step_of(now), counters=sess.counters_snapshot(),
                             published=sess.published, latency_p50_us=p50,
                             latency_p99_us=p99, detail=detail[:1024])

    def _answer(self, sess: Session, state: str, detail: str, now: int) -> None:
        st = self._session_status(sess, state, detail, now)
        self._outbox.append(_Out(sess.status_key, encode(st)))

    def _answer_gone(self, session: str, state: str, detail: str, now: int,
                     sess: Session | None) -> None:
        if sess is not None:
            st = self._session_status(sess, state, detail, now)
        else:
            st = SessionStatus(session=session, instance=self.instance, state=state,
                               now_step=0, published=0, latency_p50_us=0.0,
                               latency_p99_us=0.0, detail=detail)
        self._outbox.append(_Out(keys.status_key(session), encode(st)))

    def session_status(self, session: str) -> SessionStatus | None:
        """Status of a session this instance serves (None otherwise)."""
        with self.lock:
            route = self._routes.get(session)
            if route is None or route.sess is None:
                return None
            s = route.sess
            return self._session_status(s, s.state, s.detail, self.now_ns())

    def service_status(self) -> ServiceStatus:
        with self.lock:
            served = sorted(n for n, r in self._routes.items() if r.sess is not None)
            c = {k: int(v) for k, v in self.counters.items() if v}
            c.setdefault("refused", 0)
            c["late_total"] = c.get("late", 0) + c.get("commands_late", 0)
            c["sessions_served"] = len(served)
            c["sessions_known"] = len(self._specs)
            c["members"] = len(self.ownership.members)
            p50, p99 = self.latency.percentiles()
            return ServiceStatus(instance=self.instance, sessions=served, counters=c,
                                 latency_p50_us=p50, latency_p99_us=p99,
                                 uptime_s=(self.mono_ns() - self._started_mono) / 1e9,
                                 shard=self.settings.shard or "")

    def served_sessions(self) -> list[str]:
        with self.lock:
            return sorted(n for n, r in self._routes.items() if r.sess is not None)

    def known_specs(self) -> dict[str, SessionSpec]:
        with self.lock:
            return dict(self._specs)

    # --- queryables (transport threads) ---------------------------------------------------

    def _on_status_query(self, q: Query) -> None:
        sel = q.key
        with self.lock:
            now = self.now_ns()
            if "*" in sel:
                replies = [(r.sess.status_key, self._session_status(r.sess, r.sess.state,
                                                                    r.sess.detail, now))
                           for r in self._routes.values()
                           if r.sess is not None and intersects(sel, r.sess.status_key)]
                err = None
            else:
                parts = sel.split("/")
                name = parts[1] if len(parts) == 3 else ""
                route = self._routes.get(name)
                if route is not None and route.sess is not None:
                    s = route.sess
                    replies, err = [(s.status_key, self._session_status(s, s.state, s.detail,
                                                                        now))], None
                elif route is None and self._valid_name(name) and self.ownership.owns(name):
                    replies = []
                    err = ErrorReport(session=name, key=sel[:512], reason=f"unknown session "
                                      f"{name!r}", t_ns=now)
                else:
                    return
        for key, st in replies:
            try:
                q.reply(key, encode(st))
            except Exception as exc:  # e.g. the query was dropped meanwhile
                log.debug("status reply failed: %s", exc)
        if err is not None:
            try:
                q.reply_err(encode(err))
            except Exception as exc:
                log.debug("status reply_err failed: %s", exc)

    def _on_service_query(self, q: Query) -> None:
        try:
            q.reply(keys.service_status_key(self.instance), encode(self.service_status()))
        except Exception as exc:
            log.debug("service status reply failed: %s", exc)

    def _on_config_query(self, q: Query) -> None:
        sel = q.key
        with self.lock:
            specs = [(keys.config_key(n), s) for n, s in self._specs.items()
                     if intersects(sel, keys.config_key(n))]
        for key, spec in specs:
            try:
                q.reply(key, encode(spec))
            except Exception as exc:
                log.debug("config reply failed: %s", exc)

    @staticmethod
    def _valid_name(name: str) -> bool:
        try:
            check_name(name)
            return True
        except KeyError_:
            return False
