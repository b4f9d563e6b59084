"""The robot's side, heard by the daemon: command echoes and clock probes (issue 43).

- **Echoes**: a subscription to ``pd/*/*/echo`` (the robots' :class:`CommandEcho`, carried
  down by pd-link like a sensor); the callback only appends ``(session, payload, receipt)``
  to a bounded queue (oldest dropped and counted ``echoes_flood``); the worker hands them to
  their sessions (:meth:`RobotTimeIO.process`, :meth:`.session.Session.on_echo`).
- **Probes**: a thread of its own (:meth:`RobotTimeIO.start`) queries, every
  ``probe_interval_s``, the probe queryable ``robot/p<k>/<session>/clock`` of every served
  session whose spec has ``robot_clock: estimated``, one at a time with ``probe_timeout_s``
  each: a robot that does not answer costs this thread its timeout, never the worker or
  another session's data. t1 / t4 are read just before the query and just after its answer
  (a late t4 only widens the bound). The four timestamps go to the worker through a bounded
  queue. Counted: ``probes_sent``, ``probes_unanswered``, ``probe_replies_invalid`` (not a
  ClockProbeReply of this probe), ``probe_replies_extra`` (more than one answer: the first
  valid one is used).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Final

from pd_service.estimation.tally import Tally
from pd_service.logs import LOGGER_NAME
from pd_service.transport import Handle, Sample, Transport
from pd_service.wire import ClockProbe, ClockProbeReply, WireError, decode, encode, keys

from .config import Settings
from .dispatch import Route
from .session import Session

log = logging.getLogger(LOGGER_NAME)

#: Echoes and probe answers waiting for the worker (oldest dropped beyond it).
ECHO_INBOX: Final = 4096


class RobotTimeIO:
    """Echo receipt and clock probes of one daemon instance (see the module docstring)."""

    def __init__(self, transport: Transport, settings: Settings, now_ns: Callable[[], int],
                 wake: threading.Event, counters: Tally) -> None:
        """``counters``: the service's (a few increments from the transport and probing
        threads may race: counters, not invariants)."""
        self.t = transport
        self.settings = settings
        self.now_ns = now_ns
        self.wake = wake
        self.counters = counters
        self.echoes: deque[tuple[str, bytes, int]] = deque(maxlen=ECHO_INBOX)
        self.answers: deque[tuple[str, int, int, int, int]] = deque(maxlen=ECHO_INBOX)
        self._probe_seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._handle: Handle | None = None

    # --- echoes (transport threads) ------------------------------------------------------

    def subscribe(self) -> None:
        """Subscribe to every session's echoes."""
        self._handle = self.t.subscribe(keys.ALL_ECHOES, self.on_echo_sample)

    def on_echo_sample(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        name = keys.session_of(sample.key)
        if name is None:
            return
        if len(self.echoes) == self.echoes.maxlen:
            self.counters["echoes_flood"] += 1
        self.echoes.append((name, sample.payload, self.now_ns()))
        self.wake.set()

    # --- probes (their own thread) ------------------------------------------------------

    def start(self, sessions: Callable[[], list[str]]) -> None:
        """Probe ``sessions()`` (the served sessions whose robot clock is estimated) every
        ``probe_interval_s`` from a thread of its own (none if the interval is 0)."""
        if self.settings.probe_interval_s <= 0:
            return
        self._thread = threading.Thread(target=self._run, args=(sessions,),
                                        name="pd-clock-probes", daemon=True)
        self._thread.start()

    def _run(self, sessions: Callable[[], list[str]]) -> None:
        while not self._stop.wait(self.settings.probe_interval_s):
            try:
                self.probe_all(sessions())
            except Exception:  # a bug must not end the probes: log it
                log.exception("clock probes failed")

    def probe_all(self, names: list[str]) -> int:
        """Probe each session in ``names`` once (the thread's pass; tests call it directly);
        returns how many answered."""
        answered = 0
        for name in names:
            if self._stop.is_set():
                break
            answered += self.probe(name)
        if answered:
            self.wake.set()
        return answered

    def probe(self, name: str) -> bool:
        """One probe of ``name``'s robot; True iff it answered validly (queued)."""
        self._probe_seq += 1
        seq, c = self._probe_seq, self.counters
        t1 = self.now_ns()
        query = encode(ClockProbe(session=name, probe=seq, t1_ns=t1))
        c["probes_sent"] += 1
        try:
            replies = self.t.get(keys.robot_clock_key(name), payload=query,
                                 timeout=self.settings.probe_timeout_s)
        except Exception as exc:  # the transport closing, say: counted as unanswered
            log.debug("probe of %s failed: %s", name, exc)
            replies = []
        t4 = self.now_ns()
        found = None
        for r in replies:
            if not r.ok:
                c["probe_replies_invalid"] += 1
                continue
            try:
                rep = decode(r.payload, ClockProbeReply)
            except WireError:
                c["probe_replies_invalid"] += 1
                continue
            if rep.session != name or rep.probe != seq or rep.t1_ns != t1:
                c["probe_replies_invalid"] += 1
            elif found is None:
                found = rep
            else:
                c["probe_replies_extra"] += 1
        if found is None:
            c["probes_unanswered"] += 1
            return False
        if len(self.answers) == self.answers.maxlen:
            c["probe_answers_flood"] += 1
        self.answers.append((name, t1, found.t2_ns, found.t3_ns, t4))
        return True

    # --- the worker -----------------------------------------------------------------------

    def pending(self) -> bool:
        return bool(self.echoes or self.answers)

    def process(self, routes: dict[str, Route], now: int, touched: list[Session]) -> int:
        """Worker, under the core's lock: hand the queued echoes and probe answers to their
        sessions (those served elsewhere or unknown: counted ``echoes_unrouted``). A session
        one of whose commands entered its estimator is appended to ``touched``."""
        n = 0
        echoes, answers = self.echoes, self.answers
        while echoes:
            name, payload, recv = echoes.popleft()
            n += 1
            route = routes.get(name)
            sess = route.sess if route is not None else None
            if sess is None:
                self.counters["echoes_unrouted"] += 1
                continue
            if sess.on_echo(payload, recv, sess.step_now(now)) and sess not in touched:
                touched.append(sess)
        while answers:
            name, t1, t2, t3, t4 = answers.popleft()
            n += 1
            route = routes.get(name)
            if route is not None and route.sess is not None:
                route.sess.robot.probe(t1, t2, t3, t4)
        return n

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.settings.probe_timeout_s + 1.0)
        if self._handle is not None:
            self._handle.close()
