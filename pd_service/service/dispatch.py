"""Dispatch: transport callbacks -> bounded inboxes -> round-robin rounds of the worker.

Data path::

    transport thread(s)                         worker (one thread, under the core's lock)
    -------------------                         ------------------------------------------
    pd/p<k>/*/sensor/*  --\\                     control inbox: configs, presence  (all)
    pd/p<k>/*/cmd       ---+-> session (split)  unknown inbox: unknown sessions   (all)
    pd/*/*/config       --/   append to an      ready sessions, round-robin: <= batch_budget
                              inbox, wake         messages each per round

(one sensors and one commands subscription per owned partition k, :mod:`.subscriptions`)

Callbacks never block and never take the core's lock: they append ``(stream, key, payload,
recv_mono_ns, kind, recv_now, first_now)`` (:data:`Item`) to a bounded deque (the oldest
entry is dropped when full and counted as ``flood``). A session's inbox is bounded, so a
flooding session loses its own oldest messages; the round-robin budget keeps it from delaying
the others by more than one budget.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from time import monotonic_ns
from typing import Final

import msgpack

from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME
from pd_service.transport import Sample
from pd_service.wire import SessionSpec, keys
from pd_service.wire.keys import KeyError_, check_name

from .config import Settings
from .outbox import Outbox
from .ownership import Ownership
from .session import ANSWERED, COMMAND, READ_BACK, SENSOR, ReadBack, Refusal, Session

log = logging.getLogger(LOGGER_NAME)

#: One received message: (stream SENSOR/COMMAND, key, payload, recv_mono_ns, kind put/delete,
#: recv_now: the core's wall clock read when it was handed over (ns; a packet is judged
#: "future" against that, not against the worker's later loop time), first_now: the earliest
#: it may have arrived on the same clock (ns; the previous look at the subscriptions' queues,
#: before which it was not there): a packet is judged late or on time at that
#: (:func:`pd_service.intake.judged_step`), not at the time a busy or stalled worker took
#: it from the queue).
Item = tuple[int, str, bytes, int, str, int, int]

#: Messages of sessions nobody configured waiting for the worker (oldest dropped beyond it).
UNKNOWN_INBOX: Final = 1024
#: Config changes, and apart from them presence events and peers' specs, waiting likewise.
CONTROL_INBOX: Final = 4096
#: Read-back messages waiting for the worker after the start.
READ_BACK_INBOX: Final = 64 * UNKNOWN_INBOX

#: Inputs a resumed session keeps while it waits for its senders' caches (catch_up); more
#: (a flood meanwhile) and it takes them in at once, judged as they come from then on.
HELD_INPUTS: Final = 4096

#: Recovered messages handled per loop of ``ServiceCore.run_once`` (a finished read-back's
#: whole batch at least), counting the held inputs a session whose wait ends takes in
#: (catch_up): the rest wait for the next loop, after this one's ticks. At a partition's
#: heal or a takeover of many sessions the read-backs come in at once (up to 64 samples
#: per sender key each); handled in one go they held the worker for 100-150 ms, its ticks
#: overrunning.
READ_BACK_SLICE: Final = 512

#: The refusals of a message the session already has.
_DUPLICATE: Final = frozenset({"duplicate", "commands_duplicate"})
#: Refusals of a stamp against the current step: after a host clock step, blamed on it.
_STAMP_REASONS: Final = frozenset({"late", "future", "before_epoch", "commands_late",
                                   "commands_future", "commands_before_epoch"})


#: A look at the subscriptions' queues this much older (ns) than the hand-over of what it found
#: means the worker was busy elsewhere (a stall, a long pass): the samples may have arrived as
#: early as that look. Below it the gap is the hand-off itself (first_now = recv_now).
LOOK_SLACK_NS: Final = 1_000_000

#: Sessions served per round of a pass: each round's predictions are made while the sessions'
#: arrays are still in the caches, and the queues are looked at between rounds
#: (``ServiceCore.run_once``; the measurements behind 8: docs/performance.md).
ROUND_SESSIONS: Final = 8


def stamp_step(spec: SessionSpec, item: Item, default: int) -> int:
    """The step a message's stamp puts it at (:meth:`Dispatch.catch_up`): a measurement's
    sample step, a command's apply step - lead (the step it was sent at); ``default`` for
    one whose stamp cannot be read (judged, and refused, as it comes). Only the stamp is
    read (the msgpack map's ``step``, else ``t_ns`` / ``issued_ns``), not the validated
    message: a catch-up orders hundreds of read-back messages, and the full decode of each
    was most of its cost; a message invalid otherwise is refused when it is offered."""
    try:
        m = msgpack.unpackb(item[2])
        step = m.get("step")
        if item[0] & ~READ_BACK == SENSOR:
            if type(step) is int:
                return step
            t = m.get("t_ns")
            return spec.sample_at(t)[0] if type(t) is int else default
        if type(step) is int:
            return step - spec.lead
        t = m.get("issued_ns")
        return spec.step_of(t) if type(t) is int else default
    except Exception:  # not msgpack, not a map, a stamp out of range: as it comes
        return default


@dataclass(eq=False, slots=True)
class Route:
    """Where a session's messages go. ``inbox`` None: known, but served by another instance."""

    session: str
    inbox: deque[Item] | None = None
    sess: Session | None = None
    ready: bool = False
    flood: int = 0  # written by callbacks only
    flood_seen: int = 0  # written by the worker only


# --- control inbox entries (handled by the lifecycle, before any session's messages) -------

@dataclass(frozen=True, slots=True)
class ConfigChange:
    """A put or delete on ``pd/p<k>/<session>/config``."""

    sample: Sample


@dataclass(frozen=True, slots=True)
class PeerSpecs:
    """Specs fetched from peers off the worker thread."""

    specs: dict[str, SessionSpec]


@dataclass(frozen=True, slots=True)
class Membership:
    """A service instance's liveliness token appeared (alive) or went away."""

    key: str
    alive: bool


Control = ConfigChange | PeerSpecs | Membership


class Dispatch:
    """The inboxes and the round-robin. Callbacks (``on_*``) run on transport threads; the
    rest on the worker, under the core's lock."""

    def __init__(self, settings: Settings, counters: Tally, outbox: Outbox,
                 ownership: Ownership, wake: threading.Event,
                 now_ns: Callable[[], int] = time.time_ns,
                 clock_stepped: Callable[[int], bool] | None = None) -> None:
        self.settings = settings
        self.now_ns = now_ns
        #: Whether a host clock step explains a stamp refused at a time (ns); None: never.
        self.clock_stepped = clock_stepped
        self.counters = counters
        self.pub = outbox
        self.ownership = ownership
        self.wake = wake
        self._wake_set = wake.set
        self._wake_is_set = wake.is_set
        self.routes: dict[str, Route] = {}
        self.ready: deque[Route] = deque()
        self.control: deque[Control] = deque(maxlen=CONTROL_INBOX)
        #: Config changes, apart from presence events (a config flood cannot push those out).
        self.configs: deque[ConfigChange] = deque(maxlen=CONTROL_INBOX)
        self.unknown: deque[tuple[str, Item]] = deque(maxlen=UNKNOWN_INBOX)
        self.control_drops = 0
        self.unknown_drops = 0
        #: Recovered messages held while the core starts (None: after the start, they go to
        #: ``read_back``, apart from the inboxes: they never push out a live message).
        #: Appended by callbacks under ``_held_lock`` (the start's hand-over and a late
        #: sender's cache may race).
        self.held: list[tuple[int, Sample]] | None = []
        self._held_lock = threading.Lock()
        #: Recovered messages after the start: (stream, sample, wall clock at arrival).
        self.read_back: deque[tuple[int, Sample, int]] = deque(
            maxlen=READ_BACK_INBOX)
        self.read_back_drops = 0
        #: Read-backs finished off the worker for parked sessions: (sessions, messages).
        self.released: deque[tuple[list[str], list[tuple[int, Sample]]]] = deque()
        #: sessions parked while their takeover read-back runs (:meth:`park`)
        self.parked: set[str] = set()
        #: Sessions resumed from a state while they wait for their senders' caches: every
        #: input they get meanwhile, live (False) or read back (True), kept for
        #: :meth:`catch_up` (set by ``Lifecycle.hold_for_read_back``).
        self.held_inputs: dict[str, list[tuple[bool, Item]]] = {}
        #: Data samples (sensors and commands) taken from the subscriptions: what this
        #: instance receives (``samples_received``). Written by the one thread that drains.
        self.received = 0
        #: Held inputs taken in by catch-ups so far (the read-back slices count them).
        self.caught_up = 0

    # ================================================================== callbacks ======
    # Transport threads. No lock, no decoding, no blocking: split the key, append, wake.

    def on_sensor_sample(self, sample: Sample) -> None:
        self._enqueue(SENSOR, sample)

    def on_command_sample(self, sample: Sample) -> None:
        self._enqueue(COMMAND, sample)

    def on_read_back_sensor(self, sample: Sample) -> None:
        """A measurement read back from a sender's cache (``Transport.read_back``)."""
        self._read_back(SENSOR + READ_BACK, sample)

    def on_read_back_command(self, sample: Sample) -> None:
        self._read_back(COMMAND + READ_BACK, sample)

    def on_cache_answered(self, key: str) -> None:
        """The read of the cache of a sender on ``key`` ended (``Transport.read_back``'s
        ``answered``): queued behind that cache's samples."""
        self._read_back(ANSWERED, Sample(key, b"", "put", 0, 0))

    def _read_back(self, stream: int, sample: Sample) -> None:
        with self._held_lock:
            if self.held is not None:
                self.held.append((stream, sample))
                return
        q = self.read_back
        if len(q) == q.maxlen:
            self.read_back_drops += 1
        q.append((stream, sample, self.now_ns()))
        self._notify()

    def process_read_back(self, now: int, touched: list[Session]) -> int:
        """Worker: the recovered messages that arrived after the start (a sender that
        appeared, a takeover's read-back), after the round's live messages; at most
        :data:`READ_BACK_SLICE` of them (with the inputs of the holds they end), the rest
        in the next loop."""
        q = self.read_back
        if self.read_back_drops:
            self.counters["recovered_dropped"] += self.read_back_drops
            self.read_back_drops = 0
        n = 0
        start = self.caught_up
        while q and n + self.caught_up - start < READ_BACK_SLICE:
            stream, sample, recv_now = q.popleft()
            n += 1
            self._offer_read_back(stream, sample, recv_now, now, touched)
        return n

    def _offer_read_back(self, stream: int, sample: Sample, recv_now: int, now: int,
                         touched: list[Session]) -> None:
        name = keys.session_of(sample.key)
        route = self.routes.get(name) if name is not None else None
        sess = route.sess if route is not None else None
        if stream == ANSWERED:
            if sess is not None:
                self.cache_answered(sess, sample.key, now, touched)
            return
        if sess is None or route is None or route.inbox is None:
            # unknown, or served by another instance: nothing to do with it here
            self.counters["recovered_ignored"] += 1
            return
        item = (stream, sample.key, sample.payload, sample.recv_mono_ns, sample.kind, recv_now,
                recv_now)
        held = self.held_inputs.get(sess.name) if sess.hold_until_ns else None
        if held is not None:
            held.append((True, item))
            if len(held) >= HELD_INPUTS:
                self.catch_up(sess, now)
            return
        had = bool(sess.pending_recv)
        self._handle_read_back(sess, item, sess.step_now(now), now)
        if sess.pending_recv and not had:
            touched.append(sess)

    def park(self, route: Route) -> None:
        """Worker: keep ``route``'s live messages in its inbox, out of the rounds, until
        :meth:`process_released` (its senders' caches are being read)."""
        route.ready = True  # set and not queued: the callbacks do not queue it either
        self.parked.add(route.session)

    def cache_answered(self, sess: Session, key: str, now: int,
                       touched: list[Session]) -> None:
        """Worker: the cache of ``sess``'s sender on ``key`` was read (its samples handled
        before this); the last one awaited releases the session's hold."""
        if sess.hold_until_ns and key in sess.unanswered:
            sess.unanswered.discard(key)
            if not sess.unanswered:
                self.release_hold(sess, "answered", now, touched)

    def release_hold(self, sess: Session, how: ReadBack, now: int,
                     touched: list[Session]) -> None:
        """Worker: ``sess`` takes in what it got meanwhile (:meth:`catch_up`) and publishes
        again (its first prediction in this pass), its status saying how its wait for the
        senders' caches ended."""
        self.catch_up(sess, now)
        sess.hold_until_ns = 0
        sess.readback = how
        self.counters["readback_answered" if how == "answered" else "readback_timeout"] += 1
        if sess not in touched:
            touched.append(sess)

    def catch_up(self, sess: Session, now: int) -> None:
        """Worker: the inputs ``sess`` got while it waited for its senders' caches (live and
        read back, :attr:`held_inputs`), in the order of their stamps (a measurement's
        sample step; a command's apply step - lead, the step it was sent at), each judged
        at its own stamp's step: from the step of the state the session resumed from
        (``origin_step``; a session left at its prior: the step its wait began) up to
        now. Called while it still waits (``hold_until_ns`` set). So a state older than
        the window (a restart that took longer) takes in every sample the caches kept
        since it, as a daemon that never stopped would have, instead of refusing those
        older than the window as late; none is applied at a step after its stamp's, nor
        after now::

            k_i = max(k_{i-1}, min(now_step, stamp_i)),   k_0 = origin_step (or the wait's start)
        """
        held = self.held_inputs.pop(sess.name, None)
        if not held:
            return
        self.caught_up += len(held)
        spec = sess.spec
        now_step = sess.step_now(now)
        order = sorted(((stamp_step(spec, item, now_step), i) for i, (_, item) in
                        enumerate(held)))
        k = sess.origin_step if sess.origin_step is not None else min(now_step, spec.step_of(
            sess.hold_until_ns - int(2e9 * self.settings.recover_timeout_s)))
        for stamp, i in order:
            recovered, item = held[i]
            k = max(k, min(now_step, stamp))
            # judged at k, not at its arrival (_offer's rule for one that came after the
            # loop read its clock would take it to the current step, past later stamps)
            at = max(now, item[5])
            if recovered:
                self._handle_read_back(sess, item, k, at)
            else:
                self.handle(sess, item, k, at)
        if sess.idle and sess.heard:  # its ticks went idle while nothing was taken in
            self.pub.wake(sess, now)

    def post_released(self, sessions: list[str], items: list[tuple[int, Sample]]) -> None:
        """Any thread: the read-back of parked ``sessions`` is done (``items``: what it
        gave, ``(stream, sample)``)."""
        self.released.append((sessions, items))
        self._notify()

    def process_released(self, now: int, touched: list[Session]) -> int:
        """Worker: for each finished read-back, the parked sessions' live messages (all,
        no round budget; as in a round, they wake an idle session and a flood meanwhile is
        reported), then the recovered ones, before anything is published: a
        prediction never sees a recovered packet without the live ones received before
        it, and a message both received live and read back is refused as the recovered
        copy, quietly. Then the sessions rejoin the rounds. (A session read back without
        being parked, ``Lifecycle.settle_second_owner``'s kept one, took its live messages
        in the rounds, before.) At most :data:`READ_BACK_SLICE` messages (whole read-backs,
        with the inputs of the holds they end): the others in the next loop."""
        n = 0
        start = self.caught_up
        while self.released and n + self.caught_up - start < READ_BACK_SLICE:
            names, items = self.released.popleft()
            for name in names:
                if name not in self.parked:
                    continue
                self.parked.discard(name)
                route = self.routes.get(name)
                if route is None:
                    continue
                route.ready = False
                if route.sess is not None and route.inbox:
                    n += self._serve(route, now, touched, len(route.inbox))
                self.mark_ready(route)
            for stream, sample in items:
                self._offer_read_back(stream, sample, now, now, touched)
                n += 1
        return n

    def take_held(self, now: int, touched: list[Session]) -> int:
        """Worker (the core's start, under its lock): the live messages that arrived during
        the start, then the recovered ones held meanwhile (so that a message both received
        live and read back is refused as the recovered copy, quietly); from now on
        recovered messages go to ``read_back``. Returns the number of recovered messages."""
        while self.ready:
            self.round(now, touched, len(self.ready))
        with self._held_lock:
            held, self.held = self.held or [], None
        for stream, sample in held:
            self._offer_read_back(stream, sample, now, now, touched)
        return sum(1 for stream, _ in held if stream != ANSWERED)

    def _enqueue(self, stream: int, sample: Sample) -> None:
        key = sample.key
        self.received += 1
        parts = key.split("/", 3)  # keys.session_of, inline: pd/p<k>/<session>/...
        if len(parts) < 4:
            return
        route = self.routes.get(parts[2])
        now = self.now_ns()
        mono = sample.recv_mono_ns
        # drained samples carry the time of the previous look at their queue (the transport's
        # monotonic clock): after a stall they may have waited there since it
        gap = monotonic_ns() - mono
        item = (stream, key, sample.payload, mono, sample.kind, now,
                now - gap if gap > LOOK_SLACK_NS else now)
        if route is None:
            q = self.unknown
            if len(q) == q.maxlen:
                self.unknown_drops += 1
            q.append((parts[2], item))
            self._notify()
            return
        inbox = route.inbox
        if inbox is None:  # served by another instance
            return
        if len(inbox) == inbox.maxlen:
            route.flood += 1
        inbox.append(item)
        if not route.ready:
            route.ready = True
            self.ready.append(route)
            self._notify()

    def on_config_sample(self, sample: Sample) -> None:
        q = self.configs
        if len(q) == q.maxlen:
            self.control_drops += 1
        q.append(ConfigChange(sample))
        self._notify()

    def on_liveliness(self, key: str, alive: bool) -> None:
        self.control.append(Membership(key, alive))
        self._notify()

    def post_peer_specs(self, specs: dict[str, SessionSpec]) -> None:
        """From any thread: hand specs fetched from peers to the worker."""
        self.control.append(PeerSpecs(specs))
        self._notify()

    def _notify(self) -> None:
        """Wake the worker. A set event is left alone: Event.set takes its condition's lock
        and notifies even when already set, and the worker's own drains enqueue while it
        runs. Safe: a caller appended before reading the flag, so a set flag it saw was
        cleared only after that append, and the round after the clear takes it."""
        if not self._wake_is_set():
            self._wake_set()

    # ================================================================== worker ========

    def has_work(self) -> bool:
        return bool(self.ready or self.control or self.configs or self.unknown
                    or self.read_back or self.released)

    def mark_ready(self, route: Route) -> None:
        """Queue ``route`` for the next round if its inbox holds messages."""
        if route.inbox and not route.ready:
            route.ready = True
            self.ready.append(route)

    def round(self, now: int, touched: list[Session], limit: int) -> int:
        """Serve the first ``limit`` ready sessions in round-robin order (a session with
        messages left goes to the back); appends to ``touched`` each session that accepted its
        first measurement since it last published. Returns the number of messages handled.
        ``ServiceCore.run_once`` makes a pass over the sessions ready when it began in
        rounds of at most :data:`ROUND_SESSIONS`."""
        ready = self.ready
        budget = self.settings.batch_budget
        handled = 0
        for _ in range(min(len(ready), limit)):
            route = ready.popleft()
            route.ready = False
            if route.sess is None or route.inbox is None:
                continue
            handled += self._serve(route, now, touched, budget)
            if route.inbox and not route.ready:
                route.ready = True
                ready.append(route)
        return handled

    def _serve(self, route: Route, now: int, touched: list[Session], budget: int) -> int:
        """Up to ``budget`` of ``route``'s waiting messages into its session (a served
        route: session and inbox set): a message wakes an idle session, a flood since the
        last visit is reported first. Appends the session to ``touched`` if it accepted its
        first measurement since it last published."""
        sess, inbox = route.sess, route.inbox
        assert sess is not None and inbox is not None
        if sess.idle:
            self.pub.wake(sess, now)
        if route.flood != route.flood_seen:
            self._note_flood(route, sess, now)
        n = 0
        if sess.hold_until_ns:  # resumed, waiting for its senders' caches: kept (catch_up)
            held = self.held_inputs.get(sess.name)
            if held is not None:
                while n < budget and inbox:
                    held.append((False, inbox.popleft()))
                    n += 1
                if len(held) >= HELD_INPUTS:
                    self.catch_up(sess, now)
                return n
        now_step = sess.step_now(now)
        had_pending = bool(sess.pending_recv)
        while n < budget and inbox:
            item = inbox.popleft()
            n += 1
            self.handle(sess, item, now_step, now)
        if sess.pending_recv and not had_pending:
            touched.append(sess)
        return n

    def handle(self, sess: Session, item: Item, now_step: int, now: int) -> None:
        """Give one message to its session; count it, or refuse it (reported). A live
        message refused as a duplicate that repeats, byte for byte, one read back from a
        sender's cache and accepted (the read-back's reply overtook the live sample) is the
        same message: dropped quietly, counted as ``live_copy_of_recovered``."""
        refusal = self._offer(sess, item, now_step, now)
        if refusal is not None:
            if sess.read_back_copies and refusal.reason in _DUPLICATE \
                    and sess.take_read_back_copy(item[2], now_step):
                for c in (sess.counters, self.counters):
                    c["live_copy_of_recovered"] += 1
                return
            if refusal.reason in _STAMP_REASONS and self.clock_stepped is not None \
                    and self.clock_stepped(max(now, item[5])):
                refusal = Refusal("commands_clock_step" if refusal.reason.startswith("commands_")
                                  else "clock_step", refusal.text + " (the daemon's host clock "
                                  "stepped just before: its clock and the sender's disagree)",
                                  refusal.seq)
            self.pub.refuse(sess, item[1], refusal, now)

    def _handle_read_back(self, sess: Session, item: Item, now_step: int, now: int) -> None:
        """A message read back from a sender's cache: judged like a live one (its sample
        stamp against the window: too old is refused, never applied as current), but a
        refusal is expected (it repeats a packet the checkpoint or the live stream already
        gave, or it is older than the window) and is only counted, as
        ``recovered_<reason>`` and ``recovered_refused``, never reported nor added to
        ``refused``. Accepted ones count in ``accepted`` and ``recovered_accepted``."""
        refusal = self._offer(sess, item, now_step, now, "recovered_")
        if refusal is None:
            sess.keep_read_back_copy(item[2], now_step)
            return
        for c in (sess.counters, self.counters):
            c[f"recovered_{refusal.reason}"] += 1
            c["recovered_refused"] += 1

    def _offer(self, sess: Session, item: Item, now_step: int, now: int,
               also: str = "") -> Refusal | None:
        """One message into its session (the stream's READ_BACK bit ignored); None if
        accepted (counted as ``accepted`` / ``commands_accepted``, and ``also`` + that name
        when ``also`` is set). A packet is judged at its arrival if that came after the
        loop read its clock, and late or on time at the earliest it may have arrived
        (``first_now``: :func:`pd_service.intake.judged_step`), not at the time the worker got
        to it."""
        stream, key, payload, recv_mono, kind, recv_now, first_now = item
        if recv_now > now:
            now_step = sess.step_now(recv_now)
        first_step = (first_now - sess.epoch_ns) // sess.period_ns
        try:
            if kind != "put":
                return Refusal("malformed" if stream & ~READ_BACK == SENSOR
                               else "commands_malformed",
                               f"{kind} is not supported on {key!r}: publish a message with put")
            if stream & ~READ_BACK == SENSOR:
                refusal = sess.on_measurement(key, payload, now_step, now, recv_now, first_step)
                name = "accepted"
                if refusal is None:
                    sess.pending_recv.append(recv_mono)
            else:
                refusal = sess.on_command(key, payload, now_step, now, first_step)
                name = "commands_superseded" if sess.intake.superseded else "commands_accepted"
        except Exception as exc:  # isolation: nothing one session sends escapes the worker
            log.debug("internal error in session %s", sess.name, exc_info=True)
            return Refusal("internal_error", f"internal error: {type(exc).__name__}: {exc}")
        if refusal is None:
            for c in (sess.counters, self.counters):
                c[name] += 1
                if also:
                    c[also + name] += 1
        return refusal

    def _note_flood(self, route: Route, sess: Session, now: int) -> None:
        seen = route.flood
        dropped = seen - route.flood_seen
        route.flood_seen = seen
        self.pub.refuse(sess, keys.sensors_of(sess.name), Refusal(
            "flood", f"inbox full: dropped {dropped} oldest unread message(s) "
            f"(more than {self.settings.inbox_size} waiting)"), now, count=dropped)

    def process_unknown(self, now: int, touched: list[Session]) -> int:
        """Messages that arrived for no known session: hand them over if the session was
        configured meanwhile, else count them and (the name's owner only) report them."""
        q = self.unknown
        n = 0
        if self.unknown_drops:
            self.counters["unknown_flood"] += self.unknown_drops
            self.unknown_drops = 0
        while q:
            session, item = q.popleft()
            n += 1
            route = self.routes.get(session)
            if route is not None:
                sess = route.sess
                if sess is not None:  # configured since the message arrived
                    had = bool(sess.pending_recv)
                    self.handle(sess, item, sess.step_now(now), now)
                    if sess.pending_recv and not had:
                        touched.append(sess)
                continue
            try:
                check_name(session, "session")
            except KeyError_:
                self.pub.refuse(None, item[1], Refusal("unknown_session", ""), now,
                                session=session, report=False)
                self.counters["bad_key"] += 1
                continue
            # Every instance knows every spec, so the rendezvous owner of the name reports.
            self.pub.refuse(None, item[1], Refusal(
                "unknown_session", f"unknown session {session!r}: put a SessionSpec on "
                f"{keys.config_key(session)!r} first"), now, session=session,
                report=self.ownership.owns(session))
        return n
