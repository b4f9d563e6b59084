"""One Prometheus / OpenMetrics endpoint for every long-running executable (``pd-service
--metrics``, ``pd-link --metrics``, ``pd-ros2 --metrics``), through ``prometheus-client``.

An executable hands :func:`serve` a *collect* function that returns its metric families at
scrape time (read from the state it already keeps: no second set of counters to keep in
step). The names follow Prometheus's rules, checked by :func:`check_name`: ``pd_`` and the
executable, snake case, base units (``_seconds``, ``_bytes``), counters end in ``_total``
(prometheus-client appends it), no label whose values grow with the sessions (per-session
detail stays in the status queries; metrics carry aggregates and a bounded top-N).

The endpoint is off unless an address is given: it has no authentication, so it belongs on
loopback or a private network (deploy/README.md, "Metrics").
"""

from __future__ import annotations

import logging
import re
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

#: What an executable's metrics look like at scrape time.
Collect = Callable[[], Iterable[Any]]

#: A metric family's name: lower snake case under the ``pd_`` namespace.
NAME = re.compile(r"pd_[a-z][a-z0-9_]*")
#: Unit suffixes a name may end in (base units only).
BASE_UNITS = ("_seconds", "_bytes", "_ratio")
#: Suffixes of non-base units a name must not use.
NON_BASE_UNITS = ("_us", "_ms", "_ns", "_microseconds", "_milliseconds", "_kb", "_mb", "_percent")
#: How many sessions a top-N metric names (bounded label values).
TOP_N = 5


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) -> (host, port); port 0: any free port.
    ValueError names what is wrong."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT (e.g. 127.0.0.1:9464), got {text!r}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"port must be 0..65535 (0: any free port), got {port!r}")
    return host, int(port)


def check_name(name: str, kind: str) -> None:
    """ValueError unless ``name`` (a family's name, without the ``_total`` prometheus-client
    appends to a counter) follows the naming rules of the module docstring."""
    if not NAME.fullmatch(name) or "__" in name:
        raise ValueError(f"{name!r}: not lower snake case under pd_")
    if name.endswith(NON_BASE_UNITS):
        raise ValueError(f"{name!r}: not in base units ({', '.join(BASE_UNITS)})")
    if kind == "counter" and name.endswith("_total"):
        raise ValueError(f"{name!r}: a counter family is named without _total")
    if kind == "gauge" and name.endswith("_total"):
        raise ValueError(f"{name!r}: _total is for counters")


def counter(name: str, doc: str, value: float | None = None,
            rows: Mapping[tuple[str, ...], float] | None = None,
            label_names: tuple[str, ...] = ()) -> Any:
    """A counter family ``name`` (exposed as ``name_total``): one value, or one sample per
    ``rows`` item (label values -> value) under ``label_names`` (a bounded set: rules)."""
    from prometheus_client.core import CounterMetricFamily

    check_name(name, "counter")
    if rows is None:
        return CounterMetricFamily(name, doc, value=0.0 if value is None else value)
    fam = CounterMetricFamily(name, doc, labels=list(label_names))
    for values, v in rows.items():
        fam.add_metric(list(values), v)
    return fam


def counters(prefix: str, values: Mapping[str, float], what: str) -> list[Any]:
    """One counter family ``<prefix>_<name>`` per item of ``values`` (a counters dict)."""
    return [counter(f"{prefix}_{k}", f"{what} counter {k}.", v) for k, v in sorted(values.items())]


def gauge(name: str, doc: str, value: float | None = None,
          labels: Mapping[str, float] | None = None, label: str = "") -> Any:
    """A gauge family ``name``: one value, or one sample per ``labels`` item under the label
    ``label`` (a bounded set: states, top-N sessions)."""
    from prometheus_client.core import GaugeMetricFamily

    check_name(name, "gauge")
    if labels is None:
        return GaugeMetricFamily(name, doc, value=0.0 if value is None else value)
    fam = GaugeMetricFamily(name, doc, labels=[label])
    for key, v in labels.items():
        fam.add_metric([key], v)
    return fam


def top(values: Mapping[str, float], n: int = TOP_N) -> dict[str, float]:
    """The ``n`` largest non-zero values (ties by name), for a top-N gauge."""
    ranked = sorted((-v, k) for k, v in values.items() if v)[:n]
    return {k: -neg for neg, k in ranked}


class _Adapter:
    """A prometheus-client collector around a :data:`Collect` function."""

    def __init__(self, collect: Collect, log: logging.Logger) -> None:
        self._collect = collect
        self._log = log

    def collect(self) -> Iterable[Any]:
        try:
            return list(self._collect())
        except Exception:  # a failed scrape must not take the executable down
            self._log.exception("metrics collection failed")
            return []


@dataclass
class MetricsServer:
    """A running endpoint: ``address`` as bound (the real port when 0 was asked for)."""

    host: str
    port: int
    _server: Any
    _thread: threading.Thread

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/metrics"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5.0)


def registry_of(collect: Collect, log: logging.Logger) -> Any:
    """A fresh registry holding only ``collect`` (no process or platform collectors: the
    names stay the executable's own)."""
    from prometheus_client import CollectorRegistry

    registry = CollectorRegistry(auto_describe=False)
    registry.register(_Adapter(collect, log))
    return registry


def serve(address: str, collect: Collect, log: logging.Logger) -> MetricsServer:
    """Serve ``collect``'s metrics at ``http://address/metrics`` (text format, or OpenMetrics
    when the scraper asks for it) on a daemon thread; OSError if the address cannot be bound."""
    from prometheus_client import start_http_server

    host, port = parse_address(address)
    server, thread = start_http_server(port, addr=host, registry=registry_of(collect, log))
    bound = MetricsServer(host, int(server.server_port), server, thread)
    log.info("metrics endpoint", extra={"fields": {"url": bound.url}})
    return bound
