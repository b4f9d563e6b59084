"""Session lifecycle: specs applied, sessions installed, removed, expired, reassigned,
persisted and synced with the other instances.

Every instance keeps every spec (``specs``) and runs the sessions it owns (rendezvous over
the live instances, or a static shard; :class:`Ownership`). A spec comes from a config put
(checked, persisted, answered with a SessionStatus), from the state directory at start, or
from the peers (at start and whenever an instance joins). A session is (re)started from its
spec's prior on every change (spec replaced), or continued from the state it had: its
checkpoint at restart, the replica held for it at a takeover, the state its previous owner
hands over when it moves to an instance that joins (:meth:`Lifecycle.reassign`). Worker thread only (under the
core's lock), except :meth:`Lifecycle.load_specs` and the background sync.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from functools import partial

from pd_service.backends import Cost, build, prior_span
from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME, event
from pd_service.ratelimit import TokenBucket
from pd_service.transport import Handle, Sample, Transport
from pd_service.wire import CONFIG_RATE_LIMITED, SessionSpec, WireError, decode, keys
from pd_service.wire.keys import KeyError_, check_name

from .admission import Ledger, OverBudget
from .config import Settings
from .dispatch import ConfigChange, Dispatch, Membership, PeerSpecs, Route
from .handover.keeper import HandoverKeeper, inputs_accepted
from .outbox import Outbox
from .ownership import Ownership, next_term
from .session import ANSWERED, COMMAND, READ_BACK, SENSOR, Origin, Refusal, Session
from .spec_store import SpecStore
from .status import SessionPhase, phase_of

log = logging.getLogger(LOGGER_NAME)

#: How long a removed or expired session's name is remembered (ns): a late sync from a peer
#: does not bring it back, and a repeated delete is not answered twice.
_GONE_MEMO_NS = 10_000_000_000
#: Per-session config rate buckets kept (oldest forgotten first).
_MAX_CONFIG_BUCKETS = 10_000


#: Takeover read-backs (one session's sensors, or its commands) in flight at once.
READ_BACKS_IN_FLIGHT = 32


def config_session(key: str) -> str:
    """The session chunk of a config key of either layout (``pd/p<k>/<s>/config``,
    ``pd/<s>/config``) if it is a valid name, else ""."""
    parts = key.split("/")
    name = parts[2] if len(parts) == 4 else parts[1] if len(parts) == 3 else ""
    try:
        return check_name(name, "session")
    except KeyError_:
        return ""


def is_partition_chunk(chunk: str) -> bool:
    try:
        keys.parse_partition(chunk)
        return True
    except KeyError_:
        return False


def spawn_thread(fn: Callable[[], None]) -> None:
    threading.Thread(target=fn, name="pd-service-sync", daemon=True).start()


class Lifecycle:
    """The known specs and the sessions started from them."""

    def __init__(self, transport: Transport, settings: Settings, *, store: SpecStore | None,
                 ownership: Ownership, counters: Tally, dispatch: Dispatch,
                 outbox: Outbox, spawn: Callable[[Callable[[], None]], None],
                 keeper: HandoverKeeper | None = None) -> None:
        self.t = transport
        self.settings = settings
        self.store = store
        self.ownership = ownership
        self.counters = counters
        self.dispatch = dispatch
        self.pub = outbox
        self._spawn = spawn
        self.keeper = keeper
        self.specs: dict[str, SessionSpec] = {}
        self.gone: dict[str, int] = {}
        #: Costs of the sessions run here, against the budgets (pd_service.service.admission).
        self.ledger = Ledger(settings.max_session_bytes, settings.max_session_cpu,
                             settings.memory_budget_bytes, settings.cpu_budget)
        #: Sessions known but not run here because they do not fit: name -> reason.
        self.refused: dict[str, str] = {}
        self._config_buckets: dict[str, TokenBucket] = {}
        self._untrusted_seen: set[str] = set()
        self._config_total = TokenBucket(settings.config_rate_total,
                                         settings.config_burst_total, 0)
        #: Set at close: no more background syncs.
        self.closed = False
        #: Read-back threads of takeovers (joined at a stop: see :meth:`join_background`).
        self._readers: list[threading.Thread] = []
        #: The busy keys declared for each known session, with the spec they are of
        #: (:meth:`_declare_keys`).
        self._declared: dict[str, tuple[SessionSpec, Handle]] = {}
        #: Called after an ownership change, before the sessions move: the data
        #: subscriptions follow the owned partitions (set by the core).
        self.follow: Callable[[], None] | None = None
        #: Sessions gained from an owner that is still up (it hands their state over when
        #: it sees the new membership): name -> (deadline ns, resume source if no state
        #: came by then, the previous owner). Not served until then (:meth:`adopt_handed`).
        self.awaiting: dict[str, tuple[int, Origin, str]] = {}
        #: session -> end of its wait for its senders' caches (:meth:`hold_for_read_back`)
        self.holding: dict[str, int] = {}
        #: session -> the takeover read-backs kept open while it waits (read_back_taken)
        self._read_backs: dict[str, list[Handle]] = {}
        self._read_backs_lock = threading.Lock()

    # ================================================================== start =========

    def trusted_peers(self, instances: list[str]) -> list[str]:
        """The ``instances`` listed in the ``peers`` setting; a warning, once per name, for
        each other one (a stray or forged ``pd/@service/*`` token is never a member)."""
        trusted = set(self.settings.peers)
        out = []
        for inst in instances:
            if inst in trusted:
                out.append(inst)
            elif inst not in self._untrusted_seen and inst != self.ownership.instance:
                if len(self._untrusted_seen) < 1000:
                    self._untrusted_seen.add(inst)
                self.counters["untrusted_peer"] += 1
                event(log, "untrusted_peer", logging.WARNING, instance=inst,
                      detail="liveliness token of an instance not in the peers setting: ignored")
        return out

    def load_specs(self, peers: list[str]
                ) -> tuple[dict[str, SessionSpec], dict[str, SessionPhase]]:
        """The specs to start with and their origin ("restored" or "active"): the state
        directory's, joined with the live peers' (``peers``, who join the ownership)."""
        disk: dict[str, SessionSpec] = {}
        if self.store is not None:
            disk, bad = self.store.load_all()
            if bad:
                event(log, "specs_unreadable", logging.WARNING, files=",".join(bad))
        specs = dict(disk)
        origin: dict[str, SessionPhase] = dict.fromkeys(disk, "restored")
        if peers:
            # Union of disk and peers; the peers' version wins (a change made while we were
            # down reached them, not us). A spec deleted while we were down comes back and
            # expires after expire_s without traffic (we cannot tell it from a spec the
            # peers never had, e.g. when they started with an empty state directory).
            from_peers = self.fetch_peer_specs()
            for name, spec in from_peers.items():
                if disk.get(name) != spec:
                    specs[name], origin[name] = spec, "active"
                    self.persist(spec)
        for p in peers:
            self.ownership.join(p)
        return specs, origin

    def install_loaded(self, specs: dict[str, SessionSpec],
                          origin: dict[str, SessionPhase], now: int) -> None:
        """Start the sessions :meth:`load_specs` found (not answered: nobody asked)."""
        own = self.ownership
        for name, spec in specs.items():
            self.specs[name] = spec
            prev = own.successor(name) if own.shard is None and own.owns(name) else None
            if prev is not None:  # a live peer serves it: it hands it over on our token
                self._await_handover(name, prev, "checkpoint", now)
                continue
            detail = "restored from the state directory" if origin[name] == "restored" \
                else "synced from peers"
            self.install(name, origin[name], detail, now, answer=False, resume="checkpoint")

    def fetch_peer_specs(self, known: Callable[[str], bool] | None = None
                         ) -> dict[str, SessionSpec]:
        """Every spec the live peers hold (the first reply wins), but those of the sessions
        ``known`` says are known already. Blocks up to ``sync_timeout_s``.

        A reply is decoded only if the session its key names is neither known nor decoded
        already: each peer answers with every spec it holds, so at a join every instance
        receives all specs once per peer, and decoding them all (the models' validation,
        with the GIL held) would hold up the workers of a whole fleet for what it knows."""
        out: dict[str, SessionSpec] = {}
        t0 = time.perf_counter()
        try:
            replies = self.t.get(keys.ALL_CONFIGS, timeout=self.settings.sync_timeout_s)
        except Exception as exc:  # a failed sync is not fatal: disk state is used
            event(log, "sync_failed", logging.WARNING, reason=str(exc))
            return out
        t_get = time.perf_counter() - t0
        decoded = 0
        for r in replies:
            if not r.ok:
                continue
            name = keys.session_of(r.key)
            if name is not None and (name in out or (known is not None and known(name))):
                continue
            try:
                spec = decode(r.payload, SessionSpec)
            except WireError:
                continue
            decoded += 1
            out.setdefault(spec.session, spec)
        event(log, "synced", specs=len(out), replies=len(replies), decoded=decoded,
              get_s=round(t_get, 3), seconds=round(time.perf_counter() - t0, 3))
        return out

    # ================================================================== control =======

    def process_control(self, now: int) -> None:
        """Apply the control inbox: config changes, peers' specs, membership changes."""
        d = self.dispatch
        if d.control_drops:
            self.counters["control_flood"] += d.control_drops
            d.control_drops = 0
        q = d.control
        membership_changed = joined = False
        before: list[str | None] | None = None  # the partition table before the changes
        # Config changes: rate-limited per session and service-wide, at most config_slice
        # per round, so that replacing specs in a loop costs its sender, not the others.
        cq = d.configs
        for _ in range(min(len(cq), self.settings.config_slice)):
            change = cq.popleft()
            if not self._config_allowed(change.sample, now):
                continue
            try:
                self.apply_config(change.sample, now)
            except Exception:  # pragma: no cover - defensive
                log.exception("config handling failed")
                self.counters["internal_error"] += 1
        while q:
            item = q.popleft()
            if isinstance(item, ConfigChange):  # pragma: no cover - configs have their queue
                cq.append(item)
            elif isinstance(item, PeerSpecs):
                self.apply_sync(item.specs, now)
            elif isinstance(item, Membership):
                inst = item.key.rsplit("/", 1)[-1]
                alive = item.alive
                if inst != self.ownership.instance and not self.trusted_peers([inst]):
                    continue
                if before is None:
                    before = self.ownership.owners()
                changed = self.ownership.join(inst) if alive else self.ownership.leave(inst)
                if changed:
                    membership_changed = True
                    joined = joined or alive
                    event(log, "member_joined" if alive else "member_left", instance=inst,
                          members=len(self.ownership.members))
                    if alive and not self.closed:
                        # It may know specs we missed (e.g. it was not reachable yet when
                        # we started): fetch them off the worker thread.
                        self._spawn(self._sync_in_background)
        if membership_changed and self.ownership.shard is None:
            self.reassign(now, before)
            if joined:
                self.renew_terms(now)

    def renew_terms(self, now: int) -> None:
        """An instance joined (or came back: a partition's heal): every session still served
        here starts a new term. The joiner may have served some of them meanwhile under a
        newer term than ours; readers then drop our output until we publish a newer one,
        which, if its hand-over state never comes, would be never. Newer than the joiner's
        if the hosts' clocks agree to better than the partition lasted; the state, when it
        comes, is settled by :meth:`settle_second_owner`."""
        me, n = self.ownership.instance, 0
        for name, route in self.dispatch.routes.items():
            sess = route.sess
            if sess is not None and self.ownership.owns(name):
                sess.term = next_term(sess.term, me, now)
                n += 1
        if n:
            event(log, "terms_renewed", sessions=n, detail="an instance joined")

    def _config_allowed(self, sample: Sample, now: int) -> bool:
        """Take a token from the sender session's bucket and the service's; refuse
        (counted ``config_rate_limited``, reported within the error budget) if either is
        empty."""
        session = config_session(sample.key)
        s = self.settings
        b = self._config_buckets.get(session)
        if b is None:
            if len(self._config_buckets) >= _MAX_CONFIG_BUCKETS:  # forget the oldest
                self._config_buckets.pop(next(iter(self._config_buckets)))
            b = self._config_buckets[session] = TokenBucket(s.config_rate, s.config_burst, now)
        if b.allow(now):
            if self._config_total.allow(now):
                return True
            b.refund()  # the service-wide limit refused it: the session's share is not used
        self.pub.refuse(None, sample.key, Refusal(
            "config_rate_limited", f"{CONFIG_RATE_LIMITED}: config change refused: more than "
            f"{s.config_rate:g} per "
            f"second for this session or {s.config_rate_total:g} per second for this service "
            "(config_rate, config_rate_total)"), now, session=session,
            counted=("config_rate_limited", "config_refused"),
            report=bool(session) and self.ownership.owns(session))
        return False

    def apply_config(self, sample: Sample, now: int) -> None:
        """A put (checked, then installed) or delete (removed) on ``pd/p<k>/<session>/config``;
        one on a key of layout 1 (``pd/<session>/config``) or on another partition than the
        session's (a client with another P) is refused with the reason."""
        key = sample.key
        if keys.is_legacy_key(key):
            self._refuse_key(key, keys.legacy_reason(key), "legacy_keys", now)
            return
        try:
            session = keys.parse_key(key).session
        except KeyError_ as exc:
            if config_session(key) and is_partition_chunk(key.split("/")[1]):
                self._refuse_key(key, str(exc), "wrong_partition", now)
            else:
                self.counters["bad_key"] += 1
            return
        if sample.kind == "delete":
            self.remove(session, "removed", "config deleted", now, answer=True)
            return
        routes = self.dispatch.routes
        checked: Session | None = None
        try:
            spec = decode(sample.payload, SessionSpec)
            if spec.session != session:
                raise WireError(f"SessionSpec.session: {spec.session!r} does not match the "
                                f"key {sample.key!r}")
            min_ns = int(self.settings.min_period_ms * 1e6)
            if spec.period_ns < min_ns:
                raise WireError(f"SessionSpec.period_ns: {spec.period_ns} is below this "
                                f"service's minimum {min_ns} ns")
            far = prior_span(spec, now)
            if far is not None:
                self.counters["epoch_too_old"] += 1
                raise WireError(far)
            if session not in self.specs and len(self.specs) >= self.settings.max_sessions:
                raise WireError(f"SessionSpec.session: this service already holds "
                                f"{self.settings.max_sessions} sessions (max_sessions)")
            if self.ownership.owns(session):
                # build checks the cost against the budgets before it allocates anything,
                # then the estimator checks the spec, before anything here changes.
                try:
                    built = build(spec, admit=partial(self.ledger.check, session))
                except OverBudget as ref:
                    self.counters["admission_refused"] += 1
                    raise WireError(ref.reason) from None
                st = self.settings
                checked = Session(spec, built, "active", "", now, st.error_rate,
                                  st.error_burst, st.max_abs_input)  # installed below: built once
        except WireError as exc:
            event(log, "config_refused", session=session, reason=exc.reason)
            route = routes.get(session)
            owns = self.ownership.owns(session)
            if owns and route is not None and route.sess is not None:
                # counted (per session and service-wide) and reported by refuse
                self.pub.refuse(route.sess, sample.key, Refusal("config_refused", exc.reason),
                                now)
            else:
                self.pub.refuse(None, sample.key, Refusal("config_refused", exc.reason), now,
                                session=session, counted=("config_refused",), report=owns)
            return
        old = self.specs.get(session)
        self.gone.pop(session, None)
        if old is not None and old == spec:
            route = routes.get(session)
            if route is not None and route.sess is not None:
                self.pub.answer(route.sess, phase_of(route.sess), "unchanged (same spec)",
                                now)
            return
        self.specs[session] = spec
        failed = self.persist(spec)
        detail = "created" if old is None else "replaced (estimator restarted from the prior)"
        if old is not None and self.keeper is not None:
            self.keeper.forget(session)  # the old spec's checkpoint and replica: never resumed
        if failed:
            detail = f"{detail}; {failed}"
        self.install(session, "active", detail, now, answer=True, built=checked)

    def _refuse_key(self, key: str, reason: str, counter: str, now: int) -> None:
        """A config on a key this service does not take (layout 1, or another partition):
        counted ``counter`` and reported by the session's owner on the error key beside the
        sender's (``keys.error_key_beside``: where that client listens), within the limits."""
        session = config_session(key)
        event(log, "config_refused", session=session, reason=reason)
        self.pub.refuse(None, key, Refusal(counter, reason), now, session=session,
                        counted=(counter,), report=self.ownership.owns(session),
                        to=keys.error_key_beside(key))

    def _sync_in_background(self) -> None:
        specs = self.fetch_peer_specs(self._known)
        if specs:
            self.dispatch.post_peer_specs(specs)

    def _known(self, session: str) -> bool:
        """Any thread: ``session``'s spec is held here, or it was removed lately (a sync does
        not bring it back: :meth:`apply_sync`)."""
        return session in self.specs or session in self.gone

    def apply_sync(self, specs: dict[str, SessionSpec], now: int) -> None:
        """Specs fetched from peers: add the ones we do not know (a known one is kept: a
        newer version of it would have come as a config put)."""
        for name, spec in specs.items():
            if name in self.specs or name in self.gone:
                continue
            self.specs[name] = spec
            self.persist(spec)
            self.install(name, "active", "synced from peers", now,
                         answer=self.ownership.owns(name))

    def persist(self, spec: SessionSpec) -> str:
        """Save ``spec``; "" once durable, else why not (counted ``persist_failed``; the
        service's ``state_dir_unhealthy`` counter is 1 until a write succeeds again)."""
        if self.store is None:
            return ""
        try:
            self.store.save(spec)
        except OSError as exc:
            return self._persist_failed(spec.session, exc)
        self.counters["state_dir_unhealthy"] = 0
        return ""

    def _persist_failed(self, session: str, exc: OSError) -> str:
        self.counters["persist_failed"] += 1
        self.counters["state_dir_unhealthy"] = 1
        event(log, "persist_failed", logging.ERROR, session=session, reason=str(exc))
        return f"NOT persisted ({exc.strerror or exc}): it will not survive a restart"

    # ================================================================== sessions ======

    def install(self, session: str, state: SessionPhase, detail: str, now: int,
                answer: bool, resume: Origin = "prior", built: Session | None = None) -> None:
        """(Re)start ``session`` from its spec if we own it, else route it elsewhere;
        ``resume``: continue from its checkpoint or the replica held for it, if it passes
        (pd_service.service.handover.keeper), else from the spec's prior. ``built``: a session
        just built from this spec at ``now`` (by the config check), used instead of a new
        one."""
        self.awaiting.pop(session, None)
        routes = self.dispatch.routes
        route = routes.get(session)
        if route is None:
            route = Route(session)
        old = route.sess
        if old is not None:
            old.alive = False
        owns = self.ownership.owns(session)
        self._declare_keys(session, self.specs.get(session) if owns else None)
        if not owns:
            self.ledger.release(session)
            self.refused.pop(session, None)
            route.sess, route.inbox = None, None
            routes[session] = route
            if old is not None:
                event(log, "session_handed_over", session=session,
                      owner=self.ownership.owner(session) or "")
            return
        spec = self.specs[session]
        admitted = False  # a refusal before the ledger took the cost, or a failure after

        def admit(cost: Cost) -> None:
            nonlocal admitted
            self.ledger.admit(session, cost)
            admitted = True

        try:
            if built is not None and built.spec is spec:
                admit(built.cost)
                sess = built
                sess.state, sess.detail = state, detail
            else:
                st = self.settings
                sess = Session(spec, build(spec, admit), state, detail, now, st.error_rate,
                               st.error_burst, st.max_abs_input)
        except (OverBudget, WireError) as exc:
            self.ledger.release(session)
            if admitted:  # a persisted or synced spec the estimator refuses
                route.sess, route.inbox = None, None
                routes[session] = route
                event(log, "session_failed", logging.ERROR, session=session,
                      reason=exc.reason)
                return
            # e.g. a persisted spec over today's budget
            self.counters["admission_refused"] += 1
            event(log, "session_refused", logging.WARNING, session=session, reason=exc.reason)
            if state == "restored":  # a persisted spec that no longer fits: set aside
                self.specs.pop(session, None)
                self._declare_keys(session, None)
                routes.pop(session, None)
                if self.store is not None:
                    self.store.set_aside(session, exc.reason)
                return
            route.sess, route.inbox = None, None
            routes[session] = route
            self.refused[session] = exc.reason
            return
        self.refused.pop(session, None)
        if resume != "prior" and self.keeper is not None:
            self.keeper.resume(sess, resume, now)
            if sess.origin != "prior":
                detail = sess.detail = (f"{detail}; estimate resumed from the {sess.origin} of "
                                        f"step {sess.origin_step}")
            if self.settings.recover_samples > 0:
                self.hold_for_read_back(sess, now)
        # newer than every term this instance knows for the session (ownership.next_term)
        sess.term = next_term(max(sess.resumed_term, old.term if old is not None else 0),
                              self.ownership.instance, now)
        if route.inbox is None:
            route.inbox = deque(maxlen=self.settings.inbox_size)
        route.sess = sess
        routes[session] = route
        self.dispatch.mark_ready(route)
        self.pub.schedule(sess, sess.step_now(now) - 1)
        event(log, "session_" + ("restored" if state == "restored" else
                                 "replaced" if old is not None else "started"),
              session=session, state=state, detail=detail, n=sess.spec.n,
              sensors=len(sess.spec.sensors), period_ns=sess.spec.period_ns)
        if answer:
            self.pub.answer(sess, state, detail, now)

    def remove(self, session: str, state: SessionPhase, detail: str, now: int,
               answer: bool) -> None:
        """Forget ``session`` (its spec, stored file and route); answer if we own it."""
        spec = self.specs.pop(session, None)
        route = self.dispatch.routes.pop(session, None)
        self.ledger.release(session)
        self.refused.pop(session, None)
        owned = self.ownership.owns(session)
        if spec is None:
            if answer and owned and session not in self.gone:
                self.pub.answer_gone(session, state, "no such session", now, None)
            self.gone[session] = now
            return
        if self.store is not None:
            try:
                self.store.remove(session)
            except OSError as exc:
                detail = (f"{detail}; its file could NOT be removed ({exc.strerror or exc}): "
                          "it comes back at restart")
                self.counters["persist_failed"] += 1
                self.counters["state_dir_unhealthy"] = 1
                event(log, "remove_failed", logging.ERROR, session=session, reason=str(exc))
        if self.keeper is not None:
            self.keeper.forget(session)
        self._declare_keys(session, None)
        sess = route.sess if route is not None else None
        if sess is not None:
            sess.alive = False
        self.gone[session] = now
        if owned:
            event(log, "session_" + state, session=session, detail=detail)
            if answer:
                self.pub.answer_gone(session, state, detail, now, sess)

    def _declare_keys(self, session: str, spec: SessionSpec | None) -> None:
        """Declare the keys of ``session`` with ``spec`` (None: withdraw them): its commands,
        sensors, predictions and error reports, the keys of nearly every message it
        receives or sends (Transport.declare_keys: routed by cached routes; an overloaded
        daemon refusing late samples sends up to ``error_rate_total`` reports a second).
        Only the sessions served here: an instance receives the samples of its own
        partitions only, and what it declares stays in the routers' tables (declarations
        per instance grow with its share of the sessions, not with all of them)."""
        old = self._declared.get(session)
        if old is not None and old[0] is spec:
            return
        if old is not None:
            del self._declared[session]
            old[1].close()
        if spec is None:
            return
        names = [keys.command_key(session), keys.prediction_key(session),
                 keys.error_key(session)]
        names += [keys.sensor_key(session, s.name) for s in spec.sensors]
        if spec.path is not None:
            names.append(keys.path_key(session))
        try:
            self._declared[session] = (spec, self.t.declare_keys(names))
        except Exception as exc:  # the transport is closing, say: routing still works
            log.debug("declaring the keys of %s failed: %s", session, exc)

    def expire_idle(self, now: int) -> None:
        """Remove the sessions idle for more than their lifetime (the spec's ``expire_s``,
        else the setting's; 0: never); forget old removals."""
        default = self.settings.expire_s
        for name, route in list(self.dispatch.routes.items()):
            sess = route.sess
            if sess is None:
                continue
            expire_s = sess.spec.expire_s if sess.spec.expire_s is not None else default
            if expire_s and now - sess.last_activity_ns > expire_s * 1e9:
                self.remove(name, "expired", f"idle for more than {expire_s:g} s",
                            now, answer=True)
                # Tell the other instances (they keep every spec) that it is gone.
                self.pub.delete(keys.config_key(name))
        for name in [n for n, t in self.gone.items() if now - t > _GONE_MEMO_NS]:
            del self.gone[name]

    def read_back_taken(self, names: list[str]) -> None:
        """Off the worker (``spawn``): read back what the senders of sessions just taken
        over kept (what the previous owner accepted after its last replica, what was sent
        while nobody served them); the samples reach the worker as recovered messages.

        Up to :data:`READ_BACKS_IN_FLIGHT` read-backs (one session's sensors, or its
        commands) run at once, and a session rejoins the rounds as soon as both of its own
        end: a slow or silent sender (its query waits up to ``recover_timeout_s``) holds its
        own session only, and taking over N sessions costs ~2N / READ_BACKS_IN_FLIGHT round
        trips, not 2N."""
        s = self.settings
        t0 = time.monotonic()
        failed: list[str] = []
        lock = self._read_backs_lock
        #: per session and stream (SENSOR, COMMAND): the samples read back
        got = {(name, stream): list[tuple[int, Sample]]() for name in names
               for stream in (SENSOR, COMMAND)}
        left = dict.fromkeys(names, 2)  # per session: its read-backs not ended
        total = [0]
        posted: set[str] = set()  # sessions whose read-back went to the worker
        d = self.dispatch

        def one(task: tuple[str, int]) -> None:
            name, stream = task
            items = got[task]

            def on(sample: Sample) -> None:
                with lock:
                    if name not in posted:
                        items.append((stream + READ_BACK, sample))
                        return
                # a sender that appeared after the present caches were read (it reconnects)
                (d.on_read_back_command if stream == COMMAND else d.on_read_back_sensor)(sample)

            def on_answered(key: str) -> None:
                with lock:
                    if name not in posted:
                        items.append((ANSWERED, Sample(key, b"", "put", 0, 0)))
                        return
                d.on_cache_answered(key)

            key = keys.command_key(name) if stream == COMMAND \
                else keys.sensors_of(name)
            try:
                if not self.closed:
                    # kept open while the session waits for its senders (release_holds
                    # closes it): one that connects later is read when it appears
                    h = self.t.read_back(key, on, max_samples=s.recover_samples,
                                         timeout=s.recover_timeout_s, answered=on_answered)
                    with lock:
                        keep = name in self.holding
                        if keep:
                            self._read_backs.setdefault(name, []).append(h)
                    if not keep:
                        h.close()
            except Exception as exc:  # the transport is closing, say
                failed.append(f"{key}: {exc}")
            with lock:
                left[name] -= 1
                if left[name]:
                    return
                done = got[name, SENSOR] + got[name, COMMAND]
                total[0] += len(done)
                posted.add(name)
            d.post_released([name], done)

        tasks = deque(got)

        def work() -> None:
            while True:
                try:
                    task = tasks.popleft()  # atomic: each task is taken once
                except IndexError:
                    return
                one(task)

        # daemon threads, not an executor's (the interpreter joins those at exit, unbounded):
        # a stop closes the transport, which ends their calls, then joins them with a bound
        # (join_background)
        threads = [threading.Thread(target=work, name="pd-readback", daemon=True)
                   for _ in range(max(1, min(READ_BACKS_IN_FLIGHT, len(tasks))))]
        self._readers = [th for th in self._readers if th.is_alive()] + threads
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        if failed:
            event(log, "recover_failed", logging.WARNING, keys=len(failed), first=failed[0])
        event(log, "read_back", sessions=len(names), samples=total[0],
              seconds=f"{time.monotonic() - t0:.3f}")

    def join_background(self, timeout: float) -> bool:
        """At a stop (``closed`` set, before the transport closes): wait up to ``timeout`` s for the
        read-back threads still inside a transport call; a process that exits under them
        can crash in Zenoh's native code. True if none is left."""
        deadline = time.monotonic() + timeout
        for th in list(self._readers):
            if th.ident is not None:  # one not started yet finds ``closed`` set and ends
                th.join(max(0.0, deadline - time.monotonic()))
        return not any(th.is_alive() for th in self._readers)

    def reassign(self, now: int, before: list[str | None] | None = None) -> None:
        """Membership changed: subscribe to the data of the partitions gained and unsubscribe
        from those lost (:attr:`follow`), start the sessions we now own, stop those we no
        longer own.

        A session that moves between two live instances (a join; ``before``: the partition
        table before the change) is handed over: its old owner sends its state to the new
        one before it stops serving it (:meth:`HandoverKeeper.hand_to`); the new owner
        waits for that state (:meth:`adopt_handed`). A session whose owner went away is
        taken over at once from the replica held for it. Logged (``reassigned``) with the
        wall time of its parts (s): the subscriptions' changes, the states handed over, the
        rest (installs and removals)."""
        t0 = time.perf_counter()  # diagnostics only: how long the worker spent here
        if self.follow is not None:
            self.follow()
        t_follow = time.perf_counter() - t0
        t_hand, handed, started = 0.0, 0, 0
        own = self.ownership
        members = ",".join(sorted(own.members))
        routes = self.dispatch.routes
        taken: list[str] = []
        for name in self.specs:
            route = routes.get(name)
            running = route is not None and route.sess is not None
            owns = own.owns(name)
            if owns and not running:
                waiting = self.awaiting.get(name)
                if waiting is not None and waiting[2] in own.members:
                    continue  # its previous owner's state is on its way
                # (one whose previous owner went away before handing it over: taken over)
                prev = None if before is None else \
                    before[keys.partition_of(name, own.partitions)]
                if prev is not None and prev != own.instance and prev in own.members:
                    self._await_handover(name, prev, "replica", now)
                    continue
                self.install(name, "active", f"taken over (members {members})", now,
                             answer=True, resume="replica")
                started += 1
                if self.settings.recover_samples > 0 and not self.closed:
                    taken.append(name)
                    self.dispatch.park(routes[name])
            elif running and not owns:
                assert route is not None and route.sess is not None
                new = own.owner(name)
                if self.keeper is not None and new is not None and not self.closed:
                    t1 = time.perf_counter()
                    self.keeper.hand_to(route.sess, new, now)
                    t_hand += time.perf_counter() - t1
                handed += 1
                self.install(name, "active", "", now, answer=False)
            elif not owns:
                self.awaiting.pop(name, None)
        if taken:
            self._spawn(lambda: self.read_back_taken(taken))
        total = time.perf_counter() - t0
        event(log, "reassigned", members=members, handed_over=handed, taken_over=started,
              awaited=len(self.awaiting), seconds=round(total, 4),
              subscriptions_s=round(t_follow, 4), handover_s=round(t_hand, 4),
              rest_s=round(total - t_follow - t_hand, 4))

    def settle_second_owner(self, now: int) -> None:
        """Two owners (a partition healed): a state arrived from another instance for a
        session served here. The output of the older term ends: the session goes on here
        with a term newer than both (every reader drops the older ones). The estimate kept is
        the one that took in more inputs (:func:`.handover.keeper.inputs_accepted`; a tie:
        the newer term's), so that a side that did not receive the session's data during the
        partition does not replace one that did:

        - the other's (``term_yielded``, logged WARNING ``term_yielded``, said in the status
          detail): the session restarts from that state, as at a hand-over;
        - this instance's own (``term_kept``): the estimate stays, the term is renewed if
          the other's is not older (at a heal :meth:`renew_terms` did so already); so for a
          session the other held at its prior alone (a delete: no state, no term).

        Either way the senders' caches are read back: what reached only the other side
        inside the window comes back. A session that yields waits for them (its inputs
        meanwhile kept and taken in at their stamps, :meth:`hold_for_read_back`); one that
        keeps its estimate goes on taking in its live inputs and publishing meanwhile, not
        parked: its ticks would move its window past the live inputs waiting in a parked
        inbox, refused as late when the read-back ends. The other owner stops serving the
        session when it sees the membership (:meth:`reassign`)."""
        if self.keeper is None:
            return
        routes = self.dispatch.routes
        me = self.ownership.instance
        taken: list[str] = []
        for name, (term, writer, inputs) in self.keeper.take_terms().items():
            route = routes.get(name)
            sess = route.sess if route is not None else None
            if sess is None or not self.ownership.owns(name) or writer == me:
                continue
            if term and writer == sess.resumed_writer and term <= sess.resumed_term:
                continue  # (a copy of) the state it was resumed from or settled with
            own = inputs_accepted(sess.counters)
            if term > 0 and (inputs, term) > (own, sess.term) and self.keeper.holds(name):
                self.counters["term_yielded"] += 1
                event(log, "term_yielded", logging.WARNING, session=name, term=sess.term,
                      other_term=term, other=writer, inputs=inputs, own_inputs=own)
                self.install(name, "active", f"yielded to {writer}'s estimate (term {term}, "
                             f"{inputs} inputs accepted; this instance's term {sess.term}, "
                             f"{own}: two owners, e.g. a healed partition)", now,
                             answer=True, resume="replica")
            else:
                if term == 0:
                    self.keeper.drop_prior_mark(name)
                old = sess.term
                if term >= sess.term:
                    sess.term = next_term(term, me, now)
                sess.resumed_writer, sess.resumed_term = writer, term  # settled: copies too
                self.counters["term_kept"] += 1
                event(log, "term_kept", logging.WARNING, session=name, term=old,
                      new_term=sess.term, other_term=term, other=writer or "?", inputs=inputs,
                      own_inputs=own)
                sess.detail = (f"{sess.detail}; kept its estimate over a second owner's "
                               f"({writer or 'at its prior alone'}, term {term}, {inputs} "
                               f"inputs accepted; this instance {own})")[-1024:]
            route = routes.get(name)
            if self.settings.recover_samples > 0 and not self.closed and route is not None \
                    and route.sess is not None:
                taken.append(name)
                if route.sess.hold_until_ns:  # yielded: resumed, waits for the caches
                    self.dispatch.park(route)
        if taken:
            self._spawn(lambda: self.read_back_taken(taken))

    def _await_handover(self, name: str, prev: str, fallback: Origin, now: int) -> None:
        """``name`` is ours now but ``prev`` (alive) served it: known here, not served, until
        a state is held for it or ``recover_timeout_s`` passes (:meth:`adopt_handed`). A
        replica held already (an instance that gains a partition from another old member,
        often its successor) is resumed from at once, as at a takeover, the senders' caches
        filling the gap: its hand-over state may have come before this wait began."""
        deadline = now + int(self.settings.recover_timeout_s * 1e9)
        self.awaiting[name] = (deadline, fallback, prev)
        self._declare_keys(name, self.specs.get(name))
        routes = self.dispatch.routes
        route = routes.get(name) or Route(name)
        route.sess, route.inbox = None, None  # its messages are read back from the caches
        routes[name] = route
        event(log, "handover_awaited", session=name, previous_owner=prev)

    def next_await_ns(self) -> int | None:
        """When the first wait for a hand-over state or for a read-back ends (None: none)."""
        return min([*(w[0] for w in self.awaiting.values()), *self.holding.values()],
                   default=None)

    def hold_for_read_back(self, sess: Session, now: int) -> None:
        """A restarted or taken-over ``sess`` publishes nothing until the cache of each of
        its data keys (every sensor's, and the command's if it takes commands) has been read
        back (:meth:`Dispatch.cache_answered`), or ``2 x recover_timeout_s`` passed
        (:meth:`release_holds`): its first prediction then has what the senders kept. Its
        inputs meanwhile, live and read back, are kept and taken in at their own steps when
        the wait ends (:meth:`Dispatch.catch_up`)."""
        name = sess.name
        want = {keys.sensor_key(name, x.name) for x in sess.spec.sensors}
        if sess.intake.r:
            want.add(keys.command_key(name))
        sess.unanswered = want
        sess.hold_until_ns = self.holding[name] = now + int(2e9 * self.settings.recover_timeout_s)
        sess.readback = "waiting"
        # its inputs meanwhile are taken in at their stamps when the wait ends (catch_up)
        self.dispatch.held_inputs[name] = []

    def release_holds(self, now: int, touched: list[Session]) -> None:
        """Worker: the sessions whose wait for their senders' caches ended (answered, or
        its bound passed: then they publish with what they have, ``readback_timeout``).
        A session whose takeover read-back still runs is released when it ends."""
        routes = self.dispatch.routes
        for name, until in list(self.holding.items()):
            route = routes.get(name)
            sess = route.sess if route is not None else None
            if sess is not None and sess.hold_until_ns:
                if now < until or name in self.dispatch.parked:
                    continue
                self.dispatch.release_hold(sess, "timeout", now, touched)
            del self.holding[name]
            self.dispatch.held_inputs.pop(name, None)  # a session gone meanwhile
            with self._read_backs_lock:
                handles = self._read_backs.pop(name, [])
            for h in handles:
                h.close()

    def adopt_handed(self, now: int) -> None:
        """Start the awaited sessions whose hand-over state arrived (resumed from it), or
        whose wait ended (from the fallback: checkpoint or older replica, else the prior,
        said in their status detail and the log); then read back their senders' caches as a
        takeover does (what the old owner accepted after the state, what came meanwhile)."""
        members = ",".join(sorted(self.ownership.members))
        taken: list[str] = []
        for name, (deadline, fallback, prev) in list(self.awaiting.items()):
            arrived = self.keeper.handed(name) if self.keeper is not None else ""
            if not arrived and now < deadline:
                continue
            del self.awaiting[name]
            if name not in self.specs or not self.ownership.owns(name):
                continue
            if arrived:
                self.install(name, "active", f"handed over by {prev} (members {members})",
                             now, answer=True, resume="replica" if arrived == "replica"
                             else "prior")
            else:
                self.counters["handover_timeout"] += 1
                event(log, "handover_timeout", logging.WARNING, session=name,
                      previous_owner=prev, waited_s=self.settings.recover_timeout_s)
                self.install(name, "active", f"no state handed over by {prev} within "
                             f"recover_timeout_s (members {members})", now, answer=True,
                             resume=fallback)
            if self.settings.recover_samples > 0 and not self.closed \
                    and name in self.dispatch.routes:
                route = self.dispatch.routes[name]
                if route.sess is not None:
                    taken.append(name)
                    self.dispatch.park(route)
        if taken:
            self._spawn(lambda: self.read_back_taken(taken))
