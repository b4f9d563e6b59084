"""deploy/zenoh/router.json5 on loopback: who may publish what, and who may log in at all.

A Python Zenoh session in router mode, opened with the deployment's router.json5 (listen
endpoint and users.txt path overridden), stands in for zenohd; every other process connects to
it as a client with its role's file deploy/zenoh/<role>.json5.

Synchronisation: events and bounded polling.  The only fixed wait is the bounded negative wait
(NEGATIVE_WAIT_S) after the authorised messages sent *after* the unauthorised ones have all
arrived.  Every negative check has a control run with access control off, in which the same
sequence does deliver the unauthorised messages.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from pd_service.transport import Sample, ZenohTransport, zenoh_config
from pd_service.wire import (
    Command,
    LinearModelSpec,
    Measurement,
    SensorSpec,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
    decode,
    encode,
    keys,
)

from ._support import (
    ZENOH_DIR,
    free_port,
    load_healthcheck,
    open_client,
    open_router,
    read_users,
    wait_for,
)

pytestmark = pytest.mark.integration

NEGATIVE_WAIT_S = 0.75
ROUNDS = 5
TIMEOUT_S = 10.0


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


class Collector:
    """Subscriber callback: keeps payloads, signals when one matching a prefix arrives."""

    def __init__(self) -> None:
        self.payloads: list[bytes] = []
        self.cond = threading.Condition()

    def __call__(self, sample: Sample) -> None:
        with self.cond:
            self.payloads.append(sample.payload)
            self.cond.notify_all()

    def count(self, prefix: bytes) -> int:
        with self.cond:
            return sum(1 for p in self.payloads if p.startswith(prefix))

    def wait_count(self, prefix: bytes, n: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(
                lambda: sum(1 for p in self.payloads if p.startswith(prefix)) >= n, timeout)


def publish_race(sub: Collector, key: str, allowed: ZenohTransport, other: ZenohTransport,
                 expect_other: bool) -> int:
    """``other`` publishes on ``key`` before ``allowed`` does, ROUNDS times; returns how many
    of ``other``'s messages reached ``sub``.

    Preconditions, both waited for: ``allowed`` publishes until ``sub`` has one message (the
    subscription is known along the whole path), and ``other``'s publisher reports a matching
    subscriber (so its puts do leave its process: a Zenoh client drops a put locally when it
    knows of no subscriber; only the router can stop them).  After the rounds, wait for all
    of ``allowed``'s messages; then, if ``other``'s are expected too, wait for them, else
    wait NEGATIVE_WAIT_S more for any straggler."""
    deadline = time.monotonic() + TIMEOUT_S
    while not sub.wait_count(b"sync", 1, 0.05):
        assert time.monotonic() < deadline, f"the authorised publisher never reached {key}"
        allowed.put(key, b"sync")
    publisher = other.session.declare_publisher(key)
    try:
        wait_for(lambda: publisher.matching_status.matching, TIMEOUT_S,
                 "the refused publisher to learn of the subscriber")
        for i in range(ROUNDS):
            publisher.put(b"other-%d" % i)
            allowed.put(key, b"allowed-%d" % i)
        assert sub.wait_count(b"allowed-", ROUNDS, TIMEOUT_S), "authorised messages were lost"
        if expect_other:
            assert sub.wait_count(b"other-", ROUNDS, TIMEOUT_S), "control run: other's lost"
        else:
            sub.wait_count(b"other-", 1, NEGATIVE_WAIT_S)
    finally:
        publisher.undeclare()
    return sub.count(b"other-")


CASES = {
    # name: (subscriber role, its key expression, key published, allowed role, refused role)
    "commands": ("service", keys.ALL_COMMANDS, keys.command_key("paper"), "operator", "robot"),
    "robot-data": ("link", keys.ROBOT_ALL_SENSORS, keys.robot_sensor_key("paper", "camera"),
                   "robot", "operator"),
    "truth": ("display", keys.ALL_TRUTHS, keys.truth_key("paper"), "robot", "link"),
    "predictions": ("display", keys.ALL_PREDICTIONS, keys.prediction_key("paper"), "service",
                    "operator"),
    "paths": ("display", keys.ALL_PATHS, keys.path_key("paper"), "service", "operator"),
    "robot-camera": ("link", keys.ROBOT_ALL_CAMERAS, keys.robot_camera_key("paper"), "robot",
                     "operator"),
    "camera": ("display", keys.ALL_CAMERAS, keys.camera_key("paper"), "link", "operator"),
    "robot-echo": ("link", "robot/*/*/echo", keys.robot_echo_key("paper"), "robot", "operator"),
    "echo": ("service", "pd/*/*/echo", keys.echo_key("paper"), "link", "operator"),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_only_the_authorised_user_publishes(endpoint: str, case: str, acl: bool) -> None:
    sub_role, sub_key, key, allowed_role, other_role = CASES[case]
    with open_router(endpoint, acl=acl), open_client(sub_role, endpoint) as sub_t, \
            open_client(allowed_role, endpoint) as allowed, \
            open_client(other_role, endpoint) as other:
        sub = Collector()
        sub_t.subscribe(sub_key, sub)
        leaked = publish_race(sub, key, allowed, other, expect_other=not acl)
    if acl:
        assert leaked == 0, f"{other_role}'s puts on {key} reached the {sub_role} subscriber"
    else:
        assert leaked == ROUNDS


@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_only_the_service_probes_the_robot_clock(endpoint: str, acl: bool) -> None:
    """Issue 43's clock probes: the robot answers on robot/<p>/<s>/clock, the daemon (service
    user) queries it; no other role's query reaches it, and no other role's queryable on
    that key is asked in the robot's place (control: ACL off, both happen). Each query
    carries its sender's name; each queryable records what reached it (a get of one key
    consolidates its replies to one, so replies alone cannot tell who was asked)."""
    key = keys.robot_clock_key("paper")
    others = ("operator", "link", "display")
    with open_router(endpoint, acl=acl), contextlib.ExitStack() as stack:
        robot = stack.enter_context(open_client("robot", endpoint))
        service = stack.enter_context(open_client("service", endpoint))
        c = {role: stack.enter_context(open_client(role, endpoint)) for role in others}
        asked: list[bytes | None] = []
        forged: list[bytes | None] = []
        robot.queryable(key, lambda q: (asked.append(q.payload), q.reply(key, b"robot")))

        def probe(t: ZenohTransport, who: bytes) -> list[bytes]:
            return [r.payload for r in t.get(key, payload=who, timeout=1.0) if r.ok]
        assert wait_for(lambda: probe(service, b"service"), TIMEOUT_S,
                        "the robot's answer to the service's probe") == [b"robot"]
        # a forged clock: the link answers on the robot's key
        c["link"].queryable(key, lambda q: (forged.append(q.payload), q.reply(key, b"forged")))
        if acl:
            for _ in range(3):  # bounded negative wait: the forged queryable stays unasked
                assert probe(service, b"service") == [b"robot"]
            for role in others:
                probe(c[role], role.encode())
            assert set(asked) == {b"service"}, "another role's probe reached the robot"
            assert b"service" not in forged, "the service's probe reached a forged clock"
        else:
            wait_for(lambda: probe(service, b"service") and b"service" in forged, TIMEOUT_S,
                     "control run: the service's probe to reach the forged clock")
            for role in others:
                wait_for(lambda role=role: probe(c[role], role.encode())
                         and role.encode() in asked, TIMEOUT_S,
                         f"control run: {role}'s probe to reach the robot")


def test_authentication_refuses_bad_credentials(endpoint: str) -> None:
    users = read_users()
    with open_router(endpoint):
        # control: the right password connects with the same single attempt
        with open_client("operator", endpoint, connect_timeout_ms=0):
            pass
        bad = [("operator", users["operator"] + "x"), ("operator", users["robot"]),
               ("nobody", "DEMO-ONLY-insecure-nobody-password")]
        for user, password in bad:
            with pytest.raises(zenoh.ZError):
                open_client("operator", endpoint, user=user, password=password,
                            connect_timeout_ms=0).close()
        # no credentials at all
        conf = zenoh_config(mode="client", connect=[endpoint])
        conf.insert_json5("connect/timeout_ms", "0")
        with pytest.raises(zenoh.ZError):
            ZenohTransport(conf).close()


def test_deployment_traffic_passes_the_acl(endpoint: str) -> None:
    """What the deployment needs does get through: robot -> link -> service, operator ->
    link -> robot, service -> operator/display, status queries, liveliness, link stats."""
    with open_router(endpoint), contextlib.ExitStack() as stack:
        c = {role: stack.enter_context(open_client(role, endpoint))
             for role in ("operator", "robot", "service", "link", "display")}
        subs = {name: Collector() for name in
                ("link_robot_sensor", "service_sensor", "link_cmd", "robot_cmd",
                 "display_pred", "operator_pred", "display_truth", "operator_status")}
        c["link"].subscribe(keys.ROBOT_ALL_SENSORS, subs["link_robot_sensor"])
        c["service"].subscribe(keys.ALL_SENSORS, subs["service_sensor"])
        c["link"].subscribe(keys.ALL_COMMANDS, subs["link_cmd"])
        c["robot"].subscribe(keys.robot_command_key("paper"), subs["robot_cmd"])  # own session
        c["display"].subscribe(keys.ALL_PREDICTIONS, subs["display_pred"])
        c["operator"].subscribe(keys.prediction_key("paper"), subs["operator_pred"])
        c["display"].subscribe(keys.ALL_TRUTHS, subs["display_truth"])
        c["operator"].subscribe(keys.status_key("paper"), subs["operator_status"])
        c["service"].queryable(keys.ALL_STATUS, lambda q: q.reply(q.key, b"status"))
        c["service"].queryable(keys.service_status_key("pd-a"),
                               lambda q: q.reply(keys.service_status_key("pd-a"), b"svc"))
        c["link"].queryable(keys.link_stats_key("paper"),
                            lambda q: q.reply(keys.link_stats_key("paper"), b"stats"))
        c["service"].declare_token(keys.service_token_key("pd-a"))

        flows = [  # (publisher, key, collector)
            ("robot", keys.robot_sensor_key("paper", "camera"), "link_robot_sensor"),
            ("link", keys.sensor_key("paper", "camera"), "service_sensor"),
            ("operator", keys.command_key("paper"), "link_cmd"),
            ("link", keys.robot_command_key("paper"), "robot_cmd"),
            ("service", keys.prediction_key("paper"), "display_pred"),
            ("service", keys.prediction_key("paper"), "operator_pred"),
            ("robot", keys.truth_key("paper"), "display_truth"),
            ("service", keys.status_key("paper"), "operator_status"),
        ]
        for role, key, name in flows:
            def delivered(role=role, key=key, name=name) -> bool:
                c[role].put(key, b"msg")
                return subs[name].wait_count(b"msg", 1, 0.05)
            wait_for(delivered, TIMEOUT_S, f"{role}'s put on {key} to reach {name}")

        for role in ("operator", "display"):
            for selector, want in ((keys.status_key("paper"), b"status"),
                                   (keys.all_service_status(), b"svc"),
                                   (keys.link_stats_key("paper"), b"stats")):
                got = wait_for(lambda role=role, selector=selector: [
                    r.payload for r in c[role].get(selector, timeout=1.0) if r.ok],
                    TIMEOUT_S, f"{role}'s query {selector}")
                assert got == [want]
            alive = wait_for(lambda role=role: c[role].get_liveliness(keys.ALL_SERVICES),
                             TIMEOUT_S, f"{role} to see the service's liveliness token")
            assert alive == [keys.service_token_key("pd-a")]
        # and the robot may not query the link emulator
        assert [r for r in c["robot"].get(keys.link_stats_key("paper"), timeout=0.5)
                if r.ok] == []


# --- the real daemon behind the router -------------------------------------------------

PERIOD_NS = 50_000_000


def small_spec(session: str, epoch_ns: int) -> SessionSpec:
    """x = [p, v], p measured by "ranger" every step with a 2-step delay; lead 2."""
    d = PERIOD_NS / 1e9
    return SessionSpec(
        session=session, period_ns=PERIOD_NS, epoch_ns=epoch_ns,
        model=LinearModelSpec(A=np.array([[1.0, d], [0.0, 1.0]]), B=np.array([[0.0], [d]]),
                              Q=np.diag([1e-6, 1e-4])),
        x0=np.zeros(2), P0=np.eye(2),
        sensors=[SensorSpec(name="ranger", H=np.array([[1.0, 0.0]]), R=np.array([[0.01]]),
                            delay=2, interval=1)],
        lead=2, max_delay=4,
    )


@pytest.fixture
def daemon(endpoint: str, tmp_path) -> Iterator[subprocess.Popen]:
    """The pd-service daemon as a separate process, a client of the router (service user)."""
    pytest.importorskip("pd_service.service.daemon")
    log = open(tmp_path / "daemon.log", "wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "pd_service.service",
         "--zenoh-config", str(ZENOH_DIR / "service.json5"), "--connect", endpoint,
         "--instance", "acl-test", "--state-dir", str(tmp_path / "state"),
         "--log-level", "WARNING"],
        stdout=log, stderr=subprocess.STDOUT)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()


def session_status(t: ZenohTransport, session: str) -> SessionStatus | None:
    for r in t.get(keys.status_key(session), timeout=1.0):
        if r.ok:
            return decode(r.payload, SessionStatus)
    return None


def service_status(t: ZenohTransport, instance: str) -> ServiceStatus | None:
    for r in t.get(keys.service_status_key(instance), timeout=1.0):
        if r.ok:
            return decode(r.payload, ServiceStatus)
    return None


def test_daemon_gets_commands_from_the_operator_only(endpoint: str, daemon, tmp_path) -> None:
    """The robot's command on pd/<s>/cmd never reaches the daemon (its counters, read from
    its status queryables, show neither an acceptance nor a refusal of it), the operator's
    does, and the robot's own measurement does (so the robot was connected and heard)."""
    session = "paper"  # deploy/sessions.toml's session
    with open_router(endpoint), open_client("operator", endpoint) as operator, \
            open_client("robot", endpoint) as robot, open_client("admin", endpoint) as admin:
        def daemon_alive() -> bool:
            if daemon.poll() is not None:
                raise AssertionError("the daemon exited:\n"
                                     + (tmp_path / "daemon.log").read_text(errors="replace"))
            return keys.service_token_key("acl-test") in operator.get_liveliness(
                keys.ALL_SERVICES, timeout=0.5)
        wait_for(daemon_alive, 30.0, "the daemon's liveliness token")

        admin.put(keys.config_key(session), encode(small_spec(session, time.time_ns())))
        st = wait_for(lambda: session_status(operator, session), TIMEOUT_S,
                      "the daemon to serve the session")
        assert st.state == "active"

        now = time.time_ns()
        robot.put(keys.sensor_key(session, "ranger"),
                  encode(Measurement(session=session, sensor="ranger", seq=1, t_ns=now,
                                     z=np.array([0.0]))))
        robot.put(keys.command_key(session),
                  encode(Command(session=session, seq=1, issued_ns=now, u=np.array([9.0]))))
        operator.put(keys.command_key(session),
                     encode(Command(session=session, seq=2, issued_ns=now + 3 * PERIOD_NS,
                                    u=np.array([0.5]))))

        def counters() -> dict[str, int]:
            s = session_status(operator, session)
            return dict(s.counters) if s is not None else {}
        wait_for(lambda: (c := counters()).get("commands_accepted", 0) >= 1
                 and c.get("accepted", 0) >= 1, TIMEOUT_S,
                 "the operator's command and the robot's measurement to be accepted")
        time.sleep(NEGATIVE_WAIT_S)  # bounded negative wait for the robot's command
        c = counters()
        assert c.get("commands_accepted") == 1, c
        assert c.get("refused", 0) == 0, c
        svc = wait_for(lambda: service_status(operator, "acl-test"), TIMEOUT_S,
                       "the daemon's service status")
        assert svc.counters.get("commands_accepted") == 1, svc.counters
        assert svc.counters.get("refused", 0) == 0, svc.counters

        # the containers' health check, against this router: healthy for the running
        # daemon, unhealthy for an instance nobody runs; robot login alone is healthy
        health = load_healthcheck()
        ok, why = health.check(str(ZENOH_DIR / "service.json5"),
                               keys.service_status_key("acl-test"), 5.0, [endpoint])
        assert ok, why
        ok, why = health.check(str(ZENOH_DIR / "service.json5"),
                               keys.service_status_key("nobody"), 0.5, [endpoint])
        assert not ok and "no good reply" in why
        ok, why = health.check(str(ZENOH_DIR / "robot.json5"), None, 5.0, [endpoint])
        assert ok, why
    assert daemon.poll() is None, "the daemon died"


REPLICA_KEY = "pd/@service/pd-b/replica/s1"
REPLICAS = "pd/@service/pd-b/replica/*"


@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_replicas_pass_between_service_instances_only(endpoint: str, acl: bool) -> None:
    """A session's state replica (pd/@service/<successor>/replica/<s>) goes from one service
    instance to another; no other role reads one or writes one (control: ACL off, they do)."""
    others = ("operator", "robot", "link", "display")
    with open_router(endpoint, acl=acl), contextlib.ExitStack() as stack:
        owner = stack.enter_context(open_client("service", endpoint))
        successor = stack.enter_context(open_client("service", endpoint))
        c = {role: stack.enter_context(open_client(role, endpoint)) for role in others}
        got = Collector()
        successor.subscribe(REPLICAS, got)
        spies = {role: Collector() for role in others}
        for role in others:
            c[role].subscribe(REPLICAS, spies[role])

        def delivered() -> bool:
            owner.put(REPLICA_KEY, b"sync")
            return got.wait_count(b"sync", 1, 0.05) and (
                acl or all(s.wait_count(b"sync", 1, 0.05) for s in spies.values()))
        wait_for(delivered, TIMEOUT_S, "the owner's replica to reach its successor")
        for i in range(ROUNDS):
            for role in others:
                c[role].put(REPLICA_KEY, b"forged-%s-%d" % (role.encode(), i))
            owner.put(REPLICA_KEY, b"replica-%d" % i)
        assert got.wait_count(b"replica-", ROUNDS, TIMEOUT_S), "replicas were lost"
        if acl:
            got.wait_count(b"forged-", 1, NEGATIVE_WAIT_S)
            assert got.count(b"forged-") == 0, "another role wrote a replica"
            # (a spy does see its own forged puts: a session delivers to itself locally)
            leaked = {r: s.count(b"replica-") + s.count(b"sync") for r, s in spies.items()}
            assert not any(leaked.values()), f"replicas read by other roles: {leaked}"
        else:
            assert got.wait_count(b"forged-", ROUNDS * len(others), TIMEOUT_S)
            assert all(s.wait_count(b"replica-", ROUNDS, TIMEOUT_S) for s in spies.values())
