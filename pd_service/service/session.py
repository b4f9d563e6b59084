"""One session of the daemon: its spec, its estimator, its counters.

Pure bookkeeping around the session's estimator (a :class:`pd_service.estimation.Estimator`,
built by :mod:`pd_service.backends`); no transport, no clock reads (the core passes
``now_ns`` / ``now_step`` in), no locks (the core's worker is the only caller). Every
refusal is returned as a :class:`Refusal`; nothing raises for bad input.

Counters (per session; the service sums them), by outcome:

=========================  =================================================================
accepted                   measurement accepted by the estimator
commands_accepted          command accepted
late / future / duplicate  measurement outside ``[now - max_delay, now]`` / already stored
commands_late / _future /  command for a final step / too far ahead / already stored
commands_duplicate
commands_superseded        command that replaced an older one for the same apply step (a
                           later issued_ns, then a higher seq: pd_service.intake)
echoes / echoes_unknown /  CommandEchoes used / of no command kept for one / applied
echoes_implausible /       outside [issued, received] beyond the clock's uncertainty (or
echoes_invalid             refused by its estimator) / not a CommandEcho of this session
commands_moved /           (command_timing "echoed") commands moved to the instant their
commands_in_place /        echo names (inside its step) / already there / not moved (their
commands_echo_refused      step final, a newer command superseded them, or the new step
                           refused them)
stamps_clamped             robot stamps mapped after their receipt, held at it
stamps_remapped            samples late only by how far the clock's estimate moved while
                           they flew: put in at the latest instant they may have been taken
                           at (the estimate before the move; robot_time)
probe_replies              clock probes answered (probe_<reason>: refused by the estimator)
malformed                  bytes that are not a valid Measurement / Command (``commands_``
                           prefix for commands)
non_finite                 NaN or infinity in the payload
key_mismatch               session or sensor in the payload differ from the key
unknown_sensor             sensor not in the session's spec
wrong_dims                 z / R / u of the wrong dimension
before_epoch               stamp before the session's epoch (negative step)
invalid                    refused by the estimator's own checks (ValueError)
flood                      dropped unread because the session's inbox was full
published                  predictions published
tick_overruns              ticks that fired after their step had ended (late ticks)
steps_missed               due steps (multiples of publish_every while the session is not
                           idle) that got no prediction at all, e.g. while the worker was
                           stalled: counted when the next prediction is published (an idle
                           session skips steps on purpose: none of those is due)
errors_suppressed          ErrorReports not sent because of the rate limit
out_of_range               a value of z (``commands_out_of_range``: u) above the
                           service's ``max_abs_input`` in magnitude
internal_error             an unexpected exception while handling one message
unhealthy                  predictions found non-finite or not positive semi-definite
                           (pd_service.service.health)
recovered                  recoveries that gave a healthy estimate again, of which
                           ``recovered_from_snapshot`` / ``recovered_from_prior``
live_copy_of_recovered     live messages that repeat one already read back from a sender's
                           cache and accepted (its reply overtook the live sample): dropped
                           quietly, neither refused nor reported
=========================  =================================================================
"""

from __future__ import annotations

import zlib
from typing import Final, Literal

import numpy as np

from pd_service.backends import Built, build
from pd_service.estimation import Estimator, PredictedState
from pd_service.estimation.estimator_state import untracked
from pd_service.estimation.tally import Tally
from pd_service.intake import ARRIVED_NOW, Intake, Refusal
from pd_service.ratelimit import TokenBucket
from pd_service.wire import (
    SessionSpec,
    encode,
    keys,
)
from pd_service.wire.convert import (
    PredictionEncoder,
)
from pd_service.wire.messages import MAX_PATH_POINTS
from pd_service.wire.path import PredictedPath
from pd_service.wire.session_state import spec_fingerprint

from .health import RETRY_AFTER_S, SNAPSHOT_EVERY_S, thoroughly_healthy
from .latency import LatencyWindow
from .robot_time import RobotTime, feed_applied_command

SENSOR: Final = 0
COMMAND: Final = 1
#: Added to SENSOR / COMMAND for a message read back from a sender's cache (recovered).
READ_BACK: Final = 2
#: Not a message: the read of the cache of a sender of the sample's key ended (no payload).
ANSWERED: Final = 8

#: Where a session's estimate started from (``SessionStatus.origin``).
Origin = Literal["prior", "checkpoint", "replica"]
#: How a restarted or taken-over session's wait for its senders' caches went
#: (``SessionStatus.readback``).
ReadBack = Literal["", "waiting", "answered", "timeout"]

#: Per-session latency samples kept (µs, packet receipt -> prediction published).
SESSION_LATENCY_WINDOW = 512

#: Read-back messages remembered per session until their live copy came (or the window
#: passed): more than the senders' caches give back at once (DEFAULT_SENDER_CACHE each).
READ_BACK_COPIES = 1024


def next_slot(after: int, period: int, offset: int) -> int:
    """The first ``t > after`` with ``t = offset (mod period)``, in steps or in ns: when a
    periodic task of a session falls due next, at the session's own phase ``offset``
    (:attr:`Session.spread`). Sessions started together (one epoch, one config burst) then
    spread their snapshots, checkpoints, replicas and idle ticks over the period instead of
    all falling due in the same step."""
    return after + 1 + (offset - after - 1) % period


class Session:
    """A served session. ``state`` is "active" or "restored" (how it started)."""

    def __init__(self, spec: SessionSpec, built: Built, state: str, detail: str, now_ns: int,
                 error_rate: float, error_burst: int, max_abs: float = 1e12) -> None:
        """``built``: ``spec``'s estimator, command dimension and cost
        (:func:`pd_service.backends.build`)."""
        self.spec = spec
        self.name = spec.session
        #: The spec's clock (ns) and publish_every as plain attributes: read several times
        #: per session and step, where a (pydantic) spec attribute costs a dict lookup.
        self.epoch_ns: int = spec.epoch_ns
        self.period_ns: int = spec.period_ns
        self.publish_every: int = spec.publish_every
        self.est: Estimator = built.est
        #: What the session costs against the budgets (pd_service.service.admission).
        self.cost = built.cost
        #: The per-message rules (pd_service.intake), shared with the offline replay.
        self.intake = Intake(spec, self.est, built.nu, max_abs)
        #: The robot's clock, the learned delays, commands waiting for their echo.
        self.robot = RobotTime(spec)
        if self.robot.estimated:
            self.intake.stamp_map = self.robot.to_daemon
            self.intake.stamp_slack = self.robot.stamp_slack
        #: Whether accepted commands go to :meth:`.robot_time.RobotTime.keep_command` (a
        #: native copy of its ``listening``, read per command).
        self.keeps_commands: bool = self.robot.listening
        self.state = state
        self.detail = detail
        self.counters = Tally()
        self.seq = 0
        self.published = 0
        self.now_step: int | None = None
        self.last_pub_step: int | None = None
        #: Step of the newest prediction published on data that came after the step's tick
        #: phase (pd_service.service.outbox: the next tick waits for such data).
        self.late_data_step: int | None = None
        self.last_activity_ns = now_ns
        #: Whether a measurement or command of this session decoded since it was (re)started
        #: (created, replaced, restored, synced or taken over): until then it is idle
        #: (pd_service.service.outbox), however recent its start.
        self.heard = False
        self.latency = LatencyWindow(SESSION_LATENCY_WINDOW)
        self.limiter = TokenBucket(error_rate, error_burst, now_ns)
        self.pending_recv: list[int] = []  # recv_mono_ns of packets accepted since last publish
        #: Hashes of payloads read back from senders' caches and accepted -> the last step
        #: at which their live copy is expected (:meth:`take_read_back_copy`).
        self.read_back_copies: dict[int, int] = {}
        self.alive = True
        #: Tick bookkeeping (pd_service.service.outbox): the generation of the live heap
        #: entry (older entries are skipped) and whether the session is ticking as idle.
        self.tick_gen = 0
        self.idle = False
        #: The step from which every publish_every-th step is due again (set when an idle
        #: session wakes); the steps an idle session skipped before it are not missed.
        self.due_from = 0
        self.pred_key = keys.prediction_key(self.name)
        self.path_key = keys.path_key(self.name)
        self.encoder = PredictionEncoder(spec, self.name)
        self.error_key = keys.error_key(self.name)
        self.status_key = keys.status_key(self.name)
        # where the estimate came from ("prior", "checkpoint", "replica") and the step of
        # that state; checkpoint / replica bookkeeping (pd_service.service.handover.keeper)
        self.origin: Origin = "prior"
        self.origin_step: int | None = None
        #: A restarted or taken-over session publishes nothing until its senders' caches
        #: were read back (``Lifecycle.hold_for_read_back``): the wait's end (ns; 0: none),
        #: the data keys whose caches have not answered yet, how the wait ended.
        self.hold_until_ns = 0
        self.unanswered: set[str] = set()
        self.readback: ReadBack = ""
        #: Ownership term its predictions are published with (ownership.next_term; set at
        #: install), and the term and writer of the state it resumed from or was last
        #: settled with (``Lifecycle.settle_second_owner``; 0, "": none).
        self.term = 0
        self.resumed_term = 0
        self.resumed_writer = ""
        self.fingerprint = spec_fingerprint(spec)
        #: The session's phase of its periodic work (:func:`next_slot`), from its name.
        self.spread = zlib.crc32(self.name.encode())
        self.saved_mark: tuple[int, int, int] = (0, 0, 0)
        #: When the next checkpoint / replica is due (ns; due at once at first).
        self.next_checkpoint_ns = -(1 << 62)
        self.next_replica_ns = -(1 << 62)
        # numerical health (pd_service.service.health): the in-memory snapshot of the last
        # healthy estimator state, taken every SNAPSHOT_EVERY_S of session time
        per_s = max(1, int(1e9 // spec.period_ns))
        self.snap_every = max(1, int(SNAPSHOT_EVERY_S * per_s))
        self.retry_after = max(1, int(RETRY_AFTER_S * per_s))
        self.snapshot: object | None = None  # an EstimatorState
        #: First step at which the next snapshot may be taken (at once at first).
        self.next_snapshot_step = -(1 << 62)
        self.health_failed_step: int | None = None

    # --- time --------------------------------------------------------------------------

    def time_of(self, step: int) -> int:
        """Start time of ``step`` (ns): ``spec.time_of``."""
        return self.epoch_ns + step * self.period_ns

    def step_now(self, now_ns: int) -> int:
        """Current step ``floor((now_ns - epoch_ns) / period_ns)``, never going backwards
        (a clock stepped back by NTP holds the step instead of corrupting the estimator)."""
        k = (now_ns - self.epoch_ns) // self.period_ns
        if self.now_step is not None and k < self.now_step:
            return self.now_step
        self.now_step = k
        return k

    # --- input -------------------------------------------------------------------------

    def on_measurement(self, key: str, payload: bytes, now_step: int, now_ns: int,
                       recv_ns: int | None = None,
                       first_step: int = ARRIVED_NOW) -> Refusal | None:
        """Offer one Measurement received on ``key`` at ``recv_ns`` (default ``now_ns``);
        None if accepted. Its delay (stamp -> receipt) is learned whatever the outcome.
        ``first_step``: the step it may have arrived at first, if before ``now_step``
        (judged at its arrival: :func:`pd_service.intake.judged_step`)."""
        robot, intake = self.robot, self.intake
        recv = now_ns if recv_ns is None else recv_ns
        robot.recv_ns = recv
        refusal = intake.measurement(key, payload, now_step, first_step)
        if intake.remapped:
            robot.counters["stamps_remapped"] += 1
        if intake.decoded:
            self.last_activity_ns = now_ns
            self.heard = True
            t = intake.last_t_ns
            if t is not None:
                robot.sample(intake.last_sensor, t, recv,
                             refusal is not None and refusal.reason == "late")
        return refusal

    def on_command(self, key: str, payload: bytes, now_step: int, now_ns: int,
                   first_step: int = ARRIVED_NOW) -> Refusal | None:
        """Offer one Command; None if accepted (at its stamped apply step; with
        ``command_timing: echoed`` it moves when its echo comes, :meth:`on_echo`).
        ``first_step``: as for :meth:`on_measurement`."""
        intake = self.intake
        refusal = intake.command(key, payload, now_step, first_step)
        if intake.decoded:
            self.last_activity_ns = now_ns
            self.heard = True
            if refusal is None and self.keeps_commands and intake.last_command is not None:
                self.robot.keep_command(*intake.last_command)
        return refusal

    def on_echo(self, payload: bytes, recv_ns: int, now_step: int) -> bool:
        """A CommandEcho received at ``recv_ns``: teaches the clock and the lead; with
        ``command_timing: echoed`` its command moves to the instant it took effect. True
        iff the estimator's inputs changed."""
        got = self.robot.echo(payload, recv_ns)
        self.keeps_commands = self.robot.listening
        if got is None:
            return False
        try:
            return feed_applied_command(self.intake, self.robot.counters, got, now_step)
        except (ValueError, IndexError, KeyError):  # counted; the estimator is left as it was
            self.robot.counters["commands_echo_refused"] += 1
            return False

    # --- read-back copies ----------------------------------------------------------------

    def keep_read_back_copy(self, payload: bytes, now_step: int) -> None:
        """A message read back from a sender's cache was accepted: its live copy, if still
        on its way, is expected within the window (``max_delay + 1`` steps). Kept: the
        payload's hash, not its bytes (a false match could only silence the report of a
        message refused as a duplicate anyway)."""
        copies = self.read_back_copies
        if len(copies) >= READ_BACK_COPIES:  # oldest first: insertion order
            del copies[next(iter(copies))]
        copies[hash(payload)] = now_step + self.spec.max_delay + 1

    def take_read_back_copy(self, payload: bytes, now_step: int) -> bool:
        """Whether ``payload`` repeats a message read back and accepted (then forgotten);
        copies past their step are dropped, oldest first (their steps grow with insertion),
        so a flood of duplicates costs O(1) each."""
        copies = self.read_back_copies
        until = copies.pop(hash(payload), None)
        while copies:
            first = next(iter(copies))
            if copies[first] >= now_step:
                break
            del copies[first]
        return until is not None and until >= now_step

    # --- output ------------------------------------------------------------------------

    def counters_snapshot(self) -> dict[str, int]:
        """Non-zero counters plus the always-present ``accepted`` and ``published``."""
        out = dict(self.counters)  # one C-level copy: cheaper than a comprehension over a
        if 0 in out.values():      # dict subclass's items
            out = {k: v for k, v in out.items() if v}
        robot = self.robot.counters
        if robot:
            out.update({k: v for k, v in robot.items() if v})
        out.setdefault("accepted", 0)
        out["published"] = self.published
        return out

    def steps_missed_before(self, k: int) -> int:
        """Due steps (multiples of ``publish_every``) after the last published step and
        before step ``k`` that got no prediction: ``floor((k-1)/pe) - floor(last/pe)`` with
        ``last`` at least ``due_from - 1`` (0 before the first publication, and while the
        session is idle: its skipped steps were not due)."""
        last = self.last_pub_step
        if last is None or self.idle:
            return 0
        last = max(last, self.due_from - 1)
        if k <= last + 1:
            return 0
        pe = self.publish_every
        return (k - 1) // pe - last // pe

    def predict(self, now_step: int) -> PredictedState:
        """The estimator's prediction of x(now_step + lead)."""
        return self.est.predict(now_step)

    def pack(self, pred: PredictedState, x_data: bytes, P_data: bytes, now_step: int,
             made_ns: int) -> bytes:
        """Encoded Prediction of ``pred`` whose x and P were checked and packed as
        ``x_data``, ``P_data`` (:func:`pd_service.service.health.inspect_packed`); bumps
        seq and the published count."""
        data = self.encoder.encode_packed(pred, x_data, P_data, self.seq, made_ns,
                                          self.counters_snapshot(), self.term)
        self.seq += 1
        self.published += 1
        self.last_pub_step = now_step
        return data

    def path_due(self) -> bool:
        """Whether the Prediction just packed (seq - 1) is one the spec wants a path with."""
        path = self.spec.path
        return path is not None and (self.seq - 1) % path.every == 0

    def pack_path(self, now_step: int, made_ns: int) -> bytes:
        """Encoded PredictedPath ending at the Prediction just packed (seq - 1): the spec's
        components, one point every ``path.stride`` steps, the stride widened so that at
        most MAX_PATH_POINTS points are carried."""
        path = self.spec.path
        assert path is not None
        points = self.est.predict_path(now_step, path.stride, MAX_PATH_POINTS)
        idx = np.asarray(path.indices)
        n = points[0].x.shape[0]
        # the d x d blocks of every point in one gather: flat index i * n + j, i, j in idx
        X = np.stack([p.x for p in points])[:, idx]
        P = np.stack([p.P for p in points]).reshape(len(points), n * n)[
            :, (idx[:, None] * n + idx).reshape(-1)]
        msg = PredictedPath(
            session=self.name, seq=self.seq - 1, steps=[p.step for p in points],
            period_ns=self.period_ns, t0_ns=self.epoch_ns + points[0].step * self.period_ns,
            indices=list(path.indices), X=X, P=P, newest_step=points[-1].newest_step,
            made_ns=made_ns)
        return encode(msg)

    def prior_alone(self) -> bool:
        """The estimate is the spec's prior propagated, nothing else: the session started
        from the prior and accepted no packet and no command. Such a state needs no
        checkpoint, replica or snapshot: restarting from the prior gives the same."""
        if self.origin != "prior":
            return False
        if not self.heard:  # nothing decoded: nothing accepted
            return True
        c = self.counters
        return not c.get("accepted") and not c.get("commands_accepted")

    # --- numerical health (pd_service.service.health) ---------------------------------

    def keep_snapshot(self, pred: PredictedState, now_step: int) -> None:
        """After a healthy prediction: keep the estimator's state in memory if it is due
        (the first at once, then one per SNAPSHOT_EVERY_S of session time at the session's
        own phase, :func:`next_slot`, never two within half of it) and P passes the
        thorough test (not while the estimate is its prior alone: recovering to the prior
        gives the same)."""
        if now_step < self.next_snapshot_step or self.prior_alone():
            return
        export = getattr(self.est, "export_state", None)
        if export is None or not thoroughly_healthy(np.asarray(pred.P)):
            return
        self.snapshot = untracked(export())  # out of the cycle collector's young generation
        self.next_snapshot_step = next_slot(now_step + self.snap_every // 2, self.snap_every,
                                            self.spread)

    def reset_estimate(self, source: str) -> None:
        """Restore the estimator to its snapshot (``source`` "snapshot") or rebuild it from
        the spec's prior ("prior"). StateError (ValueError) if the snapshot does not fit."""
        if source == "snapshot":
            snap, self.snapshot = self.snapshot, None  # a snapshot that failed is not reused
            self.est.restore_state(snap)  # type: ignore[attr-defined]  # a ReplayEstimator
            return
        self.est = build(self.spec).est
        self.intake.est = self.est
        self.snapshot = None
        self.next_snapshot_step = -(1 << 62)
