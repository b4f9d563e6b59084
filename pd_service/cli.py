"""What the pd_service executables (``pd-link``, ``pd-ros2``) share around their work: the
stop signal, opening the Zenoh session with the exit code when it cannot be opened,
``--metrics``, and waiting for the stop."""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from typing import TYPE_CHECKING, Any

from pd_service.metrics import Collect, MetricsServer, parse_address, serve
from pd_service.transport import Transport
from pd_service.transport.options import error_text, open_retrying

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


def open_zenoh(conf: zenoh.Config, log: logging.Logger, wait_s: float = 0.0,
               stop: threading.Event | None = None) -> Transport | None:
    """A :class:`ZenohTransport` on the Zenoh config ``conf``, retried with backoff for
    ``wait_s`` seconds (``--connect-wait``: a router or daemon that does not answer yet, each
    retry logged); None (the error logged) if it cannot be opened: the caller then exits
    with :data:`EXIT_NO_ZENOH`."""
    from pd_service.transport.zenoh_transport import ZenohTransport

    def report(exc: BaseException, pause: float, remaining: float) -> None:
        log.warning("no answer yet, retrying", extra={"fields": {
            "error": error_text(exc), "retry_in_s": round(pause, 2),
            "left_s": round(remaining, 1)}})

    try:
        return open_retrying(lambda: ZenohTransport(conf), wait_s, stop, lambda _e: True,
                             report)
    except Exception as exc:
        log.error("cannot open Zenoh session", extra={"fields": {"error": error_text(exc)}})
        return None


def wait_for_stop(stop: threading.Event) -> None:
    """Block until ``stop`` is set (checked every 0.5 s, so signals are handled promptly)."""
    while not stop.wait(timeout=0.5):
        pass


def add_metrics_arg(ap: argparse.ArgumentParser) -> None:
    """``--metrics HOST:PORT``: the Prometheus endpoint (off by default)."""
    ap.add_argument("--metrics", metavar="HOST:PORT", type=_metrics_address,
                    help="serve Prometheus / OpenMetrics metrics at http://HOST:PORT/metrics "
                         "(port 0: any free port, logged; default: no endpoint; no "
                         "authentication: bind loopback or a private network)")


def _metrics_address(text: str) -> str:
    try:
        parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def wait_serving_metrics(stop: threading.Event, address: str | None, collect: Collect,
                         log: logging.Logger) -> int:
    """Serve ``--metrics`` (when ``address`` is given) until ``stop`` is set; the exit code:
    0, or 2 (logged) when the address cannot be bound."""
    metrics: MetricsServer | None = None
    if address is not None:
        try:
            metrics = serve(address, collect, log)
        except OSError as exc:
            log.error("cannot serve --metrics", extra={"fields": {"error": str(exc)}})
            return 2
    try:
        wait_for_stop(stop)
    finally:
        if metrics is not None:
            metrics.close()
    return 0
