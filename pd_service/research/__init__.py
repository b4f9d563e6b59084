"""Baselines and research estimators: what the benchmarks and tests compare the daemon's
estimators against, never run by the daemon (pure numpy, on top of :mod:`pd_service.estimation`).

    AugmentedStateKF, ConventionalPredictor   baselines with ObserverPredictor's API (baselines.py)
    linear_coding                             linear coding under random delay and loss
                                              (docs/linear-coding.md)
    delay_model                               the hazard-rate delay / loss model it samples from

No daemon layer (service, backends, intake, wire) imports this package (tests/test_layers.py).
"""

from .baselines import AugmentedStateKF, ConventionalPredictor

__all__ = ["AugmentedStateKF", "ConventionalPredictor"]
