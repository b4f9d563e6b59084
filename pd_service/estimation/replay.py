"""Timestamp window and exact replay, shared by every observer backend.

This is the paper's re-organized innovation recursion generalised to time stamps
(Liang et al. 2017, Sec. 3.2 and Remark 1). Measurements are placed at the step they were
*sampled*; a stretch of steps is final once no accepted packet can land in it any more::

        committed (final)            open window (may still change)          predicted
    ... ----------------------| c = now - max_delay ....... now |---- now + lead ---->
        base = x(b | stamps <= b)     checkpoints: posterior at every measured step

* ``base`` is the estimate of x(b) given every packet stamped <= b, for some b < c; it can
  never change again. Re-using it across calls is the paper's Remark 1.
* For each measured step s in the open window the engine keeps a checkpoint: the estimate of
  x(s) given all packets stamped <= s. A packet (or a command) that lands at step s
  invalidates the checkpoints from s on; the next call re-runs only that stretch, starting
  from the newest checkpoint before s. The paper's re-organised measurement M*_i(tau) is
  exactly "all packets received so far that are stamped tau": the indicator functions
  F_i(tau) are simply the presence or absence of a packet, so missing samples delete only
  their own rows.
* The output rolls the newest posterior forward to now + lead through the commands already
  known (the predictor, eq. 34), covariance included.

The result equals a Kalman filter run from step 0 over every accepted packet in stamp order,
then predicted forward: the engine only chooses *which* steps to recompute.

Inside a step, time goes on: a packet carries its ``offset`` (seconds after its step's start)
and a command may take effect at an offset too (:class:`~.inputs.InputBuffer`). The step
stays the window's unit (what is final, what is late, what a packet invalidates); a step's
packets are applied in (offset, sensor) order, and a step with a packet after its start hands
its posterior on at the *next* step's start (``_end``), so checkpoints, the base and the
prediction stay on the grid. For a continuous-time model the result equals the
continuous-discrete Kalman filter over every event in time order.

Work and memory per call are bounded by the window (max_delay + lead steps), never by the
number of elapsed steps. A backend supplies two pure functions over its own state type:
``propagate(state, step, m, U)`` (x(step) -> x(step + m) with inputs U (m, nu)) and
``update(state, step, packets)``; see :class:`Backend`.

A backend may instead supply the fused step ``advance(state, m, U, packets, old)``
(:class:`FusedBackend`): the jump and the updates in one call, offered ``old``, the step's
previous (now stale) posterior. Covariances do not depend on measured values or inputs, only
on the parent covariance, the jump and *which* packets were applied (for a linear model), so
:class:`~.linear.LinearBackend` keys its reuse on exactly that: if ``old`` was computed from
the very same parent covariance *object* with the same jump m,

* and from the same packets (only commands changed since: a late command), it keeps ``old``'s
  covariance and gains and re-runs the means only::

      x-(s) = A^m x(a) + [A^{m-1}B ... B] [u(a); ...; u(s-1)],   x(s) = x-(s) + K(s) (z(s) - H x-(s))

* from the first of this step's packets (a packet joined the step, in sensor order), it keeps
  the covariance after those and pays only for the new packets' updates.

The object identity makes the key cheap and safe: a packet at an earlier step, a
base rolled forward or a restore all produce new parent covariance objects. A model that
changes (:meth:`ReplayEstimator.invalidate_from`) is never reused across. The prediction to
now + lead is a fused step with no packets, offered the previous prediction, so its
covariance is reused while the newest posterior's covariance and the horizon are unchanged.
The reused results are bit-identical to a recompute (the same operations on the same
operands; tested).
"""

from __future__ import annotations

import bisect
import math
from typing import Final, Generic, NamedTuple, Protocol, TypeVar

import numpy as np
from mypy_extensions import mypyc_attr

from pd_service.native import kernel_function

from .checks import as_covariance, as_step, as_vector
from .estimator_state import STATE_VERSION, EstimatorState, PacketRecord, StateError
from .inputs import InputBuffer
from .tally import Tally

S = TypeVar("S")

#: A command taking effect inside a step: (row i of the span's inputs U, offset d (s),
#: u_before (nu,)): during row i's step the input is u_before on [0, d), U[i] from d on.
Cut = tuple[int, float, np.ndarray]

#: Counter names, by outcome. Measurements and commands are counted separately.
COUNTER_NAMES = (
    "accepted",
    "late",
    "future",
    "duplicate",
    "commands_accepted",
    "commands_late",
    "commands_future",
    "commands_duplicate",
    "commands_superseded",
    "commands_withdrawn",
)


#: Estimator kinds of states written by earlier versions -> the kind that reads them now:
#: the daemon's linear sessions ran a batched twin of ObserverPredictor until 2026-11 (the
#: same state: x, P, window), so their checkpoints and replicas still restore.
_KIND_ALIASES = {"StackedObserverPredictor": "ObserverPredictor"}


class Packet(NamedTuple):
    """One accepted measurement. ``sensor`` indexes the estimator's sensor list;
    ``z`` has shape (m,) (read-only); ``R`` is a per-sample (m, m) override or None;
    ``offset``: seconds after the start of the packet's step at which it was sampled,
    0 <= offset < period (0.0: on the grid). (A NamedTuple: immutable, and built with
    ``tuple.__new__`` on the hot path.)"""

    sensor: int
    z: np.ndarray
    R: np.ndarray | None
    offset: float = 0.0


def off_grid(packets: list[Packet]) -> bool:
    """Whether a step's packets (sorted by offset) include one sampled after the step's
    start: then the step's posterior is handed on at the next step's start (see
    :class:`Backend`)."""
    return bool(packets) and packets[-1][3] > 0.0


#: Read per call from C statics (Final), not looked up as ``bisect.<name>`` each time.
_bisect_left: Final = bisect.bisect_left
_insort: Final = bisect.insort
_new_tuple: Final = tuple.__new__

#: ``_kalman.freeze``: arrays made read-only in one C call (``ndarray.setflags`` parses its
#: keywords each call); None: ``setflags``, where the hot path is not compiled.
_FREEZE: Final = kernel_function("pd_service.estimation._kalman", "freeze")


def _read_only(a: np.ndarray) -> None:
    fz = _FREEZE
    if fz is not None:
        fz(a)
    else:
        a.setflags(write=False)


def _by_time(p: Packet) -> tuple[float, int]:
    return p[3], p[0]


# a plain class with Final attributes, not a frozen dataclass (whose __init__ sets each field
# through object.__setattr__): built faster compiled, and as read-only from Python
# (AttributeError); copied and pickled through __reduce__ (estimators are deep-copied)
class PredictedState:
    """Estimate of x(step): mean ``x`` (n,), covariance ``P`` (n, n). Read-only.

    ``newest_step`` is the newest sample step whose packet contributed (None before any).
    """

    __slots__ = ("step", "x", "P", "newest_step")

    def __init__(self, step: int, x: np.ndarray, P: np.ndarray, newest_step: int | None) -> None:
        self.step: Final = step
        self.x: Final = x
        self.P: Final = P
        self.newest_step: Final = newest_step

    def __reduce__(self) -> tuple[type[PredictedState],
                                  tuple[int, np.ndarray, np.ndarray, int | None]]:
        return PredictedState, (self.step, self.x, self.P, self.newest_step)

    def __repr__(self) -> str:
        return (f"PredictedState(step={self.step}, x={self.x!r}, P={self.P!r}, "
                f"newest_step={self.newest_step})")


class Backend(Protocol[S]):
    """What an observer backend supplies to :class:`ReplayEstimator`."""

    def propagate(self, state: S, step: int, m: int, U: np.ndarray) -> S:
        """Distribution of x(step) -> x(step + m), m >= 1, inputs U[j] = u(step + j), (m, nu)."""
        ...

    def update(self, state: S, step: int, packets: list[Packet]) -> S:
        """Condition x(step) on ``packets`` (at least one), sorted by (offset, sensor).

        All offsets 0.0: the posterior of x(step). Otherwise (:func:`off_grid`) each packet
        at its own time: propagate from the step's start to the first offset, update,
        propagate to the next offset, ..., then the remainder to the next step's start: the
        posterior of x(step + 1) given the packets stamped <= step (the replay hands the
        next propagation on from step + 1)."""
        ...

    def moments(self, state: S) -> tuple[np.ndarray, np.ndarray]:
        """Mean (n,) and covariance (n, n) of a state."""
        ...

    def export_state(self, state: S) -> dict[str, np.ndarray]:
        """A state as named arrays (copies), e.g. {"x": (n,), "P": (n, n)}."""
        ...

    def import_state(self, arrays: dict[str, np.ndarray]) -> S:
        """The state :meth:`export_state` described; StateError if the arrays do not fit."""
        ...


class FusedBackend(Backend[S], Protocol):
    """A backend with a fused replay step that may reuse a previous result's covariance.

    :class:`ReplayEstimator` calls :meth:`advance` instead of ``propagate`` + ``update`` when
    the backend has it. A backend may also offer ``advance_run(state, a, steps, buf, off,
    packets, chk, noreuse, cut_view) -> (state, a, done)``: the replay's loop of
    :meth:`advance` calls over several steps in one call, the inputs read in place from the
    input buffer, its commands inside steps from ``cut_view``
    (``LinearBackend.advance_run``, its C kernel); the replay makes the steps after the
    first ``done`` with :meth:`advance`.
    """

    def advance(self, state: S, m: int, U: np.ndarray, packets: list[Packet],
                old: S | None, cuts: list[Cut] | None = None) -> S:
        """x(a) -> x(a + m) (m >= 0, inputs U (m, nu)), then conditioned on ``packets``
        (sorted by (offset, sensor), possibly none). ``old`` is this step's previous, stale
        result (None if there is none, or if the model changed since); the backend may reuse
        what of it it can verify still holds (e.g. a covariance computed from the same
        parent covariance object, jump and packets).

        Off the grid (:func:`off_grid` (packets)): U has m + 1 rows, the packets apply at
        their offsets inside step a + m and the result is x(a + m + 1) (as
        :meth:`Backend.update`). ``cuts``: commands that take effect inside a step of the
        span (:data:`Cut`; None: none)."""
        ...


# compiled by mypyc (setup.py); the backends' estimators subclass it in interpreted code
@mypyc_attr(allow_interpreted_subclasses=True, serializable=True)
class ReplayEstimator(Generic[S]):
    """Accept window, counters, command buffer and replay around a :class:`Backend`.

    Parameters
    ----------
    backend: the filter's propagate / update functions.
    initial: backend state for x(0) before any measurement.
    sensor_dims: name -> measurement dimension m, in sensor-index order.
    nu: input dimension.
    lead: steps from ``now`` to the predicted step (>= 0).
    max_delay: a packet stamped s is accepted iff ``now - max_delay <= s <= now``.
    command_hold: "hold" (u holds until the next command) or "zero" (u = 0 without a command).
    """

    def __init__(
        self,
        backend: Backend[S],
        initial: S,
        sensor_dims: dict[str, int],
        nu: int,
        lead: object,
        max_delay: object,
        command_hold: str = "hold",
    ) -> None:
        # lead, max_delay, step and now are declared object where the caller's value is
        # checked here (as_step): compiled (mypyc), a narrower type would refuse a numpy int
        # or a float with a TypeError before the check could name the field
        lead = as_step(lead, "lead")
        max_delay = as_step(max_delay, "max_delay")
        if lead < 0:
            raise ValueError(f"lead: must be >= 0, got {lead}")
        if max_delay < 0:
            raise ValueError(f"max_delay: must be >= 0, got {max_delay}")
        if command_hold not in ("hold", "zero"):
            raise ValueError(f"command_hold: must be 'hold' or 'zero', got {command_hold!r}")
        self.lead = lead
        self.max_delay = max_delay
        self.command_hold = command_hold
        self._backend = backend
        self._index = {name: i for i, name in enumerate(sensor_dims)}
        self._dims = list(sensor_dims.values())
        self._nu = nu
        # Steps a base may lag behind the first open step before it is rolled forward.
        self._base_lag = max_delay + 1
        # Commands are accepted up to max_delay + 1 steps past the predicted step.
        self._cmd_ahead = lead + max_delay + 1
        capacity = self._base_lag + max_delay + 1 + self._cmd_ahead + 1
        self._inputs = InputBuffer(nu, capacity, hold=command_hold == "hold")
        self._base: S = initial
        self._base_step = 0
        self._c = 0  # first step that may still receive packets
        self._now: int | None = None
        self._packets: dict[int, list[Packet]] = {}
        self._steps: list[int] = []  # measured steps >= c, sorted
        # measured steps with a packet off the grid: their posterior is at the next step
        self._offgrid: set[int] = set()
        #: Step period in seconds where samples may lie inside a step (an offset must be
        #: below it); 0.0: on the grid only (a discrete model); None: not checked here.
        self.period_s: float | None = None
        self._chk: dict[int, S] = {}  # posterior at measured steps < dirty
        self._dirty: int | None = None  # earliest step whose posterior (mean) is stale
        self._noreuse: int | None = None  # from here on, stale posteriors are not reusable
        self._pred: S | None = None  # the last prediction's backend state (fused backends)
        self._counters = Tally({k: 0 for k in COUNTER_NAMES})
        self._cache: tuple[int, PredictedState] | None = None
        self._newest_committed: int | None = None
        # Only a subclass that overrides _on_commit is handed the committed steps.
        self._hooked = type(self)._on_commit is not ReplayEstimator._on_commit
        #: Spans without commands rolled over in one closed-form jump (read by tests).
        self.long_jumps = 0

    # --- public API --------------------------------------------------------------------

    @property
    def sensor_names(self) -> list[str]:
        return list(self._index)

    @property
    def counters(self) -> dict[str, int]:
        """Counts of accepted and refused measurements and commands, by reason."""
        return dict(self._counters)

    @property
    def now(self) -> int | None:
        """Newest ``now`` seen (None before the first call that passed one)."""
        return self._now

    @property
    def committed_step(self) -> int:
        """First step that can still change; every step before it is final."""
        return self._c

    def add_measurement(
        self, sensor: object, step: object, z: object, now: object, R: object | None = None,
        offset: object = 0.0,
    ) -> bool:
        """Offer the sample of ``sensor`` taken ``offset`` seconds after the start of
        ``step``; True iff accepted.

        Accepted iff ``now - max_delay <= step <= now``, step >= 0 and no packet of this
        sensor is already stored for the same step and offset (the same instant). A refusal
        is counted ("late", "future", "duplicate") and changes nothing. Malformed input
        (also an offset that is negative, not below the step period, or not 0.0 where the
        model has no value inside a step) raises ValueError naming the field and changes
        nothing.
        """
        idx = self._index.get(sensor) if isinstance(sensor, str) else None
        if idx is None:
            raise ValueError(f"sensor: unknown sensor {sensor!r} (known: {list(self._index)})")
        m = self._dims[idx]
        k = step if type(step) is int else as_step(step, "step")
        t = self._check_now(now)
        zv = as_vector(z, "z", m)
        Rm = None if R is None else as_covariance(R, "R", m)
        return self._accept(idx, k, zv, Rm, t, self._check_offset(offset))

    def add_checked_measurement(self, sensor: str, step: int, z: np.ndarray, now: int,
                                offset: float = 0.0) -> bool:
        """:meth:`add_measurement` of a sample without its own R, for a caller that has
        made its checks (the daemon's intake fast path): ``sensor`` one of
        :attr:`sensor_names`, ``step`` an int, ``z`` a fresh finite float64 array of the
        sensor's dimension that the estimator keeps (made read-only, not copied). Skips
        the conversion and checks of z (not those of the offset)."""
        off = offset if offset == 0.0 else self._check_offset(offset)
        return self._accept(self._index[sensor], step, z, None, self._check_now(now), off)

    def _check_offset(self, offset: object) -> float:
        """A sample's offset in seconds, checked (see :meth:`add_measurement`)."""
        if isinstance(offset, bool) or not isinstance(offset, (int, float, np.floating)):
            raise ValueError(f"offset: expected seconds (a number), got {offset!r}")
        off = float(offset)
        T = self.period_s
        if not (math.isfinite(off) and off >= 0.0):
            raise ValueError(f"offset: must be finite and >= 0 s, got {off!r}")
        if T is not None and off > 0.0 and not off < T:
            if T == 0.0:
                raise ValueError(f"offset: {off!r} s, but this model has no value inside a "
                                 "step (a discrete model: samples on the grid only)")
            raise ValueError(f"offset: must be below the step period {T} s, got {off!r}")
        return off

    def _accept(self, idx: int, k: int, zv: np.ndarray, Rm: np.ndarray | None, t: int,
                off: float) -> bool:
        """The window's verdict on a checked sample, and its storage (see add_measurement)."""
        if t != self._now:
            self._advance(t)
        if k > t:
            self._counters["future"] += 1
            return False
        if k < t - self.max_delay or k < self._c:
            self._counters["late"] += 1
            return False
        bucket = self._packets.get(k)
        if bucket is not None:
            for p in bucket:
                if p[0] == idx and p[3] == off:
                    self._counters["duplicate"] += 1
                    return False
        _read_only(zv)
        pkt = _new_tuple(Packet, (idx, zv, Rm, off))
        if bucket is None:
            self._packets[k] = [pkt]
            steps = self._steps
            if not steps or k > steps[-1]:
                steps.append(k)
            else:
                _insort(steps, k)
        else:
            bucket.append(pkt)
            bucket.sort(key=_by_time)
        if off > 0.0:
            self._offgrid.add(k)
        # _invalidate(k), inlined: posteriors from k on are stale
        if self._dirty is None or k < self._dirty:
            self._dirty = k
        self._cache = None
        self._counters["accepted"] += 1
        return True

    def add_command(self, step: object, u: object, now: object | None = None,
                    offset: object = 0.0) -> bool:
        """Offer the command u that applies from ``offset`` seconds after the start of
        ``step`` on (zero-order hold from that instant; "zero" mode: over the whole step,
        the offset ignored); True iff accepted.

        Refused ("commands_late") if ``step`` is already final (before
        :attr:`committed_step`), ("commands_future") if it lies more than ``max_delay + 1``
        steps past the predicted step ``now + lead``, ("commands_duplicate") if a command
        for ``step`` is already stored. ``now`` defaults to the newest one seen. ValueError
        for an offset as :meth:`add_measurement` refuses it.
        """
        k = step if type(step) is int else as_step(step, "step")
        return self.add_checked_command(k, as_vector(u, "u", self._nu), now,
                                        self._check_offset(offset))

    def add_checked_command(self, step: int, u: np.ndarray, now: object | None = None,
                            offset: float = 0.0) -> bool:
        """:meth:`add_command` for a caller that has made its checks (the daemon's intake
        fast path): ``step`` an int, ``u`` a finite float64 (nu,) array (copied into the
        input buffer). Skips the conversion and checks of u (not those of the offset)."""
        offset = self._command_offset(offset, now)
        ref = self._now if self._now is not None else 0
        if not self._inputs.admit(step, u, self._c, ref + self._cmd_ahead, self._counters,
                                  offset):
            return False
        # u(step) first moves x(step + 1), or the step's own posterior if it is off the grid
        self._invalidate(step if step in self._offgrid else step + 1)
        return True

    def predict(self, now: object) -> PredictedState:
        """LMMSE estimate of x(now + lead) from x0, P0, the commands and accepted packets.

        With a fused backend the returned arrays are read-only (the covariance may be the
        previous prediction's, reused): copy them to modify."""
        t = self._check_now(now)
        if t != self._now:
            self._advance(t)
        if self._cache is not None and self._cache[0] == t:
            return self._cache[1]
        target = t + self.lead
        step, state, newest = self._start(target)
        advance = getattr(self._backend, "advance", None)
        if advance is not None:
            m = target - step
            cuts = self._inputs.cuts(step, target - 1)
            U = self._inputs.slice(step, m)
            state = self._pred = (advance(state, m, U, [], self._pred) if cuts is None
                                  else advance(state, m, U, [], self._pred, cuts))
            x, P = self._backend.moments(state)
            # shared with the engine (a reused covariance, a checkpoint): read-only
            _read_only(x)
            _read_only(P)
        else:
            if target > step:
                state = self._propagate(state, step, target - step)
            x, P = self._backend.moments(state)
        pred = PredictedState(target, x, P, newest)
        self._cache = (t, pred)
        return pred

    def predict_path(self, now: object, stride: int = 1,
                     max_points: int = 0) -> list[PredictedState]:
        """The predicted states from the newest posterior (the newest measured step, or the
        base) to now + lead: the first point is that posterior itself, then one point every
        ``stride`` steps and always the target. Each point k steps ahead is the same jump the
        prediction makes, x(a + k) = A^k x(a) + [A^{k-1}B ... B] u (the backend's
        ``propagate`` over k steps from the start a), so the last point is bit-for-bit
        :meth:`predict`'s. Work: one k-step jump per point, O(points * n^3) for a linear
        model: ceil((target - a) / stride) + 1 points; ``max_points`` >= 2 widens the
        stride to stay within it (0: no bound)."""
        if type(stride) is not int or stride < 1:
            raise ValueError(f"stride: must be an int >= 1, got {stride!r}")
        if type(max_points) is not int or max_points < 0 or max_points == 1:
            raise ValueError(f"max_points: must be 0 or an int >= 2, got {max_points!r}")
        t = self._check_now(now)
        if t != self._now:
            self._advance(t)
        target = t + self.lead
        step, state, newest = self._start(target)
        if max_points and target > step:
            stride = max(stride, -(-(target - step) // (max_points - 1)))
        points: list[PredictedState] = []
        k = step
        while True:
            st = state if k == step else self._propagate(state, step, k - step)
            x, P = self._backend.moments(st)
            points.append(PredictedState(k, x, P, newest))
            if k == target:
                return points
            k = min(k + stride, target)

    def _start(self, target: int) -> tuple[int, S, int | None]:
        """Where the prediction of ``target`` starts: (step, posterior there, its newest
        sample step), the open window replayed first."""
        self._replay(None)
        step, state, newest = self._newest(target)
        if self._steps and self._steps[-1] == target and target in self._offgrid:
            # lead 0, and samples inside the target step: those at its very start count
            head = [p for p in self._packets[target] if p[3] == 0.0]
            if head:
                m = target - step
                advance = getattr(self._backend, "advance", None)
                if advance is not None:
                    cuts = self._inputs.cuts(step, target - 1)
                    U = self._inputs.slice(step, m)
                    state = (advance(state, m, U, head, None) if cuts is None
                             else advance(state, m, U, head, None, cuts))
                else:
                    if m:
                        state = self._propagate(state, step, m)
                    state = self._backend.update(state, target, head)
                step, newest = target, target
        return step, state, newest

    # --- export / restore of the window --------------------------------------------------

    def export_state(self) -> EstimatorState:
        """The committed-horizon estimate, the packets and commands inside the window, the
        counters and the backend's extras (copies; see :mod:`.state`)."""
        names = self.sensor_names
        packets: list[PacketRecord] = [
            (s, names[p.sensor], p.z.copy(), None if p.R is None else p.R.copy(), p.offset)
            for s in self._steps for p in self._packets[s]]
        inputs = self._inputs
        origin, u0, cmds = inputs.export()
        return EstimatorState(
            kind=type(self).__name__, n=int(getattr(self, "n", 0)), now=self._now,
            committed_step=self._c, base_step=self._base_step,
            newest_committed=self._newest_committed,
            base=self._backend.export_state(self._base), packets=packets,
            inputs_origin=origin, u_origin=u0, commands=cmds,
            counters=dict(self._counters), extras=self._export_extras(),
            command_offsets=dict(inputs.cut_offsets),
            u_before=inputs.u_before.copy() if inputs.cut_offsets else None)

    def restore_state(self, state: EstimatorState) -> None:
        """Continue from ``state`` (an :meth:`export_state` of an estimator built from the
        same spec). StateError, and nothing changed, if it does not fit: another version,
        estimator kind or size, packets of unknown sensors or wrong sizes, steps outside
        the window. The open window's posteriors are recomputed on the next call."""
        st = state
        if st.version != STATE_VERSION:
            raise StateError(f"version: {st.version} is not {STATE_VERSION}")
        if (_KIND_ALIASES.get(st.kind, st.kind) != type(self).__name__
                or st.n != int(getattr(self, "n", 0))):
            raise StateError(f"kind: a {st.kind} with n={st.n} does not fit a "
                             f"{type(self).__name__} with n={getattr(self, 'n', 0)}")
        c, b = int(st.committed_step), int(st.base_step)
        if not 0 <= b <= c or st.inputs_origin != b:
            raise StateError(f"steps: base step {b}, committed step {c} and input origin "
                             f"{st.inputs_origin} are inconsistent")
        if c != (0 if st.now is None else max(st.now - self.max_delay, 0)):
            raise StateError(f"now: {st.now} does not fit the committed step {c} "
                             f"(max_delay {self.max_delay})")
        base = self._backend.import_state(st.base)
        packets: dict[int, list[Packet]] = {}
        for rec in st.packets:
            if not isinstance(rec, tuple) or len(rec) != 5:
                raise StateError("packets: a record is not (step, sensor, z, R, offset)")
            step, name, z, R, off = rec
            idx = self._index.get(name)
            if idx is None:
                raise StateError(f"packets: unknown sensor {name!r}")
            m = self._dims[idx]
            hi = st.now if st.now is not None else 0
            if not c <= step <= hi:
                raise StateError(f"packets: step {step} outside the window [{c}, {hi}]")
            try:
                zv = as_vector(z, "z", m)
                Rm = None if R is None else as_covariance(R, "R", m)
                offset = self._check_offset(off)
            except ValueError as exc:
                raise StateError(f"packets: {exc}") from None
            bucket = packets.setdefault(int(step), [])
            if any(p.sensor == idx and p.offset == offset for p in bucket):
                raise StateError(f"packets: two samples of {name!r} at step {step} "
                                 f"offset {offset} s")
            zv.setflags(write=False)
            bucket.append(Packet(idx, zv, Rm, offset))
        for bucket in packets.values():
            bucket.sort(key=_by_time)
        inputs = InputBuffer(self._nu, self._inputs.capacity, self._inputs.hold)
        try:
            u0 = as_vector(st.u_origin, "u_origin", self._nu)
            ub = None if st.u_before is None else as_vector(st.u_before, "u_before", self._nu)
            offs = {int(j): self._check_offset(d) for j, d in st.command_offsets.items()}
            inputs.restore(b, u0, [(int(j), as_vector(u, "u", self._nu))
                                   for j, u in st.commands], offs, ub)
        except (ValueError, IndexError) as exc:
            raise StateError(f"commands: {exc}") from None
        unknown = set(st.counters) - set(COUNTER_NAMES)
        if unknown:
            raise StateError(f"counters: unknown names {sorted(unknown)}")
        self._restore_extras(st.extras)  # may raise StateError: before anything else changes
        self._base, self._base_step, self._c, self._now = base, b, c, st.now
        self._packets = packets
        self._steps = sorted(packets)
        self._offgrid = {s for s, bucket in packets.items() if off_grid(bucket)}
        self._chk = {}
        self._dirty = self._noreuse = c if self._steps else None
        self._pred = None
        self._counters = Tally({k: 0 for k in COUNTER_NAMES})
        self._counters.update({k: int(v) for k, v in st.counters.items()})
        self._cache = None
        self._newest_committed = st.newest_committed
        self._inputs = inputs

    def _export_extras(self) -> dict[str, np.ndarray]:
        """What the estimator learnt beyond the base (none by default)."""
        return {}

    def _restore_extras(self, extras: dict[str, np.ndarray]) -> None:
        """Install :meth:`_export_extras`' output; StateError if it does not fit. Must
        check everything before changing anything."""
        if extras:
            raise StateError(f"extras: {sorted(extras)} not expected by {type(self).__name__}")

    # --- hooks for backends that learn on the committed horizon --------------------------

    def _on_commit(self, committed: list[tuple[int, S, list[Packet]]]) -> None:
        """Called with (step, posterior, packets) for each measured step that became final,
        in step order. Default: nothing. Adaptive backends override it."""

    def _command_offset(self, offset: float, now: object | None) -> float:
        """A command's ``offset`` checked (:meth:`add_measurement`'s rules), after moving the
        window to ``now`` (None: where it is)."""
        if offset != 0.0:
            offset = self._check_offset(offset)
        if now is not None:
            t = self._check_now(now)
            if t != self._now:
                self._advance(t)
        return offset

    def supersede_command(self, step: int, u: np.ndarray, now: object | None = None,
                          offset: float = 0.0) -> bool:
        """Replace the command stored for ``step`` by ``u`` (a finite float64 (nu,) array)
        taking effect ``offset`` seconds after the step's start; True iff replaced and
        counted ("commands_superseded"). False, counting nothing, when no command is stored
        for ``step`` or ``step`` is already final (< committed_step). The caller decides
        that ``u`` is the newer of the two (pd_service.intake: a later ``issued_ns``, then a
        higher ``seq``); the estimator only refuses a final step. ValueError for an offset
        as :meth:`add_measurement` refuses it."""
        offset = self._command_offset(offset, now)
        if step < self._c or not self._inputs.has_command(step):
            return False
        self._inputs.replace(step, u, offset)
        self._counters["commands_superseded"] += 1
        self._invalidate(step if step in self._offgrid else step + 1)
        return True

    def withdraw_command(self, step: int, now: object | None = None) -> bool:
        """Forget the command stored for ``step`` (it did not take effect there: the robot
        echoed another time, pd_service.service.robot_time); True iff withdrawn. False,
        changing nothing, when none is stored for ``step`` or ``step`` is final."""
        if now is not None:
            t = self._check_now(now)
            if t != self._now:
                self._advance(t)
        inputs = self._inputs
        if step < self._c or not inputs.has_command(step):
            return False
        inputs.remove(step)
        self._counters["commands_withdrawn"] += 1
        self._invalidate(step if step in self._offgrid else step + 1)
        return True

    def invalidate_from(self, step: int) -> None:
        """Mark every open-window posterior from ``step`` on as stale (e.g. after adaptation:
        nothing computed before is reused)."""
        self._invalidate(max(step, self._c), reusable=False)

    # --- internals ---------------------------------------------------------------------

    def _check_now(self, now: object) -> int:
        if type(now) is not int:
            now = as_step(now, "now")
        if self._now is not None and now < self._now:
            raise ValueError(f"now: went backwards ({now} < {self._now})")
        return now

    def _invalidate(self, step: int, reusable: bool = True) -> None:
        """Mark posteriors from ``step`` on as stale. ``reusable`` False (the model itself
        changed, :meth:`invalidate_from`): a fused backend is not offered them either."""
        if self._dirty is None or step < self._dirty:
            self._dirty = step
        if not reusable and (self._noreuse is None or step < self._noreuse):
            self._noreuse = step
        self._cache = None
        if not reusable:
            self._pred = None

    def _propagate(self, state: S, step: int, m: int) -> S:
        inputs = self._inputs
        U = inputs.slice(step, m)
        if inputs.cut_offsets:  # commands inside these steps: a fused backend takes them
            advance = getattr(self._backend, "advance", None)
            cuts = inputs.cuts(step, step + m - 1)
            if advance is not None and cuts is not None:
                return advance(state, m, U, [], None, cuts)
        return self._backend.propagate(state, step, m, U)

    def _end(self, s: int) -> int:
        """The step at which measured step s's posterior is: s, or s + 1 off the grid."""
        return s + 1 if s in self._offgrid else s

    def _newest(self, target: int) -> tuple[int, S, int | None]:
        """Newest clean posterior at a step <= ``target`` (step, state, its newest sample
        step), or the base. (Only the newest measured step's can lie past the target: a
        sample inside the target step itself, with lead 0: it acts once the output passes
        it.)"""
        steps = self._steps
        for i in (len(steps) - 1, len(steps) - 2):
            if i >= 0:
                s = steps[i]
                e = s + 1 if s in self._offgrid else s
                if e <= target:
                    return e, self._chk[s], s
        return self._base_step, self._base, self._newest_committed

    def _replay(self, limit: int | None) -> None:
        """Recompute the posteriors of measured steps in [dirty, limit).

        A fused backend is offered each step's stale posterior, to reuse what still holds."""
        dirty = self._dirty
        if dirty is None or (limit is not None and dirty >= limit):
            return
        steps = self._steps
        i = _bisect_left(steps, dirty)
        j = len(steps) if limit is None else _bisect_left(steps, limit)
        chk = self._chk
        offgrid = self._offgrid
        if i > 0:
            a = steps[i - 1]
            state = chk[a]
            if a in offgrid:
                a += 1
        else:
            a, state = self._base_step, self._base
        backend = self._backend
        packets = self._packets
        advance = getattr(backend, "advance", None)
        if advance is not None:
            noreuse = self._noreuse
            todo = steps[i:j]
            if todo:
                inputs = self._inputs
                buf, off = inputs.window(a, todo[-1] + 1)
                cut = inputs.cut_offsets
                run = getattr(backend, "advance_run", None)
                if run is not None:  # the loop below in one C call, as far as it goes
                    state, a, done = run(state, a, todo, buf, off, packets, chk, noreuse,
                                         inputs.cut_view())
                    if done:
                        todo = todo[done:]
                for s in todo:
                    old = chk.get(s) if noreuse is None or s < noreuse else None
                    e = s + 1 if s in offgrid else s
                    cuts = inputs.cuts(a, e - 1) if cut else None
                    U = buf[a - off : e - off]
                    # cuts passed only when there are some: a backend without them still fits
                    state = (advance(state, s - a, U, packets[s], old) if cuts is None
                             else advance(state, s - a, U, packets[s], old, cuts))
                    chk[s] = state
                    a = e
        else:
            for s in steps[i:j]:
                if s > a:
                    state = self._propagate(state, a, s - a)
                state = backend.update(state, s, packets[s])
                chk[s] = state
                a = s + 1 if s in offgrid else s
        if limit is None or j == len(steps):
            self._dirty = self._noreuse = None
        else:
            self._dirty = limit
            if self._noreuse is not None and self._noreuse < limit:
                self._noreuse = limit

    def _advance(self, now: int) -> None:
        """Take ``now`` as the current step; commit steps that can no longer change."""
        if self._now is None or now > self._now:
            self._now = now
            self._cache = None
        new_c = now - self.max_delay
        if new_c <= self._c:
            return
        self._replay(new_c)
        steps = self._steps
        k = _bisect_left(steps, new_c)
        if k:
            final = steps[:k]
            chk, packets = self._chk, self._packets
            committed = ([(s, chk[s], packets[s]) for s in final] if self._hooked else None)
            last = final[-1]
            self._base_step, self._base = self._end(last), chk[last]
            self._newest_committed = last
            offgrid = self._offgrid
            for s in final:
                del chk[s], packets[s]
                offgrid.discard(s)
            del steps[:k]
            if committed is not None:
                self._on_commit(committed)
        self._c = new_c
        self._inputs.advance(self._base_step)
        if new_c - self._base_step > self._base_lag:
            # A base that fell far behind (no packets for a while) is rolled up to the window,
            # in chunks no longer than the input buffer, so tables and buffers stay bounded.
            # A backend with a closed-form jump takes a span without commands longer than
            # the buffer in one (a far epoch: O(log m), not m steps).
            cap = self._inputs.capacity
            inputs = self._inputs
            jump = getattr(self._backend, "propagate_constant", None)
            while self._base_step < new_c:
                m = min(new_c - self._base_step, cap)
                if m == cap and jump is not None and inputs.constant_from(self._base_step):
                    m = new_c - self._base_step
                    self._base = jump(self._base, m, inputs.u_of(self._base_step))
                    self.long_jumps += 1
                else:
                    self._base = self._propagate(self._base, self._base_step, m)
                self._base_step += m
                inputs.advance(self._base_step)
