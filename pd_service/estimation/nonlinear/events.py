"""Samples taken inside a step: where a nonlinear backend splits its propagation.

A packet stamped step s with offset o (s, 0 <= o < T) was sampled at s T + o. The backends
(:mod:`.unscented`, :mod:`..imm.observer`) apply the packets at offset 0 at x(s), as always,
and keep the others *pending* on the state of x(s); the next propagation over [s, s+1) with
u(s) held runs through them in time order::

    x(s) --f_{o1}--> x(s T + o1) | update(o1 packets) --f_{o2-o1}--> ... --f_{T-oj}--> x(s+1)

(f_tau = the model's ``flow(tau)``, noise Q tau / T), so the state handed on is at the grid
point s+1 and a step without inner packets is computed exactly as before (bit-for-bit).
Until then the state's moments are those of x(s) given every sample taken up to s T.
Commands stay on the grid (u(s) holds over the whole step).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from ..estimator_state import StateError, take
from ..replay import Packet
from .registry import NonlinearModel


def splits(model: NonlinearModel) -> bool:
    """Whether ``model`` can move part of a step (it has ``flow`` and ``period_s``)."""
    return model.flow is not None and model.period_s > 0.0


def split_packets(packets: Sequence[Packet],
                  can_split: bool) -> tuple[list[Packet], tuple[Packet, ...]]:
    """(packets at the step's start, packets inside it sorted by offset, ties in the given
    order). A model that cannot split applies every packet at the step's start."""
    if not can_split:
        return list(packets), ()
    start = [p for p in packets if p.offset == 0.0]
    inside = sorted((p for p in packets if p.offset != 0.0), key=_offset)
    return start, tuple(inside)


def segments(inside: Sequence[Packet], period_s: float) -> Iterator[tuple[float, list[Packet]]]:
    """(tau, group) in time order: propagate tau seconds (> 0), then update on ``group``
    (the packets sampled at that instant; empty for the last segment, up to the step's
    end). Offsets at or past the period are taken at the step's end."""
    t = 0.0
    i = 0
    while i < len(inside):
        o = min(inside[i].offset, period_s)
        group = []
        while i < len(inside) and min(inside[i].offset, period_s) == o:
            group.append(inside[i])
            i += 1
        yield o - t, group
        t = o
    if t < period_s:
        yield period_s - t, []


def export_pending(pending: Sequence[Packet]) -> dict[str, np.ndarray]:
    """Pending packets as named arrays: "pending.sensor" (j,), "pending.offset" (j,) (s),
    "pending.z.i" (m_i,) and, for a per-sample R, "pending.R.i" (m_i, m_i); {} if none."""
    if not pending:
        return {}
    out = {"pending.sensor": np.array([p.sensor for p in pending], dtype=float),
           "pending.offset": np.array([p.offset for p in pending], dtype=float)}
    for i, p in enumerate(pending):
        out[f"pending.z.{i}"] = p.z.copy()
        if p.R is not None:
            out[f"pending.R.{i}"] = p.R.copy()
    return out


def import_pending(arrays: dict[str, np.ndarray],
                   dims: Sequence[int]) -> tuple[dict[str, np.ndarray], tuple[Packet, ...]]:
    """(the other arrays, the pending packets :func:`export_pending` described) for sensors
    of dimensions ``dims``; StateError if they do not fit."""
    rest = {k: v for k, v in arrays.items() if not k.startswith("pending.")}
    if len(rest) == len(arrays):
        return rest, ()
    sensors = np.asarray(arrays.get("pending.sensor", []), dtype=float).reshape(-1)
    j = sensors.shape[0]
    offsets = take(arrays, "pending.offset", (j,))
    packets = []
    for i in range(j):
        s = int(sensors[i])
        if s != sensors[i] or not 0 <= s < len(dims) or not offsets[i] > 0.0:
            raise StateError(f"base.pending: packet {i} has a bad sensor or offset")
        m = dims[s]
        z = take(arrays, f"pending.z.{i}", (m,))
        z.setflags(write=False)
        R = take(arrays, f"pending.R.{i}", (m, m)) if f"pending.R.{i}" in arrays else None
        packets.append(Packet(s, z, R, float(offsets[i])))
    known = {"pending.sensor", "pending.offset"} | {f"pending.z.{i}" for i in range(j)} | {
        f"pending.R.{i}" for i in range(j)}
    if set(arrays) - set(rest) - known:
        raise StateError(f"base: unexpected arrays {sorted(set(arrays) - set(rest) - known)}")
    return rest, tuple(sorted(packets, key=_offset))


def _offset(p: Packet) -> float:
    return p.offset
