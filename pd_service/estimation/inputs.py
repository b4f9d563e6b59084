"""Per-step control inputs u(t) over a sliding window of steps.

Commands arrive as "u applies from step j on". In ``hold`` mode u(t) is the newest command
with step <= t (zero-order hold, zeros before the first command); in ``zero`` mode u(t) is
the command for exactly step t, else zero. The buffer keeps u(t) materialised for
``t in [origin, origin + capacity)`` so that a multi-step propagation reads its inputs as one
contiguous (m, nu) slice, with no per-step Python work.

A command may take effect inside its step (``offset`` seconds after the step's start, "hold"
mode): the buffer's row still holds it (what the step ends with), and a *cut* records the
offset; the step's input is the previous step's u before it (:meth:`InputBuffer.cuts`). In
"zero" mode offsets are ignored: a command acts over its whole step.
"""

from __future__ import annotations

import bisect
from typing import Final

import numpy as np
from mypy_extensions import mypyc_attr

from pd_service.native import kernel_function

from .tally import Tally

#: The C form of ``buf[start:end] = u`` (``_kalman.fill``; None: numpy, the reference).
_FILL: Final = kernel_function("pd_service.estimation._kalman", "fill")
#: Read per call from C statics (Final), not looked up as ``bisect.<name>``.
_bisect_left: Final = bisect.bisect_left
_insort: Final = bisect.insort


# copy.deepcopy of an estimator, compiled (setup.py), needs serializable; with mypy 2.4.1,
# serializable alone makes the compiled class skip __init__, with both flags it does not
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class InputBuffer:
    """u(t) for t in [origin, origin + capacity). Shapes: each u is (nu,).

    Stored in rows ``[off, off + capacity)`` of a (2 capacity, nu) buffer; the rows after
    the window already hold what its next steps will be (the last step's u for "hold",
    zeros for "zero"), so moving the window forward is ``off += d`` with no copy, until it
    reaches the buffer's end and is moved back to row 0 (once per ~capacity steps)."""

    def __init__(self, nu: int, capacity: int, hold: bool) -> None:
        self.nu = nu
        self.capacity = capacity
        self.hold = hold
        self.origin = 0
        self._buf = np.zeros((2 * capacity, nu))
        self._off = 0
        self._cmd_steps: list[int] = []  # explicit command steps >= origin, sorted
        self.cut_offsets: dict[int, float] = {}  # command step -> offset (s), offsets > 0
        self._cut_steps: list[int] = []  # its keys, sorted
        self.u_before = np.zeros(nu)  # u(origin - 1): a cut at the origin starts from it

    def has_command(self, step: int) -> bool:
        i = _bisect_left(self._cmd_steps, step)
        return i < len(self._cmd_steps) and self._cmd_steps[i] == step

    def admit(self, step: int, u: np.ndarray, first: int, last: int,
              counters: Tally, offset: float = 0.0) -> bool:
        """Store the command for ``step`` if ``first <= step <= last`` and none is stored for
        it yet; count the outcome in ``counters``: "commands_late" (step < first),
        "commands_future" (step > last), "commands_duplicate", or "commands_accepted"."""
        if step < first:
            counters["commands_late"] += 1
            return False
        if step > last:
            counters["commands_future"] += 1
            return False
        if self.has_command(step):
            counters["commands_duplicate"] += 1
            return False
        self.set(step, u, offset)
        counters["commands_accepted"] += 1
        return True

    def set(self, step: int, u: np.ndarray, offset: float = 0.0) -> None:
        """Record a command for ``step`` (origin <= step < origin + capacity), taking effect
        ``offset`` seconds after the step's start ("hold" mode; 0.0: at its start)."""
        i = step - self.origin
        if not 0 <= i < self.capacity:
            raise IndexError(f"step {step} outside the input window")
        k = _bisect_left(self._cmd_steps, step)
        self._cmd_steps.insert(k, step)
        start = self._off + i
        if self.hold:
            # u applies until the next explicit command, else past the window's end: the
            # rows after the window hold its last step's u
            nxt = self._cmd_steps[k + 1] if k + 1 < len(self._cmd_steps) else None
            end = self._off + nxt - self.origin if nxt is not None else self._buf.shape[0]
        else:
            end = start + 1
        fill = _FILL
        if fill is None or not fill(self._buf, start, end, u):
            self._buf[start:end] = u
        if offset > 0.0 and self.hold:
            self.cut_offsets[step] = offset
            _insort(self._cut_steps, step)

    def constant_from(self, step: int) -> bool:
        """Whether u(t) is one value for every t >= ``step`` (no explicit command after it,
        none inside a step from it on; "zero": none at it either)."""
        cmds, cut = self._cmd_steps, self._cut_steps
        last = cmds[-1] if cmds else None
        if last is not None and (last > step or (last == step and not self.hold)):
            return False
        return not cut or cut[-1] < step

    def cuts(self, first: int, last: int) -> list[tuple[int, float, np.ndarray]] | None:
        """The commands taking effect inside steps first..last (inclusive) as
        ``(step - first, offset, u(step - 1))`` (:data:`.replay.Cut`; u a read-only view of
        the buffer: for the step being computed now), None if there are none."""
        steps = self._cut_steps
        if not steps:
            return None
        i = _bisect_left(steps, first)
        if i == len(steps) or steps[i] > last:
            return None
        cut = self.cut_offsets
        out: list[tuple[int, float, np.ndarray]] = []
        while i < len(steps) and steps[i] <= last:
            j = steps[i]
            out.append((j - first, cut[j], self.u_of(j - 1)))
            i += 1
        return out

    def cut_view(self) -> tuple[list[int], dict[int, float], np.ndarray, int]:
        """(the command steps with an offset, sorted; step -> offset; u(origin - 1);
        origin): what the replay's C loop reads to find a span's cuts itself (shared, not
        copied: read at once)."""
        return self._cut_steps, self.cut_offsets, self.u_before, self.origin

    def u_of(self, step: int) -> np.ndarray:
        """u(step), read-only (a view of the buffer), for origin - 1 <= step < origin +
        capacity."""
        if step == self.origin - 1:
            return self.u_before
        i = step - self.origin
        if not 0 <= i < self.capacity:
            raise IndexError(f"step {step} outside the input window")
        return self._buf[self._off + i]
    def slice(self, step: int, m: int) -> np.ndarray:
        """Inputs u(step), ..., u(step + m - 1) as a read-only (m, nu) view."""
        i = self._off + step - self.origin
        view = self._buf[i : i + m]
        if step < self.origin or step + m > self.origin + self.capacity:
            raise IndexError(f"steps [{step}, {step + m}) outside the input window")
        return view

    def window(self, first: int, last: int) -> tuple[np.ndarray, int]:
        """(buf, off) with u(t) = buf[t - off] for first <= t < last: the slices of several
        propagations over [first, last) without a method call each. IndexError if that
        range leaves the input window."""
        if first < self.origin or last > self.origin + self.capacity:
            raise IndexError(f"steps [{first}, {last}) outside the input window")
        return self._buf, self.origin - self._off

    def export(self) -> tuple[int, np.ndarray, list[tuple[int, np.ndarray]]]:
        """(origin, u(origin) (nu,), [(step, u (nu,)) of every explicit command >= origin]):
        with :attr:`cut_offsets` and :attr:`u_before`, enough for :meth:`restore` to
        rebuild u(t) over the whole buffer."""
        steps = self._cmd_steps
        # the commands' rows in one copy (fancy indexing), handed out as views of it: they
        # share nothing with the buffer (one copy, not one ``.copy()`` per row)
        idx = np.array(steps, dtype=np.intp)
        idx += self._off - self.origin
        rows = self._buf[idx]
        cmds = list(zip(steps, rows, strict=True))
        return self.origin, self._buf[self._off].copy(), cmds

    def restore(self, origin: int, u_origin: np.ndarray,
                commands: list[tuple[int, np.ndarray]],
                offsets: dict[int, float] | None = None,
                u_before: np.ndarray | None = None) -> None:
        """Replace the contents by what :meth:`export` returned: u(origin) held ("hold") or
        zeros ("zero") until the first command, then the commands as :meth:`set` stores them
        (with their ``offsets``, step -> s; ``u_before``: u(origin - 1), default zeros).
        IndexError for a command outside [origin, origin + capacity)."""
        self.origin = origin
        self._off = 0
        self._cmd_steps = []
        self.cut_offsets = {}
        self._cut_steps = []
        self.u_before = np.zeros(self.nu) if u_before is None else u_before.copy()
        self._buf[:] = u_origin if self.hold else 0.0
        offs = offsets or {}
        for step, u in sorted(commands, key=lambda c: c[0]):
            if self.has_command(step):
                raise IndexError(f"two commands for step {step}")
            self.set(step, u, offs.get(step, 0.0))

    def advance(self, origin: int) -> None:
        """Forget steps before ``origin``; new steps at the end continue the hold."""
        d = origin - self.origin
        if d <= 0:
            return
        cap = self.capacity
        buf = self._buf
        if self.hold:  # u(origin - 1), held past the window's end
            self.u_before = buf[self._off + min(d - 1, cap - 1)].copy()
        steps = self._cut_steps
        if steps and steps[0] < origin:
            k = _bisect_left(steps, origin)
            for j in steps[:k]:
                del self.cut_offsets[j]
            del steps[:k]
        if d >= cap:  # every step new: u of the old last step ("hold") or zeros
            buf[:] = buf[self._off + cap - 1].copy() if self.hold else 0.0
            self._off = 0
        elif self._off + d + cap > buf.shape[0]:
            # back to row 0; the rows after the window: u of its last step (row cap - d - 1,
            # just moved there) or zeros
            buf[: cap - d] = buf[self._off + d : self._off + cap]
            buf[cap - d :] = buf[cap - d - 1] if self.hold else 0.0
            self._off = 0
        else:  # the rows entering the window already hold their u
            self._off += d
        self.origin = origin
        cmds = self._cmd_steps
        if cmds and cmds[0] < origin:
            del cmds[: _bisect_left(cmds, origin)]

    def replace(self, step: int, u: np.ndarray, offset: float = 0.0) -> None:
        """Replace the command stored for ``step`` by ``u`` taking effect ``offset`` seconds
        after the step's start (a newer command for the same step, or the same one moved to
        the instant the robot echoed: :meth:`.replay.ReplayEstimator.supersede_command`):
        u(t) is refilled up to the next command exactly as :meth:`set` fills it. KeyError if
        no command is stored for it."""
        if not self.has_command(step):
            raise KeyError(f"no command stored for step {step}")
        self._cmd_steps.remove(step)
        self._forget_cut(step)
        self.set(step, u, offset)

    def remove(self, step: int) -> None:
        """Forget the command stored for ``step`` (origin <= step < origin + capacity): u(t)
        from ``step`` up to the next command becomes what it was before it (the previous
        step's u, :attr:`u_before` at the origin, "hold"; zero, "zero"). KeyError if none is
        stored for it."""
        if not self.has_command(step):
            raise KeyError(f"no command stored for step {step}")
        i = step - self.origin
        k = _bisect_left(self._cmd_steps, step)
        del self._cmd_steps[k]
        self._forget_cut(step)
        start = self._off + i
        if self.hold:
            nxt = self._cmd_steps[k] if k < len(self._cmd_steps) else None
            end = self._off + nxt - self.origin if nxt is not None else self._buf.shape[0]
            self._buf[start:end] = self._buf[start - 1] if i > 0 else self.u_before
        else:
            self._buf[start] = 0.0

    def _forget_cut(self, step: int) -> None:
        """Drop ``step``'s offset (its command is replaced or removed)."""
        if self.cut_offsets.pop(step, None) is not None:
            del self._cut_steps[_bisect_left(self._cut_steps, step)]
