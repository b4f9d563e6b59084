"""Fixtures of the client tests: an in-memory bus and the paper scenario's session spec."""

from __future__ import annotations

from collections import defaultdict

import pytest

from pd_service.scenarios import get_scenario
from pd_service.transport import InMemoryBus
from pd_service.wire import SessionSpec, keys

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


class MemLink:
    """In-memory link emulator: robot/p<k>/<s>/sensor/<n> -> pd/p<k>/<s>/sensor/<n> after the
    sensor's nominal delay, pd/p<k>/<s>/cmd -> robot/p<k>/<s>/cmd after ``uplink`` steps (test
    clock ``now``)."""

    def __init__(self, bus, delays: dict[str, int], uplink: int) -> None:
        self.t = bus.transport()
        self.now = 0
        self.delays, self.uplink = delays, uplink
        self.queue: dict[int, list[tuple[str, bytes]]] = defaultdict(list)
        self.t.subscribe(keys.ROBOT_ALL_SENSORS, self._down)
        self.t.subscribe(keys.ALL_COMMANDS, self._up)

    def _down(self, s):
        p = keys.parse_key(s.key)
        self.queue[self.now + self.delays[p.sensor]].append((keys.to_operator_side(s.key),
                                                             s.payload))

    def _up(self, s):
        self.queue[self.now + self.uplink].append((keys.to_robot_side(s.key), s.payload))

    def release(self, k: int) -> None:
        for key, payload in self.queue.pop(k, []):
            self.t.put(key, payload)
