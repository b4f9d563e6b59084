"""Every executable behaves alike: each console script of the two pyproject.toml files is run
as a user runs it (the venv's entry point, a subprocess) and its ``--help`` / ``--version``
read as text: a version, ``-v``, a help text for every flag, no "default None", no
reStructuredText markup, port 0 meaning "any free port", the Zenoh password from
``$PD_ZENOH_PASSWORD``, and a missing ``--zenoh-config`` file named in the error.
deploy/make_acl.py takes the daemon's session-name rule."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from functools import cache
from pathlib import Path

import pytest

from pd_service.logs import package_version
from pd_service.transport import TOOL, add_zenoh_args, options_from_args
from pd_service.transport.options import PASSWORD_ENV
from pd_service.wire import keys

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SCRIPTS = sorted(name for f in ("pyproject.toml", "clients/python/pyproject.toml")
                 for name in tomllib.loads((ROOT / f).read_text())["project"]["scripts"])
#: Arguments a script needs besides the flag under test.
REQUIRED = {"pd-link": ["--config", str(ROOT / "deploy" / "link-paper.toml")]}
#: What a tool with subcommands needs after its shared flags to reach the transport.
AFTER = {"pd-admin": ["list"]}
RST = ("``", ":func:", ":class:", ":meth:", ":data:", ":mod:", ":attr:")
#: An option's first line in argparse's help: two spaces, the flag, then its text (or not).
OPTION = re.compile(r"^  (-\S.*?)(?:\s{2,}(\S.*))?$")


def run(script: str, *args: str, env: dict[str, str] | None = None,
        timeout: float = 60) -> subprocess.CompletedProcess[str]:
    exe = BIN / script
    if not exe.exists():
        pytest.skip(f"{script} is not installed in this venv")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "COLUMNS": "100", **(env or {})})


@cache
def help_text(script: str) -> str:
    done = run(script, "--help")
    assert done.returncode == 0, done.stderr
    return done.stdout


def options(text: str) -> dict[str, str]:
    """{option line: its help text} of an argparse help page."""
    lines = text.splitlines()
    out: dict[str, str] = {}
    for i, line in enumerate(lines):
        m = OPTION.match(line)
        if not m:
            continue
        helptext = m.group(2) or ""
        for nxt in lines[i + 1:]:  # the help continues on the lines indented past the flag
            if OPTION.match(nxt) or not re.match(r"^\s{6,}\S", nxt):
                break
            helptext += " " + nxt.strip()
        out[m.group(1).strip()] = helptext.strip()
    return out


def test_every_script_is_found() -> None:
    assert {"pd-service", "pd-link", "pd-ros2", "pd-demo", "pd-display"} <= set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_version(script: str) -> None:
    done = run(script, "--version")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"{script} {package_version()}"


@pytest.mark.parametrize("script", SCRIPTS)
def test_help_describes_every_flag(script: str) -> None:
    text = help_text(script)
    opts = options(text)
    assert any(o.startswith("--verbose, -v") or o.startswith("-v, --verbose") for o in opts)
    assert any(o.startswith("--log-level") for o in opts)
    assert any(o.startswith("--version") for o in opts)
    for opt, helptext in opts.items():
        assert helptext, f"{script}: {opt} has no help text"
    assert "default None" not in text and "(default: None)" not in text
    for markup in RST:
        assert markup not in text, f"{script}: reStructuredText {markup!r} in --help"


@pytest.mark.parametrize("script", SCRIPTS)
def test_port_zero_and_password_mean_the_same_everywhere(script: str) -> None:
    for opt, helptext in options(help_text(script)).items():
        if re.match(r"--[\w-]*port\b", opt):
            assert "0: any free port" in helptext, f"{script}: {opt}: {helptext}"
        if opt.startswith("--password"):
            assert f"${PASSWORD_ENV}" in helptext, f"{script}: {opt}: {helptext}"


def test_the_password_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    ap = argparse.ArgumentParser()
    add_zenoh_args(ap, TOOL)
    monkeypatch.setenv(PASSWORD_ENV, "from-env")
    assert options_from_args(ap.parse_args(["--user", "u"])).password == "from-env"
    assert options_from_args(ap.parse_args(["--password", "flag"])).password == "flag"


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_missing_zenoh_config_file_is_named(script: str, tmp_path: Path) -> None:
    if "--zenoh-config" not in help_text(script):
        pytest.skip(f"{script} has no --zenoh-config")
    missing = tmp_path / "no-such-dir" / "zenoh.json5"
    extra = ["--connect-wait", "0"] if "--connect-wait" in help_text(script) else []
    done = run(script, *REQUIRED.get(script, []), "--zenoh-config", str(missing), *extra,
               *AFTER.get(script, []))
    out = done.stdout + done.stderr
    assert done.returncode != 0, out
    assert str(missing) in out, out
    assert "lib.rs" not in out and ".rs:" not in out, out


def test_make_acl_takes_the_daemons_session_name_rule(tmp_path: Path) -> None:
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_acl_rule", ROOT / "deploy" / "make_acl.py")
    assert spec is not None and spec.loader is not None
    make_acl = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_acl)
    names = ["paper", "Robot.One", "robot.one", "a" * 64, "a" * 65, "-x", "x-y_z", "", "é"]
    for name in names:
        try:
            keys.check_name(name)
            daemon = True
        except keys.KeyError_:
            daemon = False
        doc = {"services": ["service"], "session": [{"name": name}]}
        try:
            make_acl.read_sessions(doc)
            acl = True
        except make_acl.InputError:
            acl = False
        assert acl == daemon, name
    # without pd_service importable (stdlib only, as on a router host) the same rule
    (tmp_path / "s.toml").write_text('services = ["service"]\n[[session]]\nname = "Robot.One"\n')
    done = subprocess.run([sys.executable, "-I", "-S", str(ROOT / "deploy" / "make_acl.py"),
                           str(tmp_path / "s.toml")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "Robot.One" in done.stderr, done.stderr
    assert make_acl.NAME_PATTERN == keys.NAME_PATTERN
