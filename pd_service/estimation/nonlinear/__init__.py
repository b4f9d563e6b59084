"""Nonlinear observer backends (unscented filters) on the shared timestamp window and replay.

Importing the package registers the built-in models: ``"omni3"`` (three-wheel
omnidirectional robot), ``"unicycle"`` (differential-drive robot) and ``"linear"`` (a linear
model, for tests).
"""

from . import models_linear, models_omni, models_unicycle  # noqa: F401  (register the built-in models)
from .adaptive import MITAdapter, MITSettings, SageHusaAdapter, SageHusaSettings, make_adapter
from .factory import make_unscented
from .registry import (
    MeasurementModel,
    NonlinearModel,
    make_model,
    register_model,
    registered_models,
    wrap_angle,
)
from .sigma import SigmaWeights
from .ukf import UnscentedObserverPredictor
from .unscented import InnovationRecord, UKFState

__all__ = [
    "InnovationRecord",
    "MITAdapter",
    "MITSettings",
    "MeasurementModel",
    "NonlinearModel",
    "SageHusaAdapter",
    "SageHusaSettings",
    "SigmaWeights",
    "UKFState",
    "UnscentedObserverPredictor",
    "make_adapter",
    "make_model",
    "make_unscented",
    "register_model",
    "registered_models",
    "wrap_angle",
]
