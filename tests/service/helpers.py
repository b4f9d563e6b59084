"""Shared helpers of the service tests: the paper's session spec, a settable clock, a
collector of everything the daemon publishes."""

from __future__ import annotations

import math
import threading
from collections import defaultdict
from dataclasses import dataclass, field

import msgpack
import numpy as np

from pd_service.scenarios.paper import RANGER_DELAY, UPLINK_DELAY, paper_scenario
from pd_service.wire import (
    Command,
    ErrorReport,
    Measurement,
    Prediction,
    SessionSpec,
    SessionStatus,
    decode,
    encode,
    keys,
)

PERIOD_NS = 50_000_000


def paper_spec(session: str, epoch_ns: int = 0, period_ns: int = PERIOD_NS, max_delay: int = 12,
               lead: int = UPLINK_DELAY, noise: str = "journal", publish_every: int = 1
               ) -> SessionSpec:
    """The paper scenario's SessionSpec (camera + ranger, x0 = 0, broad P0) on a clock of
    ``period_ns`` (the tests run it faster or slower than the model's 50 ms)."""
    if max_delay < RANGER_DELAY:
        raise ValueError(f"max_delay: the ranger's delay is {RANGER_DELAY} steps")
    spec = paper_scenario(noise).spec(session, epoch_ns, lead=lead, max_delay=max_delay,
                                      publish_every=publish_every)
    return spec.model_copy(update={"period_ns": period_ns})


def meas_bytes(session: str, sensor: str, step: int, z, seq: int = 0) -> bytes:
    return encode(Measurement(session=session, sensor=sensor, seq=seq, step=step,
                              z=np.atleast_1d(np.asarray(z, dtype=float))))


def cmd_bytes(session: str, step: int, u, seq: int = 0) -> bytes:
    return encode(Command(session=session, seq=seq, step=step,
                          u=np.atleast_1d(np.asarray(u, dtype=float))))


def cmd_now_bytes(session: str, issued_ns: int, u=(0.0,), seq: int = 0) -> bytes:
    """A Command stamped with the time it is issued (apply step now + lead): traffic that
    wakes an idle session."""
    return encode(Command(session=session, seq=seq, issued_ns=issued_ns,
                          u=np.atleast_1d(np.asarray(u, dtype=float))))


class Clock:
    """A settable wall clock (ns) for ServiceCore(now_ns=clock)."""

    def __init__(self, t_ns: int = 0) -> None:
        self.t = t_ns

    def __call__(self) -> int:
        return self.t


@dataclass
class Collector:
    """Subscribes to predictions, errors and statuses of every session; decodes them.
    Thread-safe; ``cond`` is notified on every message (for waiting on events)."""

    raw: dict[str, list[bytes]] = field(default_factory=lambda: defaultdict(list))
    predictions: dict[str, list[Prediction]] = field(default_factory=lambda: defaultdict(list))
    errors: dict[str, list[ErrorReport]] = field(default_factory=lambda: defaultdict(list))
    statuses: dict[str, list[SessionStatus]] = field(default_factory=lambda: defaultdict(list))
    order: list[tuple[str, str]] = field(default_factory=list)
    cond: threading.Condition = field(default_factory=threading.Condition)

    def attach(self, t) -> Collector:
        t.subscribe(keys.ALL_PREDICTIONS, self._on)
        t.subscribe(keys.ALL_ERRORS, self._on)
        t.subscribe(keys.ALL_STATUS, self._on)
        return self

    def _on(self, sample) -> None:
        p = keys.parse_key(sample.key)
        with self.cond:
            self.raw[p.session + "/" + p.kind].append(sample.payload)
            self.order.append((p.session, p.kind))
            if p.kind == "prediction":
                self.predictions[p.session].append(decode(sample.payload, Prediction))
            elif p.kind == "error":
                self.errors[p.session].append(decode(sample.payload, ErrorReport))
            elif p.kind == "status":
                self.statuses[p.session].append(decode(sample.payload, SessionStatus))
            self.cond.notify_all()

    def wait_for(self, pred, timeout: float = 10.0) -> bool:
        """Wait until ``pred(self)`` is true (evaluated under the lock at each message)."""
        with self.cond:
            return self.cond.wait_for(lambda: pred(self), timeout=timeout)


def storm(session: str, rng: np.random.Generator) -> list[tuple[str, bytes]]:
    """Every kind of bad input, on ``session``'s keys (and on unknown sessions)."""
    s = session
    good = msgpack.unpackb(meas_bytes(s, "ranger", 5, [1.0]))
    nan = dict(good, z={"shape": [1], "data": [math.nan]})
    inf_r = dict(good, R={"shape": [1, 1], "data": [math.inf]})
    out = [(keys.sensor_key(s, "ranger"), rng.bytes(int(n))) for n in rng.integers(0, 200, 40)]
    out += [
        (keys.sensor_key(s, "ranger"), msgpack.packb(nan)),
        (keys.sensor_key(s, "ranger"), msgpack.packb(inf_r)),
        (keys.sensor_key(s, "ranger"), b""),
        (keys.sensor_key(s, "ranger"), b"\xc1"),
        (keys.sensor_key(s, "ranger"), msgpack.packb([1, 2, 3])),
        (keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 5, [1.0, 2.0])),  # wrong dims
        (keys.sensor_key(s, "camera"), meas_bytes(s, "camera", 5, [1.0])),  # wrong dims
        (keys.sensor_key(s, "lidar"), meas_bytes(s, "lidar", 5, [1.0])),  # unknown sensor
        (keys.sensor_key(s, "ranger"), meas_bytes(s, "camera", 5, [1.0, 2.0])),  # key mismatch
        (keys.sensor_key(s, "ranger"), meas_bytes("other", "ranger", 5, [1.0])),
        (keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 2**62, [1.0])),  # far future
        (keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 0, [1.0])),  # far past
        (keys.command_key(s), rng.bytes(30)),
        (keys.command_key(s), cmd_bytes(s, 2**62, 0.5)),
        (keys.command_key(s), cmd_bytes(s, 0, 0.5)),
        (keys.command_key(s), cmd_bytes(s, 40, [0.5, 1.0])),
        (keys.command_key(s), msgpack.packb(dict(msgpack.unpackb(cmd_bytes(s, 40, 0.5)),
                                                 u={"shape": [1], "data": [math.nan]}))),
    ]
    return out
