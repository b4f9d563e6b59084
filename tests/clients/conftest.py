"""Fixtures of the client tests: an in-memory bus and the paper scenario's session spec."""

from __future__ import annotations

import pytest

from pd_service.scenarios import get_scenario
from pd_service.transport import InMemoryBus
from pd_service.wire import SessionSpec

EPOCH_NS = 1_700_000_000_000_000_000


@pytest.fixture
def bus() -> InMemoryBus:
    return InMemoryBus()


@pytest.fixture
def spec() -> SessionSpec:
    return get_scenario("paper").spec("s1", EPOCH_NS)


class Collector:
    """Records every sample published on a key expression of the bus."""

    def __init__(self, bus: InMemoryBus, keyexpr: str) -> None:
        self.samples: list = []
        self.t = bus.transport()
        self.t.subscribe(keyexpr, self.samples.append)

    def payloads(self) -> list[bytes]:
        return [s.payload for s in self.samples]
