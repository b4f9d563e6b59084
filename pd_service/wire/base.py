"""The base of every wire model (:class:`WireModel`): strict, frozen, comparable by value."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict
from pydantic_core import PydanticCustomError


def _comparable(value: Any) -> Any:
    """A hashable stand-in for a field value (arrays by shape and values)."""
    if isinstance(value, np.ndarray):
        return ("ndarray", value.shape, tuple(value.ravel().tolist()))
    if isinstance(value, WireModel):
        return value._identity()
    if isinstance(value, list | tuple):
        return tuple(_comparable(v) for v in value)
    if isinstance(value, dict):
        return tuple(sorted((k, _comparable(v)) for k, v in value.items()))
    return value


#: pydantic error type of a rule checked across a model's fields.
INVALID_ERROR = "wire_invalid"


def invalid(field: str, message: str) -> PydanticCustomError:
    """A rule failed on ``field`` (a dotted path below the validated model, e.g. ``"R"`` or
    ``"sensors.1.H"``; ``""`` for none). The error reads ``"<field>: <message>"`` (so a
    ValidationError raised in Python names the field too) and carries ``field`` in its
    context: the codec moves it into the path, ``<Message>.<loc>.<field>: <message>``, so a
    model-level check still names the field it refuses."""
    return PydanticCustomError(INVALID_ERROR, f"{field}: {message}" if field else message,
                               {"field": field})


class WireModel(BaseModel):
    """Base of every wire model: strict, frozen, no unknown fields, no NaN/inf floats.

    Equality and hashing compare array fields by shape and values (pydantic's default
    would compare numpy arrays element-wise and fail).
    """

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, allow_inf_nan=False)

    def _identity(self) -> tuple[Any, ...]:
        return (type(self).__name__,) + tuple(
            _comparable(getattr(self, name)) for name in type(self).model_fields
        )

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, WireModel)  # same type as self
        return self._identity() == other._identity()

    def __hash__(self) -> int:
        return hash(self._identity())
