"""The daemon's Prometheus endpoint (pd_service.service.scrape through pd_service.metrics):
scraped over HTTP and read with prometheus-client's own parsers (the text format and
OpenMetrics), names checked against Prometheus's rules, values against the status query,
and the series count independent of the number of sessions."""

from __future__ import annotations

import logging
import urllib.request
from collections.abc import Iterator

import pytest
from prometheus_client.openmetrics.parser import text_string_to_metric_families as parse_om
from prometheus_client.parser import text_string_to_metric_families as parse_text

from pd_service.metrics import TOP_N, MetricsServer, serve
from pd_service.service.core import ServiceCore
from pd_service.service.scrape import collect
from pd_service.transport import InMemoryBus
from pd_service.wire import encode, keys

from .helpers import PERIOD_NS, Clock, Collector, meas_bytes, paper_spec
from .test_core import make_core, settle

log = logging.getLogger("test_scrape")
#: The cores' clock: a step far past the samples' makes them late.
CLOCK = Clock(0)
LATE_AT_NS = 100 * PERIOD_NS


@pytest.fixture
def served(tmp_path) -> Iterator[tuple[ServiceCore, InMemoryBus, MetricsServer]]:
    bus = InMemoryBus()
    Collector().attach(bus.transport())
    core = make_core(bus, CLOCK, tmp_path)
    CLOCK.t = 0
    server = serve("127.0.0.1:0", lambda: collect(core.queries), log)
    try:
        yield core, bus, server
    finally:
        server.close()
        core.close()


def scrape(server: MetricsServer, openmetrics: bool = False) -> str:
    accept = "application/openmetrics-text; version=1.0.0" if openmetrics else "text/plain"
    req = urllib.request.Request(server.url, headers={"Accept": accept})
    with urllib.request.urlopen(req, timeout=10) as resp:
        return resp.read().decode()


def families(text: str, openmetrics: bool = False) -> dict[str, object]:
    parse = parse_om if openmetrics else parse_text
    return {f.name: f for f in parse(text)}


def create(bus: InMemoryBus, core: ServiceCore, names: list[str]) -> None:
    cli = bus.transport()
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(core)


def sample_value(fams: dict, family: str, suffix: str = "", **labels: str) -> float:
    for s in fams[family].samples:
        if s.name == family + suffix and all(s.labels.get(k) == v for k, v in labels.items()):
            return float(s.value)
    raise AssertionError(f"no sample {family}{suffix} {labels}")


def test_scrape_parses_and_follows_the_naming_rules(served) -> None:
    core, bus, server = served
    create(bus, core, ["s1", "s2", "s3"])
    cli = bus.transport()
    # s2 gets samples far behind its window (late): a counter and a top-N entry
    CLOCK.t = LATE_AT_NS
    for seq in range(3):
        cli.put(keys.sensor_key("s2", "camera"), meas_bytes("s2", "camera", 1, [0.0, 0.0], seq))
    settle(core)
    status = core.queries.service_status()
    for om in (False, True):
        fams = families(scrape(server, om), om)
        assert fams, "nothing scraped"
        for name, fam in fams.items():
            assert name.startswith("pd_service_"), name
            assert name == name.lower() and "__" not in name
            assert not name.endswith(("_us", "_ms", "_ns")), f"{name}: not base units"
            for s in fam.samples:
                if fam.type == "counter":
                    assert s.name in (f"{name}_total", f"{name}_created"), s.name
                labels = set(s.labels)
                assert labels <= {"session", "state"}, (name, labels)
                if "session" in labels:
                    assert name.startswith("pd_service_top_session_"), name
            if name.startswith("pd_service_top_session_"):
                assert len(fam.samples) <= TOP_N
        # values are the status query's
        assert sample_value(fams, "pd_service_late", "_total") == status.counters["late"] >= 3
        assert sample_value(fams, "pd_service_sessions_served") == 3
        assert sample_value(fams, "pd_service_top_session_late", session="s2") == \
            core.queries.session_status("s2").counters["late"]
        assert sample_value(fams, "pd_service_sessions", state="active") == 3


def test_series_do_not_grow_with_the_sessions(served) -> None:
    core, bus, server = served
    create(bus, core, [f"s{i}" for i in range(3)])
    few = families(scrape(server))
    create(bus, core, [f"s{i}" for i in range(3, 40)])
    cli = bus.transport()
    CLOCK.t = LATE_AT_NS
    for i in range(40):  # every session has a late sample: each top-N is full
        cli.put(keys.sensor_key(f"s{i}", "camera"), meas_bytes(f"s{i}", "camera", 1, [0.0, 0.0]))
    settle(core)
    many = families(scrape(server))
    assert sample_value(many, "pd_service_sessions_served") == 40
    assert len(many["pd_service_top_session_late"].samples) == TOP_N
    n_few = sum(len(f.samples) for f in few.values())
    n_many = sum(len(f.samples) for f in many.values())
    # bounded by the top-N gauges (at most TOP_N each) and the counters that became non-zero
    assert n_many <= n_few + 4 * TOP_N + len(many) - len(few)


def test_a_failing_collection_answers_empty_not_an_error() -> None:
    def broken() -> list[object]:
        raise RuntimeError("boom")

    server = serve("127.0.0.1:0", broken, log)
    try:
        assert families(scrape(server)) == {}
    finally:
        server.close()


@pytest.mark.parametrize("address", ["nohost", "127.0.0.1:99999", ":9464", "host:port"])
def test_metrics_address_is_checked(address: str) -> None:
    from pd_service.service.config import Settings

    with pytest.raises(ValueError):
        Settings(metrics=address)
