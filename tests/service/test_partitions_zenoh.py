"""Key layout 2 over real Zenoh: two daemon processes, clients of a Python Zenoh router on
loopback, each receive the data samples of their own partitions only (the router delivers
each sample to the one instance subscribed to its partition)."""

from __future__ import annotations

import threading
import time

import pytest

from pd_service.transport import ZenohTransport, zenoh_config
from pd_service.wire import SessionStatus, encode, keys

from .helpers import Collector, meas_bytes, paper_spec
from .procs import Daemon, Presence, await_service_status, endpoint, free_port, query_session_status

pytestmark = pytest.mark.integration

PERIOD = 100_000_000


def router_and_pair(tmp_path):
    """A Python Zenoh router on loopback, a client of it (with a Collector and a Presence),
    inst-x started as its client and inst-y ready to start (each the other's peer)."""
    router_ep = endpoint(free_port())
    router = ZenohTransport(zenoh_config(mode="router", listen=[router_ep]))
    t = ZenohTransport(zenoh_config(mode="client", connect=[router_ep]))
    x = Daemon("inst-x", tmp_path / "inst-x", [router_ep],
               ["--mode", "client", "--peer", "inst-y"]).start()
    y = Daemon("inst-y", tmp_path / "inst-y", [router_ep],
               ["--mode", "client", "--peer", "inst-x"])
    return router, t, Collector().attach(t), Presence(t), x, y


def test_each_instance_receives_only_its_partitions_through_a_router(tmp_path):
    router, t, col, pres, x, y = router_and_pair(tmp_path)
    y.start()
    try:
        assert pres.wait("inst-x"), x.log()
        assert pres.wait("inst-y"), y.log()
        half = keys.partitions() // 2
        for inst, d in (("inst-x", x), ("inst-y", y)):
            st = await_service_status(t, inst, lambda s: s.owned_partitions == half)
            assert st is not None and st.owned_partitions == half, d.log()
        epoch = time.time_ns()
        names = [f"z{i:02d}" for i in range(24)]
        for s in names:
            t.put(keys.config_key(s), encode(paper_spec(s, epoch_ns=epoch, period_ns=PERIOD)))
        assert col.wait_for(lambda c: all(c.statuses[s] for s in names)), x.log() + y.log()
        step = (time.time_ns() - epoch) // PERIOD
        for s in names:
            t.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", step, [1.0]))
        got = {}
        for inst in ("inst-x", "inst-y"):
            got[inst] = await_service_status(
                t, inst, lambda st: st.counters.get("samples_received", 0) >= len(st.sessions)
                and st.counters.get("sessions_known", 0) == len(names))
        sx, sy = got["inst-x"], got["inst-y"]
        assert sx is not None and sy is not None
        assert set(sx.sessions).isdisjoint(sy.sessions) and \
            set(sx.sessions) | set(sy.sessions) == set(names)
        time.sleep(0.3)  # a sample delivered to the wrong instance would be counted by now
        for inst, st in got.items():
            again = await_service_status(t, inst, lambda _: True)
            assert again is not None
            # every sample of its own sessions, none of the others'
            assert again.counters["samples_received"] == len(st.sessions), (inst, again.counters)
            assert "unknown_session" not in again.counters
            mine = {keys.partition_of(s) for s in st.sessions}
            assert len(mine) <= again.owned_partitions == half
    finally:
        y.stop()
        x.stop()
        t.close()
        router.close()


def test_a_joining_instance_resumes_the_sessions_it_takes_from_their_state(tmp_path):
    """inst-x serves every session, fed each step; inst-y joins: the sessions that move to it
    continue from inst-x's state (origin "replica", "handed over by inst-x"), not the prior."""
    router, t, col, pres, x, y = router_and_pair(tmp_path)
    stop = threading.Event()
    try:
        assert pres.wait("inst-x"), x.log()
        epoch = time.time_ns()
        names = [f"j{i:02d}" for i in range(16)]
        for s in names:
            t.put(keys.config_key(s), encode(paper_spec(s, epoch_ns=epoch, period_ns=PERIOD)))
        assert col.wait_for(lambda c: all(c.statuses[s] for s in names)), x.log()

        def feed() -> None:  # every session's ranger, each step, until the end
            while not stop.is_set():
                step = (time.time_ns() - epoch) // PERIOD
                for s in names:
                    t.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", step, [1.0]))
                stop.wait(PERIOD / 1e9)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        assert col.wait_for(lambda c: all(c.predictions[s] for s in names)), x.log()
        y.start()
        assert pres.wait("inst-y"), y.log()
        half = keys.partitions() // 2
        st = await_service_status(t, "inst-y", lambda s: s.owned_partitions == half
                                  and len(s.sessions) > 0)
        assert st is not None and st.sessions, y.log()
        moved = list(st.sessions)
        deadline = time.monotonic() + 30.0
        got: dict[str, SessionStatus | None] = {}
        while time.monotonic() < deadline:
            got = {s: query_session_status(t, s) for s in moved}
            if all(g is not None and g.instance == "inst-y" for g in got.values()):
                break
            time.sleep(0.1)
        for s, g in got.items():
            assert g is not None and g.instance == "inst-y", (s, g, y.log())
            assert g.origin == "replica" and "handed over by inst-x" in g.detail, \
                (s, g, x.log() + y.log())
    finally:
        stop.set()
        y.stop()
        x.stop()
        t.close()
        router.close()
