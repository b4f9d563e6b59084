"""Publishing: predictions, ticks, error reports and status answers, through one outbox.

Everything the worker publishes during a round is appended to the outbox and sent by
:meth:`Outbox.flush` at the end of the round (after the core's state is consistent). A
Prediction is published for every session that accepted a measurement in the round
(coalesced: one per session per round) and at every session's tick: the first step
``k > after`` with ``k % publish_every == 0`` fires at ``epoch + (k + tick_phase) * period``.
A session whose data came after the tick phase in step ``k - 1`` (and published) gets
its tick for step ``k`` late, at ``DATA_TICK_PHASE`` of the step: its data, arriving again
after ``tick_phase``, give the step's one prediction instead of a second one after the
tick's (the tick still publishes if they do not come). Data arriving before the tick
phase need no such delay: the tick finds the step published.

A session is *idle* until its first measurement or command that decodes (from its start:
created, replaced, restored, synced or taken over) and again after ``idle_after_s`` without
one: its first tick still publishes (a display sees the prior at once), then it is ticked only
at the steps ``k`` with ``k % skip == spread % skip`` (``skip``: ``idle_publish_s`` in steps;
``Session.spread``: its phase, from its name), one prediction per ``idle_publish_s``, so a
session with no traffic costs no CPU per step; its next message wakes it (:meth:`wake`):
published at once if a measurement was accepted, and ticked every step again.

Refusals are counted per session and service-wide and reported as ErrorReports, limited per
session (``error_rate``/``error_burst``) and service-wide (``error_rate_total``).
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Callable
from typing import Final

from pd_service.estimation import PredictedState
from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME, event
from pd_service.ratelimit import TokenBucket
from pd_service.transport import Transport
from pd_service.wire import ErrorReport, SessionStatus, encode, keys

from .config import Settings
from .health import inspect, inspect_packed
from .latency import LatencyWindow
from .session import Refusal, Session, next_slot
from .status import SessionPhase, session_status

log = logging.getLogger(LOGGER_NAME)

#: Where in its step the tick of a data-driven session fires (fraction of the period).
DATA_TICK_PHASE: Final = 0.95

#: Read per call from C statics (Final), not looked up as ``heapq.<name>`` each time.
_heappush: Final = heapq.heappush
_heappop: Final = heapq.heappop


class Out:
    """One pending publication: put (payload) or delete (payload None). ``recv``: receipt
    times (monotonic ns) of the measurements a prediction answers, for ``sess``'s latency.
    (A plain class: compiled, built in a fraction of a slots dataclass's time.)"""

    __slots__ = ("key", "payload", "sess", "recv")

    def __init__(self, key: str, payload: bytes | None, sess: Session | None = None,
                 recv: list[int] | None = None) -> None:
        self.key = key
        self.payload = payload
        self.sess = sess
        self.recv: list[int] = [] if recv is None else recv


class Outbox:
    """The outbox, the tick schedule and the error-report limits. Worker thread only."""

    def __init__(self, transport: Transport, settings: Settings, counters: Tally,
                 latency: LatencyWindow, mono_ns: Callable[[], int], now: int) -> None:
        self.t = transport
        self.settings = settings
        self.instance = settings.instance
        # read per session and step: plain attributes, not the (pydantic) settings'
        self._tick_phase: float = settings.tick_phase
        self._idle_ns = int(settings.idle_after_s * 1e9)
        self.counters = counters
        self.latency = latency
        self.mono_ns = mono_ns
        self.pending: list[Out] = []
        #: The tick schedule: per deadline (ns) its entries (the session's tick generation,
        #: step, deferred, session) in the order they were queued, and a heap of the
        #: deadlines; ``deferred``: the late tick of a data-driven session. Sessions that
        #: share an epoch share deadlines: queueing a tick is a dict lookup and an append,
        #: not a push into a heap of N tuples whose equal deadlines tie.
        self._tick_at: dict[int, list[tuple[int, int, bool, Session]]] = {}
        self._tick_times: list[int] = []
        #: ErrorReports about sessions nobody serves (unknown names, refused new specs).
        self.unknown_limiter = TokenBucket(settings.error_rate, settings.error_burst, now)
        self.total_limiter = TokenBucket(settings.error_rate_total,
                                         max(1, int(settings.error_rate_total)), now)

    # --- error reports --------------------------------------------------------------------

    def refuse(self, sess: Session | None, key: str, r: Refusal, now: int, *,
               session: str = "", count: int = 1, counted: tuple[str, ...] | None = None,
               report: bool = True, to: str = "", put: bool = True) -> ErrorReport | None:
        """The daemon's one way to refuse: count ``r`` and report it in an ErrorReport.

        Counted: ``count`` times each name of ``counted`` (default ``r.reason`` and
        ``refused``), on the session's counters (``sess``: served here; else None and
        ``session`` names it) and service-wide. Reported (``report``: this instance owns the
        name) on the session's error key within the limits: its own bucket (``error_rate``,
        ``error_burst``; the names not served here share one), then the service's
        (``error_rate_total``); over either, counted ``errors_suppressed`` instead. ``to``:
        report on this key instead of the session's error key; ``put`` False: not put but
        returned, for the caller to send (a query's error reply). Returns the report made."""
        if counted is None:
            counted = (r.reason, "refused")
        for name in counted:
            if sess is not None:
                sess.counters[name] += count
            self.counters[name] += count
        if counted and log.isEnabledFor(logging.DEBUG):
            event(log, "refused", logging.DEBUG, session=session if sess is None else sess.name,
                  key=key, reason=r.reason, text=r.text)
        if not report:
            return None
        limiter = self.unknown_limiter if sess is None else sess.limiter
        if limiter.allow(now) and self.total_limiter.allow(now):
            err_key = to or (keys.error_key(session) if sess is None else sess.error_key)
            name = session if sess is None else sess.name
            rep = ErrorReport(session=name, key=key[:512], seq=r.seq, reason=r.text[:1024],
                              t_ns=now)
            if put:
                self.pending.append(Out(err_key, encode(rep)))
            self.counters["errors_sent"] += 1
            return rep
        if sess is not None:
            sess.counters["errors_suppressed"] += 1
        self.counters["errors_suppressed"] += 1
        return None

    # --- status answers -------------------------------------------------------------------

    def answer(self, sess: Session, state: SessionPhase, detail: str, now: int) -> None:
        """Put the session's status (the answer to a config change)."""
        st = session_status(sess, self.instance, state, detail, now)
        self.pending.append(Out(sess.status_key, encode(st)))

    def answer_gone(self, session: str, state: SessionPhase, detail: str, now: int,
                    sess: Session | None) -> None:
        """Put the status of a session that is removed or expired (or never was)."""
        if sess is not None:
            st = session_status(sess, self.instance, state, detail, now)
        else:
            st = SessionStatus(session=session, instance=self.instance, state=state,
                               now_step=0, published=0, latency_p50_us=0.0,
                               latency_p99_us=0.0, detail=detail)
        self.pending.append(Out(keys.status_key(session), encode(st)))

    def delete(self, key: str) -> None:
        self.pending.append(Out(key, None))

    # --- predictions ----------------------------------------------------------------------

    def publish_many(self, sessions: list[Session], now: int, data: bool = False) -> None:
        """Publish a Prediction of now + lead for each session. ``data``: the publications
        answer accepted measurements (the session is data-driven)."""
        for sess in sessions:
            if sess.hold_until_ns:  # waits for its senders' caches (Lifecycle.hold_for_read_back)
                continue
            k = sess.step_now(now)
            if k < 0:  # before the session's epoch: nothing to predict yet
                sess.pending_recv.clear()
                continue
            try:
                pred = sess.predict(k)
            except Exception as exc:  # e.g. a backend's Cholesky of a broken covariance
                got = self._reset_estimate(sess, k, f"prediction failed: "
                                    f"{type(exc).__name__}: {exc}", now)
                if got is None:
                    continue
                pred = got
            missed = sess.steps_missed_before(k)
            try:
                bad, xb, pb = inspect_packed(pred.x, pred.P)
                if bad is not None:
                    got = self._reset_estimate(sess, k, bad, now)
                    if got is None:
                        continue
                    pred = got
                    _, xb, pb = inspect_packed(pred.x, pred.P)  # healthy: _reset_estimate checked
                sess.keep_snapshot(pred, k)
                payload = sess.pack(pred, xb, pb, k, now)
            except Exception as exc:  # e.g. a non-finite estimate: report, never crash
                self._publish_failed(sess, exc, now)
                continue
            self.counters["published"] += 1
            if missed:
                sess.counters["steps_missed"] += missed
                self.counters["steps_missed"] += missed
            recv, sess.pending_recv = sess.pending_recv, []
            self.pending.append(Out(sess.pred_key, payload, sess, recv))
            if sess.path_due():
                self._publish_path(sess, k, now)
            if data and now - sess.time_of(k) >= self._tick_ns(sess):
                sess.late_data_step = k

    def _reset_estimate(self, sess: Session, k: int, why: str, now: int) -> PredictedState | None:
        """The estimate of ``sess`` at step ``k`` is unusable (``why``): restore its snapshot,
        else its prior, and predict again. Returns the healthy prediction, or
        None (reported as ``internal_error``) if even the prior gives none; after such a
        failure no new attempt for ``sess.retry_after`` steps. Counted (``unhealthy``,
        ``recovered``, ``recovered_from_<source>``), logged and reported."""
        sess.counters["unhealthy"] += 1
        self.counters["unhealthy"] += 1
        failed = sess.health_failed_step
        if failed is not None and k - failed < sess.retry_after:
            sess.pending_recv.clear()
            self.refuse(sess, sess.pred_key, Refusal("internal_error", why), now)
            return None
        sources = ("snapshot", "prior") if sess.snapshot is not None else ("prior",)
        problem = why
        for source in sources:
            try:
                sess.reset_estimate(source)
                pred = sess.predict(k)
                bad = inspect(pred.x, pred.P)[0]
            except Exception as exc:
                bad = f"{type(exc).__name__}: {exc}"
            if bad is None:
                sess.health_failed_step = None
                for c in (sess.counters, self.counters):
                    c["recovered"] += 1
                    c[f"recovered_from_{source}"] += 1
                text = f"estimate recovered from its {source} at step {k}: {why}"
                event(log, "session_recovered", logging.WARNING, session=sess.name,
                      source=source, step=k, reason=why)
                # a notice, not a refusal: reported within the limits, nothing counted
                self.refuse(sess, sess.pred_key, Refusal("recovered", text), now, counted=())
                return pred
            problem = f"{problem}; from its {source}: {bad}"
        sess.health_failed_step = k
        event(log, "session_unrecoverable", logging.ERROR, session=sess.name, step=k,
              reason=problem)
        sess.pending_recv.clear()
        self.refuse(sess, sess.pred_key, Refusal(
            "internal_error", f"no healthy estimate, not even from the prior: {problem}"), now)
        return None

    def _publish_path(self, sess: Session, k: int, now: int) -> None:
        """Queue the PredictedPath beside the Prediction just queued (the spec asked for it);
        a failure is counted (``path_failed``) and reported, the Prediction still goes."""
        try:
            self.pending.append(Out(sess.path_key, sess.pack_path(k, now)))
        except Exception as exc:
            self.refuse(sess, sess.path_key, Refusal(
                "internal_error", f"path failed: {type(exc).__name__}: {exc}"), now,
                counted=("path_failed",))

    def _publish_failed(self, sess: Session, exc: Exception, now: int) -> None:
        sess.pending_recv.clear()
        self.refuse(sess, sess.pred_key, Refusal(
            "internal_error", f"prediction failed: {type(exc).__name__}: {exc}"), now)

    def flush(self) -> None:
        """Send the outbox; record receipt -> put latencies (µs) of the predictions sent."""
        out, self.pending = self.pending, []
        t = self.t
        put, mono = t.put, self.mono_ns
        for o in out:
            try:
                if o.payload is None:
                    t.delete(o.key)
                else:
                    put(o.key, o.payload)
            except Exception as exc:
                self.counters["publish_failed"] += 1
                log.debug("publish on %s failed: %s", o.key, exc)
                continue
            if o.recv and o.sess is not None:
                now_mono = mono()
                for r in o.recv:
                    us = (now_mono - r) / 1000.0
                    o.sess.latency.add(us)
                    self.latency.add(us)

    # --- ticks ----------------------------------------------------------------------------

    def schedule(self, sess: Session, after_step: int) -> None:
        """Queue the session's next tick: the first step k > after_step with
        k % publish_every == 0, at time epoch + k * period + tick_phase * period. The
        session's earlier entry, if any, is void (``tick_gen``)."""
        pe = sess.publish_every
        k = max(0, (after_step // pe + 1) * pe)
        deadline = sess.time_of(k) + self._tick_ns(sess)
        sess.tick_gen += 1
        self._queue_tick(deadline, (sess.tick_gen, k, False, sess))

    def _queue_tick(self, deadline: int, entry: tuple[int, int, bool, Session]) -> None:
        bucket = self._tick_at.get(deadline)
        if bucket is None:
            self._tick_at[deadline] = [entry]
            _heappush(self._tick_times, deadline)
        else:
            bucket.append(entry)

    def _tick_ns(self, sess: Session) -> int:
        """Where in its step the session's tick fires (ns after the step's start)."""
        return int(self._tick_phase * sess.period_ns)

    def wake(self, sess: Session, now: int) -> None:
        """An idle session got a message: tick it every step again from now on (its steps
        are due from now on: those it skipped while idle are not missed)."""
        sess.idle = False
        cur = sess.step_now(now)
        sess.due_from = cur
        self.schedule(sess, cur - 1)

    def next_tick_ns(self) -> int | None:
        return self._tick_times[0] if self._tick_times else None

    def run_ticks(self, now: int) -> None:
        """Publish for every session whose tick is due and has not published this step."""
        times, at = self._tick_times, self._tick_at
        due: list[Session] = []
        idle_ns = self._idle_ns
        while times and times[0] <= now:
            # a tick queued meanwhile for a deadline already passed (a late tick, a worker
            # behind) gets a bucket of its own: this loop takes it before it returns
            for gen, k, deferred, sess in at.pop(_heappop(times)):
                if not sess.alive or gen != sess.tick_gen:
                    continue
                cur = sess.step_now(now)
                if deferred:  # a data-driven session's late tick: publish unless data came
                    last = sess.last_pub_step
                    if cur >= 0 and (last is None or last < k):
                        due.append(sess)
                    continue
                if cur > k and not sess.idle:
                    sess.counters["tick_overruns"] += 1
                    self.counters["tick_overruns"] += 1
                defer = False
                if cur >= 0 and sess.last_pub_step != cur:
                    if cur == k and sess.late_data_step == k - 1:
                        defer = True
                    else:
                        due.append(sess)
                if not sess.heard or now - sess.last_activity_ns > idle_ns:
                    # idle (no message since it was started, or none for idle_after_s): ticked
                    # only at the steps k = phase (mod skip), one per idle_publish_s, at a
                    # phase of its own so idle sessions do not all predict in the same tick
                    skip = max(1, int(self.settings.idle_publish_s * 1e9) // sess.period_ns)
                    base = max(cur, k)
                    nxt = next_slot(base, skip, sess.spread)
                    sess.idle = True
                    self.schedule(sess, nxt - 1)
                    if defer:
                        due.append(sess)
                else:
                    sess.idle = False
                    self.schedule(sess, max(cur, k))
                    if defer:
                        self._queue_tick(sess.time_of(k) + int(DATA_TICK_PHASE * sess.period_ns),
                                         (sess.tick_gen, k, True, sess))
        if due:
            self.publish_many(due, now)
