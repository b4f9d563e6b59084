"""The SDK package stays light: ``import pd_client`` loads no tool and no matplotlib; the
tool modules import each other without cycles; connect() has the TOOL role's defaults."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import pd_client._base
from pd_client import connect
from pd_service.transport import TOOL, ZenohOptions


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", f"{code}\nimport sys; print('\\n'.join(sys.modules))"],
                         capture_output=True, text=True, check=True).stdout
    return set(out.split())


def test_import_pd_client_loads_no_tool_and_no_matplotlib():
    loaded = _modules_after("import pd_client")
    assert "pd_client" in loaded
    assert not {m for m in loaded if m == "matplotlib" or m.startswith("matplotlib.")}
    assert not {m for m in loaded if m == "pd_client.tools" or m.startswith("pd_client.tools.")}


@pytest.mark.parametrize("module, not_loaded", [
    ("pd_client.tools.record_csv", {"pd_client.tools.pd_record", "pd_client.tools.plots"}),
    ("pd_client.tools.plots", {"pd_client.tools.pd_record"}),
    ("pd_client.tools.pd_record", {"pd_client.tools.plots", "matplotlib"}),
    ("pd_client.tools.pd_demo", {"pd_client.tools.pd_record", "matplotlib"}),
])
def test_tool_modules_import_only_what_they_use(module, not_loaded):
    if module.endswith(".plots"):
        pytest.importorskip("matplotlib")
    assert not _modules_after(f"import {module}") & not_loaded


def test_connect_defaults_are_the_tool_role(monkeypatch):
    """connect() with no arguments builds the same Zenoh config as a tool without flags
    (client mode, connect tcp/127.0.0.1:7447, multicast scouting off)."""
    seen = []
    monkeypatch.setattr(pd_client._base, "ZenohTransport", seen.append)
    connect()
    want = json.loads(str(ZenohOptions().config(TOOL)))
    got = json.loads(str(seen[0]))
    assert got == want
    assert got["mode"] == "client"
    assert got["connect"]["endpoints"] == ["tcp/127.0.0.1:7447"]
    assert got["scouting"]["multicast"]["enabled"] is False
