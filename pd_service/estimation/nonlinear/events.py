"""Samples taken inside a step: where a nonlinear backend splits its propagation.

A packet stamped step s with offset o (s, 0 <= o < T) was sampled at s T + o. The backends
(:mod:`.unscented`, :mod:`..imm.observer`) update x(s) on the packets at offset 0, as always;
if the step has packets inside it, they then run through the step in time order with u(s)
held (the replay's contract, :class:`~pd_service.estimation.replay.Backend`)::

    x(s) --f_{o1}--> x(s T + o1) | update(o1 packets) --f_{o2-o1}--> ... --f_{T-oj}--> x(s+1)

(f_tau = the model's ``flow(tau)``, noise Q tau / T) and hand on x(s+1), the posterior given
the packets stamped <= s. A step without inner packets is computed exactly as before
(bit-for-bit). A command that takes effect inside step s (the core's ``cuts``) is one more
instant: the input before it until then, u(s) after. Commands between samples of a step
without inner packets stay on the grid (u(s) over the whole step).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from ..replay import Packet
from .registry import NonlinearModel


def splits(model: NonlinearModel) -> bool:
    """Whether ``model`` can move part of a step (it has ``flow`` and ``period_s``)."""
    return model.flow is not None and model.period_s > 0.0


def split_packets(packets: Sequence[Packet],
                  can_split: bool) -> tuple[list[Packet], list[Packet]]:
    """(packets at the step's start, packets inside it sorted by offset, ties in the given
    order). A model that cannot split applies every packet at the step's start."""
    if not can_split:
        return list(packets), []
    start = [p for p in packets if p.offset == 0.0]
    inside = sorted((p for p in packets if p.offset != 0.0), key=_offset)
    return start, inside


def segments(inside: Sequence[Packet], period_s: float,
             cut: float | None = None) -> Iterator[tuple[float, float, list[Packet]]]:
    """(t, tau, group) in time order: from t seconds into the step, propagate tau (> 0)
    seconds, then update on ``group`` (the packets sampled at t + tau; empty at a ``cut``,
    the instant a command takes effect, and for the last segment, up to the step's end).
    Offsets at or past the period are taken at the step's end."""
    marks = sorted({min(p.offset, period_s) for p in inside} | (
        {cut} if cut is not None and 0.0 < cut < period_s else set()))
    t = 0.0
    i = 0
    for o in marks:
        group = []
        while i < len(inside) and min(inside[i].offset, period_s) == o:
            group.append(inside[i])
            i += 1
        yield t, o - t, group
        t = o
    if t < period_s:
        yield t, period_s - t, []


def step_inputs(inputs: object, k: int) -> tuple[np.ndarray, tuple[float, np.ndarray] | None]:
    """u(k) from an estimator's input buffer and, where a command takes effect inside step k
    (the buffer's ``cuts``, where it has them), (its offset s, the input before it)."""
    u: np.ndarray = inputs.slice(k, 1)[0]  # type: ignore[attr-defined]
    cuts = getattr(inputs, "cuts", None)
    c = cuts(k, k) if cuts is not None else None
    return u, (None if not c else (float(c[0][1]), np.asarray(c[0][2])))


def _offset(p: Packet) -> float:
    return p.offset
