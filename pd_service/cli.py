"""What the pd_service executables (``pd-link``, ``pd-ros2``) share around their work: the
stop signal, opening the Zenoh session with the exit code when it cannot be opened, and
waiting for the stop."""

from __future__ import annotations

import logging
import signal
import threading
from typing import TYPE_CHECKING, Any

from pd_service.transport import Transport

if TYPE_CHECKING:
    import zenoh

#: Exit code when the Zenoh session cannot be opened.
EXIT_NO_ZENOH = 1


def stop_on_signals(log: logging.Logger) -> threading.Event:
    """An Event set (and logged) on SIGINT or SIGTERM; the handlers stay installed."""
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal received, stopping", extra={"fields": {"signal": signum}})
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return stop


def open_zenoh(conf: zenoh.Config, log: logging.Logger) -> Transport | None:
    """A :class:`ZenohTransport` on the Zenoh config ``conf``; None (the error logged) if the
    session cannot be opened: the caller then exits with :data:`EXIT_NO_ZENOH`."""
    from pd_service.transport.zenoh_transport import ZenohTransport

    try:
        return ZenohTransport(conf)
    except Exception as exc:
        log.error("cannot open Zenoh session", extra={"fields": {"error": str(exc)}})
        return None


def wait_for_stop(stop: threading.Event) -> None:
    """Block until ``stop`` is set (checked every 0.5 s, so signals are handled promptly)."""
    while not stop.wait(timeout=0.5):
        pass
