"""Observer-predictors for delayed, multi-rate, lossy measurements (pure numpy).

No networking, no clocks: time is an integer step passed in by the caller. Where the
package's hot path is compiled, the linear backend's arithmetic runs in a C kernel
(``_kalman.c``; :mod:`.linear`); its numpy form is the reference.

Public surface::

    LinearModel, Sensor              model and sensor descriptions
    ObserverPredictor                the exact re-organised-innovation observer-predictor
    PredictedState                   what predict() returns
    Estimator                        the API all of them share (a Protocol)
    ReplayEstimator, Backend, Packet the timestamp window and replay, for other backends
    EstimatorState, StateError       export_state() / restore_state(): continue exactly

The baselines with the same API (AugmentedStateKF, ConventionalPredictor) and the research
estimators are in :mod:`pd_service.research`, outside the daemon's path.
"""

from .estimator import Estimator
from .estimator_state import STATE_VERSION, EstimatorState, StateError
from .model import LinearModel, Sensor
from .observer import ObserverPredictor
from .replay import COUNTER_NAMES, Backend, Packet, PredictedState, ReplayEstimator

__all__ = [
    "Backend",
    "COUNTER_NAMES",
    "Estimator",
    "EstimatorState",
    "LinearModel",
    "ObserverPredictor",
    "Packet",
    "PredictedState",
    "ReplayEstimator",
    "STATE_VERSION",
    "Sensor",
    "StateError",
]
