"""Nonlinear observer backends (unscented filters) on the shared timestamp window and replay."""

from .registry import (
    MeasurementModel,
    NonlinearModel,
    make_model,
    register_model,
    registered_models,
    wrap_angle,
)

__all__ = [
    "MeasurementModel",
    "NonlinearModel",
    "make_model",
    "register_model",
    "registered_models",
    "wrap_angle",
]
