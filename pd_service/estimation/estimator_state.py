"""What a :class:`~.replay.ReplayEstimator` needs to continue exactly: its window, exported.

The committed horizon is summarised by one backend state (the *base*, an estimate of
x(base_step) given every packet stamped <= base_step, plus what an adaptive backend learnt);
the open window is the raw packets and commands that may still change. The posteriors at the
measured steps of the open window (the checkpoints) are NOT exported: they are a pure
function of the base, the packets and the inputs, and :meth:`ReplayEstimator.restore_state`
recomputes them with the same operations in the same order, so::

    est2.restore_state(est1.export_state())
    est1.<same calls>(...) == est2.<same calls>(...)          (bit for bit, one backend)

Inputs: u(t) for t in the input buffer's range [origin, origin + capacity) is rebuilt from
``u_origin`` (the u in effect at ``inputs_origin``: in "hold" mode it comes from a command that
may lie before the window) and the explicit ``commands`` at steps >= ``inputs_origin``.

Sizes, for n states, nu inputs, window W = max_delay + 1 steps, s sensors of m rows:
base n + n^2 (+ p n + p n^2 for tracked sensitivities, r + r n + r n^2 per IMM node),
packets <= s W (m + m^2 with R overrides), commands <= ~2W + lead (nu each).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final, TypeVar

import numpy as np

from pd_service.native import kernel_function

#: The C kernel's untrack (pd_service/estimation/_kalman.c); None in the numpy form.
_UNTRACK: Final = kernel_function("pd_service.estimation._kalman", "untrack")

_T = TypeVar("_T")

#: Version of the exported layout; a state of another version is refused on restore.
STATE_VERSION = 1

#: One stored packet: (sample step, sensor name, z (m,), R (m, m) override or None, offset:
#: seconds after the step's start at which it was sampled).
PacketRecord = tuple[int, str, np.ndarray, np.ndarray | None, float]


@dataclass
class EstimatorState:
    """Everything a session's estimator needs to continue; plain numpy arrays and ints.

    ``base``: the backend's state at ``base_step`` as named arrays (linear / UKF: "x" (n,),
    "P" (n, n); a tracked UKF adds "dx" (p, n), "dP" (p, n, n); IMM: "mu" (N, r),
    "x" (N, r, n), "P" (N, r, n, n)). ``extras``: what the estimator learnt beyond the base
    (adapted process noise "Q" (n, n), adapter memory, e.g. "mit_rings" ...), as named arrays.
    ``committed_step`` c: first step that can still change; ``now``: newest now seen.
    """

    kind: str
    n: int
    now: int | None
    committed_step: int
    base_step: int
    newest_committed: int | None
    base: dict[str, np.ndarray]
    packets: list[PacketRecord]
    inputs_origin: int
    u_origin: np.ndarray
    commands: list[tuple[int, np.ndarray]]
    counters: dict[str, int]
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    version: int = STATE_VERSION
    #: command step -> seconds after its start at which it takes effect (offsets > 0 only)
    command_offsets: dict[int, float] = field(default_factory=dict)
    #: u(inputs_origin - 1) (nu,): the input before a command taking effect inside the
    #: origin step; None: zeros
    u_before: np.ndarray | None = None

    @property
    def mean(self) -> np.ndarray:
        """Combined mean of the base (n,) (the IMM's is its mixture mean)."""
        x = self.base["x"]
        if "mu" in self.base:
            return np.asarray(np.einsum("r,rn->n", self.base["mu"][0], x[0]))
        return x

    @property
    def cov(self) -> np.ndarray:
        """Covariance of the base (n, n) (the IMM's: its mixture covariance)."""
        if "mu" in self.base:
            mu, x, P = self.base["mu"][0], self.base["x"][0], self.base["P"][0]
            m = mu @ x
            d = x - m
            return np.asarray(np.einsum("r,rab->ab", mu, P + np.einsum("ra,rb->rab", d, d)))
        return self.base["P"]


class StateError(ValueError):
    """A state that does not fit this estimator (another kind, size, version or window)."""


def take(arrays: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    """A finite float copy of ``arrays[name]`` of exactly ``shape``; StateError otherwise."""
    a = arrays.get(name)
    if a is None:
        raise StateError(f"base.{name}: missing")
    try:
        out = np.array(a, dtype=float)
    except (TypeError, ValueError):
        raise StateError(f"base.{name}: not numeric") from None
    if out.shape != shape:
        raise StateError(f"base.{name}: shape {out.shape}, expected {shape}")
    if not np.all(np.isfinite(out)):
        raise StateError(f"base.{name}: not finite")
    return out


def check_names(arrays: dict[str, np.ndarray], allowed: set[str]) -> None:
    unknown = set(arrays) - allowed
    if unknown:
        raise StateError(f"base: unexpected arrays {sorted(unknown)}")


def untracked(state: _T) -> _T:
    """``state`` (an :class:`EstimatorState` kept unchanged, e.g. a session's snapshot),
    taken with its tuples, lists and dicts out of the cycle collector where the C kernel
    runs (``_kalman.untrack``; the same object otherwise). Such a state holds only numbers,
    strings and arrays, so it can be in no reference cycle; kept tracked for its second of
    life, many sessions' snapshots fill the collector's young generation, whose collections
    then stop the daemon's worker (docs/performance.md)."""
    return state if _UNTRACK is None else _UNTRACK(state)
