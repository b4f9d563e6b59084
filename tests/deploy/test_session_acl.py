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
import zenoh

from pd_service.transport import Sample, ZenohTransport
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
direct = true

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
def system(generated: tuple[Path, Path], acl: bool, *users: str,
           router: Path | None = None) -> Iterator[dict[str, ZenohTransport]]:
    """The router (``router``: another configuration file) and a client per user."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = router or generated[0]
    users_file = generated[1]
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
    "robot-a creates a session": ("service", keys.ALL_CONFIGS, keys.config_key("new"), "admin",
                                  "robot-a"),
    "robot-b replaces its own session": ("service", keys.ALL_CONFIGS, keys.config_key("b"),
                                         "admin", "robot-b"),
    "op-a commands b": ("service", keys.ALL_COMMANDS, keys.command_key("b"), "op-b", "op-a"),
    "op-a creates a session": ("service", keys.ALL_CONFIGS, keys.config_key("a"), "admin",
                               "op-a"),
    # key layout 1: an old admin's spec put reaches the daemon (which refuses it with a
    # reason), an old robot's does not
    "robot-a's layout-1 spec": ("service", keys.LEGACY_CONFIGS, "pd/a/config", "admin",
                                "robot-a"),
    # the right session under another partition (another P): nobody's
    "robot-a in a wrong partition": ("service", keys.ALL_SENSORS,
                                     f"pd/p{(keys.partition_of('a') + 1) % keys.partitions()}"
                                     "/a/sensor/camera", "link", "robot-a"),
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
            # (polled: on a loaded machine one answer came back empty after the subscriber
            # above had seen both tokens, which are the querying session's own)
            real = [keys.service_token_key("real"), keys.service_token_key("real2")]

            def answer() -> list[str] | None:
                got = c["service"].get_liveliness(keys.ALL_SERVICES, timeout=TIMEOUT_S)
                return got if set(real) <= set(got) else None
            assert sorted(wait_for(answer, TIMEOUT_S, "both service tokens in an answer")) == real


class Recovered:
    """``Transport.read_back`` callback: keeps (key, payload), signals each arrival."""

    def __init__(self) -> None:
        self.got: list[tuple[str, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, s: Sample) -> None:
        assert s.recovered
        with self.cond:
            self.got.append((s.key, s.payload))
            self.cond.notify_all()

    def wait_for(self, want: set[tuple[str, bytes]], timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: want <= set(self.got), timeout)

    def payloads(self) -> set[bytes]:
        with self.cond:
            return {p for _, p in self.got}


def cache_tokens(t: ZenohTransport, keyexpr: str) -> list[str]:
    """The liveliness tokens of the sender caches on ``keyexpr`` that ``t`` sees."""
    return t.get_liveliness(f"{keyexpr}/@adv/pub/**", timeout=TIMEOUT_S)


def read_cache(t: ZenohTransport, token: str) -> list[tuple[str, bytes]]:
    """Query one sender cache on its token's key, as the daemon does (all its samples)."""
    return [(str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in t.session.get(
        f"{token}?_max=16", consolidation=zenoh.ConsolidationMode.NONE,
        accept_replies=zenoh.ReplyKeyExpr.ANY, timeout=NEGATIVE_WAIT_S) if r.ok is not None]


def test_service_reads_back_sender_caches(generated) -> None:
    """The daemon's read-back through the router: the caches of a direct robot (sensors), an
    operator (commands) and pd-link (its outputs) are read at once, oldest first, and a cache
    declared later is read when its token appears (Transport.read_back, as ServiceCore.start
    calls it)."""
    with system(generated, True, "service", "robot-b", "op-a", "link") as c:
        sent: set[tuple[str, bytes]] = set()
        for user, key in (("robot-b", keys.sensor_key("b", "camera")),
                          ("op-a", keys.command_key("a")),
                          ("link", keys.sensor_key("a", "ranger"))):
            pub = c[user].publisher(key, cache=8)
            for i in range(3):
                pub.put(f"{user}-{i}".encode())
                sent.add((key, f"{user}-{i}".encode()))
        wait_for(lambda: len(cache_tokens(c["service"], keys.ALL_SENSORS)) == 2
                 and len(cache_tokens(c["service"], keys.ALL_COMMANDS)) == 1,
                 TIMEOUT_S, "the daemon to see the three caches' tokens")
        got = Recovered()
        c["service"].read_back(keys.ALL_SENSORS, got, max_samples=8, timeout=TIMEOUT_S)
        c["service"].read_back(keys.ALL_COMMANDS, got, max_samples=8, timeout=TIMEOUT_S)
        with got.cond:  # read before read_back returned, each cache in its order
            assert sorted(got.got) == sorted(sent)
            for key in {k for k, _ in sent}:
                assert [p for k, p in got.got if k == key] == sorted(
                    p for k, p in sent if k == key)
        late = c["robot-b"].publisher(keys.sensor_key("b", "late"), cache=8)
        late.put(b"robot-b-late")
        assert got.wait_for({(keys.sensor_key("b", "late"), b"robot-b-late")}, TIMEOUT_S)


def over_broad(router: Path, out: Path) -> Path:
    """``router`` with a WRONG cache rule for robot-a: every cache message, both ways, on
    every session's sensor caches and samples (what a rule not scoped by session would
    give).  The control that shows the negative test notices such a rule."""
    head, body = router.read_text(encoding="utf-8").split("\n{", 1)
    conf = json.loads("{" + body)
    acl = conf["access_control"]
    acl["rules"].append({
        "id": "too-broad", "permission": "allow", "flows": ["ingress", "egress"],
        "messages": ["declare_queryable", "liveliness_token", "reply", "query",
                     "declare_liveliness_subscriber", "liveliness_query"],
        "key_exprs": [f"{keys.ALL_SENSORS}/@adv/pub/**", keys.ALL_SENSORS]})
    next(p for p in acl["policies"] if p["id"] == "user-robot-a")["rules"].append("too-broad")
    out.write_text(json.dumps(conf), encoding="utf-8")
    return out


@pytest.mark.parametrize("variant", ["acl-on", "control-acl-off", "control-over-broad"])
def test_robot_cannot_read_or_fake_another_sessions_cache(generated, tmp_path: Path,
                                                           variant: str) -> None:
    """Robot A (a direct robot, whose own sensor cache the daemon reads) neither sees nor
    reads robot B's cache (liveliness, a query on the cache's own key, Transport.read_back),
    nor declares a cache on B's keys that the daemon would read back.  Controls: access
    control off, and robot A given an over-broad cache rule: the same sequence leaks."""
    router = over_broad(generated[0], tmp_path / "broad.json5") \
        if variant == "control-over-broad" else None
    leaks = variant != "acl-on"
    with system(generated, variant != "control-acl-off", "service", "robot-a", "robot-b",
                router=router) as c:
        theirs = c["robot-b"].publisher(keys.sensor_key("b", "camera"), cache=8)
        for i in range(3):
            theirs.put(f"b-{i}".encode())
        # a cache on B's key declared by robot A, then robot A's own: when the daemon sees
        # the second token, the router has handled the first declaration (same link, in order)
        fake = c["robot-a"].publisher(keys.sensor_key("b", "fake"), cache=8)
        fake.put(b"fake-0")
        mine = c["robot-a"].publisher(keys.sensor_key("a", "camera"), cache=8)
        mine.put(b"a-0")
        wait_for(lambda: {t.split("/@adv/")[0] for t in cache_tokens(c["service"],
                                                                      keys.ALL_SENSORS)}
                 >= {keys.sensor_key("a", "camera"), keys.sensor_key("b", "camera")},
                 TIMEOUT_S, "the daemon to see robot A's and robot B's caches")
        got = Recovered()
        c["service"].read_back(keys.ALL_SENSORS, got, max_samples=8, timeout=TIMEOUT_S)
        assert {b"a-0", b"b-0", b"b-1", b"b-2"} <= got.payloads()  # the rightful caches
        if leaks:
            assert got.wait_for({(keys.sensor_key("b", "fake"), b"fake-0")}, TIMEOUT_S)
        else:  # read at once: every cache the daemon could see was read before read_back returned
            assert b"fake-0" not in got.payloads()
            assert keys.sensor_key("b", "fake") not in {
                t.split("/@adv/")[0] for t in cache_tokens(c["service"], keys.ALL_SENSORS)}

        # robot A reads B's cache: its tokens, a query on the cache's own key, read_back (its
        # own cache on B's key, "fake", it sees and reads locally, without the router)
        token_b = next(t for t in cache_tokens(c["service"], keys.sensor_key("b", "camera")))
        seen = cache_tokens(c["robot-a"], keys.sensors_of("b"))
        replies = read_cache(c["robot-a"], token_b)
        stolen = Recovered()
        c["robot-a"].read_back(keys.sensors_of("b"), stolen, max_samples=8, timeout=NEGATIVE_WAIT_S)
        if leaks:
            assert token_b in seen
            assert [p for _, p in replies] == [b"b-0", b"b-1", b"b-2"]
            assert {b"b-0", b"b-1", b"b-2"} <= stolen.payloads()
        else:
            assert token_b not in seen
            assert replies == []
            assert stolen.payloads() & {b"b-0", b"b-1", b"b-2"} == set()
            # the same query by the daemon is answered: the cache is there
            assert [p for _, p in read_cache(c["service"], token_b)] == [b"b-0", b"b-1", b"b-2"]


def test_generator_refuses_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    make_acl = load_deploy_script("make_acl.py")
    bad = {
        "unknown field": 'services = ["s"]\nadmin = ["x"]\n[[session]]\nname = "a"\n',
        "wildcard session": 'services = ["s"]\n[[session]]\nname = "*"\n',
        "no service": '[[session]]\nname = "a"\n',
        "twice": 'services = ["s"]\n[[session]]\nname = "a"\n[[session]]\nname = "a"\n',
        "bad user": 'services = ["s"]\n[[session]]\nname = "a"\nrobot = "r/x"\n',
        "not a session name": 'services = ["s"]\n[[session]]\nname = "Paper"\n',
        "a name and a newline": 'services = ["s"]\n[[session]]\nname = "a\\n"\n',
        "one router": 'services = ["s"]\n[mesh]\nzids = ["a1"]\nuser = "r"\n'
                      'password = "p"\n[[session]]\nname = "a"\n',
        "bad zid": 'services = ["s"]\n[mesh]\nzids = ["a1", "0b"]\nuser = "r"\n'
                   'password = "p"\n[[session]]\nname = "a"\n',
        "mesh without password": 'services = ["s"]\n[mesh]\nzids = ["a1", "b2"]\n'
                                 'user = "r"\n[[session]]\nname = "a"\n',
    }
    for what, text in bad.items():
        path = tmp_path / "s.toml"
        path.write_text(text, encoding="utf-8")
        assert make_acl.main([str(path)]) == 2, what
    ok = tmp_path / "ok.toml"
    ok.write_text(SESSIONS_TOML, encoding="utf-8")
    for bad_p in ("0", "4097", "x"):
        assert make_acl.main([str(ok), "--partitions", bad_p]) == 2, bad_p
        monkeypatch.setenv("PD_PARTITIONS", bad_p)
        assert make_acl.main([str(ok)]) == 2, bad_p
    monkeypatch.delenv("PD_PARTITIONS")
    capsys.readouterr()
    assert make_acl.main([str(ok), "--partitions", "7"]) == 0
    seven = capsys.readouterr().out
    assert "PD_PARTITIONS=7" in seven
    assert f'"pd/p{keys.partition_of("a", 7)}/a/cmd"' in seven
    assert make_acl.main([str(ok)]) == 0
    text = capsys.readouterr().out
    out = tmp_path / "router.json5"
    out.write_text(text, encoding="utf-8")
    assert make_acl.main([str(ok), "--check", str(out)]) == 0
    out.write_text(text.replace('"op-a"', '"op-b"'), encoding="utf-8")
    assert make_acl.main([str(ok), "--check", str(out)]) == 1
    body = json.loads("{" + text.split("\n{", 1)[1])  # after the comment header
    assert body["access_control"]["default_permission"] == "deny"
