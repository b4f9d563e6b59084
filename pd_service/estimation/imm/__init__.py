"""IMM of unscented information filters with multi-sensor likelihood fusion.

Importing this package registers the mode models ``imm_cv`` and ``imm_ct`` in the nonlinear
model registry. See docs/imm.md.

Public surface::

    make_imm                      factory: spec-like values -> ImmObserverPredictor
    ImmObserverPredictor          exact replay of delayed packets (a ReplayEstimator)
    ImmFilter, ImmState           the batched IMM-UIF recursion and its state
    range_bearing, position       measurement models; make_sensor(spec dict)
    VARIANTS                      "single", "centralised", "imm1", "imm2"
"""

from . import uif
from .factory import make_imm, make_mode
from .filter import VARIANTS, ImmFilter, ImmState
from .measurements import make_sensor, position, range_bearing
from .models import imm_ct, imm_cv
from .observer import ImmObserverPredictor, ImmPrediction

__all__ = [
    "VARIANTS",
    "ImmFilter",
    "ImmObserverPredictor",
    "ImmPrediction",
    "ImmState",
    "imm_ct",
    "imm_cv",
    "make_imm",
    "make_mode",
    "make_sensor",
    "position",
    "range_bearing",
    "uif",
]
