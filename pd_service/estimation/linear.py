"""Linear-Gaussian backend: multi-step propagation tables and the Kalman update.

Propagating m steps at once, with no per-step Python work::

    x(a+m) = A^m x(a) + [A^{m-1}B, ..., AB, B] [u(a); ...; u(a+m-1)]        (eq. 34)
    P(a+m) = A^m P(a) (A^m)^T + Qs(m),     Qs(m) = sum_{j<m} A^j Q (A^j)^T

``A^m``, ``Qs(m)`` and the stacked input matrix are computed once per model and horizon and
shared by every estimator with the same model (a daemon with 1,000 sessions of one robot type
keeps one copy).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from .model import LinearModel, Sensor
from .replay import Packet
from .state import check_names, take

LinearState = tuple[np.ndarray, np.ndarray]  # (x (n,), P (n, n))


@dataclass(frozen=True, eq=False)
class PropagationTables:
    """Precomputed powers for horizons 0..M. Shapes: Apow (M+1, n, n), Qsum (M+1, n, n),
    Gfull (n, M*nu) with column blocks [A^{M-1}B, ..., A^0 B]."""

    M: int
    Apow: np.ndarray
    Qsum: np.ndarray
    Gfull: np.ndarray

    @classmethod
    def build(cls, model: LinearModel, M: int) -> PropagationTables:
        A, B, Q = model.A, model.B, model.Q
        n, nu = model.n, model.nu
        Apow = np.empty((M + 1, n, n))
        Qsum = np.empty((M + 1, n, n))
        Apow[0] = np.eye(n)
        Qsum[0] = 0.0
        for m in range(M):
            Apow[m + 1] = A @ Apow[m]
            q = A @ Qsum[m] @ A.T + Q  # Qs(m+1) = A Qs(m) A^T + Q
            Qsum[m + 1] = 0.5 * (q + q.T)
        Gfull = np.empty((n, M * nu))
        for j in range(M):  # block j multiplies u(a + j) in an M-step jump: A^{M-1-j} B
            Gfull[:, j * nu : (j + 1) * nu] = Apow[M - 1 - j] @ B
        for arr in (Apow, Qsum, Gfull):
            arr.setflags(write=False)
        return cls(M, Apow, Qsum, Gfull)


_TABLES: dict[tuple[bytes, bytes, bytes, tuple[int, ...], int], PropagationTables] = {}
_TABLES_LOCK = threading.Lock()
#: The memo holds at most this many bytes of tables (least recently used dropped first); a
#: table larger than this is built but not kept. Sessions hold their own reference, so the
#: memo's bound is on what it keeps alive beyond them.
_TABLES_MAX_BYTES = [64 * 2**20]


def set_tables_max_bytes(limit: int) -> None:
    """Bound the shared tables' memo to ``limit`` bytes (evicting now if needed)."""
    with _TABLES_LOCK:
        _TABLES_MAX_BYTES[0] = int(limit)
        _evict(0)


def tables_nbytes(t: PropagationTables) -> int:
    return int(t.Apow.nbytes + t.Qsum.nbytes + t.Gfull.nbytes)


def _evict(extra: int) -> None:
    """Drop least recently used tables until ``extra`` more bytes fit (lock held)."""
    total = sum(tables_nbytes(t) for t in _TABLES.values())
    while _TABLES and total + extra > _TABLES_MAX_BYTES[0]:
        total -= tables_nbytes(_TABLES.pop(next(iter(_TABLES))))


def tables_for(model: LinearModel, M: int) -> PropagationTables:
    """Shared :class:`PropagationTables` for ``model`` up to horizon ``M`` (memoised, LRU,
    bounded in bytes: :func:`set_tables_max_bytes`)."""
    key = (model.A.tobytes(), model.B.tobytes(), model.Q.tobytes(), model.B.shape, M)
    with _TABLES_LOCK:
        t = _TABLES.pop(key, None)
        if t is not None:
            _TABLES[key] = t  # most recently used last
            return t
    t = PropagationTables.build(model, M)
    size = tables_nbytes(t)
    with _TABLES_LOCK:
        if size <= _TABLES_MAX_BYTES[0]:
            _evict(size)
            _TABLES[key] = t
    return t


def propagate(tables: PropagationTables, nu: int, x: np.ndarray, P: np.ndarray,
              U: np.ndarray) -> LinearState:
    """Roll (x, P) forward len(U) steps with inputs U (m, nu); m may exceed the table."""
    m = U.shape[0]
    M = tables.M
    while m > M:  # only when a session sat idle for longer than the horizon
        x, P = propagate(tables, nu, x, P, U[:M])
        U = U[M:]
        m -= M
    Am = tables.Apow[m]
    x = Am @ x
    if nu:
        # [A^{m-1}B ... B] is the last m*nu columns of the full stacked matrix.
        x = x + tables.Gfull[:, (M - m) * nu :] @ U.reshape(-1)
    P = Am @ P @ Am.T + tables.Qsum[m]
    return x, P


def kalman_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, R: np.ndarray,
                  z: np.ndarray) -> LinearState:
    """Condition N(x, P) on z = H x + v, v ~ N(0, R).

        S = H P H^T + R,   K = P H^T S^{-1}
        x+ = x + K (z - H x),   P+ = P - K H P   (symmetrised)

    A singular S (zero R on a direction P already knows exactly) uses the pseudo-inverse,
    which is still the LMMSE gain.
    """
    PHt = P @ H.T
    S = H @ PHt + R
    if S.shape[0] == 1:
        s = S[0, 0]
        K = PHt / s if s > 0.0 else PHt * 0.0
    else:
        try:
            K = np.linalg.solve(S, PHt.T).T
        except np.linalg.LinAlgError:
            K = PHt @ np.linalg.pinv(S)
    x = x + K @ (z - H @ x)
    P = P - K @ PHt.T
    return x, 0.5 * (P + P.T)


class LinearBackend:
    """Kalman filter steps for :class:`ReplayEstimator`; state = (x, P)."""

    def __init__(self, model: LinearModel, sensors: list[Sensor], horizon: int) -> None:
        self.model = model
        self.sensors = sensors
        self.tables = tables_for(model, horizon)
        self._nu = model.nu
        self._stacked: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}

    def propagate(self, state: LinearState, step: int, m: int, U: np.ndarray) -> LinearState:
        return propagate(self.tables, self._nu, state[0], state[1], U)

    def update(self, state: LinearState, step: int, packets: list[Packet]) -> LinearState:
        if len(packets) == 1:
            p = packets[0]
            sensor = self.sensors[p.sensor]
            R = sensor.R if p.R is None else p.R
            return kalman_update(state[0], state[1], sensor.H, R, p.z)
        # Several sensors sampled this step: stack the rows that are present, M*(tau) of
        # eq. (24): H* = [H_i; H_j; ...], R* = diag(R_i, R_j, ...).
        key = tuple(p.sensor for p in packets)
        stacked = self._stacked.get(key)
        if stacked is None:
            H = np.vstack([self.sensors[i].H for i in key])
            stacked = (H, block_diag([self.sensors[i].R for i in key]))
            self._stacked[key] = stacked
        H, R = stacked
        if any(p.R is not None for p in packets):
            R = block_diag([self.sensors[p.sensor].R if p.R is None else p.R for p in packets])
        z = np.concatenate([p.z for p in packets])
        return kalman_update(state[0], state[1], H, R, z)

    def moments(self, state: LinearState) -> LinearState:
        return state

    def export_state(self, state: LinearState) -> dict[str, np.ndarray]:
        return {"x": state[0].copy(), "P": state[1].copy()}

    def import_state(self, arrays: dict[str, np.ndarray]) -> LinearState:
        return import_gaussian(arrays, self.model.n)


def import_gaussian(arrays: dict[str, np.ndarray], n: int) -> LinearState:
    """(x (n,), P (n, n)) from {"x", "P"}; StateError if missing, misshapen or non-finite."""
    check_names(arrays, {"x", "P"})
    return take(arrays, "x", (n,)), take(arrays, "P", (n, n))


def block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    """diag(B_1, B_2, ...) of square blocks."""
    size = sum(b.shape[0] for b in blocks)
    out = np.zeros((size, size))
    i = 0
    for b in blocks:
        k = b.shape[0]
        out[i : i + k, i : i + k] = b
        i += k
    return out
