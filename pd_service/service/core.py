"""ServiceCore: everything the daemon does, minus threads and Zenoh.

The core composes four parts, one job each, and talks to the world only through a
:class:`~pd_service.transport.Transport` (Zenoh in the daemon, :class:`InMemoryBus` in unit
tests); it reads time only through injected clocks (``now_ns``: shared wall clock for
steps, by default a :class:`StepClock` on the host's clocks, re-anchored deliberately when the
host clock steps; ``mono_ns``: monotonic clock for latencies; ``run_clock_ns``: the one of run_once's
time budget, ``mono_ns`` by default), so tests drive it deterministically.

- :mod:`.dispatch`: callbacks -> bounded inboxes -> round-robin rounds of session messages;
- :mod:`.lifecycle`: specs applied, sessions installed / removed / expired / reassigned,
  persisted and synced with the peers;
- :mod:`.publish`: predictions (after each round, at each tick), error reports, status
  answers, the outbox;
- :mod:`.status`: SessionStatus / ServiceStatus and the status and spec queryables;
- :mod:`.clock_probes`: the robots' command echoes and the clock probes (their own thread).

One worker thread calls :meth:`ServiceCore.run_once`; it holds ``lock`` while processing one
round. The queries (transport threads) take it only to copy what a reply needs, so replies
never see a half-updated session and never stall the worker (they build, encode and send
with the lock free). Callbacks never take it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Final

from pd_service import native
from pd_service.estimation.linear import set_tables_max_bytes
from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME, event
from pd_service.transport import Handle, Transport
from pd_service.wire import ServiceStatus, SessionSpec, SessionStatus, encode, keys

from .clock_probes import RobotTimeIO
from .config import Settings
from .dispatch import ROUND_SESSIONS, Dispatch, Route
from .handover.keeper import HandoverKeeper, replicas_for
from .latency import LatencyWindow
from .lifecycle import Lifecycle, spawn_thread
from .outbox import Outbox
from .ownership import Ownership
from .robot_time import learned_spec
from .session import Session
from .spec_store import SpecStore
from .status import Queries
from .step_clock import StepClock
from .subscriptions import DataSubscriptions, data_keyexprs

log = logging.getLogger(LOGGER_NAME)

_EXPIRY_CHECK_NS: Final = 1_000_000_000
#: How often every served session is offered for a checkpoint / replica (ns).
_SWEEP_NS: Final = 250_000_000
#: A single run_once() call returns after this long even if work remains (ns).
_RUN_BUDGET_NS: Final = 50_000_000
#: Longest wait (s) at a graceful stop for a successor to confirm the states handed over.
_HANDOVER_ACK_S = 2.0
#: Most samples taken from one drained subscription per loop of run_once.
_DRAIN_LIMIT: Final = 4096


class ServiceCore:
    """Sessions, dispatch, publishing and queries of one instance. Thread model: callbacks
    from any thread; ``run_once`` from one worker thread; queries from any thread."""

    def __init__(
        self,
        transport: Transport,
        settings: Settings,
        *,
        store: SpecStore | None = None,
        now_ns: Callable[[], int] | None = None,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        run_clock_ns: Callable[[], int] | None = None,
        spawn: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        self.t = transport
        self.settings = settings
        self.instance = settings.instance
        self.store = store
        self.counters = Tally()
        if now_ns is None:
            now_ns = StepClock(time.time_ns, mono_ns)
        #: The step clock, if ``now_ns`` is one (host clock steps counted, refusals blamed).
        self.step_clock = now_ns if isinstance(now_ns, StepClock) else None
        if self.step_clock is not None:
            self.step_clock.on_step = self._on_clock_step
        self.now_ns = now_ns
        self.mono_ns = mono_ns
        #: The clock of run_once's time budget (default ``mono_ns``; a test freezes it so
        #: that how much one call does does not depend on the machine's speed).
        self.run_clock_ns = mono_ns if run_clock_ns is None else run_clock_ns
        self.lock = threading.RLock()
        set_tables_max_bytes(settings.tables_max_bytes)
        self.wake = threading.Event()
        self.ownership = Ownership(self.instance, settings.shard_tuple)
        self.latency = LatencyWindow(settings.latency_window)
        self.outbox = Outbox(transport, settings, self.counters, self.latency, mono_ns,
                                   now_ns())
        self.dispatch = Dispatch(settings, self.counters, self.outbox, self.ownership,
                                 self.wake, now_ns, None if self.step_clock is None
                                 else self.step_clock.stepped_near)
        self.keeper = HandoverKeeper(settings, store, self.ownership, self.counters,
                                  self.outbox)
        self.lifecycle = Lifecycle(transport, settings, store=store, ownership=self.ownership,
                                   counters=self.counters, dispatch=self.dispatch,
                                   outbox=self.outbox, spawn=spawn or spawn_thread,
                                   keeper=self.keeper)
        self.queries = Queries(settings, self.lock, self.counters, self.latency,
                               self.ownership, self.dispatch.routes, self.lifecycle.specs,
                               now_ns, mono_ns, refuse=self.outbox.refuse,
                               received=self._received)
        self.queries.step_clock = self.step_clock
        #: The data subscriptions of the owned partitions; they follow the ownership.
        self.subs = DataSubscriptions(transport, self.dispatch.on_sensor_sample,
                                      self.dispatch.on_command_sample, self.wake.set,
                                      self.ownership.partitions)
        self.lifecycle.follow = self._follow_ownership
        #: The robots' echoes and the clock probes (pd_service.service.clock_probes).
        self.robot_io = RobotTimeIO(transport, settings, now_ns, self.wake, self.counters)
        #: A state some awaited session waits for arrived (set on a transport thread).
        self._handed_in = False
        self.keeper.arrived = self._on_state_arrived
        #: Every known session's route (the dispatch's table; read by tests).
        self._routes: dict[str, Route] = self.dispatch.routes
        self._next_expiry_ns = 0
        self._next_sweep_ns = 0
        self._next_learn_ns = 0
        self._handles: list[Handle] = []
        self._token: Handle | None = None
        self._closed = False

    # ================================================================== lifecycle ======

    def start(self) -> None:
        """Restore specs, sync with live peers, declare everything, announce presence.

        Order matters: configs are subscribed first (queued until the initial install, so
        none is lost between the peers' snapshot and the subscription), the sessions are
        installed before sensors are subscribed (no spurious "unknown session" at restart),
        and the liveliness token comes last (peers hand sessions over only once we serve).
        """
        t, s, d, q = self.t, self.settings, self.dispatch, self.queries
        event(log, "starting", instance=self.instance, shard=s.shard or "rendezvous",
              partitions=self.ownership.partitions, key_layout=keys.KEY_LAYOUT,
              state_dir=str(self.store.dir) if self.store else "", hot_path=native.STATUS)
        self._handles.append(t.subscribe(keys.ALL_CONFIGS, d.on_config_sample))
        # an old client's (key layout 1) spec puts: refused (Lifecycle.apply_config)
        self._handles.append(t.subscribe(keys.LEGACY_CONFIGS, d.on_config_sample))
        self._handles.append(t.subscribe(replicas_for(self.instance), self.keeper.on_replica))
        self._handles.append(t.queryable(replicas_for(self.instance),
                                         self.keeper.on_replica_query))
        peers = [k.rsplit("/", 1)[-1] for k in t.get_liveliness(keys.ALL_SERVICES,
                                                                 timeout=s.sync_timeout_s)]
        peers = [p for p in peers if p != self.instance]
        peers = self.lifecycle.trusted_peers(peers)
        specs, origin = self.lifecycle.load_specs(peers)
        if self.store is not None and self.store.states_damaged() is not None:
            self.counters["checkpoint_log_damaged"] += 1
        now = self.now_ns()
        with self.lock:
            self.lifecycle.install_loaded(specs, origin, now)
        # Data arrives through drained queues, one pair per owned partition: the worker
        # takes samples in batches at the start of each loop (no GIL hand-off per sample
        # while it is busy).
        self._follow_ownership()
        if s.recover_samples > 0:
            # What the senders of the owned partitions kept while no daemon received it
            # (their caches). Read after the live subscriptions and handled before the
            # worker runs, behind the live messages that arrived meanwhile (a message both
            # received live and read back is refused as the recovered copy, quietly): the
            # first prediction has it all.
            owned = self.ownership.owned_partitions()
            for sensors, commands in data_keyexprs(owned, self.ownership.partitions).values():
                for ke, cb in ((sensors, d.on_read_back_sensor),
                               (commands, d.on_read_back_command)):
                    self._handles.append(t.read_back(ke, cb, max_samples=s.recover_samples,
                                                     timeout=s.recover_timeout_s,
                                                     answered=d.on_cache_answered))
        while self._drain():  # the live messages that arrived meanwhile, first
            pass
        with self.lock:
            now = self.now_ns()
            touched: list[Session] = []
            recovered = d.take_held(now, touched)
            if touched:
                self.outbox.publish_many([x for x in touched if x.alive], now, data=True)
                self.outbox.flush()
        self._handles.append(t.queryable(keys.ALL_STATUS, q.on_status_query))
        self._handles.append(t.queryable(keys.ALL_CONFIGS, q.on_config_query))
        self._handles.append(t.queryable(keys.LEGACY_STATUS, q.on_legacy_status_query))
        self._handles.append(t.queryable(keys.service_status_key(self.instance),
                                         q.on_service_query))
        self._handles.append(t.subscribe_liveliness(keys.ALL_SERVICES, d.on_liveliness,
                                                    history=True))
        self.robot_io.subscribe()
        self.robot_io.start(self.clocked_sessions)
        self._token = t.declare_token(keys.service_token_key(self.instance))
        with self.lock:
            served = sum(1 for r in self._routes.values() if r.sess is not None)
        event(log, "ready", instance=self.instance, sessions_known=len(specs),
              sessions_served=served, restored=sum(1 for o in origin.values() if o == "restored"),
              peers=",".join(sorted(peers)), recovered=recovered)
        self.wake.set()

    def close(self) -> None:
        """Hand the served sessions' states to their successors, withdraw presence (peers
        take over at once), then undeclare everything. The worker must be stopped."""
        if self._closed:
            return
        self._closed = True
        self.lifecycle.closed = True
        with self.lock:
            succs = self.keeper.handover(
                [r.sess for r in self._routes.values() if r.sess is not None], self.now_ns())
            self.outbox.flush()
        # the token goes only when each successor holds the final states (or the wait
        # ends): one that took over before they arrived would resume from older replicas
        for succ, states in sorted(succs.items()):
            t0, resent = time.monotonic(), self.counters["replicas_handover_resent"]
            missing = self.keeper.confirm_handover(succ, states, _HANDOVER_ACK_S)
            more = {"first": missing[0]} if missing else {}
            event(log, "handover", level=logging.WARNING if missing else logging.INFO,
                  successor=succ, sessions=len(states), unconfirmed=len(missing),
                  seconds=round(time.monotonic() - t0, 3),
                  resent=self.counters["replicas_handover_resent"] - resent, **more)
        self.keeper.close()
        self.robot_io.close()
        if self.store is not None:
            self.store.close()
        if self._token is not None:
            self._token.close()
        for h in reversed(self._handles):
            try:
                h.close()
            except Exception:  # pragma: no cover - transport already gone
                pass
        self._handles.clear()
        self.subs.close()
        with self.lock:
            served = sum(1 for r in self._routes.values() if r.sess is not None)
        event(log, "stopped", instance=self.instance, sessions_served=served,
              published=self.counters["published"])

    # ================================================================== worker ========

    def _on_clock_step(self, step_ns: int, now_ns: int) -> None:
        """Any thread: the host's wall clock stepped by ``step_ns``; the step clock follows
        it (:mod:`.step_clock`: re-anchored, or a small step back caught up at half speed)."""
        self.counters["clock_steps"] += 1
        event(log, "clock_step", logging.WARNING, instance=self.instance,
              step_ms=round(step_ns / 1e6, 3), now_ns=now_ns)
        self.wake.set()

    def _received(self) -> int:
        return self.dispatch.received

    def _follow_ownership(self) -> None:
        """Worker (or the start): subscribe to the data of the partitions owned now, and
        no other (:class:`DataSubscriptions`)."""
        owned = self.ownership.owned_partitions()
        declared, closed = self.subs.follow(owned)
        if declared or closed:
            event(log, "subscriptions", instance=self.instance, partitions=len(owned),
                  declared=declared, closed=closed)

    def _on_state_arrived(self, session: str) -> None:
        """Transport thread: wake the worker if ``session`` waits for its hand-over state, or
        is served here (a state of a newer term: :meth:`Lifecycle.settle_second_owner`)."""
        route = self.dispatch.routes.get(session)
        if session in self.lifecycle.awaiting or (route is not None and route.sess is not None):
            self._handed_in = True
            self.wake.set()

    def has_work(self) -> bool:
        """Messages, control changes or hand-over states wait (not counting samples still in
        the drains' queues: :meth:`run_once` takes those first)."""
        return self.dispatch.has_work() or self._handed_in or self.robot_io.pending()

    def arm(self) -> None:
        """Before the worker waits idle: the drain group's watcher hands the next sample
        over itself (and wakes it). A busy worker does not arm it: it drains at its next
        round."""
        self.subs.group.arm()

    def _drain(self) -> int:
        """The samples waiting in the subscriptions' queues, into the inboxes (the
        callbacks' path; no lock needed). Returns how many."""
        return self.subs.group.drain(_DRAIN_LIMIT)

    def run_once(self) -> int:
        """Process what is pending: control, unknown sessions, rounds of session inboxes
        (each followed by its coalesced publications), due ticks and idle expiry, until
        nothing is left or ~50 ms have passed. One pass when it leaves nothing waiting in
        the inboxes: samples that reach the queues meanwhile are the next loop's (the
        daemon's worker starts loops ``round_interval_us`` apart). Returns the number of messages
        handled."""
        d, pub = self.dispatch, self.outbox
        handled = 0
        t_end = self.run_clock_ns() + _RUN_BUDGET_NS
        while True:
            self._drain()
            with self.lock:
                now = self.now_ns()
                if d.control or d.configs:
                    self.lifecycle.process_control(now)
                if self.lifecycle.awaiting:  # sessions moved here by a join
                    self._handed_in = False
                    self.lifecycle.adopt_handed(now)
                if self.keeper.terms_in:  # states of other owners (a healed partition)
                    self._handed_in = False
                    self.lifecycle.settle_second_owner(now)
                touched: list[Session] = []
                if d.unknown:
                    handled += d.process_unknown(now, touched)
                # a pass over the sessions ready now, in rounds, each round's touched
                # sessions published and put before the next (dispatch.ROUND_SESSIONS): a
                # message handled in the first round of a long pass does not wait for the
                # last one (at 1,000 sessions a burst's pass can take tens of ms). Between
                # rounds the queues are looked at again: what arrived joins its session's
                # inbox (served in this pass if the session is still ahead in it), its
                # receipt bounded by that look, not by the pass's first.
                served: list[Session] = []
                left = len(d.ready)
                while left > 0:
                    handled += d.round(now, touched, ROUND_SESSIONS)
                    left -= ROUND_SESSIONS
                    if left > 0:
                        if touched:
                            pub.publish_many([s for s in touched if s.alive], now, data=True)
                            served += touched
                            touched = []
                            pub.flush()
                        self._drain()
                if self.robot_io.pending():  # after the commands their echoes may name
                    handled += self.robot_io.process(self._routes, now, touched)
                if d.released:
                    handled += d.process_released(now, touched)
                if d.read_back:
                    handled += d.process_read_back(now, touched)
                if self.lifecycle.holding:
                    self.lifecycle.release_holds(now, touched)
                if touched:
                    pub.publish_many([s for s in touched if s.alive], now, data=True)
                    served += touched
                    pub.flush()  # before the ticks and the checkpoints
                pub.run_ticks(now)
                if served:
                    self.keeper.after_round(served, now)
                if now >= self._next_sweep_ns:  # sessions that only tick commit steps too
                    self.keeper.after_round([r.sess for r in self._routes.values()
                                             if r.sess is not None], now)
                    self._next_sweep_ns = now + _SWEEP_NS
                if self.keeper.resends:
                    self.keeper.resend_due(now)
                if now >= self._next_expiry_ns:
                    self.lifecycle.expire_idle(now)
                    self._next_expiry_ns = now + _EXPIRY_CHECK_NS
                if self.settings.learned_window and now >= self._next_learn_ns:
                    self._learn_windows()
                    self._next_learn_ns = now + int(self.settings.learn_interval_s * 1e9)
                pub.flush()
            # what the pass drained it handled (a session it had passed already is ready
            # again: has_work); what arrives now waits for the next loop, not another look
            if not self.has_work() or self.run_clock_ns() >= t_end:
                return handled

    def _learn_windows(self) -> None:
        """Worker: put the learned spec (max_delay, lead) of each served session whose
        learned values moved (:func:`.robot_time.learned_spec`) on its config key, as an
        operator would: the change takes the normal path (admission, replacement)."""
        for name, r in list(self._routes.items()):
            sess = r.sess
            if sess is None:
                continue
            new = learned_spec(sess.spec, sess.robot)
            if new is not None:
                self.t.put(keys.config_key(name), encode(new))
                self.counters["learned_windows_put"] += 1
                event(log, "learned_window", session=name, max_delay=new.max_delay,
                      lead=new.lead, was_max_delay=sess.spec.max_delay, was_lead=sess.spec.lead)

    def clocked_sessions(self) -> list[str]:
        """The served sessions whose robot clock is estimated (the probing thread's list)."""
        with self.lock:
            return [name for name, r in self._routes.items()
                    if r.sess is not None and r.sess.robot.estimated]

    def next_deadline_ns(self) -> int:
        """Wall-clock time (ns) at which run_once has timed work (next tick or expiry check)."""
        with self.lock:
            due = [t for t in (self.outbox.next_tick_ns(), self.lifecycle.next_await_ns())
                   if t is not None]
            return min([self._next_expiry_ns, *due])

    # ================================================================== status ========

    def session_status(self, session: str) -> SessionStatus | None:
        """Status of a session this instance serves (None otherwise)."""
        return self.queries.session_status(session)

    def service_status(self) -> ServiceStatus:
        return self.queries.service_status()

    def served_sessions(self) -> list[str]:
        return self.queries.served_sessions()

    def known_specs(self) -> dict[str, SessionSpec]:
        return self.queries.known_specs()
