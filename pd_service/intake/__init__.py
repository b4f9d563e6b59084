"""How one message enters a session's estimator: decode (fast path first), checks against
the spec, step mapping, magnitude bounds, the estimator's window, and the refusal reason.

Two ways to read a message, one result: the full path (:func:`pd_service.wire.decode`, the
validated pydantic model, then :func:`pd_service.wire.convert.check_measurement` /
``check_command``) is the reference and names every refusal; where the hot path runs
compiled, the C kernel ``_fastread.c`` first reads the plainest form of a Measurement or
Command straight from its msgpack bytes (exact types, no per-sample R, finite values within
``max_abs``, dimensions right) and returns None for anything else, which then takes the full
path. It only ever accepts what the full path accepts, with the same values (tested on
plain, re-encoded, mutated, cut and random payloads), so both give the same outcomes and
counters; without the kernel (pure Python) every message takes the full path.

One implementation for the daemon (:class:`pd_service.service.session.Session`) and for the
offline replay of a recording (``pd-replay``), so both accept and refuse exactly alike.
No clock reads: the caller passes the session's current step ``now_step``, and, where the
message may have arrived at an earlier step (it waited for a busy or stalled worker), that
step ``first_step``: the message is then judged at the earliest step it may have arrived at
that its stamp and the estimator allow (:func:`judged_step`), not at the step the worker got
to it. Nothing raises for bad input: every refusal is a :class:`Refusal` (counter name, one
readable line, the sender's seq when it could be read).

The supersede rule: when two commands land on one apply step, the newer replaces the older
if that step is not final yet (teleoperation: the freshest command is the one that counts;
refusing it was issue 43's "the freshest command is the one dropped"). Newer means a later
``issued_ns``, then (same stamp, or commands with an explicit ``step``) a higher ``seq``. A
repeat (same stamp and seq) or an older command stays ``commands_duplicate``; a replacement
is counted ``commands_superseded``. A command whose stored rival is not known here (accepted
before a restart or hand-over, or forgotten past ``_ORDERS_KEPT`` steps) is a duplicate.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np

from pd_service.estimation import Estimator
from pd_service.estimation.replay import ReplayEstimator
from pd_service.native import kernel_function
from pd_service.wire import MAX_MESSAGE_BYTES, Command, Measurement, SessionSpec, WireError, decode
from pd_service.wire.convert import (
    check_command,
    check_measurement,
    command_time,
    measurement_time,
)

#: What the fast path reads: (seq, step or None, t_ns / issued_ns or None, z / u float64 (m,)).
_Fields = tuple[int, int | None, int | None, np.ndarray]

#: The fast path's readers (the C kernel ``_fastread.c``; None: pure Python, no fast path).
_READ_MEASUREMENT: Final = kernel_function("pd_service.intake._fastread", "read_measurement")
_READ_COMMAND: Final = kernel_function("pd_service.intake._fastread", "read_command")
_MAX_BYTES: Final = MAX_MESSAGE_BYTES  # read from a C static, not the module's globals

#: Largest |z_i| and |u_i| accepted by default (the daemon's ``max_abs_input``).
MAX_ABS_INPUT = 1e12

#: Every outcome of :meth:`Intake.measurement` (``accepted`` or a refusal's counter name) and
#: of :meth:`Intake.command`: what the daemon counts per session for each message it handled.
MEASUREMENT_OUTCOMES = ("accepted", "late", "future", "duplicate", "malformed", "non_finite",
                        "key_mismatch", "unknown_sensor", "wrong_dims", "before_epoch",
                        "out_of_range", "invalid")
COMMAND_OUTCOMES = tuple("commands_" + o for o in MEASUREMENT_OUTCOMES
                         if o != "unknown_sensor")

_CHECK_REASONS = {  # WireError prefix from wire.convert.check_* -> counter name
    "Measurement.session": "key_mismatch",
    "Measurement.sensor": "unknown_sensor",
    "Measurement.z": "wrong_dims",
    "Measurement.R": "wrong_dims",
    "Measurement.t_ns": "before_epoch",
    "Command.session": "commands_key_mismatch",
    "Command.u": "commands_wrong_dims",
    "Command.issued_ns": "commands_before_epoch",
}


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why one message was refused: counter name, one readable line, the sender's seq."""

    reason: str
    text: str
    seq: int | None = None


def _max_abs(v: np.ndarray) -> float:
    """max |v_i| of a finite vector (both paths refused non-finite values before); Python
    floats for a few values: cheaper than numpy's reductions (docs/performance.md)."""
    if v.size > 16:
        return float(np.max(np.abs(v)))
    return float(max(map(abs, v.ravel().tolist())))


def _decode_reason(exc: WireError, prefix: str) -> Refusal:
    """A message that failed to decode: counted by the error's kind, its seq echoed."""
    return Refusal(prefix + exc.kind, exc.reason, exc.seq)


def _check_reason(exc: WireError, seq: int, default: str) -> Refusal:
    head = exc.reason.split(":", 1)[0]
    return Refusal(_CHECK_REASONS.get(head, default), exc.reason, seq)


#: ``first_step`` of a message that arrived at the current step (the default: judged now).
ARRIVED_NOW: Final = 1 << 62


def judged_step(stamp: int, first_step: int, now_step: int, est_now: int | None) -> int:
    """The step a message stamped at step ``stamp`` (a measurement's sample step, a
    command's send step: apply step - lead) is judged at when it arrived between the starts
    of steps ``first_step`` and ``now_step`` (``first_step < now_step``; the worker got to
    it late): the earliest arrival consistent with its stamp and with what the estimator has
    seen (``est_now``, the newest step it was given; it never goes back)::

        k = max(first_step, min(stamp, now_step), est_now)

    So a sample inside the window when it arrived is not refused as late because its
    worker got to it later; a stamp after ``now_step`` is still judged at ``now_step``
    (future); and the inputs of a session, judged in the order they came, never take the
    estimator back (an input after one stamped later is judged at that one's step at least:
    it came after it)."""
    k = stamp if stamp < now_step else now_step
    if k < first_step:
        k = first_step
    if est_now is not None and k < est_now:
        k = est_now
    return k if k >= 0 or now_step < 0 else 0  # not before the epoch unless now is


#: Apply steps whose command order :class:`Intake` remembers at most (beyond the open window
#: the oldest are forgotten; a command for a forgotten step is then a duplicate).
_ORDERS_KEPT: Final = 4096
#: Orders kept before the first pruning of final steps (then twice what the last one left).
_ORDERS_PRUNE_FIRST: Final = 64


class Intake:
    """A session's estimator behind the per-message rules. ``decoded`` tells whether the last
    message offered could be read as a message of this session (activity, for idle
    detection), whatever its outcome."""

    def __init__(self, spec: SessionSpec, est: Estimator, nu: int,
                 max_abs: float = MAX_ABS_INPUT) -> None:
        """``est`` and ``nu`` (the command dimension, 0: no commands) as
        :class:`pd_service.backends.Built` holds them."""
        self.spec = spec
        self.est = est
        self.name = spec.session
        #: Largest |z_i| and |u_i| accepted (out_of_range otherwise). Finite: the fast
        #: path's single comparison per value also refuses NaN and infinities.
        if not 0 < max_abs < math.inf:
            raise ValueError(f"max_abs: must be positive and finite, got {max_abs!r}")
        self.max_abs = max_abs
        self.dims = {sp.name: sp.m for sp in spec.sensors}  # m = rows of R, every kind
        self.r = nu
        self.decoded = False
        #: Whether the last command accepted replaced an older one for its step
        #: (:meth:`command`: counted as ``commands_superseded``, not ``commands_accepted``).
        self.superseded = False
        #: (seq, issued_ns or None, u, apply step, order, offset (session seconds)) of
        #: the last command read (None: it did not decode): what an echo later moves
        #: (pd_service.service.robot_time).
        self.last_command: tuple[int, int | None, np.ndarray, int, tuple[int, int],
                                 float] | None = None
        #: Robot stamps -> the daemon's timeline (pd_service.service.robot_time), applied to
        #: a Measurement's t_ns before anything else; None: stamps are used as they are.
        self.stamp_map: Callable[[int], int] | None = None
        #: How much later (ns) the last stamp mapped may have been taken, because the clock's
        #: estimate moved while it was in flight (pd_service.service.robot_time): a sample
        #: late by less goes in at that latest instant; None: no such error.
        self.stamp_slack: Callable[[], int] | None = None
        #: Whether the last measurement went in at its latest instant (stamp_slack).
        self.remapped = False
        #: The (mapped) t_ns of the last measurement read, None if it had a step (or none),
        #: and the sensor its key named.
        self.last_t_ns: int | None = None
        self.last_sensor = ""
        #: apply step -> (issued_ns or -1, seq) of the command stored for it: which of two
        #: commands for one step is the newer (the supersede rule, module docstring).
        self.command_order: dict[int, tuple[int, int]] = {}
        #: command_order's size at which its final steps are next forgotten: twice what
        #: the last pruning left (the open window), so a command costs O(1) amortised.
        self._orders_prune_at = _ORDERS_PRUNE_FIRST
        #: The estimator's seconds per session second for an offset inside a step: 1.0 where
        #: its period is the session's (a continuous linear model); the model's own step
        #: over the session's where a nonlinear model runs on its own period (a fraction of
        #: the step is what carries over); 0.0: no value inside a step (a model without
        #: flow: every offset dropped, the stamp floored).
        T = getattr(est, "period_s", None)
        spec_s = spec.period_ns / 1e9
        self.off_scale = (1.0 if T is None or T == spec_s
                          else 0.0 if T == 0.0 or not spec.continuous_time
                          else T / spec_s)

    def _scaled(self, off: float) -> float:
        """An offset in session seconds as the estimator's seconds (``off_scale``), kept
        below its period where rounding would reach it."""
        T = getattr(self.est, "period_s", None)
        out = off * self.off_scale
        return math.nextafter(T, 0.0) if T and out >= T else out

    def measurement(self, key: str, payload: bytes, now_step: int,
                    first_step: int = ARRIVED_NOW) -> Refusal | None:
        """Offer one Measurement received on ``key``; None if accepted. ``first_step``: the
        step it may have arrived at first, if before ``now_step`` (:func:`judged_step`)."""
        self.decoded = False
        self.remapped = False
        self.last_sensor = sensor = key.rsplit("/", 1)[-1]
        m = self.dims.get(sensor)
        read = _READ_MEASUREMENT
        fast: _Fields | None = None if read is None or m is None else read(
            payload, self.name, sensor, m, self.max_abs, _MAX_BYTES)
        stamp_map = self.stamp_map
        if fast is not None and stamp_map is not None and fast[2] is not None:
            fast = (fast[0], fast[1], stamp_map(fast[2]), fast[3])
        self.last_t_ns = None
        off = 0.0
        if fast is not None and (fast[2] is None or fast[2] >= self.spec.epoch_ns):
            seq, s, t_in, z = fast  # |z_i| <= max_abs checked on the way
            stamp = "step" if s is not None else "t_ns"
            if s is None:
                s, off = self.spec.sample_at(t_in)  # type: ignore[arg-type]
                self.last_t_ns = t_in
            R = None
            checked = True  # z: a fresh finite (m,) array
        else:  # full decode and checks: exact refusal reasons
            try:
                msg = decode(payload, Measurement)
            except WireError as exc:
                return _decode_reason(exc, "")
            self.decoded = True
            if msg.sensor != sensor or msg.session != self.name:
                field = "session" if msg.session != self.name else "sensor"
                return Refusal("key_mismatch", f"Measurement.{field}: session/sensor "
                               f"{msg.session!r}/{msg.sensor!r} does not match the key {key!r}",
                               msg.seq)
            if msg.t_ns is not None and stamp_map is not None:  # once per message
                t = fast[2] if fast is not None and fast[2] is not None else stamp_map(msg.t_ns)
                msg = msg.model_copy(update={"t_ns": t})
            self.last_t_ns = msg.t_ns
            try:
                check_measurement(msg, self.spec)
            except WireError as exc:
                return _check_reason(exc, msg.seq, "invalid")
            (s, off), seq, z, R = measurement_time(msg, self.spec), msg.seq, msg.z, msg.R
            t_in = msg.t_ns
            checked = False
            stamp = "step" if msg.step is not None else "t_ns"
            if z.size and _max_abs(z) > self.max_abs:
                self.decoded = True
                return Refusal("out_of_range", f"Measurement.z: a value exceeds "
                               f"{self.max_abs:g} in magnitude (max_abs_input)", seq)
        self.decoded = True
        if now_step < 0:
            return Refusal("future", f"Measurement.{stamp}: sample step {s} is in the future; "
                           f"the session starts at its epoch (now step {now_step})", seq)
        if s > now_step and t_in is not None and self.spec.step_of(t_in) <= now_step:
            s = now_step  # rounded to the nearest step, past the current one: this one
        if off != 0.0 and self.off_scale != 1.0:
            off = self._scaled(off)
        est = self.est
        if first_step < now_step:  # it waited for the worker: judged at its arrival
            now_step = judged_step(s, first_step, now_step, est.now)
        try:
            if checked and isinstance(est, ReplayEstimator):
                # a variable of the class's own type: mypyc calls the method natively (on
                # the narrowed protocol-typed ``est`` it made a Python-level method call)
                rep: ReplayEstimator = est
                ok = rep.add_checked_measurement(sensor, s, z, now_step, off)
            else:  # positional: a keyword call costs a compiled method an argument parse
                ok = est.add_measurement(sensor, s, z, now_step, R, off)
        except ValueError as exc:
            return Refusal("invalid", f"Measurement.z: {exc}", seq)
        if ok:
            return None
        lo = now_step - est.max_delay
        if s > now_step:
            return Refusal("future", f"Measurement.{stamp}: sample step {s} is after the current "
                           f"step {now_step}", seq)
        if s < lo or s < est.committed_step:
            slack = self.stamp_slack
            if slack is not None and t_in is not None and stamp == "t_ns":
                # late only under the estimate that moved while it flew: at the latest
                # instant it may have been taken at (the estimate before the move), if that
                # is inside the window; never as current
                t_late = t_in + slack()
                s_late, off_late = self.spec.sample_at(t_late)
                if s_late > now_step:
                    s_late, off_late = now_step, 0.0
                if off_late != 0.0 and self.off_scale != 1.0:
                    off_late = self._scaled(off_late)
                if s_late >= max(lo, est.committed_step) \
                        and est.add_measurement(sensor, s_late, z, now_step, R, off_late):
                    self.last_t_ns = t_late
                    self.remapped = True
                    return None
            return Refusal("late", f"Measurement.{stamp}: sample step {s} is older than the "
                           f"window [{max(lo, est.committed_step)}, {now_step}] "
                           f"(max_delay {est.max_delay})", seq)
        return Refusal("duplicate", f"Measurement.{stamp}: sensor {sensor!r} already has a "
                       f"sample for step {s} at that instant (offset {off:g} s)", seq)

    def command(self, key: str, payload: bytes, now_step: int,
                first_step: int = ARRIVED_NOW) -> Refusal | None:
        """Offer one Command; None if accepted. ``first_step``: as for :meth:`measurement`
        (its stamp: the step it was sent at, apply step - lead)."""
        self.decoded = False
        self.last_command = None
        spec = self.spec
        read = _READ_COMMAND
        fast: _Fields | None = None if read is None else read(
            payload, self.name, self.r, self.max_abs, _MAX_BYTES)
        if fast is not None and (fast[1] is not None
                                 or spec.step_of(fast[2]) + spec.lead >= 0):  # type: ignore[arg-type]
            seq, j, issued, u = fast
            stamp = "step" if j is not None else "issued_ns"
            off = 0.0
            if j is None:
                j, off = spec.command_at(issued)  # type: ignore[arg-type]
            checked = True  # u: a fresh finite (nu,) array
        else:
            try:
                msg = decode(payload, Command)
            except WireError as exc:
                return _decode_reason(exc, "commands_")
            self.decoded = True
            try:
                check_command(msg, spec, self.r)
            except WireError as exc:
                return _check_reason(exc, msg.seq, "commands_invalid")
            (j, off), seq, u = command_time(msg, spec), msg.seq, msg.u
            issued = msg.issued_ns
            stamp = "step" if msg.step is not None else "issued_ns"
            checked = False
            if u.size and _max_abs(u) > self.max_abs:
                self.decoded = True
                return Refusal("commands_out_of_range", f"Command.u: a value exceeds "
                               f"{self.max_abs:g} in magnitude (max_abs_input)", seq)
        self.decoded = True
        self.superseded = False
        order = (-1 if issued is None else issued, seq) if stamp == "issued_ns" else (-1, seq)
        self.last_command = (seq, issued if stamp == "issued_ns" else None, u, j, order, off)
        if off != 0.0 and self.off_scale != 1.0:
            off = self._scaled(off)
        if first_step < now_step:  # it waited for the worker: judged at its arrival
            now_step = judged_step(j - spec.lead, first_step, now_step, self.est.now)
        if self._supersede(j, u, order, now_step, off):
            return None
        est = self.est
        try:
            if checked and isinstance(est, ReplayEstimator):
                rep: ReplayEstimator = est  # (a native call, as in measurement)
                ok = rep.add_checked_command(j, u, now_step if now_step >= 0 else None, off)
            else:
                ok = est.add_command(j, u, now_step if now_step >= 0 else None, off)
        except (ValueError, IndexError) as exc:
            return Refusal("commands_invalid", f"Command.u: {exc}", seq)
        if ok:
            self._remember_order(j, order)
            return None
        ref = est.now if est.now is not None else 0
        if j < est.committed_step:
            return Refusal("commands_late", f"Command.{stamp}: apply step {j} is already final "
                           f"(first open step {est.committed_step})", seq)
        if j > ref + est.lead + est.max_delay + 1:
            return Refusal("commands_future", f"Command.{stamp}: apply step {j} is more than "
                           f"max_delay + 1 steps past the predicted step {ref + est.lead}", seq)
        return Refusal("commands_duplicate", f"Command.{stamp}: a command for step {j} is "
                       "already stored", seq)

    def place(self, step: int, u: np.ndarray, order: tuple[int, int], now_step: int,
              offset: float = 0.0) -> bool:
        """Store a command for ``step`` from ``offset`` seconds after its start (session
        seconds, scaled here as a message's offset is) outside the message path (an echoed
        command moved to the instant it took effect: pd_service.service.robot_time), with
        the supersede rule against a command already there; True iff stored."""
        if step < 0:
            return False
        if offset != 0.0 and self.off_scale != 1.0:
            offset = self._scaled(offset)
        if self._supersede(step, u, order, now_step, offset):
            return True
        if self.est.add_command(step, u, now_step if now_step >= 0 else None, offset):
            self._remember_order(step, order)
            return True
        return False

    def withdraw(self, step: int, order: tuple[int, int], now_step: int) -> bool:
        """Take back the command of ``order`` stored for ``step`` (not one that superseded
        it); True iff withdrawn."""
        est = self.est
        if self.command_order.get(step) != order or not isinstance(est, ReplayEstimator):
            return False
        if not est.withdraw_command(step, now_step if now_step >= 0 else None):
            return False
        del self.command_order[step]
        return True

    def _remember_order(self, step: int, order: tuple[int, int]) -> None:
        """Keep ``order`` for the command stored at ``step``; forget final steps once the
        map holds twice what the last pruning left (bounded memory: about the estimator's
        open window, at most :data:`_ORDERS_KEPT`)."""
        orders = self.command_order
        orders[step] = order
        if len(orders) > self._orders_prune_at:
            first = self.est.committed_step
            for k in [k for k in orders if k < first]:
                del orders[k]
            while len(orders) > _ORDERS_KEPT:  # a window wider than the bound: oldest go
                del orders[min(orders)]
            self._orders_prune_at = max(_ORDERS_PRUNE_FIRST, 2 * len(orders))

    def _supersede(self, step: int, u: np.ndarray, order: tuple[int, int],
                   now_step: int, offset: float = 0.0) -> bool:
        """The supersede rule (module docstring): replace the command stored for ``step`` by
        this newer one; True iff replaced (``superseded`` set). Tried before the estimator's
        own admission, so a replacement is not also counted as a duplicate."""
        stored = self.command_order.get(step)
        est = self.est
        if stored is None or order <= stored or not isinstance(est, ReplayEstimator):
            return False
        uv = np.array(u, dtype=np.float64)  # a copy: the slow path's u belongs to its message
        if not est.supersede_command(step, uv, now_step if now_step >= 0 else None, offset):
            return False
        self.command_order[step] = order
        self.superseded = True
        return True
