"""Linear-coding state estimators under random bounded delay and packet loss (a baseline).

Source: linear-coding-delay-loss-zh (Lu, Wang, Jiang, Gao, Computer Simulation 2022/1). The
text we have lost almost every displayed formula (only equation numbers survive), so the
equations below are re-derived from the surviving prose and the cited structure; each
re-derivation is marked "derived" in a comment. Their correctness is pinned by tests that
compare every online variant with brute-force joint-Gaussian conditioning, and the offline
one with Monte Carlo.

Plant (paper eq. 1-3), no control input:

    x(k+1) = A x(k) + w̄(k),     w̄ = Γ w,  Cov(w̄) = Q = Γ W Γᵀ           (n states)
    y(k)   = C x(k) + v(k),      Cov(v) = R = V,  E[w̄(k) v(k)ᵀ] = S = Γ S_paper  (m outputs)

Every y(k) is sent once, stamped k, and arrives after a random delay 0..d or never (see
:mod:`pd_service.research.delay_model`); a_i(k) = 1 iff y(k - i) arrives at step k. All
packets that arrive in one step are coded into ONE m-vector with fixed weights beta_i:

    z(k) = sum_{i=0..d} beta_i a_i(k) y(k - i)                               (paper eq. 8-9)

Estimators here (all give x̂(k|k): the estimate of x(k) from what has arrived by step k):

* :class:`CodedOnlineEstimator`: uses the realised a_i(k) (paper section 5, "online");
  augmented state xi(k) = [x(k); y(k-1); ...; y(k-d)] makes z(k) a plain linear
  measurement of xi(k); gains with the Moore-Penrose inverse (paper eq. 59-60).
* :class:`NewestPacketEstimator`: the same filter fed only the newest packet of each step
  (the paper's reference [9]); older packets arriving in the same step are discarded.
* :class:`OfflineCodedEstimator`: gains from the hazards alpha_i and beta only (paper
  sections 3-4, "offline"); the a_i(k) enter as random parameters. Its gains need the
  state's second moment q(k) = E[X Xᵀ] (paper Lemma 1), which is bounded, so the gains are
  stationary, iff the plant is stable: spectral radius of A < 1. On an unstable or
  marginally stable plant (constant-velocity target) q(k) grows without bound and so does
  the estimator's error covariance.
* :class:`TimestampReplayKF`: the exact reference (every arrived packet used at its stamp,
  Kalman filter re-run over the last d stamps); handles S ≠ 0.

All four are linear minimum-mean-square-error estimators for the information they use.
Only the exact replay uses all of it; the coded ones lose information whenever two or more
packets arrive in the same step (the sum cannot be un-mixed), the offline one also loses
the arrival pattern. See docs/linear-coding.md for measured costs.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pd_service.estimation.checks import as_covariance, as_matrix, as_vector

from .delay_model import DelayModel

__all__ = [
    "CorrelatedPlant",
    "CodedEstimate",
    "CodedOnlineEstimator",
    "NewestPacketEstimator",
    "OfflineCodedEstimator",
    "TimestampReplayKF",
    "is_stationary",
]

Array = NDArray[np.float64]

Packets = Iterable[tuple[int, ArrayLike]]
"""Packets received in one step: pairs (stamp, y) with y of shape (m,)."""


# ---------------------------------------------------------------------------- validation
def _matrix(name: str, value: ArrayLike, shape: tuple[int, int]) -> Array:
    """:func:`pd_service.estimation.checks.as_matrix`, also taking a vector (shape[0],) for a column."""
    a = np.asarray(value)
    if a.ndim == 1 and shape[1] == 1 and a.shape[0] == shape[0]:
        a = a.reshape(shape)
    return as_matrix(a, name, shape)


def _vector(name: str, value: ArrayLike, size: int) -> Array:
    """:func:`pd_service.estimation.checks.as_vector`, also taking a scalar when size is 1."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected {size} numbers") from None
    return as_vector(a.reshape(1) if a.ndim == 0 else a, name, size)


@dataclass(frozen=True)
class CorrelatedPlant:
    """x(k+1) = A x(k) + w̄(k),  y(k) = C x(k) + v(k),  with E[w̄(k) v(k)ᵀ] = S.

    Attributes (shapes): A (n, n); C (m, n); Q = Cov(w̄) (n, n); R = Cov(v) (m, m);
    S = E[w̄(k) v(k)ᵀ] (n, m), zeros if omitted. The joint covariance [[Q, S], [Sᵀ, R]]
    must be positive semi-definite; R must be positive definite (paper: V > 0).
    """

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    S: np.ndarray | None = None

    def __post_init__(self) -> None:
        A = np.array(self.A, dtype=float)
        if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
            raise ValueError(f"A: expected a square (n, n) matrix, got shape {A.shape}")
        n = A.shape[0]
        A = _matrix("A", A, (n, n))
        C = np.array(self.C, dtype=float)
        if C.ndim == 1 and C.size == n:
            C = C.reshape(1, n)
        if C.ndim != 2 or C.shape[1] != n or C.shape[0] == 0:
            raise ValueError(f"C: expected shape (m, {n}), got {C.shape}")
        m = C.shape[0]
        C = _matrix("C", C, (m, n))
        Q = as_covariance(_matrix("Q", self.Q, (n, n)), "Q")
        R = as_covariance(_matrix("R", self.R, (m, m)), "R")
        if np.min(np.linalg.eigvalsh(R)) <= 0.0:
            raise ValueError("R: must be positive definite")
        S = np.zeros((n, m)) if self.S is None else _matrix("S", self.S, (n, m))
        as_covariance(np.block([[Q, S], [S.T, R]]), "[[Q, S], [S.T, R]]")
        for name, val in (("A", A), ("C", C), ("Q", Q), ("R", R), ("S", S)):
            val.setflags(write=False)
            object.__setattr__(self, name, val)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.A.shape[0]

    @property
    def m(self) -> int:
        """Measurement dimension."""
        return self.C.shape[0]


def is_stationary(plant: CorrelatedPlant) -> bool:
    """Stationarity condition of the offline estimator: spectral radius of A < 1.

    The offline gains depend on q(k) = E[X(k) X(k)ᵀ] (paper Lemma 1), whose state block obeys
    q_x(k+1) = A q_x(k) Aᵀ + Q; it converges iff A is Schur stable (for Q > 0 on the unstable
    modes). The pending-packet blocks contract by the factors (1 - alpha_i) and add nothing.
    """
    return bool(np.max(np.abs(np.linalg.eigvals(plant.A))) < 1.0)


@dataclass(frozen=True)
class CodedEstimate:
    """Estimate of x(step) from what arrived by ``step``: ``x`` (n,), covariance ``P`` (n, n)."""

    step: int
    x: np.ndarray
    P: np.ndarray


def _pinv_psd(a: np.ndarray) -> np.ndarray:
    """Moore-Penrose inverse of a symmetric PSD matrix (eigen-decomposition, relative cutoff)."""
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    cut = 1e-12 * max(float(w[-1]), 0.0) if w.size else 0.0
    inv = np.where(w > cut, 1.0 / np.where(w > cut, w, 1.0), 0.0)
    return (v * inv) @ v.T


def _as_step(value: object, name: str = "now") -> int:
    """``value`` as an integer step, else ValueError naming ``name``."""
    if isinstance(value, bool | np.bool_):
        raise ValueError(f"{name}: expected an integer step, got {value!r}")
    try:
        as_int = int(value)  # type: ignore[call-overload]
        ok = as_int == value
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ValueError(f"{name}: expected an integer step, got {value!r}")
    return as_int


class _PacketGate:
    """Validates the packets of one step: stamps in [now - d, now], each stamp at most once."""

    def __init__(self, m: int, max_delay: int) -> None:
        self.m = m
        self.d = max_delay
        self.next_step = 0
        self._seen: set[int] = set()

    def accept(self, now: int, packets: Packets) -> list[tuple[int, np.ndarray]]:
        """Return [(delay, y)] sorted by delay; raise ValueError (state unchanged) on bad input."""
        if _as_step(now) != self.next_step:
            raise ValueError(f"now: expected step {self.next_step} (one call per step), got {now!r}")
        now = int(now)
        out: dict[int, np.ndarray] = {}
        try:
            items = list(packets)
        except TypeError:
            raise ValueError("packets: expected an iterable of (stamp, y) pairs") from None
        for item in items:
            try:
                stamp, y = item
            except (TypeError, ValueError):
                raise ValueError("packets: expected (stamp, y) pairs") from None
            stamp = _as_step(stamp, "stamp")
            delay = now - stamp
            if delay < 0:
                raise ValueError(f"stamp: {stamp} is in the future of step {now}")
            if delay > self.d:
                raise ValueError(f"stamp: {stamp} is older than max_delay={self.d} at step {now}")
            if delay in out or stamp in self._seen:
                raise ValueError(f"stamp: packet {stamp} received twice")
            out[delay] = _vector(f"y (stamp {stamp})", y, self.m)
        self.next_step += 1
        self._seen.update(now - i for i in out)
        self._seen = {s for s in self._seen if s > now - self.d}
        return sorted(out.items())


def _check_beta(beta: ArrayLike, d: int) -> np.ndarray:
    b = np.array(beta, dtype=float).reshape(-1)
    if b.shape != (d + 1,):
        raise ValueError(f"beta: expected shape ({d + 1},) (one weight per delay 0..d), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("beta: values must be finite")
    return b


# ---------------------------------------------------------------------------- online coding
class CodedOnlineEstimator:
    """Online linear-coding estimator: gains from the realised arrivals a_i(k).

    Augmented state (dimension N = n + d m), derived from the paper's eq. 4:

        xi(k) = [x(k); y(k-1); ...; y(k-d)]
        xi(k+1) = F xi(k) + g(k),    F = [[A, 0, ..., 0], [C, 0, ..., 0], [0, I, 0, ...], ...]
        g(k) = [w̄(k); v(k); 0; ...; 0],   Cov(g) = Q_xi = [[Q, S, 0], [Sᵀ, R, 0], [0, 0, 0]]

    Keeping y(k-1..k-d) themselves (not C x) in the state carries the w-v correlation exactly:
    y(k-1) holds v(k-1), which x(k) shares through w̄(k-1) (block S of Q_xi).

    Coded measurement with the realised indicators (c_i = beta_i a_i(k)):

        z(k) = H(k) xi(k) + c_0 v(k),   H(k) = [c_0 C, c_1 I, ..., c_d I]

    Its noise c_0 v(k) is correlated with g(k): M(k) = E[g(k) (c_0 v(k))ᵀ] = c_0 [S; R; 0].
    One step (innovations form, Anderson & Moore ch. 5; derived: the paper's eq. 57-62 lost):

        eps   = z - H xi^(k|k-1)            Q_eps = H P Hᵀ + c_0² R
        K     = P Hᵀ Q_eps⁺                 xi^(k|k)   = xi^(k|k-1) + K eps
        L     = (F P Hᵀ + M) Q_eps⁺         xi^(k+1|k) = F xi^(k|k-1) + L eps
        P(k|k) = P - K Q_eps Kᵀ             P(k+1|k)   = F P Fᵀ + Q_xi - L Q_eps Lᵀ

    ⁺ is the Moore-Penrose inverse. With no arrival, H = 0, Q_eps = 0, Q_eps⁺ = 0 and the
    step is a pure prediction (taken as a shortcut: identical result, no decomposition).

    Args:
        plant: the system.
        max_delay: d >= 0; packets older than d steps cannot be used (treated as lost).
        beta: shape (d + 1,), coding weight for each delay value 0..d.
        x0: (n,) prior mean of x(0).  P0: (n, n) prior covariance.
        The paper sets y(-i) = 0: those state entries start known and zero.
    """

    def __init__(
        self,
        plant: CorrelatedPlant,
        max_delay: int,
        beta: ArrayLike,
        x0: ArrayLike,
        P0: ArrayLike,
    ) -> None:
        if not isinstance(plant, CorrelatedPlant):
            raise ValueError("plant: expected a CorrelatedPlant")
        if isinstance(max_delay, bool) or int(max_delay) != max_delay or max_delay < 0:
            raise ValueError(f"max_delay: expected an integer >= 0, got {max_delay!r}")
        d = int(max_delay)
        n, m = plant.n, plant.m
        self.plant = plant
        self.max_delay = d
        self.beta = _check_beta(beta, d)
        N = n + d * m
        self._n, self._m, self._N = n, m, N
        F = np.zeros((N, N))
        F[:n, :n] = plant.A
        if d > 0:
            F[n : n + m, :n] = plant.C
            for i in range(1, d):  # y(k-i) moves to slot i+1
                F[n + i * m : n + (i + 1) * m, n + (i - 1) * m : n + i * m] = np.eye(m)
        self._F = F
        Qxi = np.zeros((N, N))
        Qxi[:n, :n] = plant.Q
        S = plant.S
        assert S is not None  # CorrelatedPlant.__post_init__ fills in zeros
        Mc = np.zeros((N, m))  # E[g(k) v(k)ᵀ] = [S; R; 0]
        Mc[:n] = S
        if d > 0:
            Qxi[:n, n : n + m] = S
            Qxi[n : n + m, :n] = S.T
            Qxi[n : n + m, n : n + m] = plant.R
            Mc[n : n + m] = plant.R
        self._Qxi = Qxi
        self._M = Mc
        self._xi = np.zeros(N)
        self._xi[:n] = _vector("x0", x0, n)
        self._P = np.zeros((N, N))
        self._P[:n, :n] = as_covariance(_matrix("P0", P0, (n, n)), "P0")
        self._gate = _PacketGate(m, d)

    @property
    def next_step(self) -> int:
        """The step the next :meth:`update` call must carry."""
        return self._gate.next_step

    def _weights(self, arrived: list[tuple[int, np.ndarray]]) -> list[tuple[int, float, np.ndarray]]:
        """c_i = beta_i a_i(k) for the arrived delays i (a_i = 1 exactly for those)."""
        return [(i, float(self.beta[i]), y) for i, y in arrived]

    def update(self, now: int, packets: Packets = ()) -> CodedEstimate:
        """Process the packets received at step ``now`` (call once per step, in order).

        Args:
            now: current step (0, 1, 2, ...).
            packets: (stamp, y) pairs received at this step, now - d <= stamp <= now.

        Returns:
            x^(now|now) and its error covariance.
        """
        arrived = self._gate.accept(now, packets)
        n, m = self._n, self._m
        F, xi, P = self._F, self._xi, self._P
        coded = [(i, c, y) for i, c, y in self._weights(arrived) if c != 0.0]
        if not coded:  # H = 0: Q_eps⁺ = 0, K = L = 0 -> pure prediction
            x_f, P_f = xi[:n].copy(), P[:n, :n].copy()
            self._xi = F @ xi
            self._P = F @ P @ F.T + self._Qxi
        else:
            H = np.zeros((m, self._N))
            z = np.zeros(m)
            c0 = 0.0
            for i, c, y in coded:  # z = sum_i c_i y(k-i)
                z += c * y
                if i == 0:
                    H[:, :n] = c * self.plant.C
                    c0 = c
                else:
                    H[:, n + (i - 1) * m : n + i * m] = c * np.eye(m)
            PHt = P @ H.T
            eps = z - H @ xi  # eps = z - H xi^(k|k-1)
            Qe = H @ PHt + (c0 * c0) * self.plant.R  # Q_eps = H P Hᵀ + c_0² R
            Qe_pinv = _pinv_psd(Qe)
            K = PHt @ Qe_pinv  # K = P Hᵀ Q_eps⁺
            xf = xi + K @ eps
            Pf = P - K @ PHt.T  # P - K Q_eps Kᵀ (Q_eps⁺ Q_eps Q_eps⁺ = Q_eps⁺)
            G = F @ PHt + c0 * self._M  # F P Hᵀ + M
            L = G @ Qe_pinv
            self._xi = F @ xi + L @ eps  # xi^(k+1|k)
            Pn = F @ P @ F.T + self._Qxi - L @ G.T  # - L Q_eps Lᵀ
            self._P = 0.5 * (Pn + Pn.T)
            x_f = xf[:n]
            P_f = 0.5 * (Pf[:n, :n] + Pf[:n, :n].T)
        return CodedEstimate(step=int(now), x=x_f, P=P_f)


class NewestPacketEstimator(CodedOnlineEstimator):
    """Online estimator that uses only the newest packet of each step (paper's ref. [9]).

    Same augmented filter as :class:`CodedOnlineEstimator`; the weights select the arrived
    packet with the smallest delay (c_i = 1 for it, 0 for the rest). Older packets that
    arrive in the same step are discarded.
    """

    def __init__(self, plant: CorrelatedPlant, max_delay: int, x0: ArrayLike, P0: ArrayLike) -> None:
        super().__init__(plant, max_delay, np.ones(int(max_delay) + 1), x0, P0)

    def _weights(self, arrived: list[tuple[int, np.ndarray]]) -> list[tuple[int, float, np.ndarray]]:
        if not arrived:
            return []
        i, y = arrived[0]  # sorted by delay: the newest stamp
        return [(i, 1.0, y)]


# ---------------------------------------------------------------------------- offline coding
class _OfflineModel:
    """Random-parameter form of the coded system (derived from paper eq. 10-28).

    State X(k) = [x(k); r_1(k); ...; r_d(k)] where r_i(k) is y(k-i) if that packet has not been
    received before step k, else 0 (the paper's z_i(k-i+1) in eq. 11). With independent
    Bernoulli hazards alpha_i(k) (P = alpha_i) and noise omega = [w̄; v], Cov = Omega:

        x(k+1)     = A x(k) + w̄(k)
        r_1(k+1)   = (1 - alpha_0(k)) (C x(k) + v(k))
        r_{i+1}(k+1) = (1 - alpha_i(k)) r_i(k)                         i = 1..d-1
        z(k)       = beta_0 alpha_0(k) (C x(k) + v(k)) + sum_{i>=1} beta_i alpha_i(k) r_i(k)

    Each matrix is affine in alpha(k): F = F_c + sum_i alpha_i(k) F_i, likewise G (noise into
    X), H, D (noise into z). alpha(k) is independent of X(k) and omega(k), so with bars for
    means and sigma_i = alpha_i (1 - alpha_i):

        X(k+1) = F̄ X + nu,  nu = (F - F̄) X + G omega      z = H̄ X + eta,  eta = (H - H̄) X + D omega
        E[nu nuᵀ]  = sum sigma_i F_i q F_iᵀ + E[G Omega Gᵀ]
        E[eta etaᵀ] = sum sigma_i H_i q H_iᵀ + E[D Omega Dᵀ]
        E[nu etaᵀ] = sum sigma_i F_i q H_iᵀ + E[G Omega Dᵀ]
        q(k+1)     = F̄ q F̄ᵀ + sum sigma_i F_i q F_iᵀ + E[G Omega Gᵀ]       (paper eq. 26)

    nu and eta are white, zero mean and uncorrelated with X(k) and with every past z, so the
    Kalman filter with correlated noise on (F̄, H̄) is the linear MMSE estimator (Theorem 1).
    """

    def __init__(self, plant: CorrelatedPlant, hazards: np.ndarray, beta: np.ndarray) -> None:
        n, m = plant.n, plant.m
        d = hazards.size - 1
        N = n + d * m
        a = hazards
        sig = a * (1.0 - a)

        def blk(i: int) -> slice:  # r_i block, i = 1..d
            return slice(n + (i - 1) * m, n + i * m)

        Fc = np.zeros((N, N))
        Fc[:n, :n] = plant.A
        Fi = [np.zeros((N, N)) for _ in range(d + 1)]
        Gc = np.zeros((N, n + m))
        Gc[:n, :n] = np.eye(n)
        Gi = [np.zeros((N, n + m)) for _ in range(d + 1)]
        Hi = [np.zeros((m, N)) for _ in range(d + 1)]
        Di = [np.zeros((m, n + m)) for _ in range(d + 1)]
        Hi[0][:, :n] = beta[0] * plant.C
        Di[0][:, n:] = beta[0] * np.eye(m)
        if d > 0:
            Fc[blk(1), :n] = plant.C
            Fi[0][blk(1), :n] = -plant.C
            Gc[blk(1), n:] = np.eye(m)
            Gi[0][blk(1), n:] = -np.eye(m)
            for i in range(1, d + 1):
                Hi[i][:, blk(i)] = beta[i] * np.eye(m)
                if i < d:
                    Fc[blk(i + 1), blk(i)] = np.eye(m)
                    Fi[i][blk(i + 1), blk(i)] = -np.eye(m)
        S = plant.S
        assert S is not None  # CorrelatedPlant.__post_init__ fills in zeros
        Om = np.block([[plant.Q, S], [S.T, plant.R]])
        self.N, self.n = N, n
        self.Fbar = Fc + sum(a[i] * Fi[i] for i in range(d + 1))
        Gbar = Gc + sum(a[i] * Gi[i] for i in range(d + 1))
        self.Hbar = sum(a[i] * Hi[i] for i in range(d + 1))
        Dbar = sum(a[i] * Di[i] for i in range(d + 1))
        # E[G Omega Gᵀ] etc. (constant parts)
        self.GOG = Gbar @ Om @ Gbar.T + sum(sig[i] * Gi[i] @ Om @ Gi[i].T for i in range(d + 1))
        self.DOD = Dbar @ Om @ Dbar.T + sum(sig[i] * Di[i] @ Om @ Di[i].T for i in range(d + 1))
        self.GOD = Gbar @ Om @ Dbar.T + sum(sig[i] * Gi[i] @ Om @ Di[i].T for i in range(d + 1))
        live = [i for i in range(d + 1) if sig[i] > 0.0]
        self._terms = [(sig[i], Fi[i], Hi[i]) for i in live]

    def moments(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(E[nu nuᵀ], E[eta etaᵀ], E[nu etaᵀ], q(k+1)) for second moment q = q(k)."""
        Qnu, Reta, Snu = self.GOG.copy(), self.DOD.copy(), self.GOD.copy()
        for s, Fi, Hi in self._terms:
            Fq = Fi @ q
            Qnu += s * (Fq @ Fi.T)
            Reta += s * (Hi @ q @ Hi.T)
            Snu += s * (Fq @ Hi.T)
        q_next = self.Fbar @ q @ self.Fbar.T + Qnu
        return Qnu, Reta, Snu, 0.5 * (q_next + q_next.T)


class _OfflineGains:
    """Data-independent gain recursion of the offline estimator (one element per step)."""

    def __init__(self, model: _OfflineModel, mean0: np.ndarray, P0: np.ndarray) -> None:
        self.model = model
        self.P = P0.copy()  # P(k|k-1) of X
        self.q = P0 + np.outer(mean0, mean0)  # q(k) = E[X Xᵀ] (second moment, mean included)

    def next(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (K(k), L(k), P_x(k|k)) and advance to k+1."""
        md, P = self.model, self.P
        Qnu, Reta, Snu, q_next = md.moments(self.q)
        H, F = md.Hbar, md.Fbar
        PHt = P @ H.T
        Qe = H @ PHt + Reta  # Q_eps = H̄ P H̄ᵀ + E[eta etaᵀ]
        Qe_pinv = _pinv_psd(Qe)
        K = PHt @ Qe_pinv  # K = P H̄ᵀ Q_eps⁺
        G = F @ PHt + Snu
        L = G @ Qe_pinv  # L = (F̄ P H̄ᵀ + E[nu etaᵀ]) Q_eps⁺
        Pf = P - K @ PHt.T
        Pn = F @ P @ F.T + Qnu - L @ G.T  # P(k+1|k) = F̄ P F̄ᵀ + E[nu nuᵀ] - L Q_eps Lᵀ
        self.P = 0.5 * (Pn + Pn.T)
        self.q = q_next
        n = md.n
        return K, L, 0.5 * (Pf[:n, :n] + Pf[:n, :n].T)


class OfflineCodedEstimator:
    """Offline linear-coding estimator: gains from the hazards alpha_i and beta only.

    The arrival pattern is not used (only the coded sum z(k) is, which the receiver forms from
    the timestamps). Gains K(k), L(k) come from :class:`_OfflineModel`'s recursion, which depends
    on the prior (x0, P0), the hazards and beta alone, so it can be run ahead of time
    (:meth:`precompute`). Estimator (paper eq. 29-30):

        eps = z(k) - H̄ X^(k|k-1)
        X^(k|k) = X^(k|k-1) + K(k) eps,      X^(k+1|k) = F̄ X^(k|k-1) + L(k) eps

    Stationarity: the gains converge iff the plant is stable (:func:`is_stationary`); on a
    constant-velocity target the second moment of x grows without bound, the coded measurement
    looks ever noisier to the filter, and the error covariance diverges.

    Args:
        plant: the system.  delay_model: the true hazards (gives d = delay_model.max_delay).
        beta: shape (d + 1,) coding weights.  x0: (n,) prior mean.  P0: (n, n) prior covariance.
    """

    def __init__(
        self,
        plant: CorrelatedPlant,
        delay_model: DelayModel,
        beta: ArrayLike,
        x0: ArrayLike,
        P0: ArrayLike,
    ) -> None:
        if not isinstance(plant, CorrelatedPlant):
            raise ValueError("plant: expected a CorrelatedPlant")
        if not isinstance(delay_model, DelayModel):
            raise ValueError("delay_model: expected a DelayModel")
        d = delay_model.max_delay
        n = plant.n
        self.plant = plant
        self.max_delay = d
        self.beta = _check_beta(beta, d)
        self._model = _OfflineModel(plant, delay_model.hazards, self.beta)
        N = self._model.N
        mean0 = np.zeros(N)
        mean0[:n] = _vector("x0", x0, n)
        P0x = np.zeros((N, N))
        P0x[:n, :n] = as_covariance(_matrix("P0", P0, (n, n)), "P0")
        self._gains = _OfflineGains(self._model, mean0, P0x)
        self._ahead: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._X = mean0
        self._gate = _PacketGate(plant.m, d)

    def precompute(self, steps: int) -> None:
        """Run the gain recursion ``steps`` steps ahead (no data needed)."""
        for _ in range(int(steps)):
            self._ahead.append(self._gains.next())

    def update(self, now: int, packets: Packets = ()) -> CodedEstimate:
        """Same contract as :meth:`CodedOnlineEstimator.update`; P is the unconditional MSE."""
        arrived = self._gate.accept(now, packets)
        K, L, Pf = self._ahead.popleft() if self._ahead else self._gains.next()
        z = np.zeros(self.plant.m)
        for i, y in arrived:  # z(k) = sum_i beta_i a_i(k) y(k-i)
            z += self.beta[i] * y
        md = self._model
        eps = z - md.Hbar @ self._X
        xf = self._X + K @ eps
        self._X = md.Fbar @ self._X + L @ eps
        return CodedEstimate(step=int(now), x=xf[: self.plant.n], P=Pf)

    @staticmethod
    def steady_state(
        plant: CorrelatedPlant,
        delay_model: DelayModel,
        beta: ArrayLike,
        tol: float = 1e-10,
        max_steps: int = 100_000,
    ) -> np.ndarray:
        """Stationary error covariance P_x(k|k) of the offline estimator (paper section 4).

        Raises:
            ValueError: if the plant is not stable (no stationary gains exist), or the
                recursion has not settled within ``max_steps``.
        """
        if not is_stationary(plant):
            raise ValueError("plant: offline coding has no stationary gains unless A is stable")
        b = _check_beta(beta, delay_model.max_delay)
        md = _OfflineModel(plant, delay_model.hazards, b)
        g = _OfflineGains(md, np.zeros(md.N), np.zeros((md.N, md.N)))
        prev = None
        for _ in range(int(max_steps)):
            _, _, Pf = g.next()
            if prev is not None and np.max(np.abs(Pf - prev)) <= tol * max(1.0, np.max(np.abs(Pf))):
                return Pf
            prev = Pf
        raise ValueError("max_steps: offline covariance did not settle")


# ---------------------------------------------------------------------------- exact replay
class TimestampReplayKF:
    """Exact reference: LMMSE of x(k) from every packet received by step k, used at its stamp.

    Caches the one-step predictions x^(s|s-1), P(s|s-1) for the open stamps s = k-d..k (older
    stamps can receive nothing more and are dropped); a call re-runs the filter only from the
    oldest stamp that received a packet in this call. With S ≠ 0 the correlated-noise step is
    used (Anderson & Moore, ch. 5): for a present y(s)

        eps = y - C x^,  Q_eps = C P Cᵀ + R,  x^(s|s) = x^ + P Cᵀ Q_eps⁻¹ eps
        x^(s+1|s) = A x^ + (A P Cᵀ + S) Q_eps⁻¹ eps
        P(s+1|s)  = A P Aᵀ + Q - (A P Cᵀ + S) Q_eps⁻¹ (A P Cᵀ + S)ᵀ

    and for an absent one the plain prediction. Cost per call: at most d + 1 filter steps.
    Plain numpy reference, not tuned (the core's ObserverPredictor is the fast exact one;
    it has no S term).
    """

    def __init__(self, plant: CorrelatedPlant, max_delay: int, x0: ArrayLike, P0: ArrayLike) -> None:
        if not isinstance(plant, CorrelatedPlant):
            raise ValueError("plant: expected a CorrelatedPlant")
        if isinstance(max_delay, bool) or int(max_delay) != max_delay or max_delay < 0:
            raise ValueError(f"max_delay: expected an integer >= 0, got {max_delay!r}")
        self.plant = plant
        self.max_delay = d = int(max_delay)
        n = plant.n
        x = _vector("x0", x0, n)
        P = as_covariance(_matrix("P0", P0, (n, n)), "P0")
        self._pred: dict[int, tuple[np.ndarray, np.ndarray]] = {0: (x, P)}  # s -> x^(s|s-1), P
        self._h = 0  # oldest cached stamp
        self._buf: dict[int, np.ndarray] = {}
        self._gate = _PacketGate(plant.m, d)

    def _filter(self, x: np.ndarray, P: np.ndarray, y: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """x^(s|s), P(s|s) from the prediction and y(s) (or None)."""
        if y is None:
            return x, P
        C = self.plant.C
        PCt = P @ C.T
        Kf = PCt @ np.linalg.inv(C @ PCt + self.plant.R)  # P Cᵀ Q_eps⁻¹
        Pf = P - Kf @ PCt.T
        return x + Kf @ (y - C @ x), 0.5 * (Pf + Pf.T)

    def _predict(self, x: np.ndarray, P: np.ndarray, y: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """x^(s+1|s), P(s+1|s) from x^(s|s-1), P(s|s-1) and y(s) (or None)."""
        pl = self.plant
        A = pl.A
        if y is None:
            return A @ x, A @ P @ A.T + pl.Q
        PCt = P @ pl.C.T
        G = A @ PCt + pl.S  # A P Cᵀ + S
        L = G @ np.linalg.inv(pl.C @ PCt + pl.R)  # (A P Cᵀ + S) Q_eps⁻¹
        Pn = A @ P @ A.T + pl.Q - L @ G.T
        return A @ x + L @ (y - pl.C @ x), 0.5 * (Pn + Pn.T)

    def update(self, now: int, packets: Packets = ()) -> CodedEstimate:
        """Same contract as :meth:`CodedOnlineEstimator.update`."""
        arrived = self._gate.accept(now, packets)
        for i, y in arrived:
            self._buf[now - i] = y
        # predictions for stamps <= start are still valid (they use packets stamped < start)
        start = max(self._h, min([now - i for i, _ in arrived] + [now - 1]))
        pred = self._pred
        for s in range(start, now):
            pred[s + 1] = self._predict(*pred[s], self._buf.get(s))
        xf, Pf = self._filter(*pred[now], self._buf.get(now))
        # drop stamps s < now - d: nothing stamped there can still arrive
        while self._h < now - self.max_delay:
            del pred[self._h]
            self._buf.pop(self._h, None)
            self._h += 1
        return CodedEstimate(step=int(now), x=xf.copy(), P=Pf.copy())
