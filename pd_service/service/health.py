"""Numerical health of a session's estimate: the checks, and the in-memory snapshot it is
recovered to.

A prediction's mean ``x`` (n,) and covariance ``P`` (n, n) are checked before it is
published (:func:`inspect`, every prediction):

- every entry of ``x`` and ``P`` finite;
- ``min_i P_ii >= 0`` (a covariance's diagonal is a variance; a negative one means ``P`` lost
  positive semi-definiteness; zero is allowed: a state may be known exactly).

Before a state is kept as the session's snapshot it passes the thorough test
(:func:`thoroughly_healthy`, once per :data:`SNAPSHOT_EVERY_S` of session time):
``lambda_min(P) >= -1e-9 * max(1, max_i |P_ii|)`` (symmetric eigenvalues, O(n^3); a
Cholesky factorisation in C passes the usual healthy covariance first).

A session whose prediction fails a check (or whose prediction raises) is restored to its
snapshot (``ReplayEstimator.restore_state`` of an ``export_state`` taken at a healthy
step), or to its spec's prior when there is none or that does not help; see
:meth:`pd_service.service.outbox.Outbox.publish_many`.
"""

from __future__ import annotations

import math
from typing import Final

import msgpack
import numpy as np

from pd_service.native import kernel, kernel_function

#: The C form of :func:`inspect_packed` where the hot path runs compiled (else None).
_MOMENTS: Final = kernel("pd_service.service._moments")
_MOMENTS_OF: Final = kernel_function("pd_service.service._moments", "moments")
_pack: Final = msgpack.Packer(use_bin_type=True).pack

#: Session time between two snapshots of a healthy estimator (s).
SNAPSHOT_EVERY_S = 1.0

#: After a recovery that failed even from the prior, no new attempt for this long (session
#: time, s): the session reports ``internal_error`` meanwhile (rate-limited).
RETRY_AFTER_S = 1.0


#: Up to this many entries in P, :func:`inspect` checks Python floats: cheaper than numpy's
#: reductions for small arrays.
_SMALL: Final = 256


def inspect(x: np.ndarray, P: np.ndarray) -> tuple[str | None, list[float], list[float]]:
    """Why (x (n,), P (n, n)) may not be published (None if it may), with the entries of x
    and of P (row-major) as Python floats: read and checked once here, then packed as they
    are (:func:`inspect_packed`'s Python form). Cheap: O(n^2) reads."""
    xs, ps = x.tolist(), P.ravel().tolist()
    if P.size <= _SMALL:
        # fsum of finite values is finite unless it overflows (then numpy looks closer);
        # it raises ValueError for inf + -inf
        try:
            finite = math.isfinite(math.fsum(xs)) and math.isfinite(math.fsum(ps))
        except (OverflowError, ValueError):
            finite = False
        if not finite and not (np.isfinite(x).all() and np.isfinite(P).all()):
            return _NON_FINITE, xs, ps
        return (_NEGATIVE if ps and min(ps[::P.shape[0] + 1]) < 0.0 else None), xs, ps
    if not (np.isfinite(x).all() and np.isfinite(P).all()):
        return _NON_FINITE, xs, ps
    if P.diagonal().min() < 0.0:
        return _NEGATIVE, xs, ps
    return None, xs, ps


_NON_FINITE = "non-finite estimate (NaN or infinity in x or P)"
_NEGATIVE = "covariance not positive semi-definite (a negative variance on its diagonal)"
_VERDICTS: Final = (None, _NON_FINITE, _NEGATIVE)


def inspect_packed(x: np.ndarray, P: np.ndarray) -> tuple[str | None, bytes, bytes]:
    """:func:`inspect`'s verdict on (x (n,), P (n, n)), with x's and P's values (row-major)
    as msgpack arrays of floats, ``msgpack.packb(list)`` byte for byte: what
    ``PredictionEncoder.encode_packed`` puts in a Prediction. One C call where the hot path
    runs compiled (``_moments.c``); this Python form (the reference) otherwise, and for
    arrays it does not take (another dtype or shape)."""
    k = _MOMENTS_OF
    if k is not None:
        try:
            verdict, xb, pb = k(x, P)
        except TypeError:
            pass
        else:
            return _VERDICTS[verdict], xb, pb
    bad, xs, ps = inspect(x, P)
    return bad, _pack(xs), _pack(ps)


#: The thorough test's bound: no eigenvalue of (P + P^T) / 2 below ``-EIG_TOL * max(1,
#: max_i |P_ii|)``.
EIG_TOL = 1e-9


def thoroughly_healthy(P: np.ndarray) -> bool:
    """P (n, n) finite with no eigenvalue below ``-1e-9 * max(1, max_i |P_ii|)``.

    Where the hot path runs compiled, a Cholesky factorisation in C
    (``_moments.clearly_psd``, far cheaper than numpy's eigenvalues) first tries
    (P + P^T) / 2 + (tol / 2) I: if it succeeds, every eigenvalue
    is above -tol / 2 less a rounding error far below tol / 2, so P passes; if not, the
    eigenvalues decide (:func:`thoroughly_healthy_eig`, the reference), so the verdict is
    always theirs."""
    k = _MOMENTS
    if k is not None:
        try:
            if k.clearly_psd(P, 0.5 * EIG_TOL):
                return True
        except TypeError:  # another dtype or shape, or n > 64
            pass
    return thoroughly_healthy_eig(P)


def thoroughly_healthy_eig(P: np.ndarray) -> bool:
    """:func:`thoroughly_healthy` by numpy's eigenvalues: the reference."""
    if not P.size:
        return True
    if not np.isfinite(P).all():
        return False
    scale = max(1.0, float(np.abs(P.diagonal()).max()))
    try:
        return float(np.linalg.eigvalsh(0.5 * (P + P.T)).min()) >= -EIG_TOL * scale
    except np.linalg.LinAlgError:
        return False
