"""Every file of deploy/ parses, and the files agree with each other and with the code.

- JSON5 (router and per-role Zenoh configs): zenoh.Config.from_file, i.e. Zenoh's own parser,
  which rejects unknown fields and unknown ACL message names;
- compose.yml: PyYAML; the router image tag equals the installed eclipse-zenoh release, every
  referenced service, file and command exists, every command line parses with its tool's
  own argument parser;
- Dockerfile: the Zenoh pin and every COPY source;
- the systemd unit: configparser, and its ExecStart parses with the daemon's parser;
- router.json5's access control, evaluated statically: who may put on which key.
"""

from __future__ import annotations

import configparser
import importlib
import importlib.metadata
import json
import re
import shlex
import tomllib
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from pd_service.link.config import load_config
from pd_service.transport.keyexpr import intersects
from pd_service.wire import keys

from ._support import (
    DEPLOY,
    MESH_USER,
    REPO,
    ROLES,
    ZENOH_DIR,
    compose_routers,
    load_deploy_script,
    load_healthcheck,
    read_users,
)

ZENOH_VERSION = importlib.metadata.version("eclipse-zenoh")
JSON5_FILES = sorted(DEPLOY.rglob("*.json5"))

#: the router each role's file connects to (compose.yml: router-a the operations site,
#: router-b the robot site)
NEAREST_ROUTER = {"admin": "router-a", "operator": "router-a", "service": "router-a",
                  "display": "router-a", "robot": "router-b", "link": "router-b"}

#: console script -> module with ``build_parser()`` (the tools compose.yml runs)
TOOL_MODULES = {
    "pd-service": "pd_service.service.__main__",
    "pd-link": "pd_service.link.__main__",
    "pd-robot-sim": "pd_client.tools.pd_robot_sim",
    "pd-operator": "pd_client.tools.pd_operator",
}


def json5(path: Path) -> dict[str, Any]:
    """A Zenoh JSON5 file parsed by Zenoh, as the full resulting configuration."""
    return json.loads(str(zenoh.Config.from_file(str(path))))


def compose() -> dict[str, Any]:
    return yaml.safe_load((DEPLOY / "compose.yml").read_text(encoding="utf-8"))


def router_services() -> dict[str, dict[str, Any]]:
    """compose.yml's zenohd services (the eclipse/zenoh image)."""
    return {name: svc for name, svc in compose()["services"].items()
            if str(svc.get("image", "")).startswith("eclipse/zenoh:")}


def compose_partitions() -> int:
    """PD_PARTITIONS every Python service of compose.yml runs with (all the same)."""
    values = {svc["environment"]["PD_PARTITIONS"] for svc in compose()["services"].values()
              if "build" in svc}
    assert len(values) == 1, f"every party of the deployment needs the same P: {values}"
    return int(values.pop())


def console_scripts() -> dict[str, str]:
    """[project.scripts] of the two packages the image installs."""
    out: dict[str, str] = {}
    for pp in (REPO / "pyproject.toml", REPO / "clients" / "python" / "pyproject.toml"):
        out.update(tomllib.loads(pp.read_text(encoding="utf-8"))["project"].get("scripts", {}))
    return out


def parse_tool_args(argv: list[str]) -> None:
    """Parse ``argv`` (a command line of compose.yml or the systemd unit) with the tool's own
    argparse parser; argparse exits (SystemExit) on an unknown or malformed flag."""
    tool = Path(argv[0]).name
    if tool == "python":
        assert argv[1] == "/opt/pd-service/healthcheck.py", argv
        load_healthcheck().build_parser().parse_args(argv[2:])
        return
    module = importlib.import_module(TOOL_MODULES[tool])
    module.build_parser().parse_args(argv[1:])


# --- Zenoh configuration files ---------------------------------------------------------

def test_deploy_has_the_expected_files() -> None:
    names = {p.relative_to(DEPLOY).as_posix() for p in DEPLOY.rglob("*") if p.is_file()}
    want = {"compose.yml", "Dockerfile", "README.md", "healthcheck.py", "link-paper.toml",
            "systemd/pd-service.service", "zenoh/router.json5", "zenoh/users.txt",
            "make_acl.py", "sessions.toml",
            *(f"zenoh/{r}.json5" for r in ROLES)}
    assert want <= names


@pytest.mark.parametrize("path", JSON5_FILES, ids=lambda p: p.relative_to(DEPLOY).as_posix())
def test_json5_parses_with_zenoh(path: Path) -> None:
    conf = json5(path)
    assert conf["scouting"]["multicast"]["enabled"] is False, "explicit endpoints only"


def test_users_file_has_one_marked_demo_password_per_role() -> None:
    users = read_users()
    assert set(users) == {*ROLES, MESH_USER}
    for user, password in users.items():
        assert password.startswith("DEMO-ONLY-"), f"{user}: demo passwords must say so"
    assert len(set(users.values())) == len(users), "every role has its own password"


@pytest.mark.parametrize("role", ROLES)
def test_role_config_is_an_authenticated_client_of_the_router(role: str) -> None:
    conf = json5(ZENOH_DIR / f"{role}.json5")
    assert conf["mode"] == "client", "access control is enforced at the router only"
    # one endpoint: its nearest router, a router service of compose.yml
    assert conf["connect"]["endpoints"] == [f"tcp/{NEAREST_ROUTER[role]}:7447"]
    assert NEAREST_ROUTER[role] in router_services()
    auth = conf["transport"]["auth"]["usrpwd"]
    assert auth["user"] == role
    assert auth["password"] == read_users()[role]
    listen = conf["listen"]["endpoints"]  # a list, or Zenoh's per-mode defaults (a dict)
    assert not (listen.get("client") if isinstance(listen, dict) else listen), \
        "a client listens on nothing"


# --- access control, evaluated statically ----------------------------------------------

def acl() -> dict[str, Any]:
    return json5(ZENOH_DIR / "router.json5")["access_control"]


def test_router_json5_is_what_the_generator_makes_of_sessions_toml(monkeypatch) -> None:
    """For compose.yml's partition count P, which the header also names."""
    monkeypatch.chdir(REPO)  # the header names the sessions file as given
    make_acl = load_deploy_script("make_acl.py")
    n = str(compose_partitions())
    assert make_acl.main(["deploy/sessions.toml", "--partitions", n, "--check",
                          str(ZENOH_DIR / "router.json5")]) == 0, \
        f"run: python deploy/make_acl.py deploy/sessions.toml --partitions {n} " \
        "> deploy/zenoh/router.json5"
    assert f"PD_PARTITIONS={n}" in (ZENOH_DIR / "router.json5").read_text(encoding="utf-8")


@pytest.mark.parametrize("n", [1, 2, 7, 64, 256, 4096])
def test_generator_partitions_sessions_as_the_keys_module_does(n: int) -> None:
    """make_acl.py's own FNV-1a (stdlib only) names the same partition as
    pd_service.wire.keys.partition_of, for many names."""
    make_acl = load_deploy_script("make_acl.py")
    names = ["paper", "a", "b", "0", "z" * 64, "robot-7", "s_1", *(f"s{i}" for i in range(500)),
             *(f"fleet-{i:05d}" for i in range(0, 100_000, 997))]
    for name in names:
        assert make_acl.session_path(name, n) == f"p{keys.partition_of(name, n)}/{name}", name


def test_router_requires_auth_and_denies_by_default() -> None:
    conf = json5(ZENOH_DIR / "router.json5")
    assert conf["mode"] == "router"
    assert conf["transport"]["auth"]["usrpwd"]["dictionary_file"] == "/etc/zenoh/users.txt"
    a = conf["access_control"]
    assert a["enabled"] is True and a["default_permission"] == "deny"
    assert conf["adminspace"]["permissions"] == {"read": False, "write": False}


def test_acl_references_are_consistent() -> None:
    a = acl()
    rule_ids = [r["id"] for r in a["rules"]]
    subject_ids = [s["id"] for s in a["subjects"]]
    assert len(rule_ids) == len(set(rule_ids)) and len(subject_ids) == len(set(subject_ids))
    used: set[str] = set()
    for p in a["policies"]:
        assert set(p["rules"]) <= set(rule_ids), p["id"]
        assert set(p["subjects"]) <= set(subject_ids), p["id"]
        used |= set(p["rules"])
    assert used == set(rule_ids), f"unused rules: {set(rule_ids) - used}"
    users = set(read_users())
    named = {u for s in a["subjects"] for u in s.get("usernames") or []}
    assert named | {MESH_USER} == users, \
        "every user has a subject and every subject user can log in"
    # the mesh user is no subject: routers are matched by Zenoh id (a router that connected
    # out learns no user name of its peer), and the mesh gets no client rule
    routers = [s for s in a["subjects"] if s.get("zids")]
    assert [(s["id"], s.get("usernames")) for s in routers] == [("routers", None)]
    for r in a["rules"]:
        assert r["permission"] == "allow", "deny-by-default: rules only allow"
        assert r.get("flows"), f"{r['id']}: say the flows explicitly"
        assert all(k not in ("**", "*") for k in r["key_exprs"]), f"{r['id']}: too wide"


def allowed_users(message: str, flow: str, key: str) -> set[str]:
    """Users whose policies allow ``message`` in ``flow`` on (a key intersecting) ``key``."""
    a = acl()
    rules = {r["id"]: r for r in a["rules"]}
    subjects = {s["id"]: set(s.get("usernames") or []) for s in a["subjects"]}
    out: set[str] = set()
    for p in a["policies"]:
        for rid in p["rules"]:
            r = rules[rid]
            if (message in r["messages"] and flow in r["flows"]
                    and any(intersects(k, key) for k in r["key_exprs"])):
                for sid in p["subjects"]:
                    out |= subjects[sid]
    return out


@pytest.mark.parametrize(("message", "flow", "key", "who"), [
    # deploy/sessions.toml: session "paper" (robot "robot", operator "operator", direct;
    # created by the admin); "other" is a session nobody was given.  Key layout 2 with
    # compose.yml's P = 64: paper is in partition p57, other in p53
    # (test_session_partitions_of_the_table)
    ("put", "ingress", "pd/p57/paper/cmd", {"operator"}),
    ("delete", "ingress", "pd/p57/paper/cmd", {"operator"}),
    ("put", "ingress", "pd/p53/other/cmd", set()),
    ("put", "ingress", "robot/p57/paper/sensor/camera", {"robot"}),
    ("put", "ingress", "robot/p53/other/sensor/camera", set()),
    ("put", "ingress", "robot/p57/paper/truth", {"robot"}),
    ("put", "ingress", "pd/p57/paper/prediction", {"service"}),
    ("put", "ingress", "pd/p57/paper/error", {"service"}),
    ("put", "ingress", "pd/p57/paper/status", {"service"}),
    ("put", "ingress", "pd/p57/paper/sensor/camera", {"link", "robot"}),   # robot: direct mode
    ("put", "ingress", "pd/p53/other/sensor/camera", {"link"}),
    ("put", "ingress", "robot/p57/paper/cmd", {"link"}),
    ("put", "ingress", "pd/p57/paper/config", {"admin"}),            # the robot may not create
    ("delete", "ingress", "pd/p57/paper/config", {"admin", "service"}),  # service: expiry
    ("put", "ingress", "pd/p53/other/config", {"admin"}),
    ("delete", "ingress", "pd/p53/other/config", {"admin", "service"}),  # service: expiry
    ("put", "ingress", "pd/@service/pd-a", {"service"}),
    ("liveliness_token", "ingress", "pd/@service/pd-a", {"service"}),
    ("declare_queryable", "ingress", "pd/p57/paper/status", {"service"}),
    ("declare_queryable", "ingress", "pd/@service/pd-a/status", {"service"}),
    ("declare_queryable", "ingress", "pd/@link/paper/rules", {"link"}),
    ("query", "ingress", "pd/@link/paper/rules", {"admin"}),       # a payload replaces rules
    ("put", "ingress", "pd/@link/paper/rules", {"admin"}),
    ("put", "egress", "pd/p57/paper/cmd", {"service", "link", "robot"}),
    ("put", "egress", "pd/p57/paper/prediction", {"admin", "operator", "display"}),
    ("put", "egress", "pd/p53/other/prediction", {"admin", "display"}),
    ("put", "egress", "robot/p57/paper/truth", {"display"}),
    ("put", "egress", "robot/p57/paper/cmd", {"robot"}),
    ("put", "egress", "robot/p53/other/cmd", set()),
    # sender caches (zenoh-ext advanced publishers, <key>/@adv/pub/<zid>/<eid>/<meta>): the
    # direct robot and pd-link serve sensor caches, the operator and pd-link command caches,
    # only the daemon reads them (queries on a token's key; replies carry the samples' keys)
    ("declare_queryable", "ingress", "pd/p57/paper/sensor/camera/@adv/pub/z/1/_", {"robot", "link"}),
    ("liveliness_token", "ingress", "pd/p57/paper/sensor/camera/@adv/pub/z/1/_", {"robot", "link"}),
    ("declare_queryable", "ingress", "pd/p53/other/sensor/camera/@adv/pub/z/1/_", {"link"}),
    ("declare_queryable", "ingress", "pd/p57/paper/cmd/@adv/pub/z/1/_", {"operator", "link"}),
    ("liveliness_token", "ingress", "pd/p53/other/cmd/@adv/pub/z/1/_", {"link"}),
    ("declare_queryable", "ingress", "robot/p57/paper/sensor/camera/@adv/pub/z/1/_", set()),
    ("query", "egress", "pd/p57/paper/sensor/camera/@adv/pub/z/1/_", {"robot", "link"}),
    ("query", "egress", "pd/p57/paper/cmd/@adv/pub/z/1/_", {"operator", "link"}),
    ("reply", "ingress", "pd/p57/paper/sensor/camera", {"robot", "link", "service"}),
    ("reply", "ingress", "pd/p53/other/sensor/camera", {"link", "service"}),
    ("reply", "ingress", "pd/p57/paper/cmd", {"operator", "link", "service"}),
    ("query", "ingress", "pd/p57/paper/sensor/camera/@adv/pub/z/1/_", {"service"}),
    ("query", "ingress", "pd/p57/paper/cmd/@adv/pub/z/1/_", {"service"}),
    ("declare_liveliness_subscriber", "ingress", "pd/*/*/sensor/*/@adv/pub/**", {"service"}),
    ("liveliness_query", "ingress", "pd/*/*/cmd/@adv/pub/**", {"service"}),
    ("liveliness_token", "egress", "pd/p57/paper/sensor/camera/@adv/pub/z/1/_", {"service"}),
    ("reply", "egress", "pd/p57/paper/sensor/camera", {"service"}),
    # the right session in the wrong partition (another P) is nobody's
    ("put", "ingress", "pd/p3/paper/cmd", set()),
    ("put", "ingress", "robot/p3/paper/sensor/camera", set()),
    ("put", "egress", "pd/p3/paper/prediction", {"admin", "display"}),
    # key layout 1 (an old client): only what the daemon answers with a refusal passes
    ("put", "ingress", "pd/paper/config", {"admin"}),
    ("declare_subscriber", "ingress", "pd/paper/config", {"admin", "service"}),
    ("put", "egress", "pd/paper/config", {"admin", "service"}),
    ("query", "ingress", "pd/paper/status", {"admin", "operator", "service"}),
    ("declare_queryable", "ingress", "pd/paper/status", {"service"}),
    ("reply", "ingress", "pd/paper/status", {"service"}),
    ("reply", "egress", "pd/paper/status", {"admin", "operator", "service"}),
    ("put", "ingress", "pd/paper/error", {"service"}),
    ("put", "egress", "pd/paper/error", {"admin", "operator"}),
    ("put", "ingress", "pd/paper/cmd", set()),
    # the links' pd/*/*/camera (frames after the downlink) also matches a layout-1 sensor
    # named "camera" (chunk wildcards cannot tell p<k>/<s> from <s>/sensor); no layout-2
    # party subscribes to layout-1 sensor keys, and only links (every session's relay) may
    ("put", "ingress", "pd/paper/sensor/camera", {"link"}),
    ("put", "ingress", "pd/paper/sensor/gps", set()),
    ("put", "ingress", "robot/paper/sensor/camera", set()),
    ("put", "egress", "pd/paper/prediction", set()),
])
def test_who_may_do_what(message: str, flow: str, key: str, who: set[str]) -> None:
    assert allowed_users(message, flow, key) == who


def test_session_partitions_of_the_table() -> None:
    assert compose_partitions() == 64
    assert (keys.partition_of("paper", 64), keys.partition_of("other", 64)) == (57, 53)


def test_mesh_carries_what_any_client_may_send() -> None:
    """The routers' policy ("mesh", matched by Zenoh id) covers every key expression of every
    client rule (else a message one router let in could not reach another router's client),
    and nothing beyond pd/** and robot/** and the named verbatim chunks."""
    a = acl()
    rules = {r["id"]: r for r in a["rules"]}
    (policy,) = [p for p in a["policies"] if p["id"] == "routers"]
    assert policy["rules"] == ["mesh"]
    mesh = rules["mesh"]
    assert set(mesh["flows"]) == {"ingress", "egress"}
    clients = [r for rid, r in rules.items() if rid != "mesh"]
    assert {m for r in clients for m in r["messages"]} <= set(mesh["messages"])
    for r in clients:
        for k in r["key_exprs"]:
            assert any(zenoh.KeyExpr(m).includes(zenoh.KeyExpr(k)) for m in mesh["key_exprs"]), \
                (r["id"], k)
    assert all(k.split("/")[0] in ("pd", "robot") for k in mesh["key_exprs"])
    zids = next(s["zids"] for s in a["subjects"] if s["id"] == "routers")
    assert sorted(zids) == sorted(router_ids().values())


# --- compose ---------------------------------------------------------------------------

def test_compose_router_is_the_pinned_zenoh_release() -> None:
    c = compose()
    routers = router_services()
    assert set(routers) == {"router-a", "router-b"}
    for name, svc in routers.items():
        assert svc["image"] == f"eclipse/zenoh:{ZENOH_VERSION}", name
        assert svc["command"][:2] == ["-c", "/etc/zenoh/router.json5"], name
    for name, svc in c["services"].items():
        if "build" in svc:
            assert svc["build"]["args"]["ZENOH_VERSION"] == ZENOH_VERSION, name
            assert (DEPLOY / svc["build"]["context"] / svc["build"]["dockerfile"]).resolve() \
                == (DEPLOY / "Dockerfile").resolve()


def router_ids() -> dict[str, str]:
    return {name: args.id for name, args in compose_routers().items()}


def test_compose_routers_form_a_mesh_under_one_access_control() -> None:
    """Both routers run router.json5 (the same mounted file), each under its own Zenoh id,
    one of the mesh ids of the file; router-b connects to router-a (a connected graph), and
    the file's mesh user can log in."""
    routers = compose_routers()
    services = router_services()
    ids = router_ids()
    assert len(set(ids.values())) == len(ids) and all(ids.values())
    conf = json5(ZENOH_DIR / "router.json5")
    mesh = next(s for s in conf["access_control"]["subjects"] if s["id"] == "routers")
    assert sorted(mesh["zids"]) == sorted(ids.values())
    auth = conf["transport"]["auth"]["usrpwd"]
    assert (auth["user"], auth["password"]) == (MESH_USER, read_users()[MESH_USER])
    mounts = {tuple(svc["volumes"]) for svc in services.values()}
    assert len(mounts) == 1, "both routers mount the same router.json5 and users.txt"
    edges = {(name, ep.split("/")[1].split(":")[0]) for name, a in routers.items()
             for ep in a.connect}
    assert edges == {("router-b", "router-a")}
    assert all(a.listen == [] for a in routers.values()), "router.json5 decides the listener"
    assert services["router-b"]["depends_on"] == {"router-a": {"condition": "service_healthy"}}


def test_compose_references_exist() -> None:
    c = compose()
    services = c["services"]
    assert {"router-a", "router-b", "pd-service", "pd-service-b", "link", "robot-sim",
            "operator"} <= set(services)
    named_volumes = set(c.get("volumes") or {})
    for name, svc in services.items():
        for dep in svc.get("depends_on") or {}:
            assert dep in services, f"{name} depends on unknown service {dep}"
        if svc.get("restart") != "no":  # a one-shot service (exits when done) has none
            assert svc.get("healthcheck", {}).get("test"), f"{name} has no health check"
        mounts: dict[str, Path | None] = {}
        for v in svc.get("volumes") or []:
            source, target = v.split(":")[:2]
            if source.startswith("."):
                assert (DEPLOY / source).exists(), f"{name}: missing {source}"
                mounts[target] = DEPLOY / source
            else:
                assert source in named_volumes, f"{name}: unknown volume {source}"
                mounts[target] = None
        # every file a command names under /etc is provided by a bind mount
        words = list(svc.get("command") or []) + list(
            svc.get("healthcheck", {}).get("test", [None])[1:])
        for w in words:
            if isinstance(w, str) and w.startswith("/etc/"):
                assert any(w == t or w.startswith(t.rstrip("/") + "/") for t in mounts), \
                    f"{name}: {w} is not mounted"


def test_compose_python_services_log_in_with_their_role() -> None:
    want = {"pd-service": "service", "pd-service-b": "service", "link": "link",
            "robot-sim": "robot", "operator": "operator", "session": "admin"}
    services = compose()["services"]
    for name, role in want.items():
        cmd = services[name]["command"]
        i = cmd.index("--zenoh-config")
        assert cmd[i + 1] == f"/etc/pd-service/zenoh/{role}.json5", name
        assert "--connect" not in cmd and "--listen" not in cmd, f"{name}: the file decides"
        if name == "session":  # one shot: no health check
            continue
        hc = services[name]["healthcheck"]["test"]
        assert hc[hc.index("--zenoh-config") + 1] == cmd[i + 1], name


def test_compose_commands_exist_and_parse() -> None:
    scripts = console_scripts()
    for name, svc in compose()["services"].items():
        if "build" not in svc:
            continue
        cmd = svc["command"]
        assert cmd[0] in scripts, f"{name}: {cmd[0]} is not a console script of the image"
        assert scripts[cmd[0]].split(":")[0] == TOOL_MODULES[cmd[0]], cmd[0]
        parse_tool_args(cmd)
        if svc.get("restart") == "no":  # one shot: no health check
            continue
        test = svc["healthcheck"]["test"]
        assert test[0] == "CMD"
        parse_tool_args(test[1:])


# --- Dockerfile, systemd, link rules ---------------------------------------------------

def test_dockerfile_pins_zenoh_and_copies_existing_files() -> None:
    text = (DEPLOY / "Dockerfile").read_text(encoding="utf-8")
    assert f"ARG ZENOH_VERSION={ZENOH_VERSION}\n" in text
    assert '"eclipse-zenoh==${ZENOH_VERSION}"' in text
    copies = re.findall(r"^COPY\s+(?!--from)(.+)$", text, flags=re.M)
    assert copies
    for line in copies:
        *sources, _dest = shlex.split(line)
        for src in sources:
            assert (REPO / src).exists(), f"COPY source {src} is missing"


def test_systemd_unit_parses_and_runs_the_daemon() -> None:
    unit = configparser.ConfigParser(interpolation=None, strict=True)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    assert unit.read(DEPLOY / "systemd" / "pd-service.service")
    assert {"Unit", "Service", "Install"} <= set(unit.sections())
    svc = unit["Service"]
    argv = shlex.split(svc["ExecStart"])
    assert Path(argv[0]).name == "pd-service"
    parse_tool_args(argv)
    assert argv[argv.index("--zenoh-config") + 1] == "/etc/pd-service/zenoh/service.json5"
    assert svc["User"] != "root" and svc["KillSignal"] == "SIGTERM"
    assert svc["StateDirectory"] == "pd-service"
    assert argv[argv.index("--state-dir") + 1] == "/var/lib/pd-service"
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_link_rules_are_the_papers_link() -> None:
    """compose.yml's link emulator runs deploy/link-paper.toml: camera 10 steps, range finder
    12, uplink 10 (Liang et al. 2017, Sec. 4)."""
    cfg = load_config(DEPLOY / "link-paper.toml")
    step_ns = round(cfg.step_ms * 1e6)
    assert step_ns == 50_000_000
    delays = {r.name: r.params.delay.delay_ns / step_ns for r in (*cfg.downlink, *cfg.uplink)}
    assert {k: delays.get(k) for k in ("camera", "ranger", "commands")} == {
        "camera": 10, "ranger": 12, "commands": 10}
