"""pd-service: networked predictive display for teleoperation.

Layers (imports point one way; docs/architecture.md is the map, tests/test_layers.py enforces
it): ``estimation`` (pure numpy) <- ``wire`` (schemas, codec, keys) <- ``transport``,
``scenarios``, ``backends``, ``ros2`` <- ``service`` (the daemon) / ``link`` (the emulator).
"""

__version__ = "0.1.0"

# PD_SERVICE_PURE=1: the mypyc-compiled hot modules (setup.py) run from their .py files
from . import native as _native  # noqa: E402,F401  (installs the switch before any import)
