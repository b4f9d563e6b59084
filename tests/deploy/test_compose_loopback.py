"""compose.yml's Python services, run as local processes behind its two meshed routers.

No Docker here: the test reads the command lines of compose.yml, maps the container paths to
the repository's files (``/etc/pd-service/zenoh/X`` -> deploy/zenoh/X, ...), runs router-a and
router-b as Python Zenoh router sessions with router.json5 (ids and mesh link as compose gives
them), adds ``--connect`` to the loopback endpoint of the router the role file names, starts
the two daemon instances, the link emulator, the simulated robot and the operator exactly as
compose would, and checks that the whole system works under the access control: the daemon
accepts the robot's measurements (through the link emulator, across the mesh) and the
operator's commands, a display client receives predictions, and every service's compose
health check passes.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
import zenoh

from pd_service.wire import SessionStatus, decode, keys

from ._support import DEPLOY, ZENOH_DIR, open_client, wait_for
from .test_router_mesh import mesh

pytestmark = pytest.mark.integration

BIN = Path(sys.executable).parent
SESSION = "paper"  # compose.yml's session
START_ORDER = ("pd-service", "pd-service-b", "link", "session", "robot-sim", "operator")
#: Services that run once and exit 0 (compose: restart "no"); no health check.
ONE_SHOT = ("session",)


def local_argv(argv: list[str], endpoints: dict[str, str], state_dir: Path) -> list[str]:
    """A compose command line with container paths replaced by the repository's files and
    ``--connect`` to the loopback endpoint of the router its role file names."""
    mapping = {"/etc/pd-service/zenoh/": f"{ZENOH_DIR}/",
               "/etc/pd-service/link-paper.toml": str(DEPLOY / "link-paper.toml"),
               "/var/lib/pd-service": str(state_dir),
               "/opt/pd-service/healthcheck.py": str(DEPLOY / "healthcheck.py")}
    out = []
    for word in argv:
        for container, local in mapping.items():
            if word.startswith(container):
                word = local + word[len(container):]
        out.append(word)
    role_file = Path(out[out.index("--zenoh-config") + 1])
    router = json.loads(str(zenoh.Config.from_file(str(role_file))))["connect"]["endpoints"]
    endpoint = endpoints[router[0].split("/")[1].split(":")[0]]
    if out[0] == "python":
        return [sys.executable, *out[1:], "--connect", endpoint]
    return [str(BIN / out[0]), *out[1:], "--connect", endpoint]


@contextlib.contextmanager
def processes(commands: dict[str, list[str]], logs: Path) -> Iterator[dict[str, subprocess.Popen]]:
    procs: dict[str, subprocess.Popen] = {}
    files = []
    try:
        for name, argv in commands.items():
            f = open(logs / f"{name}.log", "wb")
            files.append(f)
            procs[name] = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT)
        yield procs
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for f in files:
            f.close()


def test_compose_services_work_under_the_acl(tmp_path: Path) -> None:
    services = yaml.safe_load((DEPLOY / "compose.yml").read_text(encoding="utf-8"))["services"]
    for name in START_ORDER:
        if not (BIN / services[name]["command"][0]).exists():
            pytest.skip(f"{services[name]['command'][0]} is not installed in this venv")
    with mesh() as endpoints:
        run_compose(services, endpoints, tmp_path)


def run_compose(services: dict, endpoints: dict[str, str], tmp_path: Path) -> None:
    commands = {name: local_argv(services[name]["command"], endpoints,
                                 tmp_path / f"state-{name}") for name in START_ORDER}

    def logs() -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}"
                         for p in sorted(tmp_path.glob("*.log")))

    with processes(commands, tmp_path) as procs, \
            open_client("display", endpoints["router-a"]) as display:
        predictions = threading.Event()
        count = [0]

        def on_prediction(_sample) -> None:
            count[0] += 1
            if count[0] >= 10:
                predictions.set()

        display.subscribe(keys.prediction_key(SESSION), on_prediction)

        def status() -> dict[str, int] | None:
            for name, p in procs.items():
                if name in ONE_SHOT and p.poll() == 0:
                    continue
                if p.poll() is not None:
                    raise AssertionError(f"{name} exited with {p.returncode}\n{logs()}")
            for r in display.get(keys.status_key(SESSION), timeout=1.0):
                if r.ok:
                    return dict(decode(r.payload, SessionStatus).counters)
            return None

        try:
            counters = wait_for(
                lambda: (c := status()) is not None and c.get("accepted", 0) >= 5
                and c.get("commands_accepted", 0) >= 5 and c,
                60.0, "the daemon to accept measurements and commands")
            assert predictions.wait(30.0), "the display received no predictions"
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{logs()}") from None
        assert counters["accepted"] >= 5 and counters["commands_accepted"] >= 5

        # every compose health check passes against the running services
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        assert all(procs[name].poll() == 0 for name in ONE_SHOT), logs()
        for name in START_ORDER:
            if name in ONE_SHOT:
                continue
            test = services[name]["healthcheck"]["test"]
            argv = local_argv(test[1:], endpoints, tmp_path / f"state-{name}")
            done = subprocess.run(argv, capture_output=True, text=True, timeout=60, env=env)
            assert done.returncode == 0, f"{name}: {done.stdout}{done.stderr}"
