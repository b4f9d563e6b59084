"""The compiled hot path (setup.py, pd_service.native): which modules run compiled, the
switch back to the .py files, and that a stale build is never run."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pd_service
from pd_service import native

PKG = Path(pd_service.__file__).parent

PROBE = ("import json, os, warnings\n"
         "if os.environ.get('PROBE_WARN') == 'error':\n"
         "    warnings.simplefilter('error', RuntimeWarning)\n"
         "try:\n    import pd_service.native as n\nexcept RuntimeWarning as w:\n"
         "    print(json.dumps({'warning': str(w)})); raise SystemExit\n"
         "print(json.dumps({'status': n.STATUS, 'compiled': n.compiled(), "
         "'kernels': [n.kernel(k) is not None for k in n.C_KERNELS], "
         "'file': n.__file__}))")


def probe(env: dict[str, str], pythonpath: Path | None = None) -> dict:
    env = {**os.environ, **env}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                         text=True, check=True, cwd="/").stdout
    return json.loads(out.splitlines()[-1])


def test_pure_switch_runs_every_hot_module_from_its_source():
    got = probe({native.PURE_ENV: "1"})
    assert got["status"] == "pure Python (PD_SERVICE_PURE=1)"
    assert set(got["compiled"]) == set(native.HOT_MODULES)
    assert not any(got["compiled"].values())
    assert got["kernels"] == [False] * len(native.C_KERNELS)  # their numpy forms run


def test_the_installed_build_is_used_whole_or_not_at_all():
    got = probe({native.PURE_ENV: ""})
    flags = set(got["compiled"].values())
    assert len(flags) == 1, got  # never a mix of compiled and source modules
    built = any(PKG.glob("native__mypyc.*"))
    assert flags == {built}
    assert got["kernels"] == [built] * len(native.C_KERNELS)  # the C kernels with them
    assert got["status"].startswith("compiled with mypyc" if built else "pure Python")


def test_a_stale_build_is_not_run(tmp_path):
    """A checkout edited after its build: the .py files run, with a warning."""
    if not any(PKG.glob("native__mypyc.*")):
        pytest.skip("no compiled build here (no C compiler at install time)")
    shutil.copytree(PKG, tmp_path / "pd_service",
                    ignore=shutil.ignore_patterns("__pycache__"))
    fresh = probe({native.PURE_ENV: ""}, tmp_path)
    assert fresh["file"].startswith(str(tmp_path)) and all(fresh["compiled"].values())
    hot = tmp_path / "pd_service" / "service" / "health.py"
    hot.write_text(hot.read_text() + "\n# edited after the build\n")
    warned = probe({native.PURE_ENV: "", "PROBE_WARN": "error"}, tmp_path)
    assert "built from other sources" in warned["warning"]
    got = probe({native.PURE_ENV: ""}, tmp_path)
    assert "stale" in got["status"] and not any(got["compiled"].values())
    assert not any(got["kernels"])


def test_an_edited_kernel_source_makes_the_build_stale(tmp_path):
    """The C kernels' sources are part of the build's digest: an edited one runs nothing
    compiled (the numpy forms and the .py files run) until rebuilt."""
    if not any(PKG.glob("native__mypyc.*")):
        pytest.skip("no compiled build here (no C compiler at install time)")
    shutil.copytree(PKG, tmp_path / "pd_service",
                    ignore=shutil.ignore_patterns("__pycache__"))
    src = tmp_path / next(iter(native.C_KERNELS.values()))
    assert all(probe({native.PURE_ENV: ""}, tmp_path)["kernels"])
    src.write_text(src.read_text() + "\n/* edited after the build */\n")
    got = probe({native.PURE_ENV: ""}, tmp_path)
    assert "stale" in got["status"] and not any(got["kernels"])


def test_setup_compiles_exactly_the_hot_modules():
    """setup.py reads the list from pd_service.native (one list), as existing files."""
    files = [native.source_path(m) for m in native.HOT_MODULES]
    assert all(f.is_file() for f in files)
    assert len(set(files)) == len(files)
    assert "native.HOT_MODULES" in (PKG.parent / "setup.py").read_text()
