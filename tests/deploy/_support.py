"""Shared helpers of the deploy tests: paths, the users file, a router and per-role clients.

The router is a Python Zenoh session in router mode opened with deploy/zenoh/router.json5
(only its listen endpoint and the path of users.txt are overridden; for a mesh also its Zenoh
id and the router it connects to, as compose.yml gives them to zenohd): in zenoh-python 1.x
such a session relays pub/sub, queries and liveliness and enforces the same access control
and user/password authentication as zenohd.  Clients are opened with the role files
deploy/zenoh/<role>.json5, their connect endpoint overridden.
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import TypeVar

import yaml

from pd_service.transport import ZenohTransport, zenoh_config
from tests.scripts import load_script

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
ZENOH_DIR = DEPLOY / "zenoh"
ROLES = ("admin", "operator", "robot", "service", "link", "display")
#: the user the routers of the mesh log in with to each other (sessions.toml [mesh])
MESH_USER = "router"

T = TypeVar("T")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_users(path: Path = ZENOH_DIR / "users.txt") -> dict[str, str]:
    """users.txt as {user: password}; raises ValueError on a line that is not user:password."""
    users: dict[str, str] = {}
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        user, sep, password = line.partition(":")
        if not sep or not user or not password or line != line.strip():
            raise ValueError(f"{path}:{n}: expected 'user:password', got {line!r}")
        if user in users:
            raise ValueError(f"{path}:{n}: user {user!r} listed twice")
        users[user] = password
    return users


def open_router(endpoint: str, *, acl: bool = True, file: Path = ZENOH_DIR / "router.json5",
                users: Path = ZENOH_DIR / "users.txt", zid: str | None = None,
                connect: Sequence[str] = (), admin_read: bool = False) -> ZenohTransport:
    """A router session configured by ``file`` (deploy/zenoh/router.json5), listening on
    ``endpoint``, its user list ``users``; ``zid`` its Zenoh id (zenohd ``--id``) and
    ``connect`` the routers it connects to (zenohd ``--connect``), for a mesh.

    ``acl=False`` turns access control off (authentication stays on): the control case that
    shows a test would notice a message the ACL failed to stop.  ``admin_read`` opens the
    router's admin space for reading (its routing tables, ``@/<zid>/router/**``)."""
    conf = zenoh_config(file=file, listen=[endpoint], connect=connect)
    if admin_read:
        conf.insert_json5("adminspace", '{"enabled": true, "permissions": {"read": true}}')
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    if zid is not None:
        conf.insert_json5("id", json.dumps(zid))
    if not acl:
        conf.insert_json5("access_control/enabled", "false")
    return ZenohTransport(conf)


def open_client(role: str, endpoint: str, *, user: str | None = None,
                password: str | None = None, connect_timeout_ms: int | None = None
                ) -> ZenohTransport:
    """A client session from deploy/zenoh/<role>.json5, connected to ``endpoint``.

    ``user``/``password`` replace the file's credentials (both must be given);
    ``connect_timeout_ms`` replaces the file's wait for the router (0: one attempt)."""
    conf = zenoh_config(file=ZENOH_DIR / f"{role}.json5", connect=[endpoint],
                        user=user, password=password)
    if connect_timeout_ms is not None:
        conf.insert_json5("connect/timeout_ms", json.dumps(connect_timeout_ms))
    return ZenohTransport(conf)


def wait_for(probe: Callable[[], T], timeout: float, what: str, interval: float = 0.05) -> T:
    """Call ``probe`` until it returns something truthy (returned) or ``timeout`` s pass
    (AssertionError naming ``what``).  Bounded polling, for states that raise no event."""
    deadline = time.monotonic() + timeout
    while True:
        value = probe()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def load_healthcheck() -> ModuleType:
    """deploy/healthcheck.py as a module (it is a script copied into the image)."""
    return load_deploy_script("healthcheck.py")


def load_deploy_script(name: str) -> ModuleType:
    """A script of deploy/ (healthcheck.py, make_acl.py) as a module."""
    return load_script(f"deploy/{name}", f"pd_deploy_{name.removesuffix('.py')}")


def zenohd_args(argv: list[str]) -> argparse.Namespace:
    """A zenohd command line of compose.yml (the flags it uses: ``-c``, ``--id``,
    ``--connect``, ``--listen``); SystemExit on anything else."""
    p = argparse.ArgumentParser(prog="zenohd", exit_on_error=False)
    p.add_argument("-c", "--config", required=True)
    p.add_argument("-i", "--id")
    p.add_argument("-e", "--connect", action="append", default=[])
    p.add_argument("-l", "--listen", action="append", default=[])
    return p.parse_args(argv)


def compose_routers() -> dict[str, argparse.Namespace]:
    """compose.yml's zenohd services (the eclipse/zenoh image): name -> parsed command."""
    services = yaml.safe_load((DEPLOY / "compose.yml").read_text(encoding="utf-8"))["services"]
    return {name: zenohd_args(svc["command"]) for name, svc in services.items()
            if str(svc.get("image", "")).startswith("eclipse/zenoh:")}
