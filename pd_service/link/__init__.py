"""pd-link: a netem-style link emulator between the robot side and the operator side.

* :mod:`pd_service.link.model`  -- pure, seeded per-message decisions (no Zenoh, no clock);
* :mod:`pd_service.link.config` -- TOML/JSON configuration with netem-style names;
* :mod:`pd_service.link.relay`  -- the relay on a transport (subscribe, delay on a heap, publish);
* ``pd-link`` (:mod:`pd_service.link.__main__`) -- the console script.

See docs/link.md.
"""

from .config import LinkConfig, Rule, load_config, parse_config
from .model import (
    DelaySpec,
    FourStateLoss,
    GilbertElliott,
    LinkModel,
    LinkParams,
    Outage,
    RandomLoss,
    Rate,
    loss_theory,
)

__all__ = [
    "DelaySpec",
    "FourStateLoss",
    "GilbertElliott",
    "LinkConfig",
    "LinkModel",
    "LinkParams",
    "Outage",
    "RandomLoss",
    "Rate",
    "Rule",
    "load_config",
    "loss_theory",
    "parse_config",
]
