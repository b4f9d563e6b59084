"""Online adaptation of chosen diagonal entries q_m of the process noise Q.

Both adapters see one :class:`~.unscented.InnovationRecord` per *committed* measured step
(packets final), in step order, and return the new Q or None (unchanged). The estimator
(:class:`~.ukf.UnscentedObserverPredictor`) replays the speculative stretch with the
resulting Q frozen, so late packets never reach these statistics.

MIT rule (gradient descent on the innovation-covariance mismatch). Innovations are kept in
windows of the last N per *kind* (sensor, gap since the previous update), and at step k the
window of the current kind gives::

    C_k   = (1/N) sum_{j=k-N+1..k} nu_j nu_j^T           (empirical innovation covariance)
    dS_k  = C_k - S_k                                     (S_k: the filter's predicted one)
    J     = 1/2 sum_i dS_ii^2
    d dS_ii / d q_m = (2/N) sum_j nu_j,i dnu_j,i / dq_m  -  dS_k,ii / dq_m
    dJ/dq_m = sum_i dS_ii  d dS_ii / d q_m

with the sensitivities dnu/dq, dS/dq from :mod:`.unscented`. Update (default "normalised",
unit-free, a step in log q_m of at most ``clip``)::

    q_m <- q_m exp(-clip(eta q_m sum_i (dS_ii / S_ii) (d dS_ii / d q_m) / S_ii, +/- clip))

or "plain": q_m <- q_m - eta dJ/dq_m. Either result is clamped to [q_min, q_max]. Kinds
whose window is not yet full do not contribute. Adapt only identifiable entries (normally the
acceleration channels): adapting all entries of Q from the innovations is not identifiable.

Why per gap: after a lost sample (or in a multi-rate pattern) the innovation after a 2-step
gap has a larger covariance than after a 1-step one; one window mixing both, compared with the
current S_k, biases q upwards (docs/nonlinear.md). Averaging S over
the window instead removes the bias but delays the feedback (S_k reacts to q at once, a window
average does not) and makes q oscillate. Gaps longer than ``max_gap`` are not used.

Sage-Husa covariance matching (the baseline), with forgetting factor b::

    d_k = (1 - b) / (1 - b^{k+1})
    Q^_k = (1 - d_k) Q^_{k-1} + d_k [Q_{k-1} + K (nu nu^T - S) K^T / gap]

(for gap = 1 this is the classical K nu nu^T K^T + P+ - (P- - Q)); only the chosen diagonal
entries are used, clamped to [q_min, q_max].
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..estimator_state import StateError
from .unscented import InnovationRecord


class Adapter(Protocol):
    """Stateful process-noise adapter. ``indices``: adapted diagonal entries of Q."""

    indices: tuple[int, ...]
    needs_sensitivities: bool

    def observe(self, rec: InnovationRecord, Q: np.ndarray) -> np.ndarray | None:
        """Take one committed innovation; return the new Q (n, n) or None if unchanged."""
        ...

    def export_memory(self) -> dict[str, np.ndarray]:
        """What the adapter remembers, as named arrays (copies)."""
        ...

    def restore_memory(self, memory: dict[str, np.ndarray]) -> None:
        """Install :meth:`export_memory`'s output; StateError (nothing changed) if it does
        not fit these settings."""
        ...


@dataclass(frozen=True)
class MITSettings:
    """MIT-rule settings. ``window`` N innovations (per sensor and gap); ``eta`` adaptation
    rate (unit-free for the normalised rule, in 1 / (units of S^2 / q^2) for the plain one);
    ``clip`` bound on one log step; ``max_gap`` longest gap (steps since the previous update)
    whose innovations are used; ``q_min`` / ``q_max`` absolute bounds, default q0 * 1e-4 /
    q0 * 1e4."""

    indices: tuple[int, ...]
    window: int = 50
    eta: float = 0.1
    rule: str = "normalised"
    clip: float = 0.1
    max_gap: int = 4
    q_min: tuple[float, ...] | None = None
    q_max: tuple[float, ...] | None = None


@dataclass(frozen=True)
class SageHusaSettings:
    """Sage-Husa settings: forgetting factor ``forgetting`` b in (0, 1); bounds as for MIT."""

    indices: tuple[int, ...]
    forgetting: float = 0.98
    q_min: tuple[float, ...] | None = None
    q_max: tuple[float, ...] | None = None


class _Ring:
    """The last N innovations of one kind: nu (N, m) and dnu (N, p, m)."""

    def __init__(self, N: int, m: int, p: int) -> None:
        self.nu = np.zeros((N, m))
        self.dnu = np.zeros((N, p, m))
        self.count = 0
        self.N = N

    def push(self, nu: np.ndarray, dnu: np.ndarray) -> None:
        i = self.count % self.N
        self.nu[i] = nu
        self.dnu[i] = dnu
        self.count += 1

    @property
    def full(self) -> bool:
        return self.count >= self.N


def _bounds(q0: np.ndarray, q_min, q_max) -> tuple[np.ndarray, np.ndarray]:
    lo = q0 * 1e-4 if q_min is None else np.asarray(q_min, dtype=float)
    hi = q0 * 1e4 if q_max is None else np.asarray(q_max, dtype=float)
    if lo.shape != q0.shape or hi.shape != q0.shape:
        raise ValueError(f"q_min/q_max: expected {q0.size} values (one per adapted index)")
    if np.any(lo <= 0) or np.any(hi < lo) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("q_min/q_max: need 0 < q_min <= q_max, finite")
    return lo, hi


def _check_indices(indices: tuple[int, ...], Q0: np.ndarray) -> tuple[int, ...]:
    n = Q0.shape[0]
    idx = tuple(int(i) for i in indices)
    if not idx:
        raise ValueError("indices: at least one diagonal entry of Q to adapt")
    if len(set(idx)) != len(idx) or any(not 0 <= i < n for i in idx):
        raise ValueError(f"indices: distinct state indices in [0, {n}) expected, got {list(idx)}")
    q0 = np.diag(Q0)[list(idx)]
    if np.any(q0 <= 0):
        raise ValueError(f"indices: adapted entries of Q must start > 0, got {q0.tolist()}")
    return idx


class MITAdapter:
    """MIT-rule adapter (see the module docstring). Needs sensitivities."""

    needs_sensitivities = True

    def __init__(self, settings: MITSettings, Q0: np.ndarray, sensor_dims: list[int]) -> None:
        s = settings
        self.indices = _check_indices(s.indices, Q0)
        if not isinstance(s.window, int) or s.window < 1:
            raise ValueError(f"window: a positive integer expected, got {s.window!r}")
        if not np.isfinite(s.eta) or s.eta <= 0:
            raise ValueError(f"eta: must be > 0, got {s.eta!r}")
        if s.rule not in ("normalised", "plain"):
            raise ValueError(f"rule: 'normalised' or 'plain', got {s.rule!r}")
        if not np.isfinite(s.clip) or s.clip <= 0:
            raise ValueError(f"clip: must be > 0, got {s.clip!r}")
        self.settings = s
        self._idx = np.array(self.indices)
        self.q_min, self.q_max = _bounds(np.diag(Q0)[self._idx], s.q_min, s.q_max)
        if not isinstance(s.max_gap, int) or s.max_gap < 1:
            raise ValueError(f"max_gap: a positive integer expected, got {s.max_gap!r}")
        self._dims = list(sensor_dims)
        self._rings: dict[tuple[int, int], _Ring] = {}  # (sensor, gap) -> window
        self.updates = 0

    def gradient_terms(self, rec: InnovationRecord) -> tuple[np.ndarray, np.ndarray, bool]:
        """Push the record; return (normalised sum, dJ/dq, any sensor contributed)."""
        if rec.dnu is None or rec.dS is None:
            raise ValueError("MIT rule: the innovation record carries no sensitivities")
        p = len(self.indices)
        g_norm = np.zeros(p)
        g_plain = np.zeros(p)
        used = False
        S_diag = np.diagonal(rec.S)
        dS_diag = np.diagonal(rec.dS, axis1=1, axis2=2)
        if not 1 <= rec.gap <= self.settings.max_gap:
            return g_norm, g_plain, False
        for sensor, a, b in rec.blocks:
            ring = self._rings.get((sensor, rec.gap))
            if ring is None:
                ring = _Ring(self.settings.window, self._dims[sensor], p)
                self._rings[(sensor, rec.gap)] = ring
            ring.push(rec.nu[a:b], rec.dnu[:, a:b])
            if not ring.full:
                continue
            used = True
            N = ring.N
            C = np.mean(ring.nu**2, axis=0)                                # C_ii
            dC = (2.0 / N) * np.einsum("ja,jpa->pa", ring.nu, ring.dnu)    # dC_ii / dq_m
            Sd = S_diag[a:b]                                               # S_ii
            dSd = dS_diag[:, a:b]                                          # dS_ii / dq_m
            dS = C - Sd                                                    # dS_ii
            ddS = dC - dSd                                                 # d dS_ii / dq_m
            g_norm += ddS @ (dS / Sd**2)         # sum_i (dS_ii / S_ii) ddS_ii / S_ii
            g_plain += ddS @ dS                  # dJ / dq_m
        return g_norm, g_plain, used

    def export_memory(self) -> dict[str, np.ndarray]:
        """"updates" (1,); "kinds" (K, 3) rows (sensor, gap, count); "nu.<i>" (N, m) and
        "dnu.<i>" (N, p, m) of the i-th kind's window."""
        out = {"updates": np.array([self.updates]),
               "kinds": np.array([(s, g, r.count) for (s, g), r in self._rings.items()],
                                 dtype=np.int64).reshape(-1, 3)}
        for i, ring in enumerate(self._rings.values()):
            out[f"nu.{i}"], out[f"dnu.{i}"] = ring.nu.copy(), ring.dnu.copy()
        return out

    def restore_memory(self, memory: dict[str, np.ndarray]) -> None:
        N, p = self.settings.window, len(self.indices)
        try:
            updates = int(np.asarray(memory["updates"]).reshape(-1)[0])
            kinds = np.asarray(memory["kinds"], dtype=np.int64).reshape(-1, 3)
        except (KeyError, IndexError, TypeError, ValueError):
            raise StateError("extras.adapter: MIT memory expected (updates, kinds)") from None
        if set(memory) != {"updates", "kinds"} | {f"{a}.{i}" for i in range(len(kinds))
                                                  for a in ("nu", "dnu")}:
            raise StateError("extras.adapter: MIT windows do not match their kinds")
        rings: dict[tuple[int, int], _Ring] = {}
        for i, (sensor, gap, count) in enumerate(kinds.tolist()):
            if not 0 <= sensor < len(self._dims) or not 1 <= gap <= self.settings.max_gap \
                    or count < 0 or (sensor, gap) in rings:
                raise StateError(f"extras.adapter: bad window kind {(sensor, gap, count)}")
            ring = _Ring(N, self._dims[sensor], p)
            nu, dnu = np.asarray(memory[f"nu.{i}"], float), np.asarray(memory[f"dnu.{i}"], float)
            if nu.shape != ring.nu.shape or dnu.shape != ring.dnu.shape \
                    or not (np.all(np.isfinite(nu)) and np.all(np.isfinite(dnu))):
                raise StateError(f"extras.adapter: window {i} of the wrong size or not finite")
            ring.nu[:], ring.dnu[:], ring.count = nu, dnu, count
            rings[(sensor, gap)] = ring
        self._rings, self.updates = rings, updates

    def observe(self, rec: InnovationRecord, Q: np.ndarray) -> np.ndarray | None:
        g_norm, g_plain, used = self.gradient_terms(rec)
        if not used:
            return None
        s = self.settings
        q = np.diag(Q)[self._idx]
        if s.rule == "normalised":
            q_new = q * np.exp(-np.clip(s.eta * q * g_norm, -s.clip, s.clip))
        else:
            q_new = q - s.eta * g_plain
        q_new = np.clip(q_new, self.q_min, self.q_max)
        self.updates += 1
        if np.array_equal(q_new, q):
            return None
        Qn = Q.copy()
        Qn[self._idx, self._idx] = q_new
        return Qn


class SageHusaAdapter:
    """Sage-Husa covariance matching on chosen diagonal entries (baseline)."""

    needs_sensitivities = False

    def __init__(self, settings: SageHusaSettings, Q0: np.ndarray, sensor_dims: list[int]) -> None:
        s = settings
        self.indices = _check_indices(s.indices, Q0)
        if not np.isfinite(s.forgetting) or not 0.0 < s.forgetting < 1.0:
            raise ValueError(f"forgetting: must be in (0, 1), got {s.forgetting!r}")
        self.settings = s
        self._idx = np.array(self.indices)
        self.q_min, self.q_max = _bounds(np.diag(Q0)[self._idx], s.q_min, s.q_max)
        self.k = 0

    def export_memory(self) -> dict[str, np.ndarray]:
        """"k" (1,): innovations seen (sets the forgetting weight d_k)."""
        return {"k": np.array([self.k])}

    def restore_memory(self, memory: dict[str, np.ndarray]) -> None:
        k = np.asarray(memory.get("k", []))
        if set(memory) != {"k"} or k.shape != (1,) or int(k[0]) < 0:
            raise StateError("extras.adapter: Sage-Husa memory expected (k)")
        self.k = int(k[0])

    def observe(self, rec: InnovationRecord, Q: np.ndarray) -> np.ndarray | None:
        b = self.settings.forgetting
        d = (1.0 - b) / (1.0 - b ** (self.k + 1))        # d_k = (1 - b) / (1 - b^{k+1})
        self.k += 1
        K = rec.K[self._idx]                             # rows of K for the adapted entries
        M = np.outer(rec.nu, rec.nu) - rec.S             # nu nu^T - S
        corr = np.einsum("ia,ab,ib->i", K, M, K) / max(rec.gap, 1)  # diag K (nu nu^T - S) K^T
        q = np.diag(Q)[self._idx]
        q_new = np.clip(q + d * corr, self.q_min, self.q_max)  # (1-d) q + d (q + corr)
        if np.array_equal(q_new, q):
            return None
        Qn = Q.copy()
        Qn[self._idx, self._idx] = q_new
        return Qn


_MIT_KEYS = {"method", "indices", "window", "eta", "rule", "clip", "max_gap", "q_min", "q_max"}
_SH_KEYS = {"method", "indices", "forgetting", "q_min", "q_max"}


def make_adapter(spec: Mapping[str, object] | None, Q0: np.ndarray,
                 sensor_dims: list[int]) -> Adapter | None:
    """Build an adapter from plain settings, as they arrive in a session spec::

        {"method": "mit", "indices": [3, 4, 5], "window": 50, "eta": 0.1,
         "rule": "normalised", "clip": 0.1, "max_gap": 4, "q_min": [...], "q_max": [...]}
        {"method": "sage_husa", "indices": [3, 4, 5], "forgetting": 0.98}
        None or {"method": "none"}  -> no adaptation

    Unknown keys or bad values raise ValueError naming the key.
    """
    if spec is None:
        return None
    if not isinstance(spec, Mapping):
        raise ValueError("adapt: expected a map of settings or None")
    method = spec.get("method", "mit")
    if method == "none":
        if set(spec) - {"method"}:
            raise ValueError("adapt: method 'none' takes no other settings")
        return None
    if method not in ("mit", "sage_husa"):
        raise ValueError(f"adapt.method: 'mit', 'sage_husa' or 'none', got {method!r}")
    allowed = _MIT_KEYS if method == "mit" else _SH_KEYS
    unknown = set(spec) - allowed
    if unknown:
        raise ValueError(f"adapt: unknown settings {sorted(unknown)} for method {method!r}")
    if "indices" not in spec:
        raise ValueError("adapt.indices: required (which diagonal entries of Q to adapt)")
    indices = spec["indices"]
    try:
        if not isinstance(indices, Iterable):
            raise TypeError
        kw: dict[str, object] = {"indices": tuple(int(i) for i in indices)}
    except (TypeError, ValueError):
        raise ValueError("adapt.indices: expected a list of integers") from None
    for key in ("q_min", "q_max"):
        bounds = spec.get(key)
        if bounds is not None:
            try:
                if not isinstance(bounds, Iterable):
                    raise TypeError
                kw[key] = tuple(float(v) for v in bounds)
            except (TypeError, ValueError):
                raise ValueError(f"adapt.{key}: expected a list of numbers") from None
    for key, integer in (("window", True), ("max_gap", True), ("eta", False), ("clip", False),
                         ("forgetting", False)):
        if key in spec:
            v = spec[key]
            if (isinstance(v, bool) or not isinstance(v, (int, float))
                    or (integer and not isinstance(v, int))):
                what = "an integer" if integer else "a number"
                raise ValueError(f"adapt.{key}: expected {what}, got {v!r}")
            kw[key] = int(v) if integer else float(v)
    if "rule" in spec:
        kw["rule"] = spec["rule"]
    if method == "mit":
        return MITAdapter(MITSettings(**kw), Q0, sensor_dims)  # type: ignore[arg-type]
    return SageHusaAdapter(SageHusaSettings(**kw), Q0, sensor_dims)  # type: ignore[arg-type]
