"""Admin side: open, replace and close sessions; read status; wait for the service.

Example::

    with Admin(transport) as admin:
        admin.wait_for_service(timeout=10)       # liveliness of a pd-service instance
        admin.open_session(spec)                 # put SessionSpec; waits for the service's ack
        print(admin.status("s1").counters)
        admin.close_session("s1")                # delete the config
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from pd_service.transport import Handle, Query, Sample, Transport
from pd_service.wire import (
    CONFIG_RATE_LIMITED,
    ErrorReport,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
    WireError,
    decode,
    encode,
    keys,
)

from ._base import ClientBase, session_name, try_decode
from .errors import (
    AccessDenied,
    InvalidMessage,
    PdClientError,
    ServiceUnavailable,
    SessionExists,
    SessionNotFound,
    SessionRefused,
    Timeout,
)

log = logging.getLogger("pd_client.admin")

_POLL_S = 0.25
#: First and longest pause before a change the service's rate limits refused is sent again (s).
_RETRY_FIRST_S, _RETRY_MAX_S = 0.05, 1.0
#: A spec put with no answer for this long is put again (s): the answer can be lost on its
#: way (a router drops it toward a congested client); a spec put twice is answered again
#: ("unchanged (same spec)").
_RESEND_SILENT_S = 2.0


def _instance_of(token_key: str) -> str:
    return token_key.rsplit("/", 1)[-1]


def _error_text(payload: bytes) -> str:
    """The reason in an error reply: an encoded ErrorReport (as pd-service sends) or text."""
    try:
        return decode(payload, ErrorReport).reason
    except WireError:
        return payload.decode("utf-8", "replace")[:200]


class _Ack:
    """Waits for the service's reaction to a config put/delete on one session."""

    def __init__(self, admin: Admin, session: str, states: set[str]) -> None:
        self.session, self.states = session, states
        self.event = threading.Event()
        self.status: SessionStatus | None = None
        self.refused: str | None = None
        self._handles: list[Handle] = [
            admin.transport.subscribe(keys.status_key(session), self._on_status),
            admin.transport.subscribe(keys.error_key(session), self._on_error),
        ]

    def _on_status(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        st = try_decode(sample, SessionStatus)
        if st is not None and st.session == self.session and st.state in self.states:
            self.status = st
            self.event.set()

    def _on_error(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        rep = try_decode(sample, ErrorReport)
        if rep is not None and rep.key == keys.config_key(self.session):
            self.refused = rep.reason
            self.event.set()

    def rate_limited(self) -> bool:
        """The service refused the change by its rate limits (not judged: send it again)."""
        return self.refused is not None and self.refused.startswith(CONFIG_RATE_LIMITED)

    def rearm(self) -> None:
        self.refused, self.status = None, None
        self.event.clear()

    def close(self) -> None:
        for h in self._handles:
            h.close()


class Admin(ClientBase):
    """Manages sessions of a pd-service deployment.

    A session is created by putting its SessionSpec on ``pd/p<k>/<session>/config`` and removed by
    deleting that key. The service acknowledges each change by putting a SessionStatus on
    ``pd/p<k>/<session>/status`` (or an ErrorReport on ``pd/p<k>/<session>/error`` naming the config
    key when it refuses the spec); with ``wait=True`` the methods below wait for that.

    ``serve_spec=True`` (default) also answers queries on ``pd/p<k>/<session>/config`` with the
    spec while this Admin is open, so that other clients (a robot, an operator) can learn
    the session's clock and model: :meth:`get_spec`, :meth:`wait_for_spec`.
    """

    def __init__(self, transport: Transport) -> None:
        super().__init__(transport)
        self._served: dict[str, tuple[SessionSpec, Handle]] = {}

    # --- sessions ------------------------------------------------------------------------

    def open_session(self, spec: SessionSpec, *, wait: bool = True, timeout: float = 5.0,
                     exist_ok: bool = False, serve_spec: bool = True) -> SessionStatus | None:
        """Create the session ``spec.session``.

        Raises SessionExists if the service already runs it (unless ``exist_ok``: then it is
        replaced), SessionRefused if the service refuses the spec, Timeout if no
        acknowledgement arrives within ``timeout`` seconds (``wait=True``). Returns the
        acknowledging SessionStatus (None when not waiting).
        """
        if not isinstance(spec, SessionSpec):
            raise InvalidMessage(f"expected a SessionSpec, got {type(spec).__name__}")
        if not exist_ok:
            try:
                st = self.status(spec.session, timeout=min(1.0, timeout))
            except (SessionNotFound, ServiceUnavailable):
                st = None
            if st is not None and st.state in ("active", "restored"):
                raise SessionExists(f"session {spec.session!r} already exists "
                                    f"(instance {st.instance}); use replace_session")
        return self._put(spec, wait, timeout, serve_spec, poll=not exist_ok)

    def replace_session(self, spec: SessionSpec, *, wait: bool = True, timeout: float = 5.0,
                        serve_spec: bool = True) -> SessionStatus | None:
        """Create or replace the session ``spec.session`` (the service restarts its
        estimator from the new spec). Same errors as :meth:`open_session`."""
        return self._put(spec, wait, timeout, serve_spec, poll=False)

    def _put(self, spec: SessionSpec, wait: bool, timeout: float, serve_spec: bool,
             poll: bool) -> SessionStatus | None:
        if not isinstance(spec, SessionSpec):
            raise InvalidMessage(f"expected a SessionSpec, got {type(spec).__name__}")
        try:
            payload = encode(spec)
        except WireError as exc:
            raise InvalidMessage(exc.reason) from None
        if serve_spec:
            self._serve(spec)
        ack = _Ack(self, spec.session, {"active", "restored"}) if wait else None
        key = keys.config_key(spec.session)
        try:
            self.transport.put(key, payload)
            if ack is None:
                return None

            def appeared() -> SessionStatus | None:  # a new session's status is an answer too
                st = self._get_status(spec.session, timeout=_POLL_S)
                return st if st is not None and st.state in ("active", "restored") else None

            st = self._answer(ack, lambda: self.transport.put(key, payload), timeout,
                              f"no acknowledgement for session {spec.session!r}",
                              appeared if poll else None, resend_silent=True)
            if ack.refused is not None:
                self._unserve(spec.session)
                raise SessionRefused(spec.session, ack.refused)
            return st
        finally:
            if ack is not None:
                ack.close()

    def close_session(self, session: str, *, wait: bool = True,
                      timeout: float = 5.0) -> SessionStatus | None:
        """Remove ``session`` (delete its config key). With ``wait``, wait for the service's
        "removed" status; raises Timeout if it does not come."""
        session = self._check(session)
        self._unserve(session)
        ack = _Ack(self, session, {"removed"}) if wait else None
        key = keys.config_key(session)
        try:
            self.transport.delete(key)
            if ack is None:
                return None
            st = self._answer(ack, lambda: self.transport.delete(key), timeout,
                              f"no acknowledgement of the removal of session {session!r}")
            if ack.refused is not None:
                raise SessionRefused(session, ack.refused)
            return st
        finally:
            if ack is not None:
                ack.close()

    def _answer(self, ack: _Ack, send: Callable[[], None], timeout: float, what: str,
                poll: Callable[[], SessionStatus | None] | None = None,
                resend_silent: bool = False) -> SessionStatus | None:
        """Wait up to ``timeout`` s for the service's answer to the config change ``send``
        made (``ack``; ``poll``, if given, may find it too): the acknowledging status, or
        None when refused (``ack.refused``). A change the config rate limits refused is
        sent again after a growing pause; with ``resend_silent`` (an idempotent change) also
        one unanswered for ``_RESEND_SILENT_S``. Raises AccessDenied or Timeout without
        answer."""
        deadline = time.monotonic() + timeout
        pause = _RETRY_FIRST_S
        sent = time.monotonic()
        while True:
            while not ack.event.wait(min(_POLL_S, max(0.0, deadline - time.monotonic()))):
                st = poll() if poll is not None else None
                if st is not None:
                    return st
                now = time.monotonic()
                if now >= deadline:
                    raise self._silent(ack.session, f"{what} within {timeout} s")
                if resend_silent and now - sent >= _RESEND_SILENT_S:
                    sent = now
                    send()
            if not (ack.rate_limited() and time.monotonic() + pause < deadline):
                return ack.status
            # refused unread by the service's config rate: send it again, a bit later
            time.sleep(pause)
            pause = min(2 * pause, _RETRY_MAX_S)
            ack.rearm()
            sent = time.monotonic()
            send()

    def _silent(self, session: str, what: str) -> PdClientError:
        """The error for a config change nobody answered: AccessDenied when a service
        subscribes to the session's config key (so the router dropped this client's change,
        or the answer to it: its access control), else Timeout."""
        config = keys.config_key(session)
        if self.transport.subscribed(config, timeout=1.0):
            return AccessDenied(f"{what}: a pd-service instance subscribes to {config} but "
                                "nothing came back: the router's access control refuses "
                                "this user's change of that session (only admins, or a "
                                "robot_creates robot, may: deploy/README.md), or hides the "
                                "service's answer from it")
        return Timeout(f"{what}: no pd-service instance listens on {config}: is pd-service "
                       "running and connected?")

    # --- status --------------------------------------------------------------------------

    def _get_status(self, session: str, timeout: float) -> SessionStatus | None:
        for r in self.transport.get(keys.status_key(session), timeout=timeout):
            if r.ok:
                try:
                    return decode(r.payload, SessionStatus)
                except WireError as exc:
                    log.warning("invalid SessionStatus from %s: %s", r.key, exc.reason)
        return None

    def status(self, session: str, timeout: float = 2.0) -> SessionStatus:
        """The session's SessionStatus, from the service instance that runs it.

        Raises SessionNotFound if no instance reports it, ServiceUnavailable if no
        instance is alive at all.
        """
        session = self._check(session)
        replies = self.transport.get(keys.status_key(session), timeout=timeout)
        errors: list[str] = []
        for r in replies:
            if not r.ok:
                errors.append(_error_text(r.payload))
                continue
            try:
                return decode(r.payload, SessionStatus)
            except WireError as exc:
                errors.append(exc.reason)
        if not errors and not self.services(timeout=min(timeout, 1.0)):
            raise ServiceUnavailable("no pd-service instance is alive")
        why = f": {errors[0]}" if errors else ""
        raise SessionNotFound(f"no service instance reports session {session!r}{why}")

    def service_status(self, timeout: float = 2.0) -> list[ServiceStatus]:
        """ServiceStatus of every live instance that answers within ``timeout`` seconds."""
        out = []
        for r in self.transport.get(keys.all_service_status(), timeout=timeout):
            if r.ok:
                try:
                    out.append(decode(r.payload, ServiceStatus))
                except WireError as exc:
                    log.warning("invalid ServiceStatus from %s: %s", r.key, exc.reason)
        return out

    def services(self, timeout: float = 1.0) -> list[str]:
        """Instance ids of the live pd-service instances (from their liveliness tokens)."""
        return sorted(_instance_of(k) for k in self.transport.get_liveliness(
            keys.ALL_SERVICES, timeout=timeout))

    def wait_for_service(self, timeout: float = 10.0) -> list[str]:
        """Wait until at least one pd-service instance is alive; return the instance ids.
        Raises ServiceUnavailable after ``timeout`` seconds."""
        alive: set[str] = set()
        event = threading.Event()

        def on_token(key: str, is_alive: bool) -> None:
            (alive.add if is_alive else alive.discard)(_instance_of(key))
            if alive:
                event.set()

        h = self.transport.subscribe_liveliness(keys.ALL_SERVICES, on_token, history=True)
        try:
            if not event.wait(timeout):
                probe = keys.config_key("probe")
                if self.transport.subscribed(probe, timeout=1.0):
                    raise AccessDenied(
                        f"no pd-service instance is visible to this user within {timeout} s, "
                        f"but one subscribes to session configs ({probe}): the router's "
                        "access control hides the instances' liveliness tokens "
                        "(pd/@service/*) from this user (only admins, operators and "
                        "robot_creates robots may watch them: deploy/README.md)")
                raise ServiceUnavailable(f"no pd-service instance became alive within {timeout} s")
            return sorted(alive)
        finally:
            h.close()

    # --- specs ---------------------------------------------------------------------------

    def _unserve(self, session: str) -> None:
        served = self._served.pop(session, None)
        if served is not None:
            served[1].close()

    def _serve(self, spec: SessionSpec) -> None:
        self._unserve(spec.session)
        payload = encode(spec)

        def answer(query: Query) -> None:
            query.reply(keys.config_key(spec.session), payload)

        h = self.transport.queryable(keys.config_key(spec.session), answer)
        self._handles.append(h)
        self._served[spec.session] = (spec, h)

    def get_spec(self, session: str, timeout: float = 1.0) -> SessionSpec | None:
        """The session's SessionSpec from whoever answers ``pd/p<k>/<session>/config`` queries
        (an Admin serving it, or the service), or None."""
        session = self._check(session)
        for r in self.transport.get(keys.config_key(session), timeout=timeout):
            if r.ok:
                try:
                    spec = decode(r.payload, SessionSpec)
                except WireError as exc:
                    log.warning("invalid SessionSpec from %s: %s", r.key, exc.reason)
                    continue
                if spec.session == session:
                    return spec
        return None

    def wait_for_spec(self, session: str, timeout: float = 10.0) -> SessionSpec:
        """Wait until the session's spec is known: put on its config key, or answered to a
        query on it. Raises Timeout after ``timeout`` seconds."""
        session = self._check(session)
        found: list[SessionSpec] = []
        event = threading.Event()

        def on_config(sample: Sample) -> None:
            if sample.kind == "put":
                spec = try_decode(sample, SessionSpec)
                if spec is not None and spec.session == session:
                    found.append(spec)
                    event.set()

        h = self.transport.subscribe(keys.config_key(session), on_config)
        try:
            deadline = time.monotonic() + timeout
            while True:
                spec = self.get_spec(session, timeout=_POLL_S)
                if spec is not None:
                    return spec
                if event.wait(min(_POLL_S, max(0.0, deadline - time.monotonic()))):
                    return found[-1]
                if time.monotonic() >= deadline:
                    raise Timeout(f"the spec of session {session!r} was not published within "
                                  f"{timeout} s")
        finally:
            h.close()

    @staticmethod
    def _check(session: str) -> str:
        return session_name(session)
