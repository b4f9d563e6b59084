"""pd_service.metrics: the address and naming rules, and ``--metrics`` of the running
executables (pd-service, pd-link as processes on loopback), scraped over HTTP and read with
prometheus-client's own parser."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from pd_service.metrics import check_name, parse_address

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
URL = re.compile(r"url=(http://\S+/metrics)")


@pytest.mark.parametrize("text, want", [("127.0.0.1:9464", ("127.0.0.1", 9464)),
                                        ("[::1]:0", ("::1", 0)), ("localhost:80", ("localhost", 80))])
def test_parse_address(text: str, want: tuple[str, int]) -> None:
    assert parse_address(text) == want


@pytest.mark.parametrize("name, kind", [("pd_service_latency_us", "gauge"),
                                        ("pd_service_late_total", "counter"),
                                        ("pd_service_x_total", "gauge"), ("Pd_bad", "gauge"),
                                        ("pd__x", "gauge"), ("service_x", "gauge")])
def test_check_name_refuses(name: str, kind: str) -> None:
    with pytest.raises(ValueError):
        check_name(name, kind)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def scrape_running(argv: list[str]) -> dict[str, object]:
    """Start ``argv`` (with ``--metrics 127.0.0.1:0``), read the endpoint's URL from its log,
    scrape it once, stop it with SIGTERM (exit code 0 expected); the parsed families."""
    p = subprocess.Popen([*argv, "--metrics", "127.0.0.1:0", "--log-level", "INFO"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         env={**os.environ, "PYTHONWARNINGS": "ignore"})
    lines: list[str] = []
    found = threading.Event()

    def read() -> None:
        assert p.stdout is not None
        for line in p.stdout:
            lines.append(line)
            if URL.search(line):
                found.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert found.wait(60), "".join(lines)
        url = next(m.group(1) for ln in lines if (m := URL.search(ln)))
        with urllib.request.urlopen(url, timeout=30) as resp:
            text = resp.read().decode()
    finally:
        p.terminate()
        code = p.wait(30)
    assert code == 0, "".join(lines)
    return {f.name: f for f in text_string_to_metric_families(text)}


@pytest.mark.integration
def test_the_daemon_serves_metrics(tmp_path: Path) -> None:
    fams = scrape_running([str(BIN / "pd-service"), "--listen", f"tcp/127.0.0.1:{free_port()}",
                           "--state-dir", str(tmp_path), "--instance", "m"])
    assert "pd_service_uptime_seconds" in fams and "pd_service_sessions_served" in fams


@pytest.mark.integration
def test_pd_link_serves_metrics() -> None:
    fams = scrape_running([sys.executable, "-m", "pd_service.link", "--config",
                           str(ROOT / "deploy" / "link-paper.toml"), "--connect",
                           f"tcp/127.0.0.1:{free_port()}"])
    rules = {s.labels["rule"] for s in fams["pd_link_rule_received"].samples}
    assert {"camera", "ranger", "commands"} <= rules
