"""Messaging adapters: Zenoh for real use, an in-memory bus for tests (same interface)."""

from .base import Handle, Query, Reply, Sample, Transport
from .memory import InMemoryBus, InMemoryTransport
from .zenoh_transport import DEFAULT_ENDPOINT, ZenohTransport, zenoh_config

__all__ = [
    "DEFAULT_ENDPOINT",
    "Handle",
    "InMemoryBus",
    "InMemoryTransport",
    "Query",
    "Reply",
    "Sample",
    "Transport",
    "ZenohTransport",
    "zenoh_config",
]
