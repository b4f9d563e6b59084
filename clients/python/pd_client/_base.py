"""Shared plumbing of the SDK classes: transport ownership, handles, message building."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Self, TypeVar

import numpy as np
from pydantic import ValidationError

from pd_service.transport import (
    TOOL,
    Handle,
    Publisher,
    Sample,
    Transport,
    ZenohOptions,
    ZenohTransport,
)
from pd_service.transport.options import Mode, error_text
from pd_service.wire import Message, SessionSpec, WireError, decode, keys
from pd_service.wire.codec import validation_reason

from .errors import InvalidMessage, ServiceUnavailable

log = logging.getLogger("pd_client")

M = TypeVar("M", bound=Message)


def connect(
    endpoint: str | Sequence[str] | None = None,
    mode: Mode | None = None,
    *,
    listen: Sequence[str] = (),
    config_file: str | Path | None = None,
    user: str | None = None,
    password: str | None = None,
) -> Transport:
    """Open a Zenoh transport to a pd-service deployment.

    ``endpoint``: where to connect (a Zenoh locator such as ``"tcp/127.0.0.1:7447"``, or a
    list). ``mode``: ``"client"`` (talk through a router or the daemon's peer), ``"peer"`` or
    ``"router"``. Without ``config_file``, what is not given takes the TOOL role's default
    (client mode, connect to ``tcp/127.0.0.1:7447``, multicast scouting off), as for the
    command-line tools; with ``config_file`` (a Zenoh JSON5 file, read first) the file
    decides what the arguments do not say. Raises :class:`ServiceUnavailable` when Zenoh
    cannot open the session (in client mode: nothing listens at ``endpoint``).

    Every session key carries the session's partition (key layout 2, docs/protocol.md §3),
    computed with the partition count P of the environment variable ``PD_PARTITIONS``
    (default 64), read once when ``pd_service.wire.keys`` is imported: it must be the same
    as the deployment's, or this client's keys reach nobody (a spec put is refused).
    """
    if isinstance(endpoint, str):
        endpoints: tuple[str, ...] = (endpoint,) if endpoint else ()
    else:
        endpoints = tuple(endpoint or ())
    return connect_options(ZenohOptions(
        mode=mode, listen=tuple(listen), connect=endpoints,
        config_file=Path(config_file) if config_file else None, user=user, password=password))


def connect_options(options: ZenohOptions) -> Transport:
    """Open a Zenoh transport from the Zenoh option group's :class:`ZenohOptions` (what is
    not given takes the TOOL role's defaults); raises :class:`ServiceUnavailable`."""
    resolved = options.resolved(TOOL)
    try:
        return ZenohTransport(options.config(TOOL))
    except Exception as exc:  # zenoh.ZError and friends
        where = ", ".join(resolved.connect) or "(no endpoint)"
        kind = resolved.mode or "configured"
        raise ServiceUnavailable(f"cannot open a Zenoh {kind} session to {where}: "
                                 f"{error_text(exc)}") from exc


def build(msg_type: type[M], **fields: Any) -> M:
    """Construct a wire message, turning pydantic's ValidationError into InvalidMessage."""
    try:
        return msg_type(**fields)
    except ValidationError as exc:
        raise InvalidMessage(validation_reason(msg_type.__name__, exc)) from None


def session_name(session: str, spec: SessionSpec | None = None) -> str:
    """``session``, checked as a name (one key chunk) and, with ``spec``, as the spec's
    session; InvalidMessage otherwise."""
    try:
        name = keys.check_name(session, "session")
    except keys.KeyError_ as exc:
        raise InvalidMessage(str(exc)) from None
    if spec is not None and spec.session != session:
        raise InvalidMessage(f"spec is for session {spec.session!r}, not {session!r}")
    return name


def as_array(value: object, what: str, ndim: int) -> np.ndarray:
    """A float64 array of ``ndim`` dimensions from a list / tuple / array / scalar."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidMessage(f"{what}: expected numbers, got {type(value).__name__}") from None
    if ndim == 1 and arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != ndim:
        raise InvalidMessage(f"{what}: expected a {ndim}-D array, got shape {list(arr.shape)}")
    return arr


def try_decode(sample: Sample, msg_type: type[M]) -> M | None:
    """Decode a sample; log and return None when it is not a valid ``msg_type``."""
    try:
        return decode(sample.payload, msg_type)
    except WireError as exc:
        log.warning("ignoring an invalid %s on %s: %s", msg_type.__name__, sample.key, exc.reason)
        return None


class ClientBase:
    """Owns the subscriptions of one SDK object; closes them (and, if owned, the transport).

    Use as a context manager. ``transport`` is shared: closing the client leaves it open
    unless the client was made by :meth:`connect` (which opens its own).
    """

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        self._handles: list[Handle] = []
        self._owns_transport = False
        self._closed = False
        self._lock = threading.Lock()

    @classmethod
    def connect(cls, *args: Any, endpoint: str | Sequence[str] | None = None,
                mode: Mode | None = None, **kwargs: Any) -> Self:
        """Open a Zenoh transport (see :func:`pd_client.connect`) owned by the new client.

        The other arguments are the class's own (e.g. ``Robot.connect("s1", endpoint=...)``).
        """
        transport = connect(endpoint, mode)
        try:
            obj = cls(transport, *args, **kwargs)
        except BaseException:
            transport.close()
            raise
        obj._owns_transport = True
        return obj

    def _sender(self, key: str, cache: int) -> Publisher:
        """This client's publisher for ``key`` (declared on first use, closed with the
        client); ``cache`` > 0: it keeps its last ``cache`` samples, which a restarted
        service reads back (``Transport.publisher``)."""
        pubs: dict[str, Publisher] = self.__dict__.setdefault("_pubs", {})
        pub = pubs.get(key)
        if pub is None:
            with self._lock:
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = self.transport.publisher(key, cache=cache)
                    self._handles.append(pub)
        return pub

    def _subscribe(self, keyexpr: str, callback: Callable[[Sample], None]) -> Handle:
        h = self.transport.subscribe(keyexpr, callback)
        self._handles.append(h)
        return h

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare this client's subscriptions (and close the transport if it owns it)."""
        if self._closed:
            return
        self._closed = True
        for h in reversed(self._handles):
            try:
                h.close()
            except Exception:  # pragma: no cover - closing twice is harmless
                pass
        self._handles.clear()
        if self._owns_transport:
            self.transport.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
