"""Checkpoints and replicas of the sessions' estimator state: restart and takeover without
going back to the prior.

- **Checkpoint** (restart): after a round, a session whose estimator changed (committed
  new steps, accepted packets or commands) since its last checkpoint, and whose checkpoint
  is due (the first at once, then one per ``checkpoint_interval_s`` at the session's own
  phase, :func:`~.session.next_slot`, never two within half an interval), writes its
  :class:`~pd_service.wire.session_state.SessionState` to the state directory's checkpoint log
  (``checkpoints.log``, :mod:`.checkpoint_log`, by the daemon's writer thread). A restarted daemon
  resumes each restored session from it.
- **Replica** (takeover): at the same moments, one per ``replica_interval_s`` or per half
  the session's window (``max_delay`` steps) if that is shorter, the
  owner puts the same message on ``pd/@service/<successor>/replica/<session>``, the successor
  being the instance that owns the session if this one goes away (the rendezvous order
  without this instance). Every instance keeps the newest replica per session it received;
  when it takes a session over it resumes from it. On a join, the owner that loses a
  session sends its state at once to the new owner, on that owner's replica key
  (:meth:`HandoverKeeper.hand_to`), which waits for it (``Lifecycle.adopt_handed``).
- A state that is from the future, corrupt, from another spec or of another version is
  refused (:mod:`pd_service.service.handover.checkpoint`): the session starts from its prior,
  the refusal is counted (``restore_refused``, ``restore_refused_<reason>``), logged and sent
  as an ErrorReport. A state older than the window is resumed and propagated forward
  (``resumed_stale``).

A session whose estimate is its prior alone (:meth:`Session.prior_alone`: started from
the prior, nothing accepted) writes and sends no state: resuming from the prior gives the same.
An encoded state larger than a message may be (64 KiB) is neither written nor sent
(``checkpoint_too_large``). On a graceful stop the owner sends every served session's
newest state to its successor and waits until the successor says it holds them
(:meth:`HandoverKeeper.handover`, :meth:`HandoverKeeper.confirm_handover`; bounded) before it
withdraws its presence, so a planned handover loses nothing that was accepted.
Worker thread only, except :meth:`HandoverKeeper.on_replica` and
:meth:`HandoverKeeper.on_replica_query` (transport threads: they only store or read the bytes)
and :meth:`HandoverKeeper.confirm_handover` (the stopping thread, the worker stopped).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Final

from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME, event
from pd_service.transport import Query, Sample
from pd_service.transport.keyexpr import intersects
from pd_service.wire import MAX_MESSAGE_BYTES, WireError, keys
from pd_service.wire.codec import unpack_fields
from pd_service.wire.keys import KeyError_, check_name

from ..config import Settings
from ..outbox import Out, Outbox
from ..ownership import Ownership
from ..session import Origin, Refusal, Session, next_slot
from ..spec_store import SpecStore
from .checkpoint import Refused, encode_state, is_stale, restore
from .checkpoint_writer import CheckpointWriter

log = logging.getLogger(LOGGER_NAME)

#: Most session states encoded after one round: sessions created together fall due
#: together, and encoding them all at once would stall the worker.
STATES_PER_ROUND = 8

#: Failed checkpoint writes are logged at most once per this many seconds (with their
#: number): a full or read-only disk fails every session's checkpoint every second.
FAILED_LOG_EVERY_S = 10.0

#: Most replicas held (sessions); the oldest received is dropped beyond it.
MAX_REPLICAS = 100_000

#: What :meth:`HandoverKeeper.on_replica` reads of a replica (the rest is skipped unbuilt).
_REPLICA_FIELDS: Final = frozenset({"session", "now_step", "term", "instance",
                                    "session_counters"})

#: Pause (s) between two rounds of a hand-over's confirmation (put again, ask again).
_HANDOVER_RETRY_S = 0.02

#: When (s after the first) a join's hand-over state is put again: at a partition's heal
#: the liveliness token may reach the old owner before the new owner's subscription does,
#: and the first put goes nowhere (seen on loopback with a 10 s partition).
HANDOVER_RESEND_S = (0.5, 2.0)


def checkpoint_key(instance: str, session: str) -> str:
    """``pd/@service/<instance>/checkpoint/<session>``: names ``instance``'s checkpoint of
    ``session`` in an ErrorReport's ``key`` (a key expression; nothing is put on it)."""
    return f"{keys.OPERATOR_ROOT}/{keys.SERVICE_CHUNK}/{check_name(instance, 'instance')}" \
           f"/checkpoint/{check_name(session, 'session')}"


def replica_key(instance: str, session: str) -> str:
    """``pd/@service/<instance>/replica/<session>``: state of ``session`` for ``instance``."""
    return f"{keys.OPERATOR_ROOT}/{keys.SERVICE_CHUNK}/{check_name(instance, 'instance')}" \
           f"/replica/{check_name(session, 'session')}"


def replicas_for(instance: str) -> str:
    """Key expression of every replica sent to ``instance``."""
    return f"{keys.OPERATOR_ROOT}/{keys.SERVICE_CHUNK}/{check_name(instance, 'instance')}" \
           "/replica/*"


def inputs_accepted(counters: Mapping[str, object]) -> int:
    """Measurements and commands a session accepted over its life (its ``accepted`` and
    ``commands_accepted`` counters; a value that is not an int counts 0): of two owners'
    estimates after a partition, the one that took in more data."""
    return sum(v for v in (counters.get("accepted"), counters.get("commands_accepted"))
               if type(v) is int and v > 0)


def state_mark(sess: Session) -> tuple[int, int, int]:
    """What changes the exported state (committed step, packets and commands accepted):
    a session whose mark did not move since its last state is not written again. Not the
    committed step alone: nothing commits during a session's first window."""
    c = sess.counters
    return sess.est.committed_step, c["accepted"], c["commands_accepted"]


class HandoverKeeper:
    """Writes checkpoints, sends replicas, keeps received replicas, resumes sessions."""

    def __init__(self, settings: Settings, store: SpecStore | None, ownership: Ownership,
                 counters: Tally, outbox: Outbox) -> None:
        self.settings = settings
        self.store = store
        self.ownership = ownership
        self.counters = counters
        self.pub = outbox
        self._lock = threading.Lock()
        #: Writes checkpoints off the worker thread (the daemon's); None: written in place.
        self.writer: CheckpointWriter | None = None
        self._rotate = 0  # where the next long after_round list starts (round-robin)
        #: Failed checkpoint writes not logged yet, and when the last were (monotonic s).
        self._failed_unlogged = 0
        self._failed_logged_at = -FAILED_LOG_EVERY_S
        #: session -> (now_step of the state, encoded SessionState), newest received
        self.replicas: dict[str, tuple[int, bytes]] = {}
        #: Called (transport thread) with the session of each replica kept: the core
        #: wakes the worker when a session waits for its hand-over state.
        self.arrived: Callable[[str], None] | None = None
        #: Sessions whose previous owner handed over only their prior (a delete on the
        #: replica key, :meth:`hand_to`), until :meth:`handed` reads it.
        self.at_prior: set[str] = set()
        #: The states received since the worker last looked (:meth:`take_terms`): session ->
        #: (term, writer, inputs accepted: :func:`inputs_accepted`); (0, "", 0) for a
        #: hand-over of a session at its prior alone. One for a session served here is a
        #: second owner's (a healed partition): ``Lifecycle.settle_second_owner``.
        self.terms_in: dict[str, tuple[int, str, int]] = {}
        #: Join hand-over states to put again: (due ns, key, state) (:data:`HANDOVER_RESEND_S`).
        self.resends: list[tuple[int, str, bytes]] = []

    # ================================================================== outgoing ======

    def _replicating(self) -> bool:
        """Replicas are on, rendezvous ownership, and someone to send them to."""
        return self.settings.replica_interval_s > 0 and len(self.ownership.members) > 1 \
            and self.ownership.shard is None

    def after_round(self, sessions: list[Session], now: int) -> None:
        """Checkpoint / replicate the sessions whose estimator changed (committed new steps
        or accepted packets or commands) since their last state, rate-bounded."""
        s = self.settings
        ck_ns, rep_ns = int(s.checkpoint_interval_s * 1e9), int(s.replica_interval_s * 1e9)
        want_ck = self.store is not None and s.checkpoint_interval_s > 0
        want_rep = self._replicating()
        if self.writer is not None:
            self._count_written()
        budget = STATES_PER_ROUND
        if len(sessions) > budget:  # a long list (the sweep): start where the last one stopped
            start = self._rotate % len(sessions)
            sessions = sessions[start:] + sessions[:start]
        for i, sess in enumerate(sessions):
            # the time checks first: most sessions of a round had their state lately
            ck = want_ck and now >= sess.next_checkpoint_ns
            rep = want_rep and now >= sess.next_replica_ns
            if not (ck or rep) or not sess.alive or sess.prior_alone():
                continue
            mark = state_mark(sess)
            if mark == sess.saved_mark:
                continue
            if budget == 0:  # the rest stay due: later rounds and the sweep take them
                self._rotate += i
                break
            budget -= 1
            data = self.encode_state(sess, now)
            if data is None:
                continue
            sess.saved_mark = mark
            # the next one at the session's own phase, at least half an interval from now:
            # sessions created together spread over the interval instead of being encoded in
            # the same few rounds every interval
            if ck:
                sess.next_checkpoint_ns = next_slot(now + ck_ns // 2, ck_ns, sess.spread)
                self._write(sess, data)
            if rep:
                # at least two per window: a successor that takes over at once then holds a
                # state inside the window, and the senders' caches give back all after it
                spec = sess.spec
                every = min(rep_ns, max(spec.max_delay // 2, 1) * spec.period_ns)
                sess.next_replica_ns = next_slot(now + every // 2, every, sess.spread)
                self._send(sess, data)

    def handover(self, sessions: list[Session], now: int) -> dict[str, dict[str, bytes]]:
        """Graceful stop: the newest state of every served session to its successor, not
        rate-bounded (the caller flushes the outbox, then has each successor confirm with
        :meth:`confirm_handover`, before withdrawing its presence). Returns what was sent:
        successor -> session -> encoded state."""
        sent: dict[str, dict[str, bytes]] = {}
        if not self._replicating():
            return sent
        for sess in sessions:
            if not sess.alive or sess.prior_alone():
                continue
            data = self.encode_state(sess, now)
            if data is not None:
                succ = self._send(sess, data)
                if succ is not None:
                    sent.setdefault(succ, {})[sess.name] = data
                self.counters["replicas_handover"] += 1
        return sent

    def hand_to(self, sess: Session, instance: str, now: int) -> bool:
        """A session this instance stops serving while it stays up (``instance`` joined and
        owns it now): its current state to ``instance`` at once, on its replica key; a
        session at its prior alone gets a delete there ("start from the prior": the new
        owner waits for one or the other, :meth:`Lifecycle.adopt_handed`). Not confirmed:
        a lost one costs the new owner ``recover_timeout_s``. True if a state was sent."""
        key = replica_key(instance, sess.name)
        data = None if sess.prior_alone() else self.encode_state(sess, now)
        self.counters["replicas_handover_join"] += 1
        if data is None:
            self.pub.delete(key)
            return False
        self.pub.pending.append(Out(key, data))
        self.counters["replica_bytes"] += len(data)
        if len(self.resends) < MAX_REPLICAS:
            self.resends += [(now + int(d * 1e9), key, data) for d in HANDOVER_RESEND_S]
        return True

    def resend_due(self, now: int) -> None:
        """Put again the join hand-over states due by ``now`` (a second copy is harmless:
        the new owner already runs the session from a state as new, see
        ``Lifecycle.settle_second_owner``)."""
        due = [r for r in self.resends if r[0] <= now]
        if not due:
            return
        self.resends = [r for r in self.resends if r[0] > now]
        for _, key, data in due:
            self.pub.pending.append(Out(key, data))
            self.counters["replicas_handover_join_resent"] += 1

    def take_terms(self) -> dict[str, tuple[int, str, int]]:
        """The states received since the last call (session -> (term, writer, inputs
        accepted)); any thread."""
        with self._lock:
            got, self.terms_in = self.terms_in, {}
        return got

    def holds(self, session: str) -> bool:
        """Whether a replica of ``session`` is held (to resume from). Any thread."""
        with self._lock:
            return session in self.replicas

    def drop_prior_mark(self, session: str) -> None:
        """Forget a prior-alone hand-over of ``session`` (it was served here: nothing to
        await). Any thread."""
        with self._lock:
            self.at_prior.discard(session)

    def handed(self, session: str) -> str:
        """What came for ``session`` from its previous owner: "replica" (a state is held),
        "prior" (its owner said it had only the prior), or "" (nothing yet). Any thread."""
        with self._lock:
            if session in self.replicas:
                return "replica"
            if session in self.at_prior:
                self.at_prior.discard(session)
                self.terms_in.pop(session, None)  # awaited: not a second owner's
                return "prior"
        return ""

    def confirm_handover(self, succ: str, states: dict[str, bytes], timeout: float) -> list[str]:
        """Ask ``succ`` for the replicas it holds (:meth:`on_replica_query`) until it holds
        every one of ``states`` (session -> encoded state) byte for byte, for at most
        ``timeout`` s. A state missing from two answers in a row is put again, once (counted
        as ``replicas_handover_resent``): one still on its way over a slow link is not sent
        again and again. Returns the sessions ``succ`` was not seen to hold (counted as
        ``replicas_handover_unconfirmed``).

        Why not trust the puts: Zenoh may drop a put on a congested link, may route it
        otherwise than the query, and sends the withdrawal of the owner's liveliness token
        (a control message) ahead of queued data; a successor that took over before the
        final state arrived resumed from an older replica (seen twice in loaded test runs;
        on an idle machine 4 to 8 of 10 first answers lacked states just put,
        docs/service.md).
        The answer is the successor's own word that it holds the state."""
        t = self.pub.t
        missing = dict(states)
        lacked: set[str] = set()  # missing from the previous answer too
        again: set[str] = set()  # put again (once each: a put on its way is not repeated)
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0.0:
                break
            try:
                replies = t.get(replicas_for(succ), timeout=min(left, 1.0))
            except Exception:  # pragma: no cover - transport closing
                log.debug("handover query to %s failed", succ, exc_info=True)
                replies = []
            for r in replies:
                session = r.key.rsplit("/", 1)[-1]
                if r.ok and missing.get(session) == r.payload:
                    del missing[session]
            if not missing:
                break
            for session, data in missing.items():
                if session in lacked and session not in again:  # lost, not slow: again
                    again.add(session)
                    self.counters["replicas_handover_resent"] += 1
                    try:
                        t.put(replica_key(succ, session), data)
                    except Exception:  # pragma: no cover - transport closing
                        log.debug("handover put to %s failed", succ, exc_info=True)
            lacked = set(missing)
            time.sleep(min(_HANDOVER_RETRY_S, max(0.0, deadline - time.monotonic())))
        self.counters["replicas_handover_unconfirmed"] += len(missing)
        return sorted(missing)

    def _send(self, sess: Session, data: bytes) -> str | None:
        succ = self.ownership.successor(sess.name)
        if succ is not None:
            self.pub.pending.append(Out(replica_key(succ, sess.name), data))
            self.counters["replicas_sent"] += 1
            self.counters["replica_bytes"] += len(data)
        return succ

    def encode_state(self, sess: Session, now: int) -> bytes | None:
        """The session's SessionState, encoded (None if too large or not exportable)."""
        export = getattr(sess.est, "export_state", None)
        if export is None:
            return None
        try:
            data = encode_state(export(), session=sess.name, instance=self.settings.instance,
                                fingerprint=sess.fingerprint, made_ns=now,
                                session_counters=dict(sess.counters),
                                published=sess.published, seq=sess.seq, term=sess.term)
        except WireError as exc:
            self.counters["checkpoint_too_large"] += 1
            event(log, "checkpoint_too_large", logging.WARNING, session=sess.name,
                  reason=exc.reason)
            return None
        if len(data) > MAX_MESSAGE_BYTES:
            self.counters["checkpoint_too_large"] += 1
            return None
        return data

    def _count_written(self) -> None:
        """Count the checkpoints the writer thread finished (worker thread)."""
        assert self.writer is not None
        done = self.writer.done
        while done:
            session, size, exc = done.popleft()
            if exc is not None:
                self._failed(session, exc)
            else:
                self.counters["checkpoints"] += 1
                self.counters["checkpoint_bytes"] += size

    def _failed(self, session: str, exc: OSError) -> None:
        """Count a checkpoint that was not written; log it, or (within FAILED_LOG_EVERY_S
        of the last such line) only count it for the next line."""
        self.counters["checkpoint_failed"] += 1
        self._failed_unlogged += 1
        t = time.monotonic()
        if t - self._failed_logged_at >= FAILED_LOG_EVERY_S:
            event(log, "checkpoint_failed", logging.ERROR, session=session, reason=str(exc),
                  failed_since_last_line=self._failed_unlogged)
            self._failed_unlogged = 0
            self._failed_logged_at = t

    def close(self) -> None:
        """Write the pending checkpoints and stop the writer thread (if any)."""
        if self.writer is not None:
            self.writer.close()
            self._count_written()

    def _write(self, sess: Session, data: bytes) -> None:
        assert self.store is not None
        if self.writer is not None:
            self.writer.submit(sess.name, data)
            return
        try:
            self.store.save_state(sess.name, data)
        except OSError as exc:
            self._failed(sess.name, exc)
            return
        self.counters["checkpoints"] += 1
        self.counters["checkpoint_bytes"] += len(data)

    def forget(self, session: str) -> None:
        """The session is gone: its checkpoint and replica too."""
        if self.writer is not None:
            self.writer.remove(session)
        elif self.store is not None:
            self.store.remove_state(session)
        with self._lock:
            self.replicas.pop(session, None)
            self.at_prior.discard(session)

    # ================================================================== incoming ======

    def on_replica(self, sample: Sample) -> None:
        """Transport thread: keep the newest replica per session (by its now_step).

        Only the few fields read here are unpacked (the window's packets and commands are
        skipped unbuilt): the whole SessionState is validated when a takeover resumes from
        it (:func:`.checkpoint.restore`, a bad one refused there as
        ``restore_refused_corrupt``): decoding every replica on arrival would hold the GIL
        against the worker, for a state that is used only if its owner fails."""
        session = sample.key.rsplit("/", 1)[-1]
        if sample.kind == "delete" or sample.payload is None:
            # a hand-over of a session at its prior alone (hand_to): no state to resume
            with self._lock:
                self.replicas.pop(session, None)
                if len(self.at_prior) < MAX_REPLICAS:
                    self.at_prior.add(session)
                if len(self.terms_in) < MAX_REPLICAS:  # term unknown: 0
                    self.terms_in[session] = (0, "", 0)
            if self.arrived is not None:
                self.arrived(session)
            return
        try:
            check_name(session, "session")
            obj = unpack_fields(sample.payload, "SessionState", _REPLICA_FIELDS)
        except (KeyError_, WireError):
            obj = {}
        step = obj.get("now_step", -1)
        if obj.get("session") != session or not (step is None or type(step) is int and step >= 0):
            self.counters["replica_malformed"] += 1
            return
        step = step or 0
        term, writer = obj.get("term", 0), obj.get("instance", "")
        counted = obj.get("session_counters")
        with self._lock:
            if type(term) is int and term > 0 and type(writer) is str \
                    and type(counted) is dict and len(self.terms_in) < MAX_REPLICAS:
                self.terms_in[session] = (term, writer, inputs_accepted(counted))
            old = self.replicas.get(session)
            if old is None or step >= old[0]:
                if old is None and len(self.replicas) >= MAX_REPLICAS:
                    self.replicas.pop(next(iter(self.replicas)))
                self.replicas[session] = (step, bytes(sample.payload))
        self.counters["replicas_received"] += 1
        if self.arrived is not None:
            self.arrived(session)

    def on_replica_query(self, query: Query) -> None:
        """Transport thread: answer a query on this instance's replica keys with each
        replica held there (its key and bytes): how an owner that stops confirms that its
        final states arrived (:meth:`confirm_handover`)."""
        own = self.settings.instance
        with self._lock:
            held = [(replica_key(own, s), data) for s, (_, data) in self.replicas.items()]
        for key, data in held:
            if intersects(query.key, key):
                try:
                    query.reply(key, data)
                except Exception as exc:
                    log.debug("replica reply failed: %s", exc)

    # ================================================================== resume ========

    def resume(self, sess: Session, source: Origin, now: int) -> None:
        """Continue ``sess`` (just built from its prior) from its checkpoint ("checkpoint")
        or from the replica held for it ("replica"); a refusal is counted and reported and
        the session stays at its prior."""
        if source == "checkpoint":
            data = self.store.load_state(sess.name) if self.store is not None else None
            if data is None and self.store is not None:
                damaged = self.store.states_damaged()
                if damaged is not None:  # its checkpoint may have been in the part dropped
                    self._refused(sess, source, Refused(
                        "damaged", f"no checkpoint in the log, which was damaged ({damaged})"),
                        now)
        else:
            with self._lock:
                held = self.replicas.pop(sess.name, None)
            data = None if held is None else held[1]
        if data is None:
            return
        now_step = sess.step_now(now)
        msg, why = restore(sess.est, data, sess.spec, sess.fingerprint, now_step)
        if msg is not None:  # a refused state's term still fences: the next term is newer
            sess.resumed_term, sess.resumed_writer = msg.term, msg.instance
        if why is not None:
            self._refused(sess, source, why, now)
            return
        assert msg is not None
        sess.origin, sess.origin_step = source, msg.now_step
        sess.counters.update({k: v for k, v in msg.session_counters.items()
                              if k not in sess.counters})
        sess.published, sess.seq = msg.published, msg.seq
        sess.saved_mark = state_mark(sess)
        self.counters[f"resumed_from_{source}"] += 1
        stale = is_stale(msg, sess.spec, now_step)
        if stale:  # older than the window: propagated forward from its committed estimate
            self.counters["resumed_stale"] += 1
        event(log, "session_resumed", session=sess.name, source=source,
              step=msg.now_step if msg.now_step is not None else -1, now_step=now_step,
              stale=stale, packets=len(msg.packets), writer=msg.instance)

    def _refused(self, sess: Session, source: str, why: Refused, now: int) -> None:
        self.counters[f"restore_refused_{why.reason}"] += 1
        text = f"{source} not resumed ({why.reason}): {why.text}; started from the prior"
        event(log, "restore_refused", logging.WARNING, session=sess.name, source=source,
              reason=why.reason, detail=why.text)
        own = self.settings.instance
        key = (checkpoint_key(own, sess.name) if source == "checkpoint"
               else replica_key(own, sess.name))
        self.pub.refuse(sess, key, Refusal("restore_refused", text), now,
                        counted=("restore_refused",))

