"""Display side: read the service's predictions (and, from a simulator, the truth).

Example::

    with Display(transport, "s1", truth=True) as display:
        for pred in display.predictions(timeout=5.0):   # blocks; or display.on_prediction(cb)
            print(pred.step, pred.x, np.diag(pred.P))
        display.latest()                                # newest Prediction, or None
"""

from __future__ import annotations

import logging
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from pd_service.transport import Sample, Transport
from pd_service.wire import ErrorReport, Prediction, keys
from pd_service.wire.fence import TermFence

from ._base import ClientBase, session_name, try_decode
from ._queue import Inbox
from .errors import Timeout
from .pairing import TruthPairs
from .truth import Truth

log = logging.getLogger("pd_client.display")

PredictionCallback = Callable[[Prediction], None]
TruthCallback = Callable[[Truth], None]


@dataclass(frozen=True, slots=True)
class DisplayStats:
    """Counters of one Display.

    ``missed``: predictions never received, from gaps in ``seq``; ``invalid``: payloads that
    did not decode; latencies are receipt time minus the prediction's ``made_ns``, µs
    (meaningful when the clocks are shared, e.g. one machine), over the last 256.
    ``stale_term``: predictions dropped as published with an older ownership term than the
    newest seen (a second owner during a partition between instances, docs/service.md);
    ``term``: the newest term seen (0: none, or a publisher older than terms).
    """

    received: int
    missed: int
    invalid: int
    truth_received: int
    errors: int
    last_error: str | None
    latency_us_last: float | None
    latency_us_p50: float | None
    latency_us_max: float | None
    stale_term: int = 0
    term: int = 0


class Display(ClientBase):
    """Predictions of one session, from ``pd/p<k>/<session>/prediction``.

    ``truth=True`` also reads a simulator's ground truth (``robot/p<k>/<session>/truth``) and
    pairs each prediction with the truth at its target step (:meth:`latest_pair`).
    ``errors=True`` (default) counts the service's ErrorReports for the session.
    ``history``: predictions and truths kept for matching, and the iterator's queue size.
    """

    def __init__(self, transport: Transport, session: str, *, truth: bool = False,
                 errors: bool = True, history: int = 4096) -> None:
        super().__init__(transport)
        self.session = session_name(session)
        self._state = threading.Lock()
        self._cond = threading.Condition(self._state)
        self._inbox: Inbox[Prediction] = Inbox(history)
        self._pred_cbs: list[PredictionCallback] = []
        self._truth_cbs: list[TruthCallback] = []
        self._latest: Prediction | None = None
        self._pairs = TruthPairs(history)
        self._latest_truth: Truth | None = None
        self._latencies: deque[float] = deque(maxlen=256)
        self._last_seq: int | None = None
        self._fence = TermFence()
        self._received = self._missed = self._invalid = self._truths = self._errors = 0
        self._last_error: str | None = None
        self._subscribe(keys.prediction_key(session), self._on_prediction)
        if truth:
            self._subscribe(keys.truth_key(session), self._on_truth)
        if errors:
            self._subscribe(keys.error_key(session), self._on_error)

    # --- callbacks from the transport ----------------------------------------------------

    def _on_prediction(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        pred = try_decode(sample, Prediction)
        with self._cond:
            if pred is None or pred.session != self.session:
                self._invalid += 1
                return
            changes = self._fence.changes
            if not self._fence.admit(pred.session, pred.term):
                return  # an older owner's (counted): the newest term's predictions only
            if self._fence.changes != changes:  # a new owner: its seq and steps go on from
                self._last_seq = self._latest = None  # the state it resumed, not from ours
            self._received += 1
            if self._last_seq is not None and pred.seq > self._last_seq + 1:
                self._missed += pred.seq - self._last_seq - 1
            # A smaller seq means the service restarted the session's numbering: start over.
            self._last_seq = pred.seq if self._last_seq is None else \
                max(self._last_seq, pred.seq) if pred.seq > self._last_seq else pred.seq
            self._latencies.append((sample.recv_ns - pred.made_ns) / 1e3)
            if self._latest is None or pred.step >= self._latest.step:
                self._latest = pred
            self._pairs.add_prediction(pred)
            self._cond.notify_all()
        self._inbox.push(pred)
        for cb in list(self._pred_cbs):
            try:
                cb(pred)
            except Exception:
                log.exception("prediction callback failed")

    def _on_truth(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        truth = try_decode(sample, Truth)
        with self._cond:
            if truth is None or truth.session != self.session:
                self._invalid += 1
                return
            self._truths += 1
            if self._latest_truth is None or truth.step >= self._latest_truth.step:
                self._latest_truth = truth
            self._pairs.add_truth(truth)
            self._cond.notify_all()
        for cb in list(self._truth_cbs):
            try:
                cb(truth)
            except Exception:
                log.exception("truth callback failed")

    def _on_error(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        report = try_decode(sample, ErrorReport)
        with self._cond:
            self._errors += 1
            if report is not None:
                self._last_error = f"{report.key}: {report.reason}"

    # --- reading -------------------------------------------------------------------------

    def on_prediction(self, callback: PredictionCallback) -> None:
        """Call ``callback(prediction)`` for each prediction, on the transport's thread (it
        must return quickly)."""
        self._pred_cbs.append(callback)

    def on_truth(self, callback: TruthCallback) -> None:
        """Call ``callback(truth)`` for each truth sample (needs ``truth=True``)."""
        self._truth_cbs.append(callback)

    def predictions(self, timeout: float | None = None) -> Iterator[Prediction]:
        """Iterate over predictions as they arrive (oldest first; if the consumer falls
        ``history`` behind, the oldest are dropped). Stops after ``timeout`` seconds without
        one (None: never) or when the display is closed."""
        return self._inbox.iterate(timeout)

    def __iter__(self) -> Iterator[Prediction]:
        return self.predictions()

    def latest(self) -> Prediction | None:
        """The prediction with the newest target step received so far, or None."""
        with self._state:
            return self._latest

    def latest_truth(self) -> Truth | None:
        with self._state:
            return self._latest_truth

    def prediction_for(self, step: int) -> Prediction | None:
        """The prediction whose target step is ``step``, if still kept."""
        with self._state:
            return self._pairs.predictions.get(step)

    def truth_at(self, step: int) -> Truth | None:
        with self._state:
            return self._pairs.truths.get(step)

    def latest_pair(self) -> tuple[Prediction, Truth] | None:
        """(prediction, truth) for the newest target step that has both, or None."""
        with self._state:
            return self._pairs.newest

    def wait(self, count: int = 1, timeout: float | None = None) -> Prediction:
        """Wait until ``count`` predictions have been received in total; return the latest.
        Raises Timeout after ``timeout`` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._received < count or self._latest is None:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise Timeout(f"{self._received} of {count} predictions for session "
                                  f"{self.session!r} within {timeout} s")
                self._cond.wait(remaining)
            return self._latest

    def wait_pair(self, min_step: int = 0, timeout: float | None = None) -> tuple[Prediction, Truth]:
        """Wait for a (prediction, truth) pair whose step is >= ``min_step``."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while (pair := self._pairs.newest) is None or pair[0].step < min_step:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise Timeout(f"no prediction/truth pair at step >= {min_step} for session "
                                  f"{self.session!r} within {timeout} s")
                self._cond.wait(remaining)
            return pair

    def stats(self) -> DisplayStats:
        with self._state:
            lat = list(self._latencies)
            return DisplayStats(
                received=self._received, missed=self._missed, invalid=self._invalid,
                truth_received=self._truths, errors=self._errors, last_error=self._last_error,
                latency_us_last=lat[-1] if lat else None,
                latency_us_p50=statistics.median(lat) if lat else None,
                latency_us_max=max(lat) if lat else None,
                stale_term=self._fence.dropped, term=self._fence.newest.get(self.session, 0),
            )

    def close(self) -> None:
        self._inbox.close()
        super().close()
        with self._cond:
            self._cond.notify_all()
