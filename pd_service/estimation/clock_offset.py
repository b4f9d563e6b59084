"""The offset and drift of a robot's clock against the daemon's, from timestamps alone.

Offset ``theta(t) = robot clock - daemon clock`` at daemon time t, modelled over the current
anchor as a line ``theta(t) = a + b t`` (b: the drift, s/s; 1e-4 = 100 ppm). Every stamp pair
bounds it, because a message never arrives before it was sent (delays d >= 0):

- a probe (NTP-style quadruple: t1 daemon sends, t2 robot receives, t3 robot answers, t4
  daemon receives) gives ``theta <= t2 - t1`` (upper: ``t2 - t1 = theta + d_up``) and
  ``theta >= t3 - t4`` (lower: ``t3 - t4 = theta - d_down``);
- a one-way robot stamp s received at r (a measurement, an echo's own send) gives
  ``theta >= s - r`` (lower);
- a command issued at i (daemon) that the robot reports applied at a (robot clock) gives
  ``theta <= a - i`` (upper).

Estimate (the convex-hull / lower-envelope method of clock synchronisation): the drift b is
the slope of the tightest line above the lower bounds (the upper convex hull's edge over their
mean time, which minimises the summed gaps: the linear programme of one-way delay skew
estimation) and of the tightest line below the upper bounds, averaged; then with
``L = max(l_i - b t_i)`` and ``U = min(u_i - b t_i)`` the offset is
``theta(t) = (L + U) / 2 - asymmetry / 2 + b t`` and its uncertainty the half-width
``(U - L) / 2 + tilt + max_drift * age`` (age: seconds since the newest bound; the bound grows
while probes stop). ``tilt`` is what the drift's own error can add at t: every drift b' in
``[b_lo, b_hi]`` (:func:`drift_range`: the slopes some line between the bounds may have) keeps
a line through the bounds that pin L and U (at t_L, t_U), so ``theta(t) >= L + b t - (b -
b_lo) (t - t_L)^+ - (b_hi - b) (t_L - t)^+`` and alike above; one loose bound can set a
hull's slope (the drift) but not this range, which only tight bounds narrow. Bounds are kept
per time bucket (the tightest of each kind per ``bucket_s``): bounded memory, a long span for
the drift, whatever the sample rate.

What is identifiable: ``U - L`` shrinks to ``d_up_min + d_down_min`` (the fastest delays seen
each way), and the midpoint is off by ``(d_up_min - d_down_min) / 2``. A *constant* asymmetry
of the delays cannot be seen in timestamps at all (shifting theta by c and the delays by
+c / -c gives the same stamps): it stays in the estimate unless configured (``asymmetry_s``
= expected ``d_up - d_down``). Jitter only widens the delays' spread; the envelopes take the
fastest, so it costs only time. With lower bounds alone (no probes, no echoes) theta is only
bounded below: the estimate is that bound (a robot stamp mapped with it is never later than
its receipt) and the uncertainty infinite.

Step changes (an NTP correction on the robot): a bound outside the current band by more than
the tolerance is held aside (``inconsistent``); ``confirm`` of them, with no bound of the
other kind contradicting them in between (an upper bound under a held lower one, or a lower
bound over a held upper one), re-anchor the estimate on them (``steps``). A step inside the
band (smaller than its width: 200 ms against the ~0.9 s of a 500 / 600 ms link) moves
every bound by the same amount d, so, per side, the median of the newest ``recent``
buckets' extremes (detrended) moves by d against the median of the (at most 16) buckets
before them (:func:`step_test`): both sides must have moved the
same way, each by more than ``step_k`` standard errors (:func:`median_shift`: from the
buckets' own spread, at least the tolerance and the drift's uncertainty times the time
between the two sets), by amounts that agree; the buckets before the step
(:func:`change_point`) are then dropped. Medians of both sides, not one side's extremes: a
bucket that holds a probe (the tightest upper bound, tens of ms under the echoes of a robot
that applies commands at its next tick) moves an extremum of the old buckets but not their
median, and a change of one way's delays moves one side only. Pure numpy, no
clock reads: every time is passed in (ns, int).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass
from typing import Final

import numpy as np

from .tally import Tally

_NS: Final = 1e-9
#: Buckets left out between the old and the recent set of the in-band step test, and the
#: most buckets of the old set it looks at.
_GUARD: Final = 2
_OLD: Final = 16
#: What :meth:`ClockOffsetEstimator.counters` may hold, by outcome.
CLOCK_COUNTERS: Final = ("bounds", "probes", "probes_invalid", "implausible", "inconsistent",
                         "steps")


@dataclass(frozen=True)
class OffsetEstimate:
    """The robot clock's offset at daemon time ``t_ns``: ``offset_s`` (robot - daemon, s),
    ``drift`` (s/s), ``half_width_s`` (theta lies within offset +- half_width if the delays are
    >= 0, the asymmetry as configured and the drift within max_drift; inf: unbounded above),
    ``lower_s`` / ``upper_s`` (the band, s), ``age_s`` (since the newest bound), ``steps``
    (step changes detected so far), ``known`` (False: no bound yet, offset 0)."""

    t_ns: int
    offset_s: float
    drift: float
    half_width_s: float
    lower_s: float
    upper_s: float
    age_s: float
    steps: int
    known: bool

    def to_daemon_ns(self, robot_ns: int) -> int:
        """A robot stamp on the daemon's timeline: ``robot_ns - theta`` (theta at
        ``robot_ns``'s own daemon time, to first order)."""
        t = (robot_ns - self.t_ns) * _NS - self.offset_s
        theta = self.offset_s + self.drift * t
        return robot_ns - round(theta * 1e9)


@dataclass(slots=True)
class _Bucket:
    """The tightest bounds seen in one time bucket (s since the anchor; -inf/inf: none)."""

    index: int
    lo: float = -np.inf  # max lower bound value
    t_lo: float = 0.0
    hi: float = np.inf  # min upper bound value
    t_hi: float = 0.0


def _span(t: np.ndarray) -> float:
    return float(t.max() - t.min()) if t.size else 0.0


def hull(t: np.ndarray, v: np.ndarray, above: bool) -> list[tuple[float, float]]:
    """The vertices (t, v), by time, of the upper (``above``) or lower convex hull of the
    points (t_i, v_i): the only points a line above (below) all of them can touch. At one
    time only the tightest point counts. Shapes: t, v (n,)."""
    order = np.lexsort((v if not above else -v, t))
    ts, vs = t[order].tolist(), v[order].tolist()
    sign = 1.0 if above else -1.0
    out: list[tuple[float, float]] = []
    for p in zip(ts, vs, strict=True):
        if out and out[-1][0] == p[0]:
            continue  # same time: the first kept is the tightest (sorted so)
        # monotone chain: pop while the turn keeps the hull convex on the wanted side
        while len(out) >= 2:
            (x1, y1), (x2, y2) = out[-2], out[-1]
            cross = (x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1)
            if sign * cross >= 0.0:
                out.pop()
            else:
                break
        out.append(p)
    return out


def hull_slope(t: np.ndarray, v: np.ndarray, above: bool) -> float | None:
    """Slope of the line above (``above``) or below all points (t_i, v_i) with the least
    summed gap: the edge of the upper (lower) convex hull over mean(t). None for fewer than
    two distinct times. Shapes: t, v (n,)."""
    if t.size < 2 or float(t.max() - t.min()) <= 0.0:
        return None
    return edge_slope(hull(t, v, above), float(np.mean(t)))


def edge_slope(edge: list[tuple[float, float]], mean_t: float) -> float | None:
    """:func:`hull_slope` from the hull's vertices ``edge`` (:func:`hull`) and the points'
    mean time ``mean_t``: the slope of the edge over it. None for fewer than two vertices."""
    if len(edge) < 2:
        return None
    for (x1, y1), (x2, y2) in zip(edge, edge[1:], strict=False):
        if x2 >= mean_t:
            return (y2 - y1) / (x2 - x1)
    (x1, y1), (x2, y2) = edge[-2], edge[-1]
    return (y2 - y1) / (x2 - x1)


def drift_range(lower: list[tuple[float, float]], upper: list[tuple[float, float]],
                max_drift: float) -> tuple[float, float]:
    """The drifts b (s/s) some line ``a + b t`` allows that lies above every lower bound and
    below every upper one, within +-max_drift: a lower bound (t_i, l_i) and an upper one
    (t_j, u_j) need ``l_i + b (t_j - t_i) <= u_j``, so

        b <= (u_j - l_i) / (t_j - t_i)  (t_j > t_i),   b >= (l_i - u_j) / (t_i - t_j)  (t_i > t_j)

    over the pairs of hull vertices (``lower``: the upper hull of the lower bounds,
    ``upper``: the lower hull of the upper ones, :func:`hull`; the extremes of ``l_i - b
    t_i`` and ``u_j - b t_j`` lie on them for every b). Bounds that contradict every drift
    give b_min > b_max (the caller widens to its own estimate)."""
    if not lower or not upper:
        return -max_drift, max_drift
    tl, vl = np.array(lower).T
    tu, vu = np.array(upper).T
    dt = tu[None, :] - tl[:, None]  # (n_lower, n_upper)
    gap = vu[None, :] - vl[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = gap / dt
    hi = float(np.min(slope[dt > 0], initial=max_drift))
    lo = float(np.max(slope[dt < 0], initial=-max_drift))
    return max(lo, -max_drift), min(hi, max_drift)


def median_shift(old: np.ndarray, new: np.ndarray, floor: float) -> tuple[float, float]:
    """How far the values ``new`` sit from ``old`` (one side's per-bucket extremes,
    detrended, s), and that figure's standard error:

        shift = median(new) - median(old)
        se = sqrt(pi / 2) * 1.4826 * MAD * sqrt(1 / n_new + 1 / n_old),  se >= floor

    MAD the median absolute deviation of both sets about their own medians (1.4826 MAD:
    the standard deviation of normal noise; sqrt(pi / 2): a median's standard error over a
    mean's); ``floor`` stands for what the spread cannot show (a side whose extremes are
    quantised, e.g. commands applied at a control tick, has none, and the drift's error
    still tilts it). Medians, not extremes: one bucket with a lucky probe (a side's
    tightest bound) moves an extreme, not a median. Shapes: old (m,), new (n,)."""
    mo, mn = float(np.median(old)), float(np.median(new))
    mad = float(np.median(np.abs(np.concatenate([old - mo, new - mn]))))
    se = math.sqrt(math.pi / 2) * 1.4826 * mad * math.sqrt(1.0 / new.size + 1.0 / old.size)
    return mn - mo, max(se, floor)


def step_test(old_lo: np.ndarray, new_lo: np.ndarray, old_hi: np.ndarray,
              new_hi: np.ndarray, k: float, floor_lo: float, floor_hi: float) -> float | None:
    """The in-band step test: the step (s) the newest buckets show against the older ones,
    None if none. A step of the robot's clock moves every bound by the same amount, so
    both sides must have moved, the same way, each by more than ``k`` of its standard
    error (:func:`median_shift`, at least its ``floor``), and by amounts that agree:

        sign(s_lo) = sign(s_hi),  |s_lo| > k se_lo,  |s_hi| > k se_hi,
        |s_lo - s_hi| <= k sqrt(se_lo^2 + se_hi^2)

    (a change of one way's delays moves one side only; noise rarely moves both, by the same
    amount); the step is their inverse-variance mean ``(s_lo / se_lo^2 + s_hi / se_hi^2) /
    (1 / se_lo^2 + 1 / se_hi^2)``. Arrays: each side's per-bucket extremes, detrended (s)."""
    s_lo, se_lo = median_shift(old_lo, new_lo, floor_lo)
    s_hi, se_hi = median_shift(old_hi, new_hi, floor_hi)
    if (s_lo * s_hi <= 0 or abs(s_lo) <= k * se_lo or abs(s_hi) <= k * se_hi
            or abs(s_lo - s_hi) > k * math.hypot(se_lo, se_hi)):
        return None
    w_lo, w_hi = se_lo ** -2, se_hi ** -2
    return (s_lo * w_lo + s_hi * w_hi) / (w_lo + w_hi)


def change_point(lo: np.ndarray, hi: np.ndarray, pre_lo: float, pre_hi: float,
                 shift: float) -> int:
    """The first bucket after a step of ``shift`` (s) among consecutive buckets whose
    extremes (detrended, s; +-inf: none of that kind) are ``lo``, ``hi``: before the step
    each side sits at its level ``pre`` (the older buckets' median), after it at
    ``pre + shift``; the least-absolute-deviation split

        c = argmin_c  sum_{i < c} |x_i - pre| + sum_{i >= c} |x_i - pre - shift|

    over both sides, then moved past a bucket whose *tighter* side (upper for a step
    forward, lower for one back) is still nearer the old level: the bucket the step fell
    into, whose bound from before would hold the new band to the old level. Never past the
    last bucket. Shapes: lo, hi (n,)."""
    n = lo.size
    cost = np.zeros(n + 1)
    for x, pre in ((lo, pre_lo), (hi, pre_hi)):
        seen = np.isfinite(x)
        d_pre = np.where(seen, np.abs(x - pre), 0.0)
        d_post = np.where(seen, np.abs(x - pre - shift), 0.0)
        cost += np.concatenate([[0.0], np.cumsum(d_pre)]) \
            + np.concatenate([np.cumsum(d_post[::-1])[::-1], [0.0]])
    c = int(np.argmin(cost[:n]))
    tight, pre = (hi, pre_hi) if shift > 0 else (lo, pre_lo)
    while c < n - 1 and np.isfinite(tight[c]) \
            and abs(tight[c] - pre) < abs(tight[c] - pre - shift):
        c += 1
    return c


class ClockOffsetEstimator:
    """Offset and drift of one robot clock (see the module docstring).

    Parameters: ``bucket_s`` time bucket of the bounds kept (s); ``buckets`` how many are kept
    (memory: ``buckets`` x 4 floats); ``max_drift`` the drift bound (s/s) that clips the drift
    estimate and grows the uncertainty while no bound comes; ``asymmetry_s`` the expected
    ``d_up - d_down`` (s; 0: symmetric, the unidentifiable part); ``tolerance_s`` how far
    outside the band a bound may fall before it is held aside; ``confirm`` inconsistent bounds
    (none contradicted meanwhile) that re-anchor (a step); ``recent`` / ``step_k`` the in-band
    step test (the buckets it compares with the older ones, and the standard errors each side
    must move;
    ``min_step_s`` the least step it reports);
    ``max_offset_s`` an offset beyond which a bound is refused as implausible; ``max_rtt_s``
    a probe's longest round trip accepted; ``drift_span_s`` the shortest span of bounds the
    drift is fitted on (shorter, e.g. just after a step: the previous drift is kept, as a
    slope over a short span would be mostly jitter, unless the band it gives is inverted);
    ``refit_s`` the least time (s of bounds) between two fits of the drift and in-band step
    tests (each O(``buckets``); between them each bound moves the band in O(1)).
    """

    def __init__(self, *, bucket_s: float = 0.25, buckets: int = 1200, max_drift: float = 5e-4,
                 asymmetry_s: float = 0.0, tolerance_s: float = 1e-3, confirm: int = 4,
                 recent: int = 3, step_k: float = 3.0, min_step_s: float = 1e-3,
                 max_offset_s: float = 1e8, max_rtt_s: float = 30.0,
                 drift_span_s: float = 2.0, refit_s: float = 1.0) -> None:
        if not (bucket_s > 0 and buckets >= 2 * recent and recent >= 2 and confirm >= 1
                and max_drift >= 0 and tolerance_s >= 0 and step_k > 0 and max_rtt_s > 0):
            raise ValueError("clock offset estimator: bucket_s > 0, buckets >= 2 recent, "
                             "recent >= 2, confirm >= 1, max_drift, tolerance_s >= 0, "
                             "step_k, max_rtt_s > 0")
        self.bucket_s = bucket_s
        self.max_drift = max_drift
        self.asymmetry_s = asymmetry_s
        self.tolerance_s = tolerance_s
        self.confirm = confirm
        self.recent = recent
        self.step_k = step_k
        self.min_step_s = min_step_s
        self.max_offset_s = max_offset_s
        self.max_rtt_ns = int(max_rtt_s * 1e9)
        self.drift_span_s = drift_span_s
        self.refit_s = refit_s
        self._refitted = -np.inf  # s since the anchor of the last full refit
        self._buckets: deque[_Bucket] = deque(maxlen=buckets)
        self._anchor_ns: int | None = None
        self._drift = 0.0
        #: The drifts the kept bounds allow (s/s, :func:`drift_range`): how far a line
        #: through the band may tilt away from ``_drift``
        self._drift_lo, self._drift_hi = -max_drift, max_drift
        #: How far the drift may be off (s/s): half the two sides' slopes' difference, else
        #: max_drift (one side, or a span too short)
        self._drift_spread = max_drift
        self._band: tuple[float, float] = (-np.inf, np.inf)  # L, U detrended (s)
        self._pinned: tuple[float, float] = (0.0, 0.0)  # the times (s) of the bounds L, U
        self._newest = -np.inf  # s since the anchor of the newest bound
        # bounds outside the band, held until confirmed (a step) or contradicted
        self._pending_lo: list[tuple[float, float]] = []
        self._pending_hi: list[tuple[float, float]] = []
        self.counters = Tally({k: 0 for k in CLOCK_COUNTERS})
        #: Size (s) of the last step change detected (robot clock moved by it), 0.0 before.
        self.last_step_s = 0.0

    # --- input ---------------------------------------------------------------------------

    def add_probe(self, t1_ns: int, t2_ns: int, t3_ns: int, t4_ns: int) -> str | None:
        """One probe's quadruple (t1, t4 daemon clock; t2, t3 robot clock; ns). None if used,
        else the counter it was refused under ("probes_invalid": t4 < t1, t3 < t2, or a
        round trip over max_rtt; "implausible", "inconsistent" as :meth:`add_lower`)."""
        rtt = (t4_ns - t1_ns) - (t3_ns - t2_ns)
        if t4_ns < t1_ns or t3_ns < t2_ns or rtt < 0 or rtt > self.max_rtt_ns:
            self.counters["probes_invalid"] += 1
            return "probes_invalid"
        self.counters["probes"] += 1
        a = self.add_upper(self._event_ns(t2_ns, t1_ns, t4_ns), t2_ns - t1_ns)
        b = self.add_lower(self._event_ns(t3_ns, t1_ns, t4_ns), t3_ns - t4_ns)
        return a or b

    def add_one_way(self, robot_ns: int, recv_ns: int) -> str | None:
        """A robot stamp ``robot_ns`` received at daemon time ``recv_ns``: theta >= s - r."""
        return self.add_lower(self._event_ns(robot_ns, None, recv_ns), robot_ns - recv_ns)

    def add_echo(self, issued_ns: int, applied_ns: int) -> str | None:
        """A command issued (sent) at daemon time ``issued_ns`` and applied at robot time
        ``applied_ns``: theta <= applied - issued."""
        return self.add_upper(self._event_ns(applied_ns, issued_ns, None),
                              applied_ns - issued_ns)

    def add_lower(self, t_ns: int, value_ns: int) -> str | None:
        """theta(t) >= value (ns), t the daemon time of the robot's event. None if used, else
        "implausible" (|value| beyond max_offset_s) or "inconsistent" (above the band: held
        aside, a step if confirmed)."""
        return self._add(t_ns, value_ns, True)

    def add_upper(self, t_ns: int, value_ns: int) -> str | None:
        """theta(t) <= value (ns); outcomes as :meth:`add_lower`."""
        return self._add(t_ns, value_ns, False)

    def _event_ns(self, robot_ns: int, after_ns: int | None, before_ns: int | None) -> int:
        """The daemon time of a robot event stamped ``robot_ns``, mapped with the current
        estimate and kept within what the exchange bounds it to (sent ``after_ns``, received
        ``before_ns``); the bounds of one robot event then share a time bucket whichever way
        they travelled (the in-band step test compares buckets)."""
        ref = before_ns if before_ns is not None else after_ns
        assert ref is not None
        theta = self.estimate_at((ref - self._anchor_ns) * _NS) if self._anchor_ns is not None \
            else float("nan")
        t = robot_ns - round(theta * 1e9) if np.isfinite(theta) else ref
        if after_ns is not None:
            t = max(t, after_ns)
        if before_ns is not None:
            t = min(t, before_ns)
        return t

    def _add(self, t_ns: int, value_ns: int, lower: bool) -> str | None:
        if abs(value_ns) * _NS > self.max_offset_s:
            self.counters["implausible"] += 1
            return "implausible"
        if self._anchor_ns is None:
            self._anchor_ns = t_ns
        t = (t_ns - self._anchor_ns) * _NS
        v = value_ns * _NS
        d = v - self._drift * t  # detrended
        lo, hi = self._band
        tol = self.tolerance_s
        if lower and d > hi + tol:
            return self._hold(self._pending_lo, t, v)
        if not lower and d < lo - tol:
            return self._hold(self._pending_hi, t, v)
        # only a bound of the other kind contradicts held ones (theta >= l > u, beyond what
        # any drift allows between them): a looser one of their kind fits a step too (stamps
        # 600 ms late among probes 1 ms wide)
        held = self._pending_hi if lower else self._pending_lo
        if held and any((v - vp if lower else vp - v) > tol + self.max_drift * abs(t - tp)
                        for tp, vp in held):
            held.clear()
        opened = self._buckets[-1].index if self._buckets else None
        if not self._store(t, v, lower):  # most bounds are not their bucket's tightest
            return None
        # the band follows each bound at once (O(1)); the hulls (the drift), O(buckets), are
        # fitted when a bucket is opened and refit_s has passed, or when the band inverts
        # (the drift is off); the step test, O(recent), at every bucket opened
        t_lo, t_hi = self._pinned
        if lower and d > lo:
            lo, t_lo = d, t
        elif not lower and d < hi:
            hi, t_hi = d, t
        self._band = (lo, hi)
        self._pinned = (t_lo, t_hi)
        if lo > hi + tol or (self._buckets[-1].index != opened
                             and t - self._refitted >= self.refit_s):
            self._refitted = t
            self._refit()
        if self._buckets[-1].index != opened:
            self._step_inside_band()
        return None

    def _hold(self, pending: list[tuple[float, float]], t: float, v: float) -> str | None:
        self.counters["inconsistent"] += 1
        pending.append((t, v))
        if len(pending) < self.confirm:
            return "inconsistent"
        # a step: keep only what came since the first held bound, then the held ones
        first = pending[0][0]
        lower = pending is self._pending_lo
        held = list(pending)
        self._pending_lo.clear()
        self._pending_hi.clear()
        old = self.estimate_at(first)
        self._drop_before(first)
        for tp, vp in held:
            self._store(tp, vp, lower)
        self._refit()
        self._note_step(self.estimate_at(self._newest) - old)
        return None

    def _store(self, t: float, v: float, lower: bool) -> bool:
        """Keep the bound if it is its bucket's tightest; True iff it changed a bucket."""
        self.counters["bounds"] += 1
        self._newest = max(self._newest, t)
        index = math.floor(t / self.bucket_s)
        bs = self._buckets
        if not bs or bs[-1].index < index:
            bs.append(_Bucket(index))
            b = bs[-1]
        else:  # late or same bucket: find it (rare: the newest buckets first)
            b = next((x for x in reversed(bs) if x.index == index), None)  # type: ignore[assignment]
            if b is None:
                if index < bs[0].index:
                    if len(bs) == bs.maxlen:
                        return False  # older than everything kept, and no room
                    b = _Bucket(index)
                    bs.appendleft(b)
                else:
                    b = _Bucket(index)
                    pos = next(i for i, x in enumerate(bs) if x.index > index)
                    bs.insert(pos, b)
        if lower and v > b.lo:
            b.lo, b.t_lo = v, t
            return True
        if not lower and v < b.hi:
            b.hi, b.t_hi = v, t
            return True
        return False

    def _drop_before(self, t: float) -> None:
        index = int(np.floor(t / self.bucket_s))
        bs = self._buckets
        while bs and bs[0].index < index:
            bs.popleft()
        if bs and bs[0].index == index:  # the step's own bucket: its bounds predate it
            bs.popleft()

    # --- the fit -------------------------------------------------------------------------

    def _arrays(self, buckets: list[_Bucket] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        bs = list(self._buckets) if buckets is None else buckets
        tl = np.array([b.t_lo for b in bs if b.lo > -np.inf])
        vl = np.array([b.lo for b in bs if b.lo > -np.inf])
        th = np.array([b.t_hi for b in bs if b.hi < np.inf])
        vh = np.array([b.hi for b in bs if b.hi < np.inf])
        return tl, vl, th, vh

    def _refit(self) -> None:
        tl, vl, th, vh = self._arrays()
        lower = hull(tl, vl, True) if vl.size else []
        upper = hull(th, vh, False) if vh.size else []
        fits = ((edge_slope(lower, float(np.mean(tl))) if tl.size else None, _span(tl)),
                (edge_slope(upper, float(np.mean(th))) if th.size else None, _span(th)))
        for span in (self.drift_span_s, 0.0):  # a short span only if the band is inverted
            slopes = [s for s, sp in fits if s is not None and sp >= span]
            if slopes:
                self._drift = float(np.clip(np.mean(slopes), -self.max_drift, self.max_drift))
            self._drift_spread = min(self.max_drift, 0.5 * abs(slopes[0] - slopes[1])) \
                if len(slopes) == 2 and span > 0.0 else self.max_drift
            b = self._drift
            il = int(np.argmax(vl - b * tl)) if vl.size else -1
            ih = int(np.argmin(vh - b * th)) if vh.size else -1
            lo = float(vl[il] - b * tl[il]) if vl.size else -np.inf
            hi = float(vh[ih] - b * th[ih]) if vh.size else np.inf
            self._band = (lo, hi)
            self._pinned = (float(tl[il]) if vl.size else 0.0, float(th[ih]) if vh.size else 0.0)
            if lo <= hi:
                break
        # what tilt the bounds leave the line: one loose bound can set a hull's slope
        b_lo, b_hi = drift_range(lower, upper, self.max_drift)
        self._drift_lo, self._drift_hi = min(b_lo, b_hi, self._drift), max(b_lo, b_hi, self._drift)

    def _step_inside_band(self) -> None:
        """The in-band step test (module docstring, :func:`step_test`): the newest
        ``recent`` buckets holding both kinds against the (at most :data:`_OLD`) before
        them, less a guard of :data:`_GUARD` (one robot event's bounds may fall a bucket or
        two apart, mapped with an estimate off by up to its half-width). A bounded look
        back: the test runs at every bucket opened; the step's drop of the older buckets is
        what a refit sees."""
        kept = self._buckets
        bs = list(itertools.islice(kept, max(0, len(kept) - 2 * self.recent - _GUARD - _OLD),
                                   None))
        both = [i for i, b in enumerate(bs) if b.lo > -np.inf and b.hi < np.inf]
        n = self.recent
        if len(both) < 2 * n + _GUARD:
            return
        split = both[-n]
        old, new = bs[max(0, split - _GUARD - _OLD):max(0, split - _GUARD)], bs[split:]
        b = self._drift
        tl, vl, th, vh = self._arrays(new)
        ol, vol, oh, voh = self._arrays(old)
        if min(ol.size, oh.size) < _OLD // 2:  # too few to tell their spread
            return
        # what the spreads cannot show: the tolerance, and the drift's error over the time
        # between the two sets
        base = max(self.min_step_s, self.tolerance_s) / self.step_k
        gap_l = float(np.median(tl) - np.median(ol))
        gap_h = float(np.median(th) - np.median(oh))
        shift = step_test(vol - b * ol, vl - b * tl, voh - b * oh, vh - b * th, self.step_k,
                          math.hypot(base, self._drift_spread * gap_l),
                          math.hypot(base, self._drift_spread * gap_h))
        if shift is None or abs(shift) < self.min_step_s:
            return
        # where it happened: the medians put it somewhere in the newest buckets
        seg = bs[max(0, split - _GUARD):]
        lo = np.array([x.lo - b * x.t_lo for x in seg])
        hi = np.array([x.hi - b * x.t_hi for x in seg])
        pre_lo, pre_hi = float(np.median(vol - b * ol)), float(np.median(voh - b * oh))
        c = change_point(lo, hi, pre_lo, pre_hi, shift)
        moved = np.concatenate([lo[c:] - pre_lo, hi[c:] - pre_hi])
        first = len(bs) - len(seg) + c
        for _ in range(len(kept) - (len(bs) - first)):
            kept.popleft()
        self._refit()
        # its size: how far the buckets after it sit from the older ones (the estimate had
        # moved part of the way already)
        self._note_step(float(np.median(moved[np.isfinite(moved)])))

    def _note_step(self, size: float) -> None:
        self.counters["steps"] += 1
        if np.isfinite(size):
            self.last_step_s = size

    def estimate_at(self, t: float) -> float:
        """The offset (s) at ``t`` s since the anchor (nan when unknown)."""
        lo, hi = self._band
        if hi < np.inf and lo > -np.inf:
            mid = 0.5 * (lo + hi) - 0.5 * self.asymmetry_s
        elif lo > -np.inf:
            mid = lo
        elif hi < np.inf:
            mid = hi
        else:
            return float("nan")
        return mid + self._drift * t

    # --- output --------------------------------------------------------------------------

    def held_outside_s(self) -> float:
        """How far (s) the bounds held aside lie outside the band: a step the estimator
        suspects but has not confirmed (``confirm`` bounds re-anchor it), which the
        half-width does not include (0.0: none held). A held lower bound ``l`` at ``t``
        says theta(t) >= l, above the band's upper side U + b t by l - b t - U; a held upper
        bound alike below L."""
        lo, hi = self._band
        b = self._drift
        out = 0.0
        if np.isfinite(hi):
            for tp, vp in self._pending_lo:
                out = max(out, vp - b * tp - hi)
        if np.isfinite(lo):
            for tp, vp in self._pending_hi:
                out = max(out, lo - (vp - b * tp))
        return out

    def estimate(self, now_ns: int) -> OffsetEstimate:
        """The estimate at daemon time ``now_ns`` (ns)."""
        steps = self.counters["steps"]
        if self._anchor_ns is None or not self._buckets:
            return OffsetEstimate(now_ns, 0.0, 0.0, np.inf, -np.inf, np.inf, np.inf, steps, False)
        t = (now_ns - self._anchor_ns) * _NS
        b = self._drift
        lo, hi = self._band
        age = max(0.0, t - self._newest)
        grow = self.max_drift * age
        offset = self.estimate_at(t)
        # a line with drift b' in [b_lo, b_hi] still meets each bound that pins the band:
        # theta(t) >= L + b t - (b - b_lo) (t - t_L)^+ - (b_hi - b) (t_L - t)^+, and alike up
        t_lo, t_hi = self._pinned
        down_b, up_b = b - self._drift_lo, self._drift_hi - b
        tilt_lo = down_b * max(0.0, t - t_lo) + up_b * max(0.0, t_lo - t)
        tilt_hi = up_b * max(0.0, t - t_hi) + down_b * max(0.0, t_hi - t)
        lower, upper = lo + b * t - grow - tilt_lo, hi + b * t + grow + tilt_hi
        # an inverted band (bounds that contradict each other by x): x is the uncertainty
        half = 0.5 * abs(hi - lo) + max(tilt_lo, tilt_hi) + grow \
            if hi < np.inf and lo > -np.inf else np.inf
        return OffsetEstimate(now_ns, offset, b, half, lower, upper, age, steps, True)
