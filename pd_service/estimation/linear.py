"""Linear-Gaussian backend: multi-step propagation tables and the Kalman step.

Propagating m steps at once, with no per-step Python work::

    x(a+m) = A^m x(a) + [A^{m-1}B, ..., AB, B] [u(a); ...; u(a+m-1)]        (eq. 34)
    P(a+m) = A^m P(a) (A^m)^T + Qs(m),     Qs(m) = sum_{j<m} A^j Q (A^j)^T

``A^m``, ``Qs(m)`` and the stacked input matrix are computed once per model and horizon and
shared by every estimator with the same model (a daemon with 1,000 sessions of one robot type
keeps one copy).

:class:`LinearBackend` is the ObserverPredictor's backend: one fused step per measured step
(:meth:`LinearBackend.advance`: jump, then the Kalman update on the step's packets). The step
exists twice: the numpy form here, the reference, written for 4 x 4 matrices where numpy's
per-call overhead dominates (``ndarray.dot``, closed-form 2 x 2 / 3 x 3 Cholesky factors
instead of LAPACK, a column and an entry for a unit-row scalar sensor, contiguous operands,
covariances kept exactly symmetric without a symmetrisation pass); and, where the hot path
runs compiled (``pd_service.native``), the C kernel ``_kalman.c``: the same formulas in one
call per step (``_kalman.advance``), or per replay (``_kalman.replay``, the replay's loop of
steps). The numpy form runs with ``PD_SERVICE_PURE=1``, without a compiler, for sizes beyond
the kernel's and for a step the kernel hands back (a nearly singular innovation
covariance); the kernel is tested against it.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Final, NamedTuple, cast

import numpy as np
from mypy_extensions import mypyc_attr

from pd_service.native import kernel, kernel_function

from .estimator_state import check_names, take
from .model import LinearModel, Sensor
from .replay import Cut, Packet

#: The C form of :meth:`LinearBackend.advance`'s step (pd_service/estimation/_kalman.c), None
#: where the hot path runs as pure Python (``PD_SERVICE_PURE=1``, no compiler, a stale
#: build): the numpy form below is the reference it is tested against. ``advance`` makes one
#: step, ``replay`` the replay's loop of them (:meth:`LinearBackend.advance_run`).
_KALMAN: Final = kernel("pd_service.estimation._kalman")
_ADVANCE: Final = kernel_function("pd_service.estimation._kalman", "advance")
_REPLAY: Final = kernel_function("pd_service.estimation._kalman", "replay")
#: The C form of :meth:`LinearBackend.split_step` (a model with Taylor polynomials).
_SPLIT: Final = kernel_function("pd_service.estimation._kalman", "split")

LinearState = tuple[np.ndarray, np.ndarray]  # (x (n,), P (n, n))


# a plain Python class where linear.py is compiled: a frozen dataclass is deep-copied
# through its __setstate__, which a compiled frozen class refuses
@mypyc_attr(native_class=False)
@dataclass(frozen=True, eq=False)
class PropagationTables:
    """Precomputed powers for horizons 0..M. Shapes: Apow (M+1, n, n), Qsum (M+1, n, n),
    Gfull (n, M*nu) with column blocks [A^{M-1}B, ..., A^0 B].

    ``jumps[m]`` = (A^m, (A^m)^T / 2 contiguous, Qs(m), [A^{m-1}B ... B] (n, m*nu)): the
    arrays of a jump of m steps (views, and one halved transposed copy: halving is exact),
    read by the hot path with one list index. With ``M = A^m P (A^m)^T / 2``, ``M + M^T``
    is A^m P (A^m)^T made exactly symmetric at the cost of one addition.
    """

    M: int
    Apow: np.ndarray
    Qsum: np.ndarray
    Gfull: np.ndarray
    jumps: tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], ...] = ()

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
        ApowT2 = 0.5 * np.swapaxes(Apow, 1, 2)  # C-contiguous: a new array
        for arr in (Apow, Qsum, Gfull, ApowT2):
            arr.setflags(write=False)
        jumps = tuple((Apow[m], ApowT2[m], Qsum[m], Gfull[:, (M - m) * nu :])
                      for m in range(M + 1))
        return cls(M, Apow, Qsum, Gfull, jumps)


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
    """Bytes of a table's arrays (the halved transposed powers included, views once)."""
    return int(2 * t.Apow.nbytes + t.Qsum.nbytes + t.Gfull.nbytes)


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


class Gaussian(NamedTuple):
    """State of :class:`LinearBackend`: mean ``x`` (n,) and covariance ``P`` (n, n), plus what
    re-running its mean recursion with the same covariance needs.

    A state the backend computed from a parent state by :meth:`LinearBackend.advance` (a jump
    of ``m`` steps, then one Kalman update per packet, in sensor order) records ``src``, the
    parent's covariance *object*, ``sensors``, the sensor indices of the packets applied, and
    ``stages``, per packet the gain that maps the prior mean to the posterior mean, as
    float64 records in one ``bytes`` object (:func:`read_stages`; both forms of the step
    write and read them). Arrays are never written after creation. (A NamedTuple: built
    with ``tuple.__new__`` on the hot path, cheaper than a class with ``__init__``.)
    """

    x: np.ndarray
    P: np.ndarray
    src: np.ndarray | None = None
    m: int = 0
    sensors: tuple[int, ...] = ()
    stages: bytes = b""


#: One packet's mean update, as :func:`read_stages` gives it: ``(sensor, kind, j, c, z, K)``.
#: Kind 1 (one unit row ``H = e_j``), 2 (one row ``H = h`` (n,)): ``z`` (1,), x+ = x- +
#: K (c (z - h x-)) with ``K`` = P- h / sqrt(s) (n,), ``c`` = 1 / sqrt(s), s = h P- h^T + r
#: (one vector operation less than forming P- h / s); kind 3 (``H`` (r, n)): x+ = x- +
#: K (z - H x-), ``K`` (n, r), z (r,), j = -1, c = 0. H is the sensor's.
Stage = tuple[int, int, int, float, np.ndarray, np.ndarray]

_new: Final = tuple.__new__


def read_stages(stages: bytes, n: int) -> list[Stage]:
    """The :data:`Stage` of each record of a step's stages for a state of ``n`` values.

    A record is the float64 values ``sensor, kind, j, c, r, z (r), K (n * r, row-major),
    H (r * n; not for kind 1)`` (``_kalman.c``, "Stages"); K is copied (an aligned array)."""
    d = np.frombuffer(stages, dtype=np.float64)
    out: list[Stage] = []
    at = 0
    while at < d.size:
        sensor, kind, j, c, rows = d[at : at + 5].tolist()
        r = int(rows)
        nr = n * r
        z = d[at + 5 : at + 5 + r]
        K = d[at + 5 + r : at + 5 + r + nr].copy()
        out.append((int(sensor), int(kind), int(j), c, z, K.reshape(n, r) if kind == 3 else K))
        at += 5 + r + nr + (0 if kind == 1 else nr)
    return out


def _record(sensor: int, kind: int, j: int, c: float, z: np.ndarray, K: np.ndarray,
            H: np.ndarray) -> np.ndarray:
    """One stage's record (:func:`read_stages`), as the C kernel writes it."""
    head = np.array((sensor, kind, j, c, z.size), dtype=np.float64)
    parts = (head, z, K.ravel()) if kind == 1 else (head, z, K.ravel(), H.ravel())
    return np.concatenate(parts)


#: One sensor prepared for the update: (kind, H (r, n) or h (n,), H^T (n, r), R (r, r),
#: r_scalar, j) with kind and j as in :data:`Stage`.
_Rows = tuple[int, np.ndarray, np.ndarray, np.ndarray, float, int]


def _rows(H: np.ndarray, R: np.ndarray) -> _Rows:
    """Prepare measurement rows H (r, n) with noise R (r, r) for :meth:`LinearBackend.advance`:
    kind 1 (one unit row e_j: P- h and h x- are a column and an entry, no products), 2 (one
    row) or 3 (r >= 2 rows; several unit rows gain nothing: strided slices make the
    following products slower than the saved ones)."""
    H = np.array(H, dtype=np.float64)
    H.setflags(write=False)
    HT = np.ascontiguousarray(H.T)
    if H.shape[0] == 1:
        h = np.ascontiguousarray(H[0])
        nz = np.flatnonzero(h)
        unit = nz.size == 1 and h[nz[0]] == 1.0
        return (1 if unit else 2), h, HT, R, float(R[0, 0]), int(nz[0]) if unit else -1
    return 3, H, HT, R, 0.0, -1


def _chol_inv(S: np.ndarray) -> np.ndarray | None:
    """L^{-1} for the Cholesky factor S = L L^T of a 2 x 2 or 3 x 3 S (lower triangle read),
    by closed formulas (no LAPACK call); None for another size or when a pivot is not
    clearly positive (S singular or nearly so: the caller then uses LU / pinv)."""
    r = S.shape[0]
    if r == 2:
        (a, _), (b, d) = S.tolist()
        if not a > 0.0:
            return None
        l11 = math.sqrt(a)
        l21 = b / l11
        q = d - l21 * l21
        if not q > _PIVOT * d:
            return None
        l22 = math.sqrt(q)
        return np.array(((1.0 / l11, 0.0), (-l21 / (l11 * l22), 1.0 / l22)))
    if r == 3:
        (a, _, _), (b, e, _), (c, f, i) = S.tolist()
        if not a > 0.0:
            return None
        l11 = math.sqrt(a)
        l21, l31 = b / l11, c / l11
        q2 = e - l21 * l21
        if not q2 > _PIVOT * e:
            return None
        l22 = math.sqrt(q2)
        l32 = (f - l31 * l21) / l22
        q3 = i - l31 * l31 - l32 * l32
        if not q3 > _PIVOT * i:
            return None
        l33 = math.sqrt(q3)
        return np.array(((1.0 / l11, 0.0, 0.0),
                         (-l21 / (l11 * l22), 1.0 / l22, 0.0),
                         ((l21 * l32 - l22 * l31) / (l11 * l22 * l33), -l32 / (l22 * l33),
                          1.0 / l33)))
    return None


#: A Cholesky pivot must exceed this fraction of its diagonal entry (else LU / pinv).
_PIVOT: Final = 1e-10


# compiled by mypyc (setup.py) where the hot path is; deep-copied with its estimator
# (serializable) and subclassed by tests (allow_interpreted_subclasses; see inputs.py)
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class LinearBackend:
    """Kalman filter steps for :class:`ReplayEstimator`; state = :class:`Gaussian`.

    :meth:`advance` is the replay's fused step (jump, then one update per packet). The
    covariance recursion does not depend on the values of z and u, only on the parent
    covariance, the jump m and which packets (sensors, R) were applied; a step whose ``old``
    posterior was computed from the same covariance object with the same m re-runs only the
    mean through the packets ``old`` applied::

        x- = A^m x + [A^{m-1}B ... B] [u(a); ...; u(a+m-1)]      x+ = x- + K (z - H x-)

    with the stored gains K, keeps the covariance after them, and updates only with packets
    that joined the step since (if ``old``'s packets are the first of the step's, in sensor
    order; otherwise the step is recomputed from the prior).
    """

    def __init__(self, model: LinearModel, sensors: list[Sensor], horizon: int) -> None:
        self.model = model
        self.sensors = sensors
        self.tables = tables_for(model, horizon)
        self._nu = model.nu
        self._M = self.tables.M
        self._jumps = self.tables.jumps
        self._single = [_rows(s.H, s.R) for s in sensors]
        k = _KALMAN
        #: Whether :meth:`advance` runs the C kernel (built, and the sizes fit its buffers)
        #: or the numpy form. (A flag, not the module: estimators are deep-copied.)
        self.use_kernel = k is not None and model.n <= k.MAX_N and all(
            s.m <= k.MAX_R for s in sensors)
        self._G = self.tables.Gfull if self._nu else None  # the kernel reads its last m*nu columns
        taylor = model.taylor
        #: The Taylor coefficients and period the kernel's split step reads (None: numpy).
        self._coef = None if taylor is None else taylor.coef
        self._period = model.period if model.period is not None else 0.0

    def propagate(self, state: Gaussian, step: int, m: int, U: np.ndarray) -> Gaussian:
        return self.advance(state, m, U, [], None)

    def advance_run(self, state: Gaussian, a: int, steps: list[int], buf: np.ndarray, off: int,
                    packets: dict[int, list[Packet]], chk: dict[int, Gaussian],
                    noreuse: int | None,
                    cut_view: tuple[list[int], dict[int, float], np.ndarray, int]
                    ) -> tuple[Gaussian, int, int]:
        """The replay's loop of :meth:`advance` calls over the measured ``steps`` (rising,
        after ``a``) in one C call (``_kalman.replay``), the inputs u(t) = buf[t - off] read
        in place, the commands inside steps from ``cut_view``
        (:meth:`.inputs.InputBuffer.cut_view`)::

            for s in steps:
                e = s + 1 if off_grid(packets[s]) else s
                old = chk.get(s) if noreuse is None or s < noreuse else None
                chk[s] = state = advance(state, s - a, buf[a - off : e - off], packets[s], old,
                                         <the cuts inside steps a .. e - 1>)
                a = e

        Returns (state, a, done): the first ``done`` steps were made and stored (the same
        calls, the same bits as the loop); the caller makes the rest with :meth:`advance`
        (the numpy form, or a jump longer than the tables). Without the kernel: none. The C
        loop does not call :meth:`advance`: a subclass (or a test's patch) that replaces
        ``advance`` replaces this too."""
        run = _REPLAY if self.use_kernel else None
        if run is None:
            return state, a, 0
        cut_steps, cut_offsets, u_before, origin = cut_view
        return cast(tuple[Gaussian, int, int],
                    run(Gaussian, self._jumps, self._G, self._single, state, a, steps, buf, off,
                        packets, chk, noreuse, cut_steps, cut_offsets, u_before, origin,
                        self._coef, self._period))

    def update(self, state: Gaussian, step: int, packets: list[Packet]) -> Gaussian:
        return self.advance(state, 0, U=np.empty((0, self._nu)), packets=packets, old=None)

    def advance(self, state: Gaussian, m: int, U: np.ndarray, packets: list[Packet],
                old: Gaussian | None, cuts: list[Cut] | None = None) -> Gaussian:
        """x(a) -> x(a + m) with inputs U (m, nu), then one Kalman update per packet in
        ``packets`` (sorted by sensor, possibly none; sequential updates equal the stacked one
        of eq. (24), R* being block diagonal). ``old`` (this step's previous result, or None)
        was computed from the same covariance object and jump: its covariance after its
        packets is reused if they are the first of ``packets`` (a packet that joins a step
        costs only its own update); the mean is re-run through its stored gains::

            P- = A^m P (A^m)^T + Qs(m)
            S = H P- H^T + R = L L^T,   W = P- H^T L^{-T},   K = W L^{-1} = P- H^T S^{-1}
            x+ = x- + K (z - H x-),   P+ = P- - W W^T
            one row h:  s = h P- h^T + r,  W = P- h / sqrt(s),  K = W / sqrt(s)  (0 if s <= 0)

        Every covariance is kept exactly symmetric (the filter's covariance recursion is not
        stable against antisymmetric rounding errors): A^m P (A^m)^T is formed as M + M^T
        with M = A^m P (A^m)^T / 2, and the downdate W W^T is symmetric by construction. A
        2 x 2 or 3 x 3 S is factored by closed formulas; a larger or (nearly) singular S
        goes through LU, or the pseudo-inverse, and an explicit symmetrisation. The result
        depends only on the parent state, the inputs and the packets, not on whether ``old``
        was reused (the same operations either way).

        With the kernel (:attr:`use_kernel`) the step is one C call (``_kalman.advance``);
        a step it does not take (a jump longer than the tables, a nearly singular S) is
        made by the numpy form, :meth:`numpy_step`.

        A step with events inside it (packets off the grid, commands taking effect inside a
        step: ``cuts``) is :meth:`split_step`; a span with commands inside steps but no
        packets (the prediction, a base rolled forward) keeps the grid step's covariance
        (inputs do not move it; reused as above) and walks the mean alone
        (:meth:`split_step`, ``mean_only``).
        """
        if cuts is not None or (packets and packets[-1][3] > 0.0):
            if packets:
                return self._split(state, m, U, packets, cuts, False)
            g = self._grid(state, m, U, packets, old)
            x = self._split(state, m, U, packets, cuts, True)[0]
            return _new(Gaussian, (x, g[1], g[2], g[3], g[4], g[5]))
        return self._grid(state, m, U, packets, old)

    def _split(self, state: Gaussian, m: int, U: np.ndarray, packets: list[Packet],
               cuts: list[Cut] | None, mean_only: bool) -> Gaussian:
        """:meth:`split_step` by the kernel where it takes it (``_kalman.split``)."""
        spl = _SPLIT if self.use_kernel and self._coef is not None and m < self._M else None
        if spl is not None:
            got = spl(Gaussian, self._jumps, self._G, self._single, state, m, U, packets,
                      [] if cuts is None else cuts, self._coef, self._period, mean_only)
            if got is not None:  # else a packet the kernel does not take: numpy
                return cast(Gaussian, got)
        return self.split_step(state, m, U, packets, cuts, mean_only)

    def _grid(self, state: Gaussian, m: int, U: np.ndarray, packets: list[Packet],
              old: Gaussian | None) -> Gaussian:
        """A step on the grid: the kernel's where it takes it, else :meth:`numpy_step`."""
        adv = _ADVANCE if self.use_kernel and m <= self._M else None
        if adv is not None:
            got = adv(Gaussian, self._jumps, self._G, self._single, state, m, U, packets, old)
            if got is not None:  # else a step the kernel does not take: the numpy form's
                return cast(Gaussian, got)
        return self.numpy_step(state, m, U, packets, old)

    def numpy_step(self, state: Gaussian, m: int, U: np.ndarray, packets: list[Packet],
                   old: Gaussian | None) -> Gaussian:
        """:meth:`advance` in numpy: the reference form of the step, and the whole step
        where the kernel is not used or does not take it."""
        x, P = state[0], state[1]
        npk = len(packets)
        done: tuple[int, ...] = ()
        reuse = False
        if old is not None and old[2] is P and old[3] == m:
            done = old[4]
            k = len(done)
            if k == 0:
                reuse = True
            elif k <= npk and packets[0].sensor == done[0]:
                reuse = k == 1 or tuple([p.sensor for p in packets[:k]]) == done
            if not reuse:
                done = ()  # old applied other packets first: start from the prior
        Pp = P
        if m == 0:
            xp = x
        else:
            xp, Pj = self._jump(x, None if reuse else P, m, U)
            if Pj is not None:
                Pp = Pj
        stages = b""
        if reuse:  # the covariance after old's packets is unchanged: their means only
            assert old is not None
            stages = old[5]
            if stages:
                xp = self._remean(xp, stages)
            if len(done) == npk:
                return _new(Gaussian, (xp, old[1], P, m, done, stages))
            Pp = old[1]
        if not npk:
            return _new(Gaussian, (xp, Pp, P, m, (), b""))
        sensors = (packets[0].sensor,) if npk == 1 else tuple([p.sensor for p in packets])
        xp, Pp, records = self._apply(xp, Pp, packets, len(done))
        return _new(Gaussian, (xp, Pp, P, m, sensors,
                               stages + np.concatenate(records).tobytes()))

    def _apply(self, xp: np.ndarray, Pp: np.ndarray, packets: list[Packet],
               start: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """The Kalman updates of ``packets[start:]`` on (x-, P-), in turn: (x+, P+, the
        stages' records) (formulas: :meth:`advance`)."""
        single = self._single
        records: list[np.ndarray] = []
        for i in range(start, len(packets)):
            p = packets[i]
            kind, H, HT, R, r, j = single[p.sensor]
            z = p.z
            if p.R is not None:
                R = p.R
                r = float(R[0, 0])
            if kind <= 2:  # one row: s = h P- h^T + r is a scalar
                zs = z.item(0)
                if kind == 1:
                    PHt = Pp[:, j]
                    s = Pp.item(j, j) + r
                    innov = zs - xp.item(j)
                else:
                    PHt = Pp.dot(H)
                    s = float(H.dot(PHt)) + r
                    innov = zs - H.dot(xp)
                if not s > 0.0:  # h P- h^T + r = 0: the sample tells nothing new (K = 0)
                    records.append(_record(p.sensor, kind, j, 0.0, z, PHt * 0.0, H))
                    continue
                c = 1.0 / math.sqrt(s)
                w = PHt * c  # K = w c, and K (P- h)^T = w w^T, exactly symmetric
                xp = xp + w * (c * innov)
                Pp = Pp - w[:, None].dot(w[None, :])
                records.append(_record(p.sensor, kind, j, c, z, w, H))
                continue
            PHt = Pp.dot(HT)
            S = H.dot(PHt) + R
            Li = _chol_inv(S)
            if Li is not None:  # S = L L^T, W = P- H^T L^-T: K = W L^-1, K (P- H^T)^T = W W^T
                W = PHt.dot(Li.T)
                K = W.dot(Li)
                Pn = Pp - W.dot(W.T)  # exactly symmetric (numpy computes W W^T with syrk)
            else:
                try:
                    K = np.linalg.solve(S, PHt.T).T
                except np.linalg.LinAlgError:
                    K = PHt.dot(np.linalg.pinv(S))
                Pn = Pp - K.dot(PHt.T)
                Pn = (Pn + Pn.T) * 0.5
                K = np.ascontiguousarray(K)  # as read back from the record: a remean's bits
            xp = xp + K.dot(z - H.dot(xp))
            Pp = Pn
            records.append(_record(p.sensor, 3, -1, 0.0, z, K, H))
        return xp, Pp, records

    def split_step(self, state: Gaussian, m: int, U: np.ndarray, packets: list[Packet],
                   cuts: list[Cut] | None, mean_only: bool = False) -> Gaussian:
        """:meth:`advance` for a step with events inside steps (numpy; a continuous-time
        model): from x(a), the packets at their own times ``a + m + offset`` and the
        commands taking effect at theirs (``cuts``, :data:`.replay.Cut`), in time order;
        the result is at a + m + 1 if a packet lies off the grid (U then has m + 1 rows),
        else at a + m. Between events the exact discretisation over each interval tau
        (:meth:`.model.LinearModel.over`), whole steps by the tables::

            x(t + tau) = A(tau) x(t) + B(tau) u,   P(t + tau) = A(tau) P(t) A(tau)^T + Q(tau)

        with u the input in effect (u_before of a cut until its offset, then its row of
        U). A state made here is never reused as ``old`` (it records no parent).
        ``mean_only`` (no packets): x walked alone, P the state's."""
        model = self.model
        T = model.period
        if T is None:
            raise ValueError("a discrete model (A, B, Q only) takes samples and commands on "
                             "the grid only")
        end = m + 1 if packets and packets[-1][3] > 0.0 else m
        if U.shape[0] < end:
            raise ValueError(f"U: {U.shape[0]} rows for a step ending {end} steps on")
        cut_at = {i: (d, ub) for i, d, ub in cuts or ()}
        # events in time order: (row, offset, 0: a command's cut / 1: packet, its index)
        events = sorted([(i, d, 0, 0) for i, d, _ in cuts or ()]
                        + [(m, p[3], 1, k) for k, p in enumerate(packets)])
        events.append((end, 0.0, 2, 0))
        if mean_only and packets:
            raise ValueError("split_step: the mean alone only without packets")
        x = state[0]
        P: np.ndarray | None = None if mean_only else state[1]
        r, f = 0, 0.0  # the cursor: row r, f seconds into it
        for row, off, what, k in events:
            if row > r:
                if f > 0.0:  # the rest of row r
                    x, P = self._segment(x, P, T - f, self._u_in(U, cut_at, r, f))
                    r, f = r + 1, 0.0
                if row > r:
                    x, P = self._jump(x, P, row - r, U[r:row])
                    r = row
            if off > f:
                x, P = self._segment(x, P, off - f, self._u_in(U, cut_at, r, f))
                f = off
            if what == 1:
                assert P is not None
                x, P, _ = self._apply(x, P, [packets[k]], 0)
        return _new(Gaussian, (x, state[1] if P is None else P, None, 0, (), b""))

    def _u_in(self, U: np.ndarray, cut_at: dict[int, tuple[float, np.ndarray]], row: int,
              f: float) -> np.ndarray:
        """The input in effect f seconds into row ``row`` of U (before a cut: its u_before)."""
        c = cut_at.get(row)
        if c is not None and f < c[0]:
            return c[1]
        return U[row] if self._nu else np.zeros(0)

    def _segment(self, x: np.ndarray, P: np.ndarray | None, tau: float,
                 u: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(x, P) propagated over tau seconds with u held: A x + B u, A P A^T + Q, the
        covariance made exactly symmetric as in :meth:`_jump` (P None: the mean alone)."""
        A, B, Q = self.model.over(tau)
        xp = A.dot(x)
        if self._nu:
            xp += B.dot(u)
        if P is None:
            return xp, None
        Mh = A.dot(P).dot(A.T) * 0.5
        Pp = Mh + Mh.T.copy()
        Pp += Q
        return xp, Pp

    def _jump(self, x: np.ndarray, P: np.ndarray | None, m: int,
              U: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """x- and P- (None: the mean only) after m >= 1 steps with inputs U (m, nu); a jump
        longer than the tables (a session idle that long) in table-sized jumps first."""
        M = self._M
        while m > M:
            x, P = self._jump(x, P, M, U[:M])
            U = U[M:]
            m -= M
        A, AT2, Qs, G = self._jumps[m]
        xp = A.dot(x)
        if self._nu:
            xp += G.dot(U.reshape(-1))
        if P is None:
            return xp, None
        Mh = A.dot(P).dot(AT2)  # A^m P (A^m)^T / 2
        Pp = Mh + Mh.T.copy()  # copying the transpose first: a contiguous addition
        Pp += Qs
        return xp, Pp

    def propagate_constant(self, state: Gaussian, m: int, u: np.ndarray) -> Gaussian:
        """x(a) -> x(a + m) with one input u (nu,) over all m >= 1 steps (no command inside
        the span): O(log m) products instead of m steps (a session whose epoch lies far in
        the past, or idle for long). Blocks of span s = 2^i, by doubling::

            A_2s = A_s A_s,   Q_2s = A_s Q_s A_s^T + Q_s,   g_2s = A_s g_s + g_s

        (A_s = A^s, Q_s = sum_{j<s} A^j Q A^jT, g_s = sum_{j<s} A^j B u), each applied for a
        set bit of m: x <- A_s x + g_s, P <- A_s P A_s^T + Q_s (the blocks commute: all are
        powers of one A under one input). Equal to m single steps up to rounding."""
        model = self.model
        As, Qs = model.A, model.Q
        gs = model.B.dot(u) if self._nu else np.zeros(model.n)
        x, P = state[0], state[1]
        while True:
            if m & 1:
                x = As.dot(x) + gs
                P = As.dot(P).dot(As.T) + Qs
                P = 0.5 * (P + P.T)
            m >>= 1
            if not m:
                return Gaussian(x, P)
            gs = As.dot(gs) + gs
            Qs = As.dot(Qs).dot(As.T) + Qs
            Qs = 0.5 * (Qs + Qs.T)
            As = As.dot(As)

    def _remean(self, x: np.ndarray, stages: bytes) -> np.ndarray:
        """The mean recursion of ``stages`` from the prior mean ``x`` (no covariance work)."""
        single = self._single
        for sensor, kind, j, c, z, K in read_stages(stages, x.shape[0]):
            if kind == 1:
                x = x + K * (c * (z.item(0) - x[j]))
            elif kind == 2:
                x = x + K * (c * (z.item(0) - single[sensor][1].dot(x)))
            else:
                x = x + K.dot(z - single[sensor][1].dot(x))
        return x

    def moments(self, state: Gaussian) -> LinearState:
        return state.x, state.P

    def export_state(self, state: Gaussian) -> dict[str, np.ndarray]:
        return {"x": state.x.copy(), "P": state.P.copy()}

    def import_state(self, arrays: dict[str, np.ndarray]) -> Gaussian:
        return Gaussian(*import_gaussian(arrays, self.model.n))


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
