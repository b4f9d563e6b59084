"""Stacked evaluation of many sessions' Kalman steps: the same estimator, batched numerics.

Per-session numpy work on 4 x 4 matrices is dominated by call overhead (~2 µs a call, a
dozen calls per Kalman step), so a daemon serving hundreds of sessions spends most of its
time entering numpy. This module keeps the estimator's bookkeeping exactly as it is (the
timestamp window, commits, command buffer and replay of
:class:`pd_service.estimation.ReplayEstimator`) and changes only *when* the arithmetic runs:

- :class:`LazyLinearBackend` is a fused Backend whose ``advance`` (propagate m steps, then
  condition on the step's packets) returns a :class:`Node` (an operation plus its parent)
  instead of computing at once: one node per measured step and one per prediction;
- :func:`resolve` evaluates the pending chains of many sessions together: chains are
  aligned by depth and, at each depth, the nodes with the same operation and shape are
  computed as one stack (``(S, n, n)`` arrays through ``np.matmul`` / ``np.linalg.solve``);
- :class:`StackedObserverPredictor` is the session estimator built on them: same API and
  same results as :class:`~pd_service.estimation.ObserverPredictor` (to rounding: the
  matrix products are the same, the matrix-vector ones are done as stacked matmuls).

The same formulas as ``pd_service.estimation.linear``::

    propagate m steps:  x <- A^m x + [A^{m-1}B ... B] [u(a); ...; u(a+m-1)]
                        P <- A^m P (A^m)^T + Qs(m)
    update:             S = H P H^T + R,  K = P H^T S^{-1}  (K = P H^T / s for one row,
                        0 if s = 0; pinv when S is singular)
                        x <- x + K (z - H x),  P <- P - K (P H^T)^T,  P <- (P + P^T) / 2

Each slice of a stacked product is computed by the same kernel as the single product, so
a session's numbers do not depend on which other sessions share its batch (tested).
Memory stays bounded: a resolved node drops its parent, and a chain deeper than
``MAX_PENDING_DEPTH`` is resolved on the spot.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
from mypy_extensions import mypyc_attr

from pd_service.estimation import LinearModel, Packet, ReplayEstimator, Sensor
from pd_service.estimation.checks import as_covariance, as_vector
from pd_service.estimation.linear import block_diag, import_gaussian, kalman_update, tables_for

#: Longest chain of pending operations before a node is resolved on its own.
MAX_PENDING_DEPTH = 64

#: Node operations: propagate, update, propagate then update (one node per measured step).
_PROP, _UPD, _ADV = 1, 2, 3


#: x and P of a pending node (an empty array: read them after :func:`resolve`).
_PENDING = np.empty(0)
_PENDING.setflags(write=False)


class Node:
    """A Gaussian state (x (n,), P (n, n)), resolved or pending.

    Pending: ``op`` is ``_PROP`` with ``arg = (m, bu, tables)`` (bu = the inputs'
    contribution to x), ``_UPD`` with ``arg = (H, R, z)`` or ``_ADV`` with
    ``arg = (m, bu, tables, H, R, z)`` (the two in turn), applied to ``parent``; ``x`` and
    ``P`` are empty.
    Resolved: ``op`` is 0, ``x`` and ``P`` hold the values, ``parent`` is None.
    """

    __slots__ = ("parent", "op", "arg", "x", "P", "depth")

    def __init__(self, parent: Node | None, op: int, arg: tuple[Any, ...],
                 x: np.ndarray = _PENDING, P: np.ndarray = _PENDING) -> None:
        self.parent = parent
        self.op = op
        self.arg = arg
        self.x = x
        self.P = P
        self.depth: int = 0 if parent is None or parent.op == 0 else parent.depth + 1

    @classmethod
    def resolved(cls, x: np.ndarray, P: np.ndarray) -> Node:
        return cls(None, 0, (), x, P)

    def value(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, P), resolving the chain on its own if still pending."""
        if self.op:
            resolve([self])
        return self.x, self.P


_INTERNED: dict[tuple[tuple[int, ...], bytes], np.ndarray] = {}
#: The interned matrices take at most this many bytes (oldest dropped first).
_INTERN_MAX_BYTES = 8 * 2**20
_interned_bytes = [0]


def _intern(arr: np.ndarray) -> np.ndarray:
    """One shared read-only copy per distinct matrix, so that sessions of the same robot
    type share their H objects and their updates fall in the same stacked group."""
    key = (arr.shape, arr.tobytes())
    got = _INTERNED.get(key)
    if got is None:
        got = np.array(arr, dtype=np.float64)
        got.setflags(write=False)
        while _INTERNED and _interned_bytes[0] + got.nbytes > _INTERN_MAX_BYTES:
            _interned_bytes[0] -= _INTERNED.pop(next(iter(_INTERNED))).nbytes
        _INTERNED[key] = got
        _interned_bytes[0] += got.nbytes
    return got


class LazyLinearBackend:
    """Backend for :class:`ReplayEstimator` whose state is a :class:`Node`."""

    def __init__(self, model: LinearModel, sensors: list[Sensor], horizon: int) -> None:
        self.model = model
        self.sensors = sensors
        self._H = [_intern(s.H) for s in sensors]
        self.tables = tables_for(model, horizon)
        self._nu = model.nu
        self._stacked: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray]] = {}

    def propagate(self, state: Node, step: int, m: int, U: np.ndarray) -> Node:
        t = self.tables
        M = t.M
        node = state
        while m > 0:
            k = min(m, M)
            if node.op and node.depth >= MAX_PENDING_DEPTH:
                resolve([node])
            node = Node(node, _PROP, (k, self._bu(U, k), t))
            U = U[k:]
            m -= k
        return node

    def _bu(self, U: np.ndarray, k: int) -> np.ndarray | None:
        """[A^{k-1}B, ..., B] [u(a); ...; u(a+k-1)] for the first k rows of U (k <= M): the
        last k*nu columns of the full stacked matrix (.dot: half the call cost of @ on tiny
        arrays; one per node, stacked or not). None without inputs."""
        if not self._nu:
            return None
        if U.shape[0] != k:
            U = U[:k]
        return self.tables.jumps[k][3].dot(U.reshape(-1))  # the view Gfull[:, (M-k)*nu:]

    def advance(self, state: Node, m: int, U: np.ndarray, packets: list[Packet],
                old: Node | None) -> Node:
        """x(a) -> x(a + m), then conditioned on ``packets``: one node (the propagation of
        a jump longer than the tables' horizon M goes first, in nodes of M steps, as
        :meth:`propagate` splits it). The same products as ``update(propagate(...))``, so
        the same bits. ``old`` is not used (nothing is computed before :func:`resolve`)."""
        if not packets:
            return self.propagate(state, 0, m, U)
        if m <= 0:
            return self.update(state, 0, packets)
        M = self.tables.M
        if m > M:
            head = M * ((m - 1) // M)
            state = self.propagate(state, 0, head, U)
            U, m = U[head:], m - head
        H, R, z = self._measurement(packets)
        if state.op and state.depth >= MAX_PENDING_DEPTH:
            resolve([state])
        return Node(state, _ADV, (m, self._bu(U, m), self.tables, H, R, z))

    def update(self, state: Node, step: int, packets: list[Packet]) -> Node:
        H, R, z = self._measurement(packets)
        if state.op and state.depth >= MAX_PENDING_DEPTH:
            resolve([state])
        return Node(state, _UPD, (H, R, z))

    def _measurement(self, packets: list[Packet]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(H, R, z) of a step's packets (sorted by sensor): one sensor's, or the stacked
        rows of the sensors present, M*(tau) of eq. (24)."""
        if len(packets) == 1:
            p = packets[0]
            sensor = self.sensors[p.sensor]
            H, R, z = self._H[p.sensor], (sensor.R if p.R is None else p.R), p.z
        else:  # stacked rows of the sensors present this step, M*(tau) of eq. (24)
            key = tuple(p.sensor for p in packets)
            stacked = self._stacked.get(key)
            if stacked is None:
                Hs = _intern(np.vstack([self.sensors[i].H for i in key]))
                stacked = (Hs, block_diag([self.sensors[i].R for i in key]))
                self._stacked[key] = stacked
            H, R = stacked
            if any(p.R is not None for p in packets):
                R = block_diag([self.sensors[p.sensor].R if p.R is None else p.R
                                 for p in packets])
            z = np.concatenate([p.z for p in packets])
        return H, R, z

    def moments(self, state: Node) -> tuple[Node, Node]:
        """The node itself, twice: read ``.x`` / ``.P`` after :func:`resolve`."""
        return state, state

    def export_state(self, state: Node) -> dict[str, np.ndarray]:
        """{"x": (n,), "P": (n, n)} of the node (resolved on the spot if pending)."""
        x, P = state.value()
        return {"x": x.copy(), "P": P.copy()}

    def import_state(self, arrays: dict[str, np.ndarray]) -> Node:
        return Node.resolved(*import_gaussian(arrays, self.model.n))


# ------------------------------------------------------------------ batched evaluation ---

def resolve(nodes: Iterable[Node]) -> None:
    """Resolve every pending node on the chains ending at ``nodes``, stacked by depth."""
    chains: list[list[Node]] = []
    seen: set[int] = set()
    for nd in nodes:
        chain: list[Node] = []
        while nd is not None and nd.op and id(nd) not in seen:
            seen.add(id(nd))
            chain.append(nd)
            nd = nd.parent  # type: ignore[assignment]  # None ends the loop
        if chain:
            chain.reverse()
            chains.append(chain)
    if not chains:
        return
    if len(chains) == 1:  # nothing to stack: plain 2-D products (bit-identical to a slice)
        for nd in chains[0]:
            _ONE[nd.op](nd)
        return
    # Chains of different sessions never share nodes. Two targets of one estimator can:
    # ``seen`` cuts the second chain where it joins the first; a node whose parent is not
    # resolved yet when its depth comes is left for a second pass, in order.
    depth = 0
    longest = max(len(c) for c in chains)
    leftovers: list[Node] = []
    while depth < longest:
        # same operation, same tables / H (objects shared by sessions of one model): one stack
        groups: dict[tuple[int, int, int], list[Node]] = {}
        for c in chains:
            if depth < len(c):
                nd = c[depth]
                if nd.parent is not None and nd.parent.op:  # parent not resolved yet
                    leftovers.append(nd)
                    continue
                op, arg = nd.op, nd.arg
                if op == _PROP:
                    key = (op, id(arg[2]), 0)
                elif op == _UPD:
                    key = (op, id(arg[0]), 0)
                else:
                    key = (op, id(arg[2]), id(arg[3]))
                grp = groups.get(key)
                if grp is None:
                    groups[key] = [nd]
                else:
                    grp.append(nd)
        for (op, _, _), grp in groups.items():
            if len(grp) <= _SMALL_GROUP:
                one = _ONE[op]
                for nd in grp:
                    one(nd)
            else:
                _GROUP[op](grp)
        depth += 1
    for nd in leftovers:
        if nd.op:
            resolve([nd])


#: Groups up to this size are computed node by node (stacking costs more than it saves).
_SMALL_GROUP = 2


def _set(nd: Node, x: np.ndarray, P: np.ndarray) -> None:
    nd.x, nd.P, nd.op, nd.parent, nd.arg = x, P, 0, None, ()


def _prop(x: np.ndarray, P: np.ndarray, m: int, bu: np.ndarray | None,
          t: Any) -> tuple[np.ndarray, np.ndarray]:
    """One propagation, the single form of :func:`_prop_stack` (same products, so the same
    bits as a slice of the stack)."""
    Am = t.Apow[m]
    xn = (Am @ x[:, None])[:, 0]
    if bu is not None:
        xn = xn + bu
    return xn, Am @ P @ Am.T + t.Qsum[m]


def _upd(x: np.ndarray, P: np.ndarray, H: np.ndarray, R: np.ndarray,
         z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One update, the single form of :func:`_upd_stack` (same products, same bits); a
    singular S: the reference's pinv form."""
    PHt = P @ H.T
    S = H @ PHt + R
    if H.shape[0] == 1:
        s = S[0, 0]
        K = PHt / s if s > 0.0 else np.zeros_like(PHt)
    else:
        try:
            K = np.linalg.solve(S, PHt.T).T
        except np.linalg.LinAlgError:
            return kalman_update(x, P, H, R, z)
    innov = z - (H @ x[:, None])[:, 0]
    xn = x + (K @ innov[:, None])[:, 0]
    Pn = P - K @ PHt.T
    return xn, 0.5 * (Pn + Pn.T)


def _propagate_one(nd: Node) -> None:
    m, bu, t = nd.arg
    x, P = _prop(nd.parent.x, nd.parent.P, m, bu, t)  # type: ignore[union-attr]  # pending: has a parent
    _set(nd, x, P)


def _update_one(nd: Node) -> None:
    H, R, z = nd.arg
    x, P = _upd(nd.parent.x, nd.parent.P, H, R, z)  # type: ignore[union-attr]  # pending: has a parent
    _set(nd, x, P)


def _advance_one(nd: Node) -> None:
    m, bu, t, H, R, z = nd.arg
    x, P = _prop(nd.parent.x, nd.parent.P, m, bu, t)  # type: ignore[union-attr]  # pending: has a parent
    x, P = _upd(x, P, H, R, z)
    _set(nd, x, P)


def _stack(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.stack`` of equal-shape arrays, the same copy (and bits) at a third of the cost
    for the few small arrays of a group."""
    return np.array(arrays)


def _finish(grp: Sequence[Node], X: np.ndarray, P: np.ndarray) -> None:
    for i, nd in enumerate(grp):
        nd.x = X[i]
        nd.P = P[i]
        nd.op = 0
        nd.parent = None
        nd.arg = ()


def _parents(grp: list[Node]) -> tuple[np.ndarray, np.ndarray]:
    """The stacked (S, n) means and (S, n, n) covariances of the group's parents."""
    X = _stack([nd.parent.x for nd in grp])  # type: ignore[union-attr]  # a pending node has a parent
    P = _stack([nd.parent.P for nd in grp])  # type: ignore[union-attr]  # a pending node has a parent
    return X, P


def _prop_stack(grp: list[Node], X: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Propagations of a group whose ``arg`` starts with (m, bu, tables), one tables."""
    t = grp[0].arg[2]
    ms = np.fromiter((nd.arg[0] for nd in grp), dtype=np.intp, count=len(grp))
    Am = t.Apow[ms]  # (S, n, n)
    Xn = np.matmul(Am, X[:, :, None])[:, :, 0]  # A^m x
    if grp[0].arg[1] is not None:
        Xn = Xn + _stack([nd.arg[1] for nd in grp])  # + [A^{m-1}B ... B] U
    return Xn, np.matmul(np.matmul(Am, P), np.swapaxes(Am, 1, 2)) + t.Qsum[ms]


def _upd_stack(H: np.ndarray, R: np.ndarray, Z: np.ndarray, X: np.ndarray,
               P: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Updates with one H (m, n), R (S, m, m), Z (S, m); None if S is singular somewhere
    (the caller then goes node by node, with the same products: the others keep their
    bits)."""
    m = H.shape[0]
    PHt = np.matmul(P, H.T)  # (S, n, m)
    S = np.matmul(H, PHt) + R  # (S, m, m)
    if m == 1:
        s = S[:, 0, 0]
        pos = s > 0.0
        K = np.zeros_like(PHt)
        K[pos] = PHt[pos] / s[pos, None, None]
    else:
        try:
            K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, 1, 2)), 1, 2)
        except np.linalg.LinAlgError:
            return None
    innov = Z - np.matmul(H, X[:, :, None])[:, :, 0]
    Xn = X + np.matmul(K, innov[:, :, None])[:, :, 0]
    Pn = P - np.matmul(K, np.swapaxes(PHt, 1, 2))
    return Xn, 0.5 * (Pn + np.swapaxes(Pn, 1, 2))


def _propagate_group(grp: list[Node]) -> None:
    X, P = _parents(grp)
    Xn, Pn = _prop_stack(grp, X, P)
    _finish(grp, Xn, Pn)


def _update_group(grp: list[Node]) -> None:
    X, P = _parents(grp)
    _update_and_finish(grp, X, P, 0, _update_one)


def _advance_group(grp: list[Node]) -> None:
    X, P = _parents(grp)
    X, P = _prop_stack(grp, X, P)
    _update_and_finish(grp, X, P, 3, _advance_one)


def _update_and_finish(grp: list[Node], X: np.ndarray, P: np.ndarray, at: int,
                       one: Callable[[Node], None]) -> None:
    """Condition the group's (X, P) on (H, R, z) = ``arg[at:at + 3]`` and finish its nodes; a
    singular S somewhere: each node by ``one`` instead (from its parent, the same products,
    so the others keep their bits)."""
    got = _upd_stack(grp[0].arg[at], _stack([nd.arg[at + 1] for nd in grp]),
                     _stack([nd.arg[at + 2] for nd in grp]), X, P)
    if got is None:
        for nd in grp:
            one(nd)
        return
    _finish(grp, got[0], got[1])


#: The single-node and the stacked evaluation of each operation.
_ONE = {_PROP: _propagate_one, _UPD: _update_one, _ADV: _advance_one}
_GROUP = {_PROP: _propagate_group, _UPD: _update_group, _ADV: _advance_group}


# ------------------------------------------------------------------ the estimator -------

# compiled (setup.py): a compiled subclass of a serializable class needs both flags too, else
# (mypy 2.4.1) its __init__ is skipped
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class StackedObserverPredictor(ReplayEstimator[Node]):
    """:class:`~pd_service.estimation.ObserverPredictor` with lazy, batchable numerics.

    ``predict(now)`` returns a PredictedState whose ``x`` and ``P`` are the same pending
    :class:`Node`; call :func:`resolve` on many of them, then read ``node.x`` / ``node.P``.
    """

    def __init__(self, model: LinearModel, sensors: Sequence[Sensor], x0: object, P0: object,
                 lead: int, max_delay: int, command_hold: str = "hold") -> None:
        sensors = list(sensors)
        if not sensors:
            raise ValueError("sensors: at least one sensor is required")
        names = [s.name for s in sensors]
        if len(set(names)) != len(names):
            raise ValueError(f"sensors: duplicate names in {names}")
        for s in sensors:
            if s.H.shape[1] != model.n:
                raise ValueError(f"sensor {s.name!r} H: expected {model.n} columns, "
                                 f"got {s.H.shape[1]}")
        x = as_vector(x0, "x0", model.n)
        P = as_covariance(P0, "P0", model.n)
        super().__init__(backend=None,  # type: ignore[arg-type]  # set below (needs horizon)
                         initial=Node.resolved(x, P), sensor_dims={s.name: s.m for s in sensors},
                         nu=model.nu, lead=lead, max_delay=max_delay,
                         command_hold=command_hold)
        self.model = model
        self.sensors = sensors
        # moments() of this backend are pending Nodes, not arrays: predict()'s x and P are
        # read after resolve() (Session.pack, the core's batched resolve)
        self._backend = LazyLinearBackend(  # type: ignore[assignment]
            model, sensors, self._inputs.capacity)

    @property
    def n(self) -> int:
        return self.model.n
