"""A minimal stand-in for the pd-service daemon, for the client tests only.

It speaks the same keys and messages as the daemon for what the clients need: configs
(create/replace/delete, acknowledged by a SessionStatus put), sensor and command streams fed
to :func:`pd_service.backends.build`, a Prediction per ``tick``, ErrorReports
for refused input, the status queryable and a liveliness token. It is NOT the daemon: no
state directory, no latency stats, no sharding.

In tests on the in-memory bus the test drives time: set ``now`` and call ``tick()``. Run as
a process (``python -m tests.clients.mini_daemon --listen tcp/127.0.0.1:PORT``) it ticks in
real time on each session's clock.
"""

from __future__ import annotations

import argparse
import signal
import threading
import time
from collections.abc import Callable

from pd_service.backends import build
from pd_service.transport import Query, Sample, Transport
from pd_service.wire import (
    Command,
    ErrorReport,
    Measurement,
    SessionSpec,
    SessionStatus,
    WireError,
    decode,
    encode,
    keys,
)
from pd_service.wire.convert import (
    check_command,
    check_measurement,
    command_step,
    measurement_step,
    prediction_from,
)


class _Session:
    def __init__(self, spec: SessionSpec) -> None:
        self.spec = spec
        built = build(spec)
        self.est = built.est
        self.nu = built.nu
        self.seq = 0
        self.last_now: int | None = None


class MiniDaemon:
    def __init__(self, transport: Transport, instance: str = "mini", realtime: bool = False):
        self.t = transport
        self.instance = instance
        self.realtime = realtime
        self.now: int = 0  # the test's clock (in-memory mode)
        self.sessions: dict[str, _Session] = {}
        self.lock = threading.RLock()
        self.errors: list[ErrorReport] = []
        self.handles = [
            transport.subscribe(keys.ALL_CONFIGS, self._on_config),
            transport.subscribe(keys.ALL_SENSORS, self._on_sensor),
            transport.subscribe(keys.ALL_COMMANDS, self._on_command),
            transport.queryable(keys.ALL_STATUS, self._on_status_query),
            transport.declare_token(keys.service_token_key(instance)),
        ]

    def _now(self, s: _Session) -> int:
        now = s.spec.step_of(time.time_ns()) if self.realtime else self.now
        if s.last_now is not None:
            now = max(now, s.last_now)
        s.last_now = now
        return max(now, 0)

    def _status(self, s: _Session, state: str) -> SessionStatus:
        return SessionStatus(session=s.spec.session, instance=self.instance, state=state,
                             now_step=s.last_now or 0, counters=s.est.counters,
                             published=s.seq, latency_p50_us=0.0, latency_p99_us=0.0)

    def _error(self, session: str, key: str, seq: int | None, reason: str) -> None:
        rep = ErrorReport(session=session, key=key, seq=seq, reason=reason, t_ns=time.time_ns())
        self.errors.append(rep)
        self.t.put(keys.error_key(session), encode(rep))

    def _on_config(self, sample: Sample) -> None:
        session = keys.parse_key(sample.key).session
        with self.lock:
            if sample.kind == "delete":
                s = self.sessions.pop(session, None)
                if s is not None:
                    self.t.put(keys.status_key(session), encode(self._status(s, "removed")))
                return
            try:
                spec = decode(sample.payload, SessionSpec)
                if spec.session != session:
                    raise WireError(f"SessionSpec.session: {spec.session!r} on key {sample.key}")
                s = _Session(spec)
            except WireError as exc:
                self._error(session, sample.key, None, exc.reason)
                return
            self.sessions[session] = s
            st = self._status(s, "active")
        self.t.put(keys.status_key(session), encode(st))

    def _on_sensor(self, sample: Sample) -> None:
        self._on_input(sample, self._add_measurement)

    def _on_command(self, sample: Sample) -> None:
        self._on_input(sample, self._add_command)

    def _on_input(self, sample: Sample, add: Callable[[_Session, bytes], None]) -> None:
        """``add(session, payload)`` for a served session; its errors become ErrorReports."""
        session = keys.parse_key(sample.key).session
        with self.lock:
            s = self.sessions.get(session)
            if s is None:
                return
            try:
                add(s, sample.payload)
            except (WireError, ValueError) as exc:
                self._error(session, sample.key, None, str(exc))

    def _add_measurement(self, s: _Session, payload: bytes) -> None:
        msg = decode(payload, Measurement)
        check_measurement(msg, s.spec)
        s.est.add_measurement(msg.sensor, measurement_step(msg, s.spec), msg.z,
                              now=self._now(s), R=msg.R)

    def _add_command(self, s: _Session, payload: bytes) -> None:
        msg = decode(payload, Command)
        check_command(msg, s.spec, s.nu)
        s.est.add_command(command_step(msg, s.spec), msg.u, now=self._now(s))

    def _on_status_query(self, query: Query) -> None:
        with self.lock:
            for name, s in self.sessions.items():
                key = keys.status_key(name)
                if query.key in (key, keys.ALL_STATUS):
                    query.reply(key, encode(self._status(s, "active")))

    def tick(self) -> None:
        """Publish one Prediction per session, for x(now + lead)."""
        with self.lock:
            out = []
            for name, s in self.sessions.items():
                now = self._now(s)
                pred = s.est.predict(now)
                msg = prediction_from(pred, s.spec, name, s.seq, time.time_ns(), s.est.counters)
                s.seq += 1
                out.append((keys.prediction_key(name), encode(msg)))
        for key, payload in out:
            self.t.put(key, payload)

    def run(self, stop: threading.Event) -> None:
        """Real-time mode: tick at the first session's period (or every 10 ms)."""
        while not stop.is_set():
            with self.lock:
                period = min((s.spec.period_ns for s in self.sessions.values()), default=10**7)
            self.tick()
            stop.wait(period / 1e9)

    def close(self) -> None:
        for h in reversed(self.handles):
            h.close()


def main() -> None:
    from pd_service.transport import ZenohTransport, zenoh_config

    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True)
    args = ap.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    signal.signal(signal.SIGINT, lambda *a: stop.set())
    with ZenohTransport(zenoh_config(mode="peer", listen=[args.listen])) as t:
        d = MiniDaemon(t, realtime=True)
        print("mini daemon ready", flush=True)
        d.run(stop)
        d.close()


if __name__ == "__main__":
    main()
