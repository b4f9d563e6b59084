"""Input checks shared by every estimator: shapes, finite values, covariances.

Every check raises ``ValueError`` whose message starts with the field name, so a caller
(the daemon, a test) can tell the user exactly what was wrong.
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np

#: Relative tolerance for symmetry and positive semi-definiteness of covariances:
#: ``|M - M^T| <= PSD_RTOL * max(1, max|M|)`` and ``min eig(M) >= -PSD_RTOL * max(1, max|M|)``.
PSD_RTOL = 1e-9

#: Vectors up to this length are checked for NaN / infinity element by element in Python.
_SHORT: Final = 8
_isfinite: Final = math.isfinite


def as_vector(value: object, field: str, size: int | None = None) -> np.ndarray:
    """Return ``value`` as a finite float64 vector of shape (size,)."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{field}: not a numeric vector ({exc})") from None
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim != 1:
        raise ValueError(f"{field}: expected a vector, got shape {arr.shape}")
    if size is not None and arr.shape[0] != size:
        raise ValueError(f"{field}: expected length {size}, got {arr.shape[0]}")
    if arr.shape[0] <= _SHORT:
        # a short vector: math.isfinite over a list is cheaper than np.isfinite().all()
        for v in arr.tolist():
            if not _isfinite(v):
                raise ValueError(f"{field}: contains NaN or infinity")
    elif not np.isfinite(arr).all():
        raise ValueError(f"{field}: contains NaN or infinity")
    return arr



def as_matrix(value: object, field: str, shape: tuple[int | None, int | None]) -> np.ndarray:
    """Return ``value`` as a finite float64 matrix; ``None`` in ``shape`` means any size."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{field}: not a numeric matrix ({exc})") from None
    if arr.ndim == 0 and shape == (1, 1):
        arr = arr.reshape(1, 1)
    if arr.ndim != 2:
        raise ValueError(f"{field}: expected a matrix, got shape {arr.shape}")
    for axis, want in enumerate(shape):
        if want is not None and arr.shape[axis] != want:
            raise ValueError(f"{field}: expected shape {_fmt(shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{field}: contains NaN or infinity")
    return arr


def as_covariance(value: object, field: str, size: int | None = None) -> np.ndarray:
    """Return ``value`` as a symmetric positive semi-definite (size, size) matrix.

    The tolerance is :data:`PSD_RTOL` relative to the largest entry; the returned matrix is
    exactly symmetrised, ``(M + M^T) / 2``.
    """
    arr = as_matrix(value, field, (size, size))
    if arr.shape[0] != arr.shape[1]:
        raise ValueError(f"{field}: covariance must be square, got shape {arr.shape}")
    scale = max(1.0, float(np.max(np.abs(arr)))) if arr.size else 1.0
    if np.max(np.abs(arr - arr.T), initial=0.0) > PSD_RTOL * scale:
        raise ValueError(f"{field}: covariance is not symmetric")
    sym = 0.5 * (arr + arr.T)
    if sym.size and float(np.linalg.eigvalsh(sym)[0]) < -PSD_RTOL * scale:
        raise ValueError(f"{field}: covariance is not positive semi-definite")
    return sym


def as_step(value: object, field: str) -> int:
    """Return ``value`` as a Python int (numpy integers accepted, bools and floats refused)."""
    if type(value) is int:  # the usual case, first (bool is a subclass, not this type)
        return value
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{field}: expected an integer step, got {type(value).__name__}")
    return int(value)


def as_positive(value: object, field: str) -> float:
    """Return ``value`` as a finite float > 0."""
    try:
        v = float(value)  # type: ignore[arg-type]  # any object; float() says if it cannot
    except (TypeError, ValueError):
        raise ValueError(f"{field}: expected a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{field}: must be finite and > 0, got {value!r}")
    return v


def as_nonnegative(value: object, field: str, strict: bool) -> float:
    """Return ``value`` as a finite float >= 0 (> 0 if ``strict``)."""
    try:
        v = float(value)  # type: ignore[arg-type]  # any object; float() says if it cannot
    except (TypeError, ValueError):
        raise ValueError(f"{field}: expected a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0.0 or (strict and v == 0.0):
        raise ValueError(f"{field}: must be a finite number {'> 0' if strict else '>= 0'}, "
                         f"got {value!r}")
    return v


def _fmt(shape: tuple[int | None, int | None]) -> str:
    return "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
