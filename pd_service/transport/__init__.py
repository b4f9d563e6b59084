"""Messaging adapters: Zenoh for real use, an in-memory bus for tests (same interface)."""

from .base import (
    DEFAULT_SENDER_CACHE,
    DrainGroup,
    DrainMember,
    Handle,
    Publisher,
    Query,
    Reply,
    Sample,
    Transport,
)
from .memory import InMemoryBus, InMemoryTransport
from .options import (
    DAEMON,
    DEFAULT_ENDPOINT,
    LINK,
    TOOL,
    Role,
    ZenohOptions,
    add_zenoh_args,
    options_from_args,
    zenoh_config,
)
from .zenoh_transport import ZenohTransport

__all__ = [
    "DEFAULT_SENDER_CACHE",
    "DAEMON",
    "LINK",
    "TOOL",
    "Role",
    "ZenohOptions",
    "add_zenoh_args",
    "options_from_args",
    "DEFAULT_ENDPOINT",
    "DrainGroup",
    "DrainMember",
    "Handle",
    "InMemoryBus",
    "InMemoryTransport",
    "Publisher",
    "Query",
    "Reply",
    "Sample",
    "Transport",
    "ZenohTransport",
    "zenoh_config",
]
