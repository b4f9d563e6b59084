"""Numeric arrays on the wire, and the covariance checks shared by every message.

Wire form (msgpack or JSON), row-major::

    {"shape": [rows, cols], "data": [a11, a12, ..., a1c, a21, ...]}     # a matrix
    {"shape": [n], "data": [x1, ..., xn]}                                 # a vector

In Python every array field is a read-only, C-contiguous ``numpy.float64`` array. Accepted
inputs: the wire form above, or a numpy array of a real numeric dtype (copied). Plain Python
lists are *not* accepted: the wire has one array encoding, and a Python caller writes
``np.asarray([...])``.

Rules (each gives a readable reason through ``PydanticCustomError``):

- ``shape`` has exactly 1 entry for a vector, 2 for a matrix; every entry is an integer in
  ``1..MAX_DIM`` (64);
- ``data`` is a flat list of ``len == prod(shape)`` numbers: msgpack float or int (an int is
  taken as a float; booleans, strings, nil and nested lists are refused);
- every value is finite.

Covariance tolerance (:func:`psd_problem`), with ``s = max(1, max|M|)``:

- symmetric:  ``max|M - M^T| <= PSD_RTOL * s``;
- positive semi-definite: ``min eig((M + M^T)/2) >= -PSD_RTOL * s``, ``PSD_RTOL`` (1e-9) from
  :mod:`pd_service.estimation.checks`, the one tolerance of both layers.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from pydantic import PlainSerializer, PlainValidator, WithJsonSchema
from pydantic_core import PydanticCustomError

from pd_service.estimation.checks import PSD_RTOL

#: Largest size of any array axis (state, input and measurement dimensions).
MAX_DIM = 64

_NUMBER_TYPES = frozenset((float, int))
_REAL_KINDS = frozenset("fiu")


def _fail(message: str) -> PydanticCustomError:
    return PydanticCustomError("wire_array", message)


#: Error type of a non-finite array value (the codec counts it as ``non_finite``).
NON_FINITE_ERROR = "wire_non_finite"


def _non_finite(message: str) -> PydanticCustomError:
    return PydanticCustomError(NON_FINITE_ERROR, message)


def _type_name(value: object) -> str:
    return "nil" if value is None else type(value).__name__


def _check_shape(shape: tuple[int, ...] | list[Any], ndim: int) -> None:
    what = "a vector" if ndim == 1 else "a matrix"
    if len(shape) != ndim:
        raise _fail(f"expected {what} (shape with {ndim} entr{'y' if ndim == 1 else 'ies'}), "
                    f"got shape {list(shape)}")
    for size in shape:
        if not 1 <= size <= MAX_DIM:
            raise _fail(f"every array dimension must be between 1 and {MAX_DIM}, "
                        f"got shape {list(shape)}")


def _from_wire(value: dict[Any, Any], ndim: int) -> np.ndarray:
    """``{"shape": [...], "data": [...]}`` -> read-only float64 array of that shape."""
    if len(value) != 2 or "shape" not in value or "data" not in value:
        raise _fail(f"an array is a map with exactly the keys 'shape' and 'data', got keys "
                    f"{sorted(map(str, value))[:4]}")
    shape, data = value["shape"], value["data"]
    if type(shape) is not list or not set(map(type, shape)) <= {int}:
        raise _fail("array 'shape' must be a list of integers")
    _check_shape(shape, ndim)
    if type(data) is not list:
        raise _fail(f"array 'data' must be a flat list of numbers, got {_type_name(data)}")
    size = shape[0] if ndim == 1 else shape[0] * shape[1]
    if len(data) != size:
        raise _fail(f"array 'data' has {len(data)} values but shape {shape} needs {size}")
    bad = set(map(type, data)) - _NUMBER_TYPES
    if bad:
        found = ", ".join(sorted("nil" if t is type(None) else t.__name__ for t in bad))
        raise _fail(f"array 'data' must hold only numbers, found {found}")
    # Finite check, fast path: fsum of finite values is finite unless it overflows, in
    # which case the exact element-wise check below decides.
    try:
        total = math.fsum(data)
    except OverflowError:
        total = math.inf
    try:
        arr = np.array(data, dtype=np.float64)
    except (OverflowError, ValueError, TypeError):
        raise _non_finite("array 'data' holds a value that is not a finite float64") from None
    if not math.isfinite(total) and not np.isfinite(arr).all():
        raise _non_finite("array 'data' must hold finite numbers only (no NaN or infinity)")
    if ndim == 2:
        arr = arr.reshape(shape)
    arr.flags.writeable = False
    return arr


def _from_numpy(value: np.ndarray, ndim: int) -> np.ndarray:
    if value.dtype.kind not in _REAL_KINDS:
        raise _fail(f"expected a real numeric array, got dtype {value.dtype}")
    _check_shape(value.shape, ndim)
    arr = np.array(value, dtype=np.float64, order="C", copy=True)
    if not np.isfinite(arr).all():
        raise _non_finite("array must hold finite numbers only (no NaN or infinity)")
    arr.flags.writeable = False
    return arr


def _validator(ndim: int):
    def validate(value: Any) -> np.ndarray:
        if type(value) is dict:
            return _from_wire(value, ndim)
        if isinstance(value, np.ndarray):
            return _from_numpy(value, ndim)
        raise _fail("expected an array: a map with 'shape' and 'data' (or a numpy array in "
                    f"Python), got {_type_name(value)}")

    return validate


def to_wire(arr: np.ndarray) -> dict[str, list]:
    """numpy array -> ``{"shape": [...], "data": [...]}`` (row-major, Python floats)."""
    return {"shape": list(arr.shape), "data": arr.ravel().tolist()}


def _json_schema(ndim: int) -> dict[str, Any]:
    what = "vector" if ndim == 1 else "matrix, row-major"
    return {
        "type": "object",
        "description": f"A {what}: data holds prod(shape) finite numbers.",
        "properties": {
            "shape": {"type": "array", "minItems": ndim, "maxItems": ndim,
                      "items": {"type": "integer", "minimum": 1, "maximum": MAX_DIM}},
            "data": {"type": "array", "maxItems": MAX_DIM**ndim, "items": {"type": "number"}},
        },
        "required": ["shape", "data"],
        "additionalProperties": False,
    }


#: A 1-D float64 array: wire form ``{"shape": [n], "data": [...]}``.
Vector = Annotated[
    np.ndarray,
    PlainValidator(_validator(1)),
    PlainSerializer(to_wire),
    WithJsonSchema(_json_schema(1)),
]
#: A 2-D float64 array: wire form ``{"shape": [rows, cols], "data": [row-major...]}``.
Matrix = Annotated[
    np.ndarray,
    PlainValidator(_validator(2)),
    PlainSerializer(to_wire),
    WithJsonSchema(_json_schema(2)),
]


def psd_problem(m: np.ndarray) -> str | None:
    """Why ``m`` is not a covariance matrix, or None if it is one (within ``PSD_RTOL``).

    With ``s = max(1, max|m|)``: square; ``max|m - m^T| <= PSD_RTOL * s``;
    ``min eig((m + m^T)/2) >= -PSD_RTOL * s``.
    """
    if m.ndim != 2 or m.shape[0] != m.shape[1]:
        return f"must be square, got shape {list(m.shape)}"
    if m.shape[0] <= 2:
        return _psd_problem_small(m.ravel().tolist())
    return _psd_problem_numpy(m)


def _psd_problem_numpy(m: np.ndarray) -> str | None:
    s = max(1.0, float(np.abs(m).max()))
    tol = PSD_RTOL * s
    if s > 1e150:  # work on m / s so that m - m^T and LAPACK cannot overflow
        problem = _psd_problem_numpy(m / s)
        return None if problem is None else f"{problem} (after dividing by max|M| = {s:.3g})"
    asym = float(np.abs(m - m.T).max())
    if asym > tol:
        return _asymmetric(asym, tol)
    # Same formula as pd_service.estimation.checks.as_covariance, so both layers agree.
    min_eig = float(np.linalg.eigvalsh(0.5 * (m + m.T))[0])
    return _indefinite(min_eig, tol)


def _psd_problem_small(v: list[float]) -> str | None:
    """psd_problem for 1x1 (``v = [a]``) and 2x2 (``v = [a, b, c, d]``) in closed form
    (8x faster than numpy at this size): the smallest eigenvalue of [[a, e], [e, d]],
    e = (b + c)/2, is (a + d)/2 - hypot((a - d)/2, e). Halves are taken first so that
    nothing overflows for entries up to the float64 limit."""
    tol = PSD_RTOL * max(1.0, max(map(abs, v)))
    if len(v) == 1:
        return _indefinite(v[0], tol)
    a, b, c, d = v
    asym = abs(b - c)
    if asym > tol:
        return _asymmetric(asym, tol)
    return _indefinite(0.5 * a + 0.5 * d - math.hypot(0.5 * a - 0.5 * d, 0.5 * b + 0.5 * c), tol)


def _asymmetric(asym: float, tol: float) -> str:
    return f"must be symmetric (max |M - M^T| = {asym:.3g} > tolerance {tol:.3g})"


def _indefinite(min_eig: float, tol: float) -> str | None:
    if min_eig >= -tol:
        return None
    return (f"must be positive semi-definite (min eigenvalue {min_eig:.3g} < "
            f"-tolerance {-tol:.3g})")  # also reached for a NaN from LAPACK

