"""One session of the daemon: its spec, its estimator, its counters.

Pure bookkeeping around the session's estimator (a :class:`pd_service.estimation.Estimator`,
built by :func:`pd_service.backends.build_estimator`); no transport, no clock reads (the core passes
``now_ns`` / ``now_step`` in), no locks (the core's worker is the only caller). Every
refusal is returned as a :class:`Refusal`; nothing raises for bad input.

Counters (per session; the service sums them), by outcome:

=========================  =================================================================
accepted                   measurement accepted by the estimator
commands_accepted          command accepted
late / future / duplicate  measurement outside ``[now - max_delay, now]`` / already stored
commands_late / _future /  command for a final step / too far ahead / already stored
commands_duplicate
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
steps_missed               due steps (multiples of publish_every) that got no prediction at
                           all, e.g. while the worker was stalled: counted when the next
                           prediction is published
errors_suppressed          ErrorReports not sent because of the rate limit
internal_error             an unexpected exception while handling one message
=========================  =================================================================
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Literal

from pd_service.backends import build_estimator
from pd_service.estimation import Estimator, PredictedState
from pd_service.wire import (
    Command,
    Measurement,
    SessionSpec,
    WireError,
    decode,
    keys,
)
from pd_service.wire.convert import (
    check_command,
    check_measurement,
    command_dim,
    command_step,
    encode_prediction,
    measurement_step,
)
from pd_service.wire.state import spec_fingerprint

from .fastpath import read_command, read_measurement
from .stacked import Node, StackedObserverPredictor
from .stats import LatencyWindow, TokenBucket

SENSOR, COMMAND = 0, 1

#: Where a session's estimate started from (``SessionStatus.origin``).
Origin = Literal["prior", "checkpoint", "replica"]

#: Per-session latency samples kept (µs, packet receipt -> prediction published).
SESSION_LATENCY_WINDOW = 512

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


def _decode_reason(exc: WireError, prefix: str) -> Refusal:
    """A message that failed to decode: counted by the error's kind, its seq echoed."""
    return Refusal(prefix + exc.kind, exc.reason, exc.seq)


def _check_reason(exc: WireError, seq: int, default: str) -> Refusal:
    head = exc.reason.split(":", 1)[0]
    return Refusal(_CHECK_REASONS.get(head, default), exc.reason, seq)


class Session:
    """A served session. ``state`` is "active" or "restored" (how it started)."""

    def __init__(self, spec: SessionSpec, state: str, detail: str, now_ns: int,
                 error_rate: float, error_burst: int) -> None:
        self.spec = spec
        self.name = spec.session
        # WireError for a spec it refuses; a linear model's numerics are batched across
        # sessions (pd_service.service.stacked), equal to ObserverPredictor to rounding
        self.est: Estimator = build_estimator(spec, StackedObserverPredictor)
        self.state = state
        self.detail = detail
        self.counters: Counter[str] = Counter()
        self.seq = 0
        self.published = 0
        self.now_step: int | None = None
        self.last_pub_step: int | None = None
        self.last_activity_ns = now_ns
        self.latency = LatencyWindow(SESSION_LATENCY_WINDOW)
        self.limiter = TokenBucket(error_rate, error_burst, now_ns)
        self.pending_recv: list[int] = []  # recv_mono_ns of packets accepted since last publish
        self.alive = True
        self.dims = {sp.name: sp.m for sp in spec.sensors}  # m = rows of R, every kind
        self.r = command_dim(spec)  # a nonlinear model's own input dimension (0: none)
        self.pred_key = keys.prediction_key(self.name)
        self.error_key = keys.error_key(self.name)
        self.status_key = keys.status_key(self.name)
        # where the estimate came from ("prior", "checkpoint", "replica") and the step of
        # that state; checkpoint / replica bookkeeping (pd_service.service.failover)
        self.origin: Origin = "prior"
        self.origin_step: int | None = None
        self.fingerprint = spec_fingerprint(spec)
        self.saved_mark: tuple[int, int, int] = (0, 0, 0)
        self.last_checkpoint_ns = -(1 << 62)
        self.last_replica_ns = -(1 << 62)

    # --- time --------------------------------------------------------------------------

    def step_now(self, now_ns: int) -> int:
        """Current step ``floor((now_ns - epoch_ns) / period_ns)``, never going backwards
        (a clock stepped back by NTP holds the step instead of corrupting the estimator)."""
        k = (now_ns - self.spec.epoch_ns) // self.spec.period_ns
        if self.now_step is not None and k < self.now_step:
            return self.now_step
        self.now_step = k
        return k

    # --- input -------------------------------------------------------------------------

    def on_measurement(self, key: str, payload: bytes, now_step: int, now_ns: int) -> Refusal | None:
        """Offer one Measurement received on ``key``; None if accepted."""
        sensor = key.rsplit("/", 1)[-1]
        fast = read_measurement(payload, self.name, sensor, self.dims)
        if fast is not None and (fast[2] is None or fast[2] >= self.spec.epoch_ns):
            seq, s, t_ns, z = fast
            stamp = "step" if s is not None else "t_ns"
            if s is None:
                s = self.spec.step_of(t_ns)  # type: ignore[arg-type]
            R = None
        else:  # full decode and checks: exact refusal reasons
            try:
                msg = decode(payload, Measurement)
            except WireError as exc:
                return _decode_reason(exc, "")
            self.last_activity_ns = now_ns
            if msg.sensor != sensor or msg.session != self.name:
                field = "session" if msg.session != self.name else "sensor"
                return Refusal("key_mismatch", f"Measurement.{field}: session/sensor "
                               f"{msg.session!r}/{msg.sensor!r} does not match the key {key!r}",
                               msg.seq)
            try:
                check_measurement(msg, self.spec)
            except WireError as exc:
                return _check_reason(exc, msg.seq, "invalid")
            seq, s, z, R = msg.seq, measurement_step(msg, self.spec), msg.z, msg.R
            stamp = "step" if msg.step is not None else "t_ns"
        self.last_activity_ns = now_ns
        if now_step < 0:
            return Refusal("future", f"Measurement.{stamp}: sample step {s} is in the future; "
                           f"the session starts at its epoch (now step {now_step})", seq)
        est = self.est
        try:
            ok = est.add_measurement(sensor, s, z, now=now_step, R=R)
        except ValueError as exc:
            return Refusal("invalid", f"Measurement.z: {exc}", seq)
        if ok:
            self.counters["accepted"] += 1
            return None
        lo = now_step - est.max_delay
        if s > now_step:
            return Refusal("future", f"Measurement.{stamp}: sample step {s} is after the current "
                           f"step {now_step}", seq)
        if s < lo or s < est.committed_step:
            return Refusal("late", f"Measurement.{stamp}: sample step {s} is older than the "
                           f"window [{max(lo, est.committed_step)}, {now_step}] "
                           f"(max_delay {est.max_delay})", seq)
        return Refusal("duplicate", f"Measurement.{stamp}: sensor {sensor!r} already has a "
                       f"sample for step {s}", seq)

    def on_command(self, key: str, payload: bytes, now_step: int, now_ns: int) -> Refusal | None:
        """Offer one Command; None if accepted."""
        spec = self.spec
        fast = read_command(payload, self.name, self.r)
        if fast is not None and (fast[1] is not None
                                 or spec.step_of(fast[2]) + spec.lead >= 0):  # type: ignore[arg-type]
            seq, j, issued, u = fast
            stamp = "step" if j is not None else "issued_ns"
            if j is None:
                j = spec.step_of(issued) + spec.lead  # type: ignore[arg-type]
        else:
            try:
                msg = decode(payload, Command)
            except WireError as exc:
                return _decode_reason(exc, "commands_")
            self.last_activity_ns = now_ns
            try:
                check_command(msg, spec, self.r)
            except WireError as exc:
                return _check_reason(exc, msg.seq, "commands_invalid")
            seq, j, u = msg.seq, command_step(msg, spec), msg.u
            stamp = "step" if msg.step is not None else "issued_ns"
        self.last_activity_ns = now_ns
        est = self.est
        try:
            ok = est.add_command(j, u, now=now_step if now_step >= 0 else None)
        except (ValueError, IndexError) as exc:
            return Refusal("commands_invalid", f"Command.u: {exc}", seq)
        if ok:
            self.counters["commands_accepted"] += 1
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

    # --- output ------------------------------------------------------------------------

    def counters_snapshot(self) -> dict[str, int]:
        """Non-zero counters plus the always-present ``accepted`` and ``published``."""
        out = {k: v for k, v in self.counters.items() if v}
        out.setdefault("accepted", 0)
        out["published"] = self.published
        return out

    def steps_missed_before(self, k: int) -> int:
        """Due steps (multiples of ``publish_every``) after the last published step and
        before step ``k`` that got no prediction: ``floor((k-1)/pe) - floor(last/pe)``
        (0 before the first publication)."""
        last = self.last_pub_step
        if last is None or k <= last + 1:
            return 0
        pe = self.spec.publish_every
        return (k - 1) // pe - last // pe

    def predict(self, now_step: int) -> PredictedState:
        """The estimator's prediction of x(now_step + lead); with the stacked engine its
        x and P are a pending Node until :func:`pd_service.service.stacked.resolve`."""
        return self.est.predict(now_step)

    def pack(self, pred: PredictedState, now_step: int, made_ns: int) -> bytes:
        """Encoded Prediction of a resolved ``pred``; bumps seq and the published count."""
        node: object = pred.x  # typed ndarray; the stacked engine puts its Node there
        if isinstance(node, Node):  # stacked: resolves alone if still pending
            pred = PredictedState(pred.step, *node.value(), pred.newest_step)
        data = encode_prediction(pred, self.spec, self.name, self.seq, made_ns,
                                 self.counters_snapshot())
        self.seq += 1
        self.published += 1
        self.last_pub_step = now_step
        return data

    def prediction(self, now_step: int, made_ns: int) -> bytes:
        """predict + pack for one session alone."""
        return self.pack(self.predict(now_step), now_step, made_ns)
