"""Typed exceptions of the client SDK. Every error the SDK raises is a :class:`PdClientError`."""

from __future__ import annotations


class PdClientError(Exception):
    """Base class of every pd_client error."""


class InvalidMessage(PdClientError, ValueError):
    """A message the SDK refused to send or could not read (bad field, wrong dimension).

    ``reason`` is one readable line naming the field, as the wire layer words it.
    """

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class Timeout(PdClientError, TimeoutError):
    """Nothing (or not enough) arrived within the time allowed."""


class ServiceUnavailable(PdClientError):
    """No pd-service daemon (or no Zenoh router/peer) could be reached."""


class SessionRefused(PdClientError):
    """The service refused a session configuration; ``reason`` says why."""

    def __init__(self, session: str, reason: str) -> None:
        super().__init__(f"session {session!r} refused: {reason}")
        self.session = session
        self.reason = reason


class SessionExists(PdClientError):
    """The session runs already (:meth:`pd_client.Admin.open_session` without exist_ok)."""


class SessionNotFound(PdClientError):
    """The service does not know this session."""


class AccessDenied(PdClientError):
    """The router's access control refused this client's message (a Zenoh router drops it
    silently): the service listens on the key, but nothing this client sent reached it, or
    its answer could not reach this client."""
