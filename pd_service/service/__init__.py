"""The pd-service daemon: one observer-predictor per session over Zenoh.

- :mod:`.core`: :class:`ServiceCore`, everything but threads and Zenoh (unit-testable on
  :class:`pd_service.transport.InMemoryBus` with an injected clock), composed of
  :mod:`.dispatch`, :mod:`.lifecycle`, :mod:`.publish` and :mod:`.status`;
- :mod:`.daemon`: Zenoh transport, worker thread, signals;
- :mod:`.config`: settings (defaults < file < ``PD_SERVICE_*`` env < flags);
- :mod:`.__main__`: the ``pd-service`` command.

See docs/service.md.
"""

from .config import ConfigError, Settings, load_settings
from .core import ServiceCore
from .spec_store import SpecStore

__all__ = ["ConfigError", "ServiceCore", "Settings", "SpecStore", "load_settings"]
