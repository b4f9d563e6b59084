"""One session's view of its robot's time (issue 43): the robot clock's offset, the delays
learned online, the commands waiting for their echo.

Per session (:class:`RobotTime`, owned by :class:`.session.Session`; the core's worker is its
only caller, no locks, no clock reads: every time is passed in):

- **robot stamps -> the daemon's timeline** (spec ``robot_clock: estimated``): every robot
  stamp is a one-way bound on the offset (:class:`ClockOffsetEstimator`), then mapped with the
  estimate, never later than its receipt (a sample is never taken after it arrived), before
  the window check; probes (:mod:`.clock_probes`) and echoes bound it from the other side.
  While a sample was in flight the estimate may have moved (a clock step seen on one side
  of the band moves it by half the step at once): the daemon then cannot tell which offset
  the sample's stamp was taken under, so the sample is judged late only if it is late under
  every estimate held over the window (:attr:`RobotTime.slack_ns`); pd_service.intake puts
  one that is not in at the latest instant it may have been taken at, counted
  ``stamps_remapped``.
  With ``robot_clock: shared`` stamps are used as they are (and no bound is fed).
- **delays learned online** (every spec): per sensor and over all samples the gap sample
  stamp -> receipt (:class:`DelayStats`), the recommended ``max_delay`` (the smallest window
  that would have refused at most :data:`LATE_SHARE` of the samples as late, + 10 %); per
  echoed command the gap issue -> applied and the recommended ``lead`` (the median).
- **echoes**: every accepted command is remembered (seq -> issued, u, the step it entered at)
  until the robot's :class:`CommandEcho` says when it took effect (a session with
  ``robot_clock: shared`` and ``command_timing: stamped`` only from the first echo of its
  robot on, counting the echoes before it ``echoes_unknown``: a robot that never echoes
  costs nothing per command): the echo bounds the offset
  and teaches the lead (issue -> applied); with spec ``command_timing: echoed`` the command
  then moves to that instant, inside its step (:func:`feed_applied_command`, the one seam
  to the issue-42 estimator API). Until its echo a command acts at its stamped apply step (the prediction
  of a command still in flight); one never echoed stays there.

Bad input is counted (``echoes_unknown``: an echo of no kept command; ``echoes_implausible``:
applied before the command was issued or after the echo arrived, beyond the offset's
uncertainty, or a bound the offset estimator refused; ``echoes_invalid``: not a CommandEcho of
this session; ``commands_kept_dropped``: kept commands pushed out unechoed), never raised.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Final

import numpy as np
from pydantic import ValidationError

from pd_service.estimation.clock_offset import ClockOffsetEstimator, OffsetEstimate
from pd_service.estimation.delay_learning import LATE_SHARE, DelayStats
from pd_service.estimation.tally import Tally
from pd_service.intake import Intake
from pd_service.wire import ClockStatus, CommandEcho, DelayStatus, SessionSpec, WireError, decode

#: Commands kept for their echo per session (oldest pushed out, counted): those in flight
#: over one round trip (100 Hz over 2.5 s; an echo usually takes its command out first).
COMMANDS_KEPT: Final = 256
#: An offset estimate that moved by more than this since the last status, or whose bound is
#: wider, gets a status warning (ns).
CLOCK_WARN_NS: Final = 50_000_000
#: A clock estimate with no new bound for this long is stale (s).
CLOCK_STALE_S: Final = 10.0
#: Samples (and echoes, for the lead) seen before a learned window (lead) is applied: at a
#: late share of 0.1 % fewer would not tell the window from noise.
LEARN_MIN_SAMPLES: Final = 1000
LEARN_MIN_ECHOES: Final = 100
#: An offset estimate that moved by more than this (s) from the last one kept (carried on
#: by its drift) is kept too, for the window's span: what :attr:`RobotTime.slack_ns` spans.
CLOCK_MOVE_S: Final = 1e-4


#: What an echo hands on for its command: (applied_ns on the daemon's timeline, u (nu,),
#: the step it entered at, its order (issued_ns or -1, seq): pd_service.intake, the offset
#: (session seconds) it entered at inside that step).
Applied = tuple[int, np.ndarray, int, tuple[int, int], float]


def feed_applied_command(intake: Intake, counters: Tally, applied: Applied,
                         now_step: int) -> bool:
    """The seam to the estimator: move an echoed command from the instant it entered at to
    the one it took effect at, ``applied_ns``: its step k = floor((applied_ns - epoch_ns) /
    period_ns) and, for a continuous-time spec, the offset (applied_ns - epoch_ns - k
    period_ns) / 1e9 s into it (a discrete model: the step's start, the floor); True iff
    the estimator's inputs changed. Counted in ``counters``: ``commands_in_place`` (already
    at that instant), ``commands_moved``, ``commands_echo_refused`` (its old step final,
    superseded, or the new one refused: then it stays where it was)."""
    applied_ns, u, entered, order, entered_off = applied
    spec = intake.spec
    step = spec.step_of(applied_ns)
    off = (applied_ns - spec.time_of(step)) / 1e9 if spec.continuous_time else 0.0
    if step == entered and off == entered_off:
        counters["commands_in_place"] += 1
        return False
    if not intake.withdraw(entered, order, now_step):
        counters["commands_echo_refused"] += 1
        return False
    if intake.place(step, u, order, now_step, off):
        counters["commands_moved"] += 1
        return True
    intake.place(entered, u, order, now_step, entered_off)  # back: still our best guess
    counters["commands_echo_refused"] += 1
    return True


class RobotTime:
    """One session's robot clock, learned delays and commands waiting for their echo."""

    def __init__(self, spec: SessionSpec) -> None:
        self.spec = spec
        self.estimated = spec.robot_clock == "estimated"
        self.echoed = spec.command_timing == "echoed"
        #: Whether accepted commands are kept for their echo (:meth:`keep_command`): from the
        #: start when the spec uses echoes, else from the first echo of this session.
        self.listening = self.estimated or self.echoed
        self.clock = ClockOffsetEstimator(asymmetry_s=spec.clock_asymmetry_ns * 1e-9)
        self.counters = Tally()
        self.samples = DelayStats(spec.period_ns, spec.epoch_ns)
        self.by_sensor: dict[str, DelayStats] = {}
        self.applied = DelayStats(spec.period_ns, spec.epoch_ns)
        #: seq -> (issued_ns on the daemon's timeline or None, u (nu,), step, order, offset s)
        self.kept: OrderedDict[int, tuple[int | None, np.ndarray, int, tuple[int, int], float]] = \
            OrderedDict()
        #: Receipt (daemon clock, ns) of the message being read: the bound of its stamp.
        self.recv_ns = 0
        self.seen = 0
        self.late = 0
        self._last: OffsetEstimate | None = None
        #: (daemon ns, offset s, drift) of the estimates held over the last window (the one
        #: in force at its start first): a new one when it moved by over CLOCK_MOVE_S
        self._held: deque[tuple[int, float, float]] = deque()
        self._window_ns = spec.max_delay * spec.period_ns
        #: How much later (ns) the last stamp mapped may have been taken, because the
        #: estimate moved while it may have been in flight: ``max_k |theta_now - (theta_k +
        #: b_k (now - t_k))|`` over the estimates k held over the window, never past its
        #: receipt (0: it did not move).
        self.slack_ns = 0

    # --- stamps ---------------------------------------------------------------------------

    def to_daemon(self, t_ns: int) -> int:
        """A robot stamp received at :attr:`recv_ns` on the daemon's timeline (the identity
        for a shared clock): the stamp bounds the offset first, then is mapped with it, and
        a mapped stamp after its receipt is held at the receipt (counted ``stamps_clamped``)."""
        if not self.estimated:
            return t_ns
        recv = self.recv_ns
        self.clock.add_one_way(t_ns, recv)
        est = self.clock.estimate(recv)
        mapped = est.to_daemon_ns(t_ns) if est.known else t_ns
        moved = self._moved(est) if est.known else 0
        if mapped > recv:
            self.counters["stamps_clamped"] += 1
            self.slack_ns = 0
            return recv
        self.slack_ns = min(moved, recv - mapped)
        return mapped

    def stamp_slack(self) -> int:
        """:attr:`slack_ns` (pd_service.intake's ``stamp_slack``)."""
        return self.slack_ns

    def _moved(self, est: OffsetEstimate) -> int:
        """:attr:`slack_ns` for ``est`` (the estimate at its receipt), and ``est`` kept if
        it moved (O(1) amortised: the estimates kept over one window are few)."""
        held, now = self._held, est.t_ns
        while len(held) >= 2 and held[1][0] <= now - self._window_ns:
            held.popleft()
        worst = 0.0
        gap = math.inf
        for t, offset, drift in held:
            gap = abs(est.offset_s - offset - drift * (now - t) * 1e-9)
            worst = max(worst, gap)
        if gap > CLOCK_MOVE_S:  # the newest kept is the last one compared
            held.append((now, est.offset_s, est.drift))
        return int(worst * 1e9)

    def sample(self, sensor: str, stamp_ns: int, recv_ns: int, late: bool) -> None:
        """A decoded sample of ``sensor`` stamped ``stamp_ns`` (daemon timeline) received at
        ``recv_ns``; ``late``: refused as late."""
        self.seen += 1
        self.late += late
        self.samples.add(stamp_ns, recv_ns)
        stats = self.by_sensor.get(sensor)
        if stats is None:
            stats = self.by_sensor[sensor] = DelayStats(self.spec.period_ns, self.spec.epoch_ns,
                                                        capacity=1024)
        stats.add(stamp_ns, recv_ns)

    # --- commands and echoes ----------------------------------------------------------------

    def keep_command(self, seq: int, issued_ns: int | None, u: np.ndarray, step: int,
                     order: tuple[int, int], offset: float = 0.0) -> None:
        """A command accepted at ``step`` (``offset`` session seconds into it): ``seq``,
        issued at ``issued_ns`` (daemon timeline; None: a command with an explicit step,
        whose issue time is unknown), ``u``, its ``order`` (pd_service.intake), kept for its
        echo (the oldest beyond
        :data:`COMMANDS_KEPT` go, counted ``commands_kept_dropped``)."""
        kept = self.kept
        kept[seq] = (issued_ns, u, step, order, offset)
        kept.move_to_end(seq)
        if len(kept) > COMMANDS_KEPT:
            kept.popitem(last=False)
            self.counters["commands_kept_dropped"] += 1

    def echo(self, payload: bytes, recv_ns: int) -> Applied | None:
        """An echo received at ``recv_ns``: teaches the clock and the lead; returns what
        :func:`feed_applied_command` needs to move its command (``command_timing: echoed``),
        else None (counted when bad)."""
        c = self.counters
        try:
            msg = decode(payload, CommandEcho)
        except WireError:
            c["echoes_invalid"] += 1
            return None
        if msg.session != self.spec.session:
            c["echoes_invalid"] += 1
            return None
        self.listening = True
        entry = self.kept.get(msg.seq)
        if entry is None:
            c["echoes_unknown"] += 1
            return None
        issued, u, entered, order, entered_off = entry
        if self.estimated:
            if msg.sent_ns is not None:
                self.clock.add_one_way(msg.sent_ns, recv_ns)
            if issued is not None and self.clock.add_echo(issued, msg.applied_ns) is not None:
                c["echoes_implausible"] += 1
                return None
            est = self.clock.estimate(recv_ns)
            applied = est.to_daemon_ns(msg.applied_ns) if est.known else msg.applied_ns
            slack = int(min(est.half_width_s, 3600.0) * 1e9) if est.known else 0
        else:
            applied, slack = msg.applied_ns, 0
        first = issued if issued is not None else self.spec.epoch_ns
        if not first - slack <= applied <= recv_ns + slack:
            c["echoes_implausible"] += 1
            return None
        applied = min(max(applied, first), recv_ns)
        del self.kept[msg.seq]
        c["echoes"] += 1
        if issued is not None:
            self.applied.add(issued, applied)
        return (applied, u, entered, order, entered_off) if self.echoed else None

    def probe(self, t1_ns: int, t2_ns: int, t3_ns: int, t4_ns: int) -> None:
        """A probe's four timestamps (t1, t4 daemon clock; t2, t3 robot clock)."""
        self.counters["probe_replies"] += 1
        why = self.clock.add_probe(t1_ns, t2_ns, t3_ns, t4_ns)
        if why is not None:
            self.counters[f"probe_{why}"] += 1

    # --- status -------------------------------------------------------------------------

    def recommended_max_delay(self) -> int | None:
        """The window the samples seen recommend (steps), None before any."""
        return self.samples.recommended_window(LATE_SHARE)

    def view(self, now_ns: int) -> RobotView:
        """Copies of what a status reports (under the core's lock; the statistics are
        computed from them after it: :class:`RobotView`). The clock's status is taken here:
        it remembers the last one (its jump warning)."""
        return RobotView(self.clock_status(now_ns), self.samples.copy(),
                         {k: v.copy() for k, v in self.by_sensor.items()},
                         self.applied.copy(), self.late / max(self.seen, 1))

    def clock_status(self, now_ns: int) -> ClockStatus | None:
        """The offset estimate now (None for a shared clock), with a warning when it is
        unknown, unbounded, stale, a step is suspected (its uncertainty then covers the held
        bounds) or it just jumped."""
        if not self.estimated:
            return None
        est = self.clock.estimate(now_ns)
        last, self._last = self._last, est
        held = self.clock.held_outside_s()
        warning = ""
        if not est.known:
            warning = "robot clock offset unknown (no stamp yet)"
        elif not np.isfinite(est.half_width_s):
            warning = "robot clock offset bounded on one side only (no probe or echo yet)"
        elif est.age_s > CLOCK_STALE_S:
            warning = f"robot clock estimate stale ({est.age_s:.0f} s without a stamp)"
        elif held > 0.0:
            warning = (f"robot clock step suspected: bounds {held * 1e3:.1f} ms outside the "
                       f"estimate, not yet confirmed")
        elif last is not None and last.known and (
                est.steps > last.steps
                or abs(est.offset_s - last.offset_s - last.drift * (now_ns - last.t_ns) * 1e-9)
                > CLOCK_WARN_NS * 1e-9):
            warning = "robot clock offset jumped"
        # a suspected step widens what the status reports (not the mapping's own half-width)
        half = est.half_width_s + held
        unc = None if not np.isfinite(half) else int(min(half, 9e9) * 1e9)
        return ClockStatus(known=est.known, offset_ns=round(est.offset_s * 1e9),
                           uncertainty_ns=unc, drift_ppm=est.drift * 1e6, age_s=min(est.age_s, 1e12),
                           steps=est.steps, warning=warning)

    def delay_status(self) -> dict[str, DelayStatus]:
        """Per sensor, and ``cmd`` for issue -> applied, the delays kept (ms)."""
        return delay_statuses(self.by_sensor, self.applied)


def delay_statuses(by_sensor: dict[str, DelayStats], applied: DelayStats) \
        -> dict[str, DelayStatus]:
    """Per sensor, and ``cmd`` for issue -> applied, the delays kept (ms)."""
    out: dict[str, DelayStatus] = {}
    for name, stats in [*sorted(by_sensor.items()), ("cmd", applied)]:
        s = stats.summary()
        if s.count and s.p50_ns is not None and s.p99_ns is not None and s.max_ns is not None:
            out[name] = DelayStatus(count=s.count, p50_ms=s.p50_ns / 1e6,
                                    p99_ms=s.p99_ns / 1e6, max_ms=s.max_ns / 1e6)
    return out


@dataclass(frozen=True)
class RobotView:
    """A session's robot time as its status reports it: the clock's status and copies of
    the delay statistics (:meth:`RobotTime.view`, under the core's lock); the sorts behind
    the statistics run when read, after the lock is released."""

    clock: ClockStatus | None
    samples: DelayStats
    by_sensor: dict[str, DelayStats]
    applied: DelayStats
    late_share: float

    def delay_status(self) -> dict[str, DelayStatus]:
        """Per sensor, and ``cmd``, the delays kept (ms)."""
        return delay_statuses(self.by_sensor, self.applied)

    def recommended_max_delay(self) -> int | None:
        """:meth:`RobotTime.recommended_max_delay` of the copy."""
        return self.samples.recommended_window(LATE_SHARE)

    def recommended_lead(self) -> int | None:
        """The median issue -> applied gap of the echoed commands (steps), None before any."""
        return self.applied.quantile_gap()


def learned_spec(spec: SessionSpec, robot: RobotTime) -> SessionSpec | None:
    """The spec with the learned ``max_delay`` (and ``lead``, once echoes taught it) when
    either differs from the spec's by more than a step and 10 %; None otherwise, before
    :data:`LEARN_MIN_SAMPLES` samples, or when the result is not a valid spec (a window
    shorter than a sensor's delay, say). The daemon's ``learned_window`` setting puts it on
    the session's config key: it then goes through the normal admission path."""
    if robot.samples.seen < LEARN_MIN_SAMPLES:
        return None
    window = robot.recommended_max_delay()
    lead = robot.applied.quantile_gap() if robot.applied.seen >= LEARN_MIN_ECHOES else None
    update: dict[str, int] = {}
    if window is not None and abs(window - spec.max_delay) > max(1, spec.max_delay // 10):
        update["max_delay"] = max(window, 0)
    if lead is not None and abs(lead - spec.lead) > max(1, spec.lead // 10):
        update["lead"] = max(lead, 0)
    if not update:
        return None
    try:
        return SessionSpec.model_validate({**spec.model_dump(), **update})
    except ValidationError:
        robot.counters["learned_window_invalid"] += 1
        return None
