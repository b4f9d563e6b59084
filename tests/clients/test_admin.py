"""Admin: sessions opened / replaced / closed with the service's acknowledgement, status,
liveliness, spec discovery. The service is the in-memory MiniDaemon (or a fake that refuses)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from pd_client import (
    AccessDenied,
    Admin,
    PdClientError,
    ServiceUnavailable,
    SessionNotFound,
    SessionRefused,
    Timeout,
)
from pd_service.wire import (
    CONFIG_RATE_LIMITED,
    ErrorReport,
    ServiceStatus,
    SessionStatus,
    encode,
    keys,
)

from .conftest import EPOCH_NS
from .mini_daemon import MiniDaemon


@pytest.fixture
def daemon(bus):
    d = MiniDaemon(bus.transport(), instance="inst-a")
    yield d
    d.close()


def test_wait_for_service_sees_liveliness(bus):
    with Admin(bus.transport()) as admin:
        with pytest.raises(ServiceUnavailable):
            admin.wait_for_service(timeout=0.01)
        assert admin.services() == []
        d = MiniDaemon(bus.transport(), instance="inst-a")
        assert admin.wait_for_service(timeout=1) == ["inst-a"]
        assert admin.services() == ["inst-a"]
        d.close()
        assert admin.services() == []


def test_wait_for_service_wakes_when_token_appears(bus):
    with Admin(bus.transport()) as admin:
        timer = threading.Timer(0.05, lambda: MiniDaemon(bus.transport(), instance="late"))
        timer.start()
        assert admin.wait_for_service(timeout=5) == ["late"]
        timer.join()


def test_open_status_replace_close(bus, daemon, spec):
    with Admin(bus.transport()) as admin:
        st = admin.open_session(spec, timeout=1)
        assert (st.session, st.state, st.instance) == ("s1", "active", "inst-a")
        assert "s1" in daemon.sessions
        assert admin.status("s1").state == "active"
        with pytest.raises(PdClientError, match="already exists"):
            admin.open_session(spec, timeout=1)
        spec2 = spec.model_copy(update={"lead": 5})
        assert admin.replace_session(spec2, timeout=1).state == "active"
        assert daemon.sessions["s1"].spec.lead == 5
        assert admin.close_session("s1", timeout=1).state == "removed"
        assert "s1" not in daemon.sessions
        with pytest.raises(SessionNotFound):
            admin.status("s1", timeout=0.1)


def test_open_without_service_times_out(bus, spec):
    with Admin(bus.transport()) as admin:
        with pytest.raises(Timeout, match="no acknowledgement"):
            admin.open_session(spec, timeout=0.05)
        assert admin.open_session(spec, wait=False) is None
        with pytest.raises(ServiceUnavailable):
            admin.status("s1", timeout=0.05)
        with pytest.raises(Timeout):
            admin.close_session("s1", timeout=0.05)


def test_refusal_is_reported(bus, spec):
    refuser = bus.transport()

    def refuse(sample):
        s = keys.parse_key(sample.key).session
        refuser.put(keys.error_key(s), encode(ErrorReport(
            session=s, key=sample.key, seq=None, reason="too many sessions", t_ns=0)))

    refuser.subscribe(keys.ALL_CONFIGS, refuse)
    with Admin(bus.transport()) as admin:
        with pytest.raises(SessionRefused, match="too many sessions") as exc:
            admin.open_session(spec, timeout=1)
        assert exc.value.session == "s1"
        assert admin.get_spec("s1") is None  # a refused spec is not served


def test_a_change_the_rate_limits_refused_is_sent_again(bus, spec):
    """The service refuses the first two puts by its config rate (reason
    ``config_rate_limited: ...``), then acknowledges: open_session and close_session
    succeed, having sent each change again."""
    svc = bus.transport()
    seen: list[str] = []

    def serve(sample):
        s = keys.parse_key(sample.key).session
        seen.append(sample.kind)
        if len(seen) in (1, 2, 4):
            svc.put(keys.error_key(s), encode(ErrorReport(
                session=s, key=sample.key, seq=None, t_ns=0,
                reason=f"{CONFIG_RATE_LIMITED}: config change refused: more than 20 per s")))
            return
        state = "active" if sample.kind == "put" else "removed"
        svc.put(keys.status_key(s), encode(SessionStatus(
            session=s, instance="i", state=state, now_step=0, published=0,
            latency_p50_us=0.0, latency_p99_us=0.0)))

    svc.subscribe(keys.ALL_CONFIGS, serve)
    with Admin(bus.transport()) as admin:
        assert admin.replace_session(spec, timeout=5).state == "active"
        assert admin.close_session("s1", timeout=5).state == "removed"
    assert seen == ["put", "put", "put", "delete", "delete"]


def test_a_spec_put_whose_answer_was_lost_is_put_again(bus, spec, monkeypatch):
    """The service's first answer never reaches the client (a router drops it toward a
    congested client): the spec is put again after a silence and the second answer counts;
    without it replace_session would fail though the session runs."""
    import pd_client.admin as admin_module
    monkeypatch.setattr(admin_module, "_RESEND_SILENT_S", 0.1, raising=False)
    svc = bus.transport()
    seen: list[str] = []

    def serve(sample):
        s = keys.parse_key(sample.key).session
        seen.append(sample.kind)
        if len(seen) == 1:
            return  # created, but the answer is lost
        svc.put(keys.status_key(s), encode(SessionStatus(
            session=s, instance="i", state="active", now_step=0, published=0,
            latency_p50_us=0.0, latency_p99_us=0.0, detail="unchanged (same spec)")))

    svc.subscribe(keys.ALL_CONFIGS, serve)
    with Admin(bus.transport()) as admin:
        assert admin.replace_session(spec, timeout=5).state == "active"
    assert seen == ["put", "put"]


def test_a_service_that_listens_but_never_answers_is_an_access_refusal(bus, spec):
    """Something subscribes to the config key (a service, seen through the router) but no
    answer comes back: what a router's access control does to a user it refuses."""
    bus.transport().subscribe(keys.ALL_CONFIGS, lambda sample: None)
    with Admin(bus.transport()) as admin:
        with pytest.raises(AccessDenied, match="access control"):
            admin.replace_session(spec, timeout=0.05)
        with pytest.raises(AccessDenied, match="access control"):
            admin.wait_for_service(timeout=0.05)


def test_spec_is_served_and_discovered(bus, daemon, spec):
    with Admin(bus.transport()) as owner, Admin(bus.transport()) as other:
        assert other.get_spec("s1") is None
        with pytest.raises(Timeout):
            other.wait_for_spec("s1", timeout=0.05)
        owner.open_session(spec, timeout=1)
        assert other.get_spec("s1") == spec
        assert other.wait_for_spec("s1", timeout=1) == spec
        owner.close_session("s1", timeout=1)
        assert other.get_spec("s1") is None


def test_wait_for_spec_catches_a_put(bus, spec):
    with Admin(bus.transport()) as admin:
        putter = bus.transport()
        timer = threading.Timer(0.05, lambda: putter.put(keys.config_key("s1"), encode(spec)))
        timer.start()
        assert admin.wait_for_spec("s1", timeout=5) == spec
        timer.join()


def test_service_status_and_bad_names(bus):
    svc = bus.transport()
    status = ServiceStatus(instance="inst-a", sessions=["s1"], latency_p50_us=1.0,
                           latency_p99_us=2.0, uptime_s=3.0)
    svc.queryable(keys.service_status_key("inst-a"),
                  lambda q: q.reply(keys.service_status_key("inst-a"), encode(status)))
    with Admin(bus.transport()) as admin:
        assert admin.service_status() == [status]
        with pytest.raises(ValueError):
            admin.status("Bad Session")
        with pytest.raises(ValueError):
            admin.open_session({"session": "s1"})  # type: ignore[arg-type]


def test_spec_round_trip_keeps_arrays(spec):
    assert spec.epoch_ns == EPOCH_NS and np.allclose(spec.model.A[0], [1, 0.05, 0, 0])


def test_status_error_reply_gives_the_reason(bus):
    svc = bus.transport()
    svc.declare_token(keys.service_token_key("inst-a"))
    svc.queryable(keys.ALL_STATUS, lambda q: q.reply_err(encode(ErrorReport(
        session="nosuch", key=q.key, seq=None, reason="unknown session 'nosuch'", t_ns=0))))
    with Admin(bus.transport()) as admin:
        with pytest.raises(SessionNotFound, match="unknown session 'nosuch'"):
            admin.status("nosuch")
