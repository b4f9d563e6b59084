"""Queries and status: SessionStatus / ServiceStatus, and the status and spec queryables.

Queryables run on the transport's threads. They hold the core's lock (which the worker
holds while processing one round) only to copy what a reply needs (a :class:`StatusSnapshot`:
counters, the latency window, a few scalars; microseconds), so replies never see a
half-updated session; percentiles, building and validating the message, encoding and
sending happen after the lock is released, so a query never stalls the worker.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol, cast

import numpy as np

from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME
from pd_service.transport import Query
from pd_service.transport.keyexpr import intersects
from pd_service.wire import ErrorReport, ServiceStatus, SessionSpec, SessionStatus, encode, keys
from pd_service.wire.keys import KeyError_, check_name

from .config import Settings
from .latency import LatencyWindow, percentiles
from .ownership import Ownership
from .robot_time import RobotView
from .session import Refusal, Session
from .step_clock import StepClock

#: ``Outbox.refuse``: the refusal funnel (counted, reported within the error limits).
Refuse = Callable[..., "ErrorReport | None"]

log = logging.getLogger(LOGGER_NAME)

#: ``SessionStatus.state``: how a session started (active, restored) or ended.
SessionPhase = Literal["active", "restored", "expired", "removed"]


@dataclass(frozen=True, slots=True)
class StatusSnapshot:
    """What a SessionStatus needs, copied from a session (under the core's lock)."""

    name: str
    status_key: str
    state: SessionPhase
    detail: str
    spec: SessionSpec  # immutable; for now_step
    counters: dict[str, int]
    published: int
    latency_us: np.ndarray  # a copy of the session's LatencyWindow
    origin: Literal["prior", "checkpoint", "replica"]
    origin_step: int | None
    robot: RobotView  # the robot's time: copies, read after the lock (robot_time)
    readback: Literal["", "waiting", "answered", "timeout"]
    term: int

    def status(self, instance: str, now: int) -> SessionStatus:
        """The SessionStatus at wall-clock time ``now`` (ns); needs no lock."""
        p50, p99 = percentiles(self.latency_us)
        robot = self.robot
        return SessionStatus(session=self.name, instance=instance, state=self.state,
                             now_step=self.spec.step_of(now), counters=self.counters,
                             published=self.published, latency_p50_us=p50,
                             latency_p99_us=p99, detail=self.detail[:1024],
                             origin=self.origin, origin_step=self.origin_step,
                             clock=robot.clock, delays=robot.delay_status(),
                             recommended_max_delay=robot.recommended_max_delay(),
                             recommended_lead=robot.recommended_lead(),
                             late_share=robot.late_share,
                             readback=self.readback, term=self.term)


def snapshot_of(sess: Session, state: SessionPhase, detail: str,
                now: int | None = None) -> StatusSnapshot:
    """Copy of what ``sess``'s status needs (hold the lock while calling this); ``now``
    (ns): the time of the clock estimate (default: the session's last activity)."""
    return StatusSnapshot(sess.name, sess.status_key, state, detail, sess.spec,
                          sess.counters_snapshot(), sess.published, sess.latency.values(),
                          sess.origin, sess.origin_step,
                          sess.robot.view(sess.last_activity_ns if now is None else now),
                          sess.readback, sess.term)


def session_status(sess: Session, instance: str, state: SessionPhase, detail: str,
                   now: int) -> SessionStatus:
    """The status of a served session at wall-clock time ``now`` (ns)."""
    return snapshot_of(sess, state, detail, now).status(instance, now)


def phase_of(sess: Session) -> SessionPhase:
    """The state a session was started with."""
    # Session.state is typed str; the lifecycle only ever creates it with a SessionPhase.
    return cast(SessionPhase, sess.state)


def current_snapshot(sess: Session, now: int | None = None) -> StatusSnapshot:
    """The view of a session in the state and detail it was last answered with."""
    return snapshot_of(sess, phase_of(sess), sess.detail, now)


def valid_name(name: str) -> bool:
    try:
        check_name(name)
        return True
    except KeyError_:
        return False


class Routed(Protocol):
    """A known session as the queries see it (a dispatch route)."""

    @property
    def sess(self) -> Session | None:
        """The Session this instance runs; None: served by another instance."""


class Queries:
    """Read-only views of the core's state, for the queryables and the daemon's API.

    ``routes``: every known session name -> its route; ``specs``: every known spec. Both
    are read under ``lock``."""

    def __init__(self, settings: Settings, lock: threading.RLock, counters: Tally,
                 latency: LatencyWindow, ownership: Ownership,
                 routes: Mapping[str, Routed],
                 specs: Mapping[str, SessionSpec], now_ns: Callable[[], int],
                 mono_ns: Callable[[], int], *, refuse: Refuse | None = None,
                 received: Callable[[], int] = lambda: 0) -> None:
        self.settings = settings
        self.instance = settings.instance
        self.lock = lock
        self.counters = counters
        self.latency = latency
        self.ownership = ownership
        self.routes = routes
        self.specs = specs
        self.now_ns = now_ns
        #: The core's step clock, if it has one (the host clock steps it re-anchored to).
        self.step_clock: StepClock | None = None
        self.mono_ns = mono_ns
        self._started_mono = mono_ns()
        #: The refusal funnel (a layout-1 status query's refusal is rate-limited by it).
        self.refuse = refuse
        #: The data samples received so far (``samples_received``; read under the lock).
        self.received = received
        #: session -> (its spec, encoded): the spec query's replies (specs are frozen and
        #: replaced, never changed); every peer asks for all of them at each join
        self._spec_bytes: dict[str, tuple[SessionSpec, bytes]] = {}

    # --- the daemon's API (any thread) ----------------------------------------------------

    def session_status(self, session: str) -> SessionStatus | None:
        """Status of a session this instance serves (None otherwise)."""
        with self.lock:
            route = self.routes.get(session)
            if route is None or route.sess is None:
                return None
            now = self.now_ns()
            view = current_snapshot(route.sess, now)
        return view.status(self.instance, now)

    def service_status(self) -> ServiceStatus:
        """The instance's status; holds the lock only to copy counters and latencies."""
        with self.lock:
            served = [n for n, r in self.routes.items() if r.sess is not None]
            c = {k: int(v) for k, v in self.counters.items() if v}
            known, members = len(self.specs), len(self.ownership.members)
            owned = len(self.ownership.owned_partitions())
            received = self.received()
            latency = self.latency.values()
        c.setdefault("refused", 0)
        c["late_total"] = c.get("late", 0) + c.get("commands_late", 0)
        c["sessions_served"] = len(served)
        c["sessions_known"] = known
        c["members"] = members
        c["samples_received"] = received
        p50, p99 = percentiles(latency)
        return ServiceStatus(instance=self.instance, sessions=sorted(served), counters=c,
                             latency_p50_us=p50, latency_p99_us=p99,
                             uptime_s=(self.mono_ns() - self._started_mono) / 1e9,
                             shard=self.settings.shard or "",
                             partitions=self.ownership.partitions, key_layout=keys.KEY_LAYOUT,
                             owned_partitions=owned, clock_stepped_ns=(
                                 0 if self.step_clock is None else self.step_clock.stepped_ns))

    def served_sessions(self) -> list[str]:
        with self.lock:
            return sorted(n for n, r in self.routes.items() if r.sess is not None)

    def known_specs(self) -> dict[str, SessionSpec]:
        with self.lock:
            return dict(self.specs)

    # --- queryables (transport threads) ---------------------------------------------------

    def on_status_query(self, q: Query) -> None:
        sel = q.key
        unknown = ""
        with self.lock:  # copies only: the statuses are built after it is released
            now = self.now_ns()
            if "*" in sel:
                sessions = [r.sess for r in self.routes.values() if r.sess is not None]
                views = [current_snapshot(s, now) for s in sessions
                         if intersects(sel, s.status_key)]
            else:
                parts = sel.split("/")
                name = parts[2] if len(parts) == 4 else ""
                route = self.routes.get(name)
                if route is not None and route.sess is not None:
                    views = [current_snapshot(route.sess, now)]
                elif route is None and valid_name(name) and self.ownership.owns(name):
                    views, unknown = [], name
                else:
                    return
        now = self.now_ns()
        err: ErrorReport | None = None
        if unknown:
            err = ErrorReport(session=unknown, key=sel[:512],
                              reason=f"unknown session {unknown!r}", t_ns=now)
        for view in views:
            try:
                q.reply(view.status_key, encode(view.status(self.instance, now)))
            except Exception as exc:  # e.g. the query was dropped meanwhile
                log.debug("status reply failed: %s", exc)
        if err is not None:
            try:
                q.reply_err(encode(err))
            except Exception as exc:
                log.debug("status reply_err failed: %s", exc)

    def on_legacy_status_query(self, q: Query) -> None:
        """A status query of key layout 1 (``pd/<session>/status``, an old client): its
        session's owner answers with an error reply saying where the keys are now, within
        the error-report limits (``Outbox.refuse``); counted ``legacy_keys``. A wildcard
        query names no session: counted, not answered."""
        sel = q.key
        name = sel.split("/")[1] if keys.is_legacy_key(sel) else ""
        err: ErrorReport | None = None
        with self.lock:
            if self.refuse is None:
                return
            now = self.now_ns()
            why = keys.legacy_reason(sel) if name else ""
            err = self.refuse(None, sel, Refusal("legacy_keys", why), now, session=name,
                              counted=("legacy_keys",),
                              report=bool(name) and self.ownership.owns(name), put=False)
        if err is not None:
            try:
                q.reply_err(encode(err))
            except Exception as exc:
                log.debug("legacy status reply_err failed: %s", exc)

    def on_service_query(self, q: Query) -> None:
        try:
            q.reply(keys.service_status_key(self.instance), encode(self.service_status()))
        except Exception as exc:
            log.debug("service status reply failed: %s", exc)

    def on_config_query(self, q: Query) -> None:
        sel = q.key
        with self.lock:
            specs = [(keys.config_key(n), s) for n, s in self.specs.items()
                     if intersects(sel, keys.config_key(n))]
        for key, spec in specs:
            try:
                q.reply(key, self._encoded_spec(spec))
            except Exception as exc:
                log.debug("config reply failed: %s", exc)

    def _encoded_spec(self, spec: SessionSpec) -> bytes:
        """``spec`` encoded, once per spec (any thread: a lost race encodes it twice)."""
        cache = self._spec_bytes
        got = cache.get(spec.session)
        if got is not None and got[0] is spec:
            return got[1]
        data = encode(spec)
        if len(cache) > 2 * len(self.specs) + 64:  # the sessions gone meanwhile, out
            cache.clear()
        cache[spec.session] = (spec, data)
        return data
