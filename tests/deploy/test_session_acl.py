"""deploy/make_acl.py: a router configuration generated from two sessions, enforced by a Python
Zenoh router on loopback (user/password authentication, access control scoped by session).

Sessions ``a`` (robot ``robot-a``, operator ``op-a``) and ``b`` (``robot-b``, ``op-b``);
``admin`` creates sessions and administers pd-link; ``service`` is the daemon.  Every negative
check has a control run with access control off in which the same sequence does deliver the
refused messages (see test_router_acl.publish_race).
"""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from pd_service.transport import ZenohTransport
from pd_service.wire import keys

from ._support import free_port, load_deploy_script, open_client, open_router, wait_for
from .test_router_acl import NEGATIVE_WAIT_S, ROUNDS, TIMEOUT_S, Collector, publish_race

pytestmark = pytest.mark.integration

SESSIONS_TOML = """
admins = ["admin"]
link_admins = ["admin"]
services = ["service"]
links = ["link"]
displays = ["display"]

[[session]]
name = "a"
robot = "robot-a"
operator = "op-a"

[[session]]
name = "b"
robot = "robot-b"
operator = "op-b"
direct = true
"""
USERS = ("admin", "service", "link", "display", "robot-a", "op-a", "robot-b", "op-b")
ROLE_FILE = {"admin": "admin", "service": "service", "link": "link", "display": "display",
             "robot-a": "robot", "robot-b": "robot", "op-a": "operator", "op-b": "operator"}


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(router.json5 generated from SESSIONS_TOML, users.txt)."""
    d = tmp_path_factory.mktemp("acl")
    (d / "sessions.toml").write_text(SESSIONS_TOML, encoding="utf-8")
    make_acl = load_deploy_script("make_acl.py")
    text = make_acl.render(make_acl.read_sessions(
        make_acl.tomllib.loads(SESSIONS_TOML)), "sessions.toml")
    (d / "router.json5").write_text(text, encoding="utf-8")
    (d / "users.txt").write_text("".join(f"{u}:pw-{u}\n" for u in USERS), encoding="utf-8")
    return d / "router.json5", d / "users.txt"


@contextlib.contextmanager
def system(generated: tuple[Path, Path], acl: bool, *users: str) -> Iterator[dict[str, ZenohTransport]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router, users_file = generated
    with open_router(endpoint, acl=acl, file=router, users=users_file), \
            contextlib.ExitStack() as stack:  # fmt: skip
        yield {u: stack.enter_context(open_client(ROLE_FILE[u], endpoint, user=u,
                                                  password=f"pw-{u}")) for u in users}


CASES = {
    # name: (subscriber, its key expression, key published, allowed user, refused user)
    "robot-a on b's robot-side sensors": ("link", keys.ROBOT_ALL_SENSORS,
                                          keys.robot_sensor_key("b", "camera"), "robot-b",
                                          "robot-a"),
    "robot-a on b's operator-side sensors": ("service", keys.ALL_SENSORS,
                                             keys.sensor_key("b", "camera"), "robot-b",
                                             "robot-a"),
    "robot-a creates a session": ("service", "pd/*/config", keys.config_key("new"), "admin",
                                  "robot-a"),
    "robot-b replaces its own session": ("service", "pd/*/config", keys.config_key("b"),
                                         "admin", "robot-b"),
    "op-a commands b": ("service", keys.ALL_COMMANDS, keys.command_key("b"), "op-b", "op-a"),
    "op-a creates a session": ("service", "pd/*/config", keys.config_key("a"), "admin", "op-a"),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_users_are_scoped_to_their_sessions(generated, case: str, acl: bool) -> None:
    """The allowed user's puts arrive (admin: creating a session), the refused user's do not."""
    sub_user, sub_key, key, allowed, refused = CASES[case]
    with system(generated, acl, sub_user, allowed, refused) as c:
        sub = Collector()
        c[sub_user].subscribe(sub_key, sub)
        leaked = publish_race(sub, key, c[allowed], c[refused], expect_other=not acl)
    assert leaked == (0 if acl else ROUNDS), f"{refused}'s puts on {key}"


@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_only_link_admins_replace_link_rules(generated, acl: bool) -> None:
    """A query with a payload on pd/@link/<i>/rules replaces pd-link's rules: the admin's
    reaches the link's queryable and is answered; an operator's and a robot's never reach it."""
    with system(generated, acl, "link", "admin", "op-a", "robot-a") as c:
        asked: list[tuple[str, bytes | None]] = []

        def serve(q) -> None:  # type: ignore[no-untyped-def]
            asked.append((q.key, q.payload))
            q.reply(keys.link_rules_key("lab"), b"new rules")
        c["link"].queryable(keys.link_rules_key("lab"), serve)
        got = wait_for(lambda: [r.payload for r in c["admin"].get(
            keys.link_rules_key("lab"), b"[[downlink]]", timeout=1.0) if r.ok],
            TIMEOUT_S, "the admin's rules query to be answered")
        assert got == [b"new rules"]
        n = len(asked)
        for user in ("op-a", "robot-a"):
            replies = [r for r in c[user].get(keys.link_rules_key("lab"), b"[[uplink]]",
                                              timeout=NEGATIVE_WAIT_S) if r.ok]
            assert (replies == []) if acl else (len(replies) == 1), user
        assert len(asked) == (n if acl else n + 2)


@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_operator_reads_only_its_sessions_predictions(generated, acl: bool) -> None:
    with system(generated, acl, "service", "op-a") as c:
        got = Collector()
        c["op-a"].subscribe(keys.prediction_key("a"), got)
        c["op-a"].subscribe(keys.prediction_key("b"), got)  # refused (a wildcard would be too)

        def arrived(session: str, want: bytes) -> bool:
            c["service"].put(keys.prediction_key(session), want)
            return got.wait_count(want, 1, 0.05)
        wait_for(lambda: arrived("a", b"mine"), TIMEOUT_S, "a's prediction to reach op-a")
        for _ in range(ROUNDS):
            c["service"].put(keys.prediction_key("b"), b"theirs")
            c["service"].put(keys.prediction_key("a"), b"mine")
        assert got.wait_count(b"mine", ROUNDS + 1, TIMEOUT_S)
        if acl:
            got.wait_count(b"theirs", 1, NEGATIVE_WAIT_S)
            assert got.count(b"theirs") == 0
        else:
            assert got.wait_count(b"theirs", ROUNDS, TIMEOUT_S)


@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_only_services_declare_membership_tokens(generated, acl: bool) -> None:
    """A token on pd/@service/<i> makes a daemon instance own sessions: only ``service`` may
    declare one.  A second service token declared after the stray ones is seen first."""
    with system(generated, acl, "service", "display", "robot-a", "admin") as c:
        seen: set[str] = set()
        cond = threading.Condition()

        def on_token(key: str, alive: bool) -> None:
            with cond:
                if alive:
                    seen.add(key)
                    cond.notify_all()
        c["service"].subscribe_liveliness(keys.ALL_SERVICES, on_token)
        c["service"].declare_token(keys.service_token_key("real"))
        with cond:
            assert cond.wait_for(lambda: keys.service_token_key("real") in seen, TIMEOUT_S)
        for user in ("display", "robot-a", "admin"):
            c[user].declare_token(keys.service_token_key(f"fake-{user}"))
        c["service"].declare_token(keys.service_token_key("real2"))
        with cond:
            assert cond.wait_for(lambda: keys.service_token_key("real2") in seen, TIMEOUT_S)
            fakes = {f"fake-{u}" for u in ("display", "robot-a", "admin")}
            if acl:
                cond.wait_for(lambda: any(keys.service_token_key(f) in seen for f in fakes),
                              NEGATIVE_WAIT_S)
                assert not {keys.service_token_key(f) for f in fakes} & seen, seen
            else:
                assert cond.wait_for(
                    lambda: {keys.service_token_key(f) for f in fakes} <= seen, TIMEOUT_S)
        if acl:  # a daemon's liveliness query sees only the services' tokens too
            assert sorted(c["service"].get_liveliness(keys.ALL_SERVICES, timeout=1.0)) == [
                keys.service_token_key("real"), keys.service_token_key("real2")]


def test_generator_refuses_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make_acl = load_deploy_script("make_acl.py")
    bad = {
        "unknown field": 'services = ["s"]\nadmin = ["x"]\n[[session]]\nname = "a"\n',
        "wildcard session": 'services = ["s"]\n[[session]]\nname = "*"\n',
        "no service": '[[session]]\nname = "a"\n',
        "twice": 'services = ["s"]\n[[session]]\nname = "a"\n[[session]]\nname = "a"\n',
        "bad user": 'services = ["s"]\n[[session]]\nname = "a"\nrobot = "r/x"\n',
    }
    for what, text in bad.items():
        path = tmp_path / "s.toml"
        path.write_text(text, encoding="utf-8")
        assert make_acl.main([str(path)]) == 2, what
    ok = tmp_path / "ok.toml"
    ok.write_text(SESSIONS_TOML, encoding="utf-8")
    capsys.readouterr()
    assert make_acl.main([str(ok)]) == 0
    text = capsys.readouterr().out
    out = tmp_path / "router.json5"
    out.write_text(text, encoding="utf-8")
    assert make_acl.main([str(ok), "--check", str(out)]) == 0
    out.write_text(text.replace('"op-a"', '"op-b"'), encoding="utf-8")
    assert make_acl.main([str(ok), "--check", str(out)]) == 1
    body = json.loads("{" + text.split("\n{", 1)[1])  # after the comment header
    assert body["access_control"]["default_permission"] == "deny"
