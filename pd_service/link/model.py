"""Pure, seeded netem-style decisions for one message stream.

No Zenoh, no clock reads: the caller passes each message's arrival time (integer ns on any
monotonic clock) and its payload, and gets back what to release and when, on the same clock::

    model = LinkModel(LinkParams(delay=DelaySpec(delay_ns=500_000_000)), seed="42/camera")
    decision = model.process(arrival_ns, payload)
    for rel in decision.releases:          # 0 (dropped), 1, or 2 (duplicated) copies
        publish_at(rel.time_ns, rel.payload)

The pipeline per message follows Linux ``sch_netem.c`` (``netem_enqueue``):

1. outage window: ``drop`` -> the message is gone; ``stall`` -> it is held and sent when the
   window ends (its send time becomes the window's end);
2. duplicate?  (``count = 1 + dup``);  loss?  (``count -= 1``);  ``count == 0`` -> dropped;
3. a duplicate copy is sent through the rest of the pipeline again with duplication off (as
   netem re-enqueues the clone at the root qdisc), so it meets the loss model once more;
4. corrupt?  flip one random bit in one random byte (``corrupt_bits`` times);
5. reorder?  when at least ``gap - 1`` messages were delayed since the last reordered one, with
   probability ``reorder`` the message is sent *immediately* (no delay, no rate limit), which
   lets it overtake the delayed ones;
6. otherwise delay = ``delay + jitter * t`` with ``t`` drawn from the distribution table;
7. rate limit: ``t_send = max(t_last, t_in + delay) + size / rate`` (netem: messages queue behind
   each other, so the link is never faster than ``rate``);
8. ``in_order`` (not in netem): ``t_send = max(t_send, t_last_release)``, i.e. a FIFO link
   where jitter never reorders.

Where pd-link departs from netem (on purpose, documented in docs/link.md):

* correlation.  netem mixes each uniform draw with the previous one
  (``u_n = (1 - rho) v + rho u_{n-1}``), which also changes the loss/duplicate/corrupt *rate* and
  narrows the jitter.  Here a "correlated percent" is a two-state Markov chain that keeps the
  rate at ``p`` and has lag-1 correlation ``rho`` exactly, and correlated delay uses a Gaussian
  AR(1) copula that keeps the delay distribution exactly and has rank correlation ~``rho``.
* state per stream.  Each concrete key gets its own model (own random streams, own Markov
  state, own rate queue) unless the rule says ``shared``, so runs repeat exactly regardless of
  how messages of different streams interleave.

Every random component has its own ``random.Random`` stream derived from the seed, so turning
on, e.g., duplication does not change which messages the loss model drops.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Literal

import numpy as np

NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000

Distribution = Literal["uniform", "normal", "pareto", "paretonormal"]
DISTRIBUTIONS: tuple[str, ...] = ("uniform", "normal", "pareto", "paretonormal")
OutageMode = Literal["drop", "stall"]

# netem's tables hold int16 values scaled by NETEM_DIST_SCALE = 8192, so |t| <= 32767/8192.
TABLE_LIMIT = 32767 / 8192
# netem's pareto.c: X = U^(-1/a) with a = 3 (mean a/(a-1) = 1.5), t = (X - 1.5) * 4/3.
PARETO_ALPHA = 3.0

_STD_NORMAL = NormalDist()
_SQRT2 = math.sqrt(2.0)


# --- parameters ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DelaySpec:
    """netem ``delay TIME [JITTER [CORRELATION]] [distribution D]``.

    ``delay_ns``, ``jitter_ns``: integer ns, >= 0.  ``correlation``: fraction in [0, 1).
    The delay of one message is ``max(0, delay_ns + jitter_ns * t)``, ``t`` ~ ``distribution``:
    uniform on [-1, 1); standard normal; netem's pareto; netem's paretonormal (see
    :func:`quantile`).
    """

    delay_ns: int = 0
    jitter_ns: int = 0
    correlation: float = 0.0
    distribution: Distribution = "uniform"

    def __post_init__(self) -> None:
        _check_int(self.delay_ns, "delay_ns", lo=0)
        _check_int(self.jitter_ns, "jitter_ns", lo=0)
        _check_prob(self.correlation, "delay correlation", upper_open=True)
        if self.distribution not in DISTRIBUTIONS:
            raise ValueError(
                f"distribution {self.distribution!r} must be one of {', '.join(DISTRIBUTIONS)}"
            )


@dataclass(frozen=True, slots=True)
class RandomLoss:
    """netem ``loss random P [CORR]``: P(loss) = ``p``; lag-1 correlation ``correlation``.

    As a Markov chain on "was the last message lost":
    P(lost | last lost) = p + rho (1 - p),  P(lost | last delivered) = p (1 - rho).
    Mean loss rate p, mean burst length 1 / ((1 - p)(1 - rho)).
    """

    p: float
    correlation: float = 0.0

    def __post_init__(self) -> None:
        _check_prob(self.p, "loss")
        _check_prob(self.correlation, "loss correlation", upper_open=True)


@dataclass(frozen=True, slots=True)
class GilbertElliott:
    """netem ``loss gemodel p [r [1-h [1-k]]]``.

    Two states, Good and Bad.  Per message: first the state moves (G->B with ``p``, B->G with
    ``r``), then the message is lost with probability ``one_minus_k`` in Good and
    ``one_minus_h`` in Bad.  netem's defaults: r = 1 - p, 1-h = 1, 1-k = 0 (with only ``p`` and
    ``r`` given this is the "simple Gilbert" model: loss rate p/(p+r), mean burst 1/r).
    """

    p: float
    r: float
    one_minus_h: float = 1.0
    one_minus_k: float = 0.0

    def __post_init__(self) -> None:
        for name in ("p", "r", "one_minus_h", "one_minus_k"):
            _check_prob(getattr(self, name), f"gemodel {name.replace('one_minus_', '1-')}")
        if self.p == 0 and self.r == 0:
            raise ValueError("gemodel: p and r cannot both be 0 (the chain would never move)")


@dataclass(frozen=True, slots=True)
class FourStateLoss:
    """netem ``loss state p13 [p31 [p32 [p23 [p14]]]]`` (Salsano et al., the "GI" model).

    States: 1 = delivered, gap period; 2 = delivered, burst period; 3 = lost, burst period;
    4 = isolated loss in the gap period.  Transitions 1->3 ``p13``, 1->4 ``p14``, 3->1 ``p31``,
    3->2 ``p32``, 2->3 ``p23``, 4->1 always; a message is lost iff the new state is 3 or 4.
    netem's defaults: p31 = 1 - p13, p32 = 0, p23 = 1, p14 = 0.
    """

    p13: float
    p31: float
    p32: float = 0.0
    p23: float = 1.0
    p14: float = 0.0

    def __post_init__(self) -> None:
        for name in ("p13", "p31", "p32", "p23", "p14"):
            _check_prob(getattr(self, name), f"state {name}")
        if self.p13 + self.p14 > 1.0 + 1e-12:
            raise ValueError("state: p13 + p14 must be <= 100%")
        if self.p31 + self.p32 > 1.0 + 1e-12:
            raise ValueError("state: p31 + p32 must be <= 100%")


LossSpec = RandomLoss | GilbertElliott | FourStateLoss


@dataclass(frozen=True, slots=True)
class Outage:
    """A window during which the link is down: ``[start_ns, start_ns + duration_ns)``.

    Times are integer ns relative to the model's epoch (pd-link: when the rule set took
    effect).  With ``every_ns > 0`` the window repeats every ``every_ns`` from ``start_ns`` on.
    """

    start_ns: int
    duration_ns: int
    every_ns: int = 0

    def __post_init__(self) -> None:
        _check_int(self.start_ns, "outage start", lo=0)
        _check_int(self.duration_ns, "outage duration", lo=1)
        _check_int(self.every_ns, "outage period", lo=0)
        if self.every_ns and self.every_ns <= self.duration_ns:
            raise ValueError("outage: the period ('every') must be longer than the duration")

    def end_if_inside(self, t_rel: int) -> int | None:
        """End (relative ns) of the window containing ``t_rel``, or None if the link is up."""
        if t_rel < self.start_ns:
            return None
        s = self.start_ns
        if self.every_ns:
            s += ((t_rel - self.start_ns) // self.every_ns) * self.every_ns
        end = s + self.duration_ns
        return end if t_rel < end else None


@dataclass(frozen=True, slots=True)
class Rate:
    """netem ``rate RATE [PACKETOVERHEAD]``, or a message rate.

    Exactly one of ``bytes_per_s`` / ``msgs_per_s`` is set.  Transmission time of one message:
    ``(len(payload) + overhead_bytes) / bytes_per_s`` or ``1 / msgs_per_s`` seconds.
    """

    bytes_per_s: float | None = None
    msgs_per_s: float | None = None
    overhead_bytes: int = 0

    def __post_init__(self) -> None:
        if (self.bytes_per_s is None) == (self.msgs_per_s is None):
            raise ValueError("rate: give exactly one of bytes/s or messages/s")
        value = self.bytes_per_s if self.bytes_per_s is not None else self.msgs_per_s
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"rate must be a finite number > 0, got {value!r}")
        _check_int(self.overhead_bytes, "packet_overhead")

    def transmit_ns(self, size: int) -> int:
        """Time on the wire of one message of ``size`` bytes, integer ns."""
        if self.msgs_per_s is not None:
            return round(NS_PER_S / self.msgs_per_s)
        assert self.bytes_per_s is not None
        return round(max(0, size + self.overhead_bytes) * NS_PER_S / self.bytes_per_s)


@dataclass(frozen=True, slots=True)
class LinkParams:
    """Everything one rule does to a message.  Probabilities are fractions in [0, 1]."""

    delay: DelaySpec = field(default_factory=DelaySpec)
    loss: LossSpec | None = None
    duplicate: float = 0.0
    duplicate_correlation: float = 0.0
    reorder: float = 0.0
    reorder_correlation: float = 0.0
    gap: int = 1
    corrupt: float = 0.0
    corrupt_correlation: float = 0.0
    corrupt_bits: int = 1
    rate: Rate | None = None
    outages: tuple[Outage, ...] = ()
    outage_mode: OutageMode = "drop"
    in_order: bool = False

    def __post_init__(self) -> None:
        for name in ("duplicate", "reorder", "corrupt"):
            _check_prob(getattr(self, name), name)
            _check_prob(getattr(self, f"{name}_correlation"), f"{name} correlation",
                        upper_open=True)
        _check_int(self.gap, "gap", lo=1)
        _check_int(self.corrupt_bits, "corrupt_bits", lo=1)
        if self.reorder > 0 and self.delay.delay_ns == 0:
            # tc: "reordering not possible without specifying some delay"
            raise ValueError("reorder needs some delay (reordered messages overtake delayed ones)")
        if self.outage_mode not in ("drop", "stall"):
            raise ValueError(f"outage_mode {self.outage_mode!r} must be 'drop' or 'stall'")
        if self.loss is not None and not isinstance(
            self.loss, RandomLoss | GilbertElliott | FourStateLoss
        ):
            raise ValueError(f"loss must be a loss model, got {type(self.loss).__name__}")


# --- decisions -------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Release:
    """One copy to publish at ``time_ns`` (same clock as the arrival time)."""

    time_ns: int
    payload: bytes
    duplicate: bool = False
    reordered: bool = False
    corrupted: bool = False


@dataclass(frozen=True, slots=True)
class Decision:
    """What happens to one input message.

    ``releases``: 0, 1 or 2 copies.  ``dropped``: None, ``"loss"`` or ``"outage"`` (set iff no
    copy survives).  ``stalled``: the message was held by an outage in ``stall`` mode.
    """

    releases: tuple[Release, ...]
    dropped: Literal["loss", "outage"] | None = None
    stalled: bool = False


# --- distributions ---------------------------------------------------------------------


def quantile(distribution: str, u: float) -> float:
    """Quantile function of netem's jitter tables, ``t = Q(u)`` for ``u`` in [0, 1).

    * uniform:       t = 2u - 1                                  (netem without a table)
    * normal:        t = Phi^-1(u)                               (normal.dist)
    * pareto:        t = ((1 - u)^(-1/3) - 1.5) * 4/3             (pareto.c, a = 3)
    * paretonormal:  t = (Phi^-1(u) + 3 * pareto(u)) / 4          (paretonormal.c: the two
      quantile functions averaged 1:3 at the same u)

    Tabled values are clipped to +-32767/8192 (~ +-4) as netem's int16 tables are.
    """
    if distribution == "uniform":
        return 2.0 * u - 1.0
    if distribution == "normal":
        return _clip(_norm_ppf(u))
    if distribution == "pareto":
        return _clip(_pareto_t(u))
    if distribution == "paretonormal":
        return _clip((_clip(_norm_ppf(u)) + 3.0 * _clip(_pareto_t(u))) / 4.0)
    raise ValueError(f"unknown distribution {distribution!r}")


def _norm_ppf(u: float) -> float:
    return _STD_NORMAL.inv_cdf(min(max(u, 1e-15), 1.0 - 1e-15))


def _norm_cdf(z: float) -> float:
    # Phi(z) = (1 + erf(z / sqrt 2)) / 2
    return 0.5 * (1.0 + math.erf(z / _SQRT2))


def _pareto_t(u: float) -> float:
    # X = (1 - u)^(-1/a) ~ Pareto(x_m = 1, a = 3): mean 1.5, std sqrt(3)/2;  t = (X - 1.5) 4/3
    return ((1.0 - u) ** (-1.0 / PARETO_ALPHA) - 1.5) * (4.0 / 3.0)


def _clip(t: float) -> float:
    return TABLE_LIMIT if t > TABLE_LIMIT else (-TABLE_LIMIT if t < -TABLE_LIMIT else t)


# --- random components -----------------------------------------------------------------


class CorrelatedBernoulli:
    """Bernoulli(p) events with lag-1 correlation rho, as a two-state Markov chain.

    P(X_n = 1 | X_{n-1} = 1) = p + rho (1 - p)
    P(X_n = 1 | X_{n-1} = 0) = p (1 - rho)
    The stationary P(X = 1) stays p; corr(X_n, X_{n-1}) = rho; the first draw is Bernoulli(p).
    """

    __slots__ = ("_rng", "_p", "_after_1", "_after_0", "_last")

    def __init__(self, p: float, rho: float, rng: random.Random) -> None:
        self._rng = rng
        self._p = p
        self._after_1 = p + rho * (1.0 - p)
        self._after_0 = p * (1.0 - rho)
        self._last: bool | None = None

    def draw(self) -> bool:
        last = self._last
        threshold = self._p if last is None else (self._after_1 if last else self._after_0)
        x = self._rng.random() < threshold
        self._last = x
        return x


class DelaySampler:
    """Draws one message's delay (integer ns) from a :class:`DelaySpec`.

    Without correlation ``u ~ U[0, 1)``.  With correlation rho, a Gaussian AR(1) drives it:
    z_n = rho z_{n-1} + sqrt(1 - rho^2) e_n,  e_n ~ N(0, 1),  u_n = Phi(z_n)
    so u_n stays exactly uniform (the delay keeps its distribution) and consecutive delays are
    correlated (Pearson correlation exactly rho for the normal distribution).
    delay = max(0, delay + jitter * Q(u)).
    """

    __slots__ = ("_spec", "_rng", "_z", "_rho", "_innov")

    def __init__(self, spec: DelaySpec, rng: random.Random) -> None:
        self._spec = spec
        self._rng = rng
        self._rho = spec.correlation
        self._innov = math.sqrt(1.0 - spec.correlation**2)
        self._z: float | None = None

    def draw(self) -> int:
        spec = self._spec
        if spec.jitter_ns == 0:
            return spec.delay_ns
        if self._rho == 0.0:
            u = self._rng.random()
            t = quantile(spec.distribution, u)
        else:
            e = self._rng.gauss(0.0, 1.0)
            z = e if self._z is None else self._rho * self._z + self._innov * e
            self._z = z
            t = _clip(z) if spec.distribution == "normal" else quantile(
                spec.distribution, _norm_cdf(z)
            )
        return max(0, spec.delay_ns + round(spec.jitter_ns * t))


class _LossProcess:
    """Per-message loss decision of one loss model (stateful)."""

    __slots__ = ("_spec", "_rng", "_state", "_bern")

    def __init__(self, spec: LossSpec, rng: random.Random) -> None:
        self._spec = spec
        self._rng = rng
        self._state = 1  # GE: 1 = Good, 2 = Bad.  4-state: 1..4, starts in 1 as netem
        self._bern = (
            CorrelatedBernoulli(spec.p, spec.correlation, rng)
            if isinstance(spec, RandomLoss)
            else None
        )

    def lost(self) -> bool:
        if self._bern is not None:
            return self._bern.draw()
        spec = self._spec
        rnd = self._rng.random
        if isinstance(spec, GilbertElliott):
            # transition first, then the loss draw in the new state (netem loss_gilb_ell)
            if self._state == 1:
                if rnd() < spec.p:
                    self._state = 2
            elif rnd() < spec.r:
                self._state = 1
            loss_p = spec.one_minus_k if self._state == 1 else spec.one_minus_h
            return rnd() < loss_p
        assert isinstance(spec, FourStateLoss)
        u = rnd()
        s = self._state
        if s == 1:
            if u < spec.p14:
                self._state = 4
            elif u < spec.p14 + spec.p13:
                self._state = 3
        elif s == 2:
            if u < spec.p23:
                self._state = 3
        elif s == 3:
            if u < spec.p32:
                self._state = 2
            elif u < spec.p32 + spec.p31:
                self._state = 1
        else:  # 4 -> 1 always
            self._state = 1
        return self._state >= 3


# --- the model -------------------------------------------------------------------------


class LinkModel:
    """netem-style decisions for one stream (see the module docstring for the pipeline).

    ``seed``: anything ``random.Random`` accepts (int or str); each component derives its own
    stream from it.  ``epoch_ns``: the time outage windows are relative to.
    Not thread-safe: one caller at a time.
    """

    def __init__(self, params: LinkParams, seed: int | str = 0, epoch_ns: int = 0) -> None:
        if not isinstance(params, LinkParams):
            raise ValueError("params must be LinkParams")
        self.params = params
        self.epoch_ns = int(epoch_ns)

        def stream(name: str) -> random.Random:
            return random.Random(f"{seed}/{name}")

        p = params
        self._delay = DelaySampler(p.delay, stream("delay"))
        self._loss = _LossProcess(p.loss, stream("loss")) if p.loss is not None else None
        self._dup = (
            CorrelatedBernoulli(p.duplicate, p.duplicate_correlation, stream("duplicate"))
            if p.duplicate > 0
            else None
        )
        self._reorder = (
            CorrelatedBernoulli(p.reorder, p.reorder_correlation, stream("reorder"))
            if p.reorder > 0
            else None
        )
        self._corrupt = (
            CorrelatedBernoulli(p.corrupt, p.corrupt_correlation, stream("corrupt"))
            if p.corrupt > 0
            else None
        )
        self._flip_rng = stream("corrupt-position")
        self._counter = 0  # messages delayed since the last reordered one (netem q->counter)
        self._last_tx_ns: int | None = None  # rate limiter: when the link is free again
        self._last_release_ns: int | None = None  # in_order

    # one message ------------------------------------------------------------------------

    def process(self, arrival_ns: int, payload: bytes) -> Decision:
        """Decide the fate of one message that reached the link at ``arrival_ns``."""
        t = int(arrival_ns)
        payload = bytes(payload)
        stalled = False
        if self.params.outages:
            end = self._outage_end(t)
            if end is not None:
                if self.params.outage_mode == "drop":
                    return Decision((), "outage")
                t, stalled = end, True

        count = 1
        if self._dup is not None and self._dup.draw():
            count += 1
        if self._loss is not None and self._loss.lost():
            count -= 1
        if count == 0:
            return Decision((), "loss", stalled)

        releases: list[Release] = []
        if count == 2:
            # netem enqueues the clone first, through the whole qdisc with duplication off,
            # so the copy meets the loss model again.
            if self._loss is None or not self._loss.lost():
                releases.append(self._send(t, payload, duplicate=True))
        releases.append(self._send(t, payload, duplicate=False))
        return Decision(tuple(releases), None, stalled)

    def _send(self, t: int, payload: bytes, duplicate: bool) -> Release:
        corrupted = False
        if self._corrupt is not None and self._corrupt.draw() and payload:
            payload = self._flip(payload)
            corrupted = True

        gap = self.params.gap
        if self._reorder is not None and self._counter >= gap - 1 and self._reorder.draw():
            # netem: "put one out of N packets at the front of the queue": sent now.
            self._counter = 0
            return Release(t, payload, duplicate, True, corrupted)

        release = t + self._delay.draw()
        self._counter += 1
        rate = self.params.rate
        if rate is not None:
            # t_send = max(t_link_free, t_in + delay) + size / rate
            if self._last_tx_ns is not None and self._last_tx_ns > release:
                release = self._last_tx_ns
            release += rate.transmit_ns(len(payload))
            self._last_tx_ns = release
        if self.params.in_order:
            if self._last_release_ns is not None and release < self._last_release_ns:
                release = self._last_release_ns
            self._last_release_ns = release
        return Release(release, payload, duplicate, False, corrupted)

    def _flip(self, payload: bytes) -> bytes:
        # netem: skb->data[rand % len] ^= 1 << (rand % 8)
        buf = bytearray(payload)
        rng = self._flip_rng
        for _ in range(self.params.corrupt_bits):
            buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
        return bytes(buf)

    def _outage_end(self, t: int) -> int | None:
        """Absolute end of the outage containing ``t`` (chained windows followed), or None."""
        rel = t - self.epoch_ns
        end_rel: int | None = None
        for _ in range(64):  # follow back-to-back windows; bounded
            found = None
            for w in self.params.outages:
                e = w.end_if_inside(rel if end_rel is None else end_rel)
                if e is not None and (found is None or e > found):
                    found = e
            if found is None:
                break
            end_rel = found
        return None if end_rel is None else self.epoch_ns + end_rel


# --- theory (for tests, docs and the startup log) ----------------------------------------


def loss_chain(spec: LossSpec) -> tuple[np.ndarray, np.ndarray]:
    """Transition matrix ``T`` (row-stochastic, shape (S, S)) and per-state loss probability
    ``l`` (shape (S,)) of a loss model, with the convention "move, then lose in the new state".
    """
    if isinstance(spec, RandomLoss):
        p, rho = spec.p, spec.correlation
        a = p * (1 - rho)  # delivered -> lost
        b = p + rho * (1 - p)  # lost -> lost
        return np.array([[1 - a, a], [1 - b, b]]), np.array([0.0, 1.0])
    if isinstance(spec, GilbertElliott):
        return (
            np.array([[1 - spec.p, spec.p], [spec.r, 1 - spec.r]]),
            np.array([spec.one_minus_k, spec.one_minus_h]),
        )
    if isinstance(spec, FourStateLoss):
        s = spec
        T = np.array(
            [
                [1 - s.p13 - s.p14, 0.0, s.p13, s.p14],
                [0.0, 1 - s.p23, s.p23, 0.0],
                [s.p31, s.p32, 1 - s.p31 - s.p32, 0.0],
                [1.0, 0.0, 0.0, 0.0],
            ]
        )
        return T, np.array([0.0, 0.0, 1.0, 1.0])
    raise ValueError(f"not a loss model: {spec!r}")


def loss_theory(spec: LossSpec) -> tuple[float, float]:
    """Stationary loss rate and mean loss-burst length (messages) of a loss model.

    pi = stationary distribution of T (pi T = pi, sum pi = 1);
    rate = sum_s pi_s l_s;
    P(delivered, then lost) = sum_{s,s'} pi_s (1 - l_s) T_ss' l_s';
    mean burst = rate / P(delivered, then lost)  (losses per burst).
    Returns (rate, inf) if bursts never end and (0, 0) if nothing is ever lost.
    """
    T, l = loss_chain(spec)
    n = T.shape[0]
    # solve pi (T - I) = 0 with sum(pi) = 1 (least squares on the stacked system)
    A = np.vstack([(T - np.eye(n)).T, np.ones(n)])
    rhs = np.zeros(n + 1)
    rhs[-1] = 1.0
    pi, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    rate = float(pi @ l)
    starts = float((pi * (1 - l)) @ T @ l)
    if rate <= 0:
        return 0.0, 0.0
    if starts <= 0:
        return rate, math.inf
    return rate, rate / starts


def reorder_theory(reorder: float, gap: int) -> float:
    """Fraction of messages sent out of turn by netem's reorder with uncorrelated draws.

    A cycle is ``gap - 1`` forced delays, then Geometric trials until one is reordered:
    mean cycle length = gap - 1 + 1/reorder, one reordered message per cycle.
    """
    if reorder <= 0:
        return 0.0
    return 1.0 / (gap - 1 + 1.0 / reorder)


# --- validation helpers ----------------------------------------------------------------


def _check_prob(x: float, what: str, *, upper_open: bool = False) -> None:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        raise ValueError(f"{what} must be a number, got {x!r}")
    if x < 0 or x > 1 or (upper_open and x >= 1):
        bound = "100%)" if upper_open else "100%]"
        raise ValueError(f"{what} must be in [0%, {bound}, got {x * 100:g}%")


def _check_int(x: int, what: str, *, lo: int | None = None) -> None:
    if isinstance(x, bool) or not isinstance(x, int):
        raise ValueError(f"{what} must be an integer, got {x!r}")
    if lo is not None and x < lo:
        raise ValueError(f"{what} must be >= {lo}, got {x}")
