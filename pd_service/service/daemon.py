"""The daemon: a Zenoh transport, a :class:`ServiceCore`, one worker thread, signals.

Threads:

- Zenoh's own threads run the callbacks (they only append to inboxes) and the queryables;
- one worker thread runs :meth:`ServiceCore.run_once` whenever woken by a callback or when
  the next tick / expiry check is due;
- the main thread waits for SIGTERM / SIGINT, returning the C heap's free pages once a minute
  (:mod:`.heap`), then stops the worker, withdraws the liveliness token (peers take over at
  once), undeclares everything and closes the session.

Specs are persisted as they change, so there is nothing else to flush at shutdown.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import sys
import threading
import time

from pd_service.logs import LOGGER_NAME, event, name_os_thread
from pd_service.metrics import MetricsServer, serve
from pd_service.transport import Transport

from .config import Settings
from .core import ServiceCore
from .handover.checkpoint_writer import CheckpointWriter
from .heap import TRIM_INTERVAL_S, return_free_heap
from .scrape import collect
from .spec_store import SpecStore

log = logging.getLogger(LOGGER_NAME)

#: Free heap handed back that is worth a log line (bytes).
_TRIM_LOGGED_BYTES = 16 << 20

#: Longest the worker sleeps without a wake-up (s): bounds the reaction to a stop request.
_MAX_SLEEP_S = 0.5
#: A busy worker loop (start to the next one's start, s) longer than this is reported.
_SLOW_LOOP_S = 0.1
#: After a loop that handled messages, the worker keeps looking at its queues itself
#: (every ``round_interval_us``) for this long (s) before it arms the drains' watcher.
_BUSY_S = 0.1


def make_transport(settings: Settings) -> Transport:
    """A ZenohTransport from the settings (peer on tcp/127.0.0.1:7447 by default)."""
    from pd_service.transport import DAEMON, ZenohTransport

    return ZenohTransport(settings.zenoh.config(DAEMON))


def tune_gc() -> None:
    """Garbage collection for a long-running worker: what exists now (modules, schemas,
    restored sessions) is never scanned again, and the young generation is collected every
    100,000 net allocations instead of 700.

    A young collection's pause grows with the tracked objects alive and younger than the
    last collection, not with the threshold; the threshold sets how often they come
    (measurements: docs/service.md, "Performance"). The hot path makes no reference
    cycles, so rarer collections leave none of its garbage waiting."""
    gc.freeze()
    gc.set_threshold(100_000, 10, 10)


class Daemon:
    """Runs a ServiceCore on a transport (Zenoh unless one is given) with a worker thread."""

    def __init__(self, settings: Settings, transport: Transport | None = None) -> None:
        self.settings = settings
        self._given_transport = transport
        self.transport: Transport | None = None
        self.core: ServiceCore | None = None
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._worker_error: BaseException | None = None
        self.metrics: MetricsServer | None = None

    def start(self) -> ServiceCore:
        # Zenoh's threads need the GIL for every callback; with the default 5 ms switch
        # interval a busy worker would delay each hand-off by up to 5 ms.
        sys.setswitchinterval(self.settings.switch_interval_us * 1e-6)
        transport = self._given_transport or make_transport(self.settings)
        self.transport = transport
        store = SpecStore(self.settings.effective_state_dir)
        self.core = ServiceCore(transport, self.settings, store=store)
        # checkpoints are written by a thread of their own: the worker never waits for fsync
        self.core.keeper.writer = CheckpointWriter(store)
        self.core.start()
        # inserted before the worker runs: trim_heap (main thread) then adds no key under it
        self.core.counters["heap_trims"] = self.core.counters["heap_returned_bytes"] = 0
        tune_gc()
        if self.settings.metrics:
            core = self.core
            self.metrics = serve(self.settings.metrics, lambda: collect(core.queries), log)
        self._worker = threading.Thread(target=self._work, name="pd-service-worker", daemon=True)
        self._worker.start()
        return self.core

    def _work(self) -> None:
        name_os_thread("pd-worker")
        path = os.environ.get("PD_SERVICE_PROFILE")  # diagnostics: cProfile of the worker
        if not path:
            self._loop()
            return
        import cProfile

        prof = cProfile.Profile()
        try:
            prof.runcall(self._loop)
        finally:
            prof.dump_stats(path)

    def _loop(self) -> None:
        core = self.core
        assert core is not None
        wake, stop = core.wake, self._stop
        interval = self.settings.round_interval_us * 1e-6  # s
        last_handled = -_BUSY_S  # monotonic time (s) of the last loop that handled messages
        prev = None  # the previous busy loop: (its start, run_once's wall and CPU time, s)
        while not stop.is_set():
            t0, c0 = time.monotonic(), time.thread_time()
            if prev is not None and t0 - prev[0] > _SLOW_LOOP_S:
                self._slow_loop(t0 - prev[0], prev[1], prev[2])
            handled = 0
            try:
                handled = core.run_once()
            except Exception as exc:  # the loop must survive anything
                log.exception("worker round failed")
                self._worker_error = exc
                core.counters["internal_error"] += 1
            prev = (t0, time.monotonic() - t0, time.thread_time() - c0)
            core.counters["worker_loops"] += 1
            if handled:
                last_handled = t0
            elif t0 - last_handled >= _BUSY_S or core.has_work():
                # idle: the drains hand the next sample over themselves and wake the worker
                prev = None  # (an idle wait is no slow loop)
                core.arm()
                if core.has_work():
                    continue
                timeout = (core.next_deadline_ns() - core.now_ns()) / 1e9
                if timeout > 0:
                    wake.wait(min(timeout, _MAX_SLEEP_S))
                wake.clear()
                continue
            # Batches: what arrives meanwhile waits in the drains' queues (not armed: no
            # thread switch) and is handled together by the next loop (one prediction per
            # session touched); a loop that took longer than the interval goes on at once.
            # For _BUSY_S after messages the worker looks again itself rather than arming
            # the watcher (its polls and the wake-up cost more than one look).
            rest = interval - (time.monotonic() - t0)
            if rest > 0:
                time.sleep(rest)

    def _slow_loop(self, period: float, run: float, cpu: float) -> None:
        """A busy worker loop took ``period`` s from its start to the next one's (sessions
        it serves saw no prediction meanwhile): counted (``worker_slow_loops``) and logged
        with run_once's wall and CPU time (s): wall far above CPU is a worker waiting for
        the interpreter (another thread held the GIL) or for a core; ``period`` far above
        ``run`` is a pause that overslept (the machine did not run the worker)."""
        core = self.core
        assert core is not None
        core.counters["worker_slow_loops"] += 1
        event(log, "worker_slow", logging.WARNING, instance=self.settings.instance,
              seconds=round(period, 3), run_s=round(run, 3), run_cpu_s=round(cpu, 3))

    def stop(self) -> None:
        """Stop the worker, withdraw presence, undeclare everything, close the transport."""
        self._stop.set()
        if self.metrics is not None:
            self.metrics.close()
        if self.core is not None:
            self.core.wake.set()
        if self._worker is not None:
            self._worker.join(timeout=10.0)
        if self.core is not None:
            self.core.close()
            # read-backs still inside a Zenoh query end (answered, or their timeout) before
            # the session closes: closing it under them can abort the process in native code
            s = self.core.settings
            if not self.core.lifecycle.join_background(2 * s.recover_timeout_s + 1.0):
                log.warning("takeover read-backs still running at exit")
        if self.transport is not None and self._given_transport is None:
            try:
                self.transport.close()
            except Exception:  # pragma: no cover
                log.exception("transport close failed")

    def trim_heap(self) -> None:
        """Return the C heap's free pages (:mod:`.heap`); counted ``heap_trims`` and
        ``heap_returned_bytes``, logged ``event=heap_returned`` when 16 MB or more."""
        got = return_free_heap()
        if got is None or self.core is None:
            return
        before, after = got
        freed = max(0, before - after)
        counters = self.core.counters
        counters["heap_trims"] += 1
        counters["heap_returned_bytes"] += freed
        if freed >= _TRIM_LOGGED_BYTES:
            event(log, "heap_returned", mb=round(freed / 2**20, 1),
                  rss_mb=round(after / 2**20, 1))

    def run_forever(self) -> int:
        """Start, serve until SIGTERM / SIGINT, stop cleanly. Returns the exit status."""
        got: list[int] = []

        def on_signal(signum: int, _frame: object) -> None:
            got.append(signum)
            self._stop.set()

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
        try:
            self.start()
            next_trim = time.monotonic() + TRIM_INTERVAL_S
            while not self._stop.wait(1.0):
                if time.monotonic() >= next_trim:
                    next_trim = time.monotonic() + TRIM_INTERVAL_S
                    self.trim_heap()
        finally:
            event(log, "stopping", signal=signal.Signals(got[0]).name if got else "",
                  instance=self.settings.instance)
            self.stop()
            for s, h in old.items():
                signal.signal(s, h)
        return 0
