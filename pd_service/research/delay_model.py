"""Bounded random delay with packet loss, in the hazard form of the linear-coding paper.

Time is an integer step. A packet stamped ``s`` (the measurement y(s)) arrives at step
``s + i`` with probability ``p_i`` for i = 0..d, and never with probability ``1 - sum(p)``
(delays beyond the bound d count as lost).

The paper (linear-coding-delay-loss-zh, section 2) writes the same law with independent
Bernoulli variables alpha_i(k), P{alpha_i(k) = 1} = alpha_i, one per delay value and per
receive step: packet y(k - i) is received at step k iff it was not received at steps
k - i, ..., k - 1 and alpha_i(k) = 1, i.e. the indicator

    a_i(k) = alpha_i(k) * prod_{j<i} (1 - alpha_j(k - i + j)).

So alpha_i is the hazard P(delay = i | delay >= i) and

    p_i = alpha_i * prod_{j<i} (1 - alpha_j),      P(lost) = prod_{j<=d} (1 - alpha_j).

Distinct packets use disjoint alpha variables, so delays are independent across packets.
The sampler below draws exactly this hazard chain (one uniform per packet and delay value).
It is pure numpy and takes a ``numpy.random.Generator`` so callers control the seed; the
link emulator can reuse it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

LOST = -1
"""Delay value returned by :meth:`DelayModel.sample` for a packet that never arrives."""

_TOL = 1e-12


@dataclass(frozen=True)
class DelayModel:
    """Hazard-rate model of bounded random delay plus loss.

    Attributes:
        hazards: shape (d + 1,), ``hazards[i] = P(delay = i | delay >= i)`` in [0, 1].
    """

    hazards: np.ndarray

    def __post_init__(self) -> None:
        h = np.array(self.hazards, dtype=float).reshape(-1)
        if h.size == 0:
            raise ValueError("hazards: need at least one entry (max_delay >= 0)")
        if not np.all(np.isfinite(h)) or np.any(h < 0.0) or np.any(h > 1.0):
            raise ValueError(f"hazards: every entry must be a probability in [0, 1], got {h}")
        h.setflags(write=False)
        object.__setattr__(self, "hazards", h)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_probabilities(
        cls, delay_probs: Sequence[float] | np.ndarray, extra_loss: float = 0.0
    ) -> DelayModel:
        """Build the model from the delay distribution.

        Args:
            delay_probs: shape (d + 1,), ``P(delay = i)`` for i = 0..d; the sum must be <= 1
                and the remainder ``1 - sum`` is the probability of a delay beyond d (lost).
                Example: (0.5, 0.25, 0.15, 0.05) means 5% loss.
            extra_loss: probability in [0, 1) that a packet is dropped independently of its
                delay, applied on top: P(delay = i) becomes ``(1 - extra_loss) * delay_probs[i]``.
        """
        p = np.asarray(delay_probs, dtype=float).reshape(-1)
        if p.size == 0:
            raise ValueError("delay_probs: need at least one entry (max_delay >= 0)")
        if not np.all(np.isfinite(p)) or np.any(p < 0.0):
            raise ValueError(f"delay_probs: entries must be finite and >= 0, got {p}")
        if p.sum() > 1.0 + 1e-9:
            raise ValueError(f"delay_probs: sum must be <= 1, got {p.sum()}")
        if not (np.isfinite(extra_loss) and 0.0 <= extra_loss < 1.0):
            raise ValueError(f"extra_loss: must be in [0, 1), got {extra_loss}")
        p = p * (1.0 - extra_loss)
        # alpha_i = p_i / P(delay >= i),  P(delay >= i) = 1 - sum_{j<i} p_j
        survive = 1.0 - np.concatenate(([0.0], np.cumsum(p)[:-1]))
        h = np.where(survive > _TOL, p / np.maximum(survive, _TOL), 1.0)
        return cls(np.clip(h, 0.0, 1.0))

    # ------------------------------------------------------------------ derived laws
    @property
    def max_delay(self) -> int:
        """The delay bound d (steps)."""
        return int(self.hazards.size - 1)

    @property
    def delay_pmf(self) -> np.ndarray:
        """Shape (d + 1,): ``P(delay = i) = alpha_i * prod_{j<i} (1 - alpha_j)``."""
        h = self.hazards
        survive = np.concatenate(([1.0], np.cumprod(1.0 - h)[:-1]))
        return h * survive

    @property
    def loss_probability(self) -> float:
        """``P(lost) = prod_{j<=d} (1 - alpha_j)``."""
        return float(np.prod(1.0 - self.hazards))

    # ------------------------------------------------------------------ sampling
    def sample(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """Draw the delays of ``size`` consecutive packets by the hazard chain.

        Returns:
            int array, shape (size,): the delay in steps (0..d) or :data:`LOST`.
        """
        if not isinstance(rng, np.random.Generator):
            raise ValueError("rng: expected a numpy.random.Generator (seed it for reproducibility)")
        if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 0:
            raise ValueError(f"size: expected a non-negative integer, got {size!r}")
        u = rng.random((int(size), self.hazards.size))
        hit = u < self.hazards  # alpha_i(s + i) = 1: received at delay i if not received before
        first = np.argmax(hit, axis=1)
        return np.where(hit.any(axis=1), first, LOST).astype(np.int64)


def arrivals_by_step(delays: np.ndarray, horizon: int) -> list[list[int]]:
    """Group packet stamps by receive step.

    Args:
        delays: int array, shape (T,): delay of the packet stamped s (or :data:`LOST`).
        horizon: number of receive steps to return (steps 0..horizon-1).

    Returns:
        ``out[k]`` = stamps received at step k, newest first (ascending delay).
    """
    out: list[list[int]] = [[] for _ in range(int(horizon))]
    for s, dly in enumerate(np.asarray(delays).tolist()):
        if dly != LOST and s + dly < horizon:
            out[s + dly].append(s)
    for lst in out:
        lst.sort(reverse=True)
    return out
