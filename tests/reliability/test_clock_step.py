"""Host clock steps on the daemon's side, faked through the injected clocks: the core's
StepClock reads a wall clock that steps (``HostClock.off``) and a monotonic one that does
not. The senders stamp with the true time (explicit steps). Every prediction must equal an
offline ObserverPredictor fed the same messages at the step the daemon is at (computed here
from the host clocks, not read from the daemon); refusals the step causes are counted as
``clock_step`` / ``commands_clock_step``."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation import ObserverPredictor
from pd_service.scenarios.paper import (
    paper_command,
    paper_model,
    paper_prior,
    paper_sensors,
    simulate_paper,
)
from pd_service.service import ServiceCore, Settings, SpecStore
from pd_service.service.step_clock import StepClock
from pd_service.transport import InMemoryBus
from pd_service.wire import ServiceStatus, decode, encode, keys
from tests.service.helpers import PERIOD_NS, Collector, cmd_bytes, meas_bytes, paper_spec

HOUR_NS = 3_600_000_000_000
EPOCH_NS = 10 * HOUR_NS  # the senders' epoch: far from 0 so that -1 h stays positive


class HostClock:
    """True time ``t`` (ns, what the senders' clocks read); the daemon host's wall clock
    reads ``t + off``; its monotonic clock never steps."""

    def __init__(self, t: int, off: int = 0) -> None:
        self.t, self.off = t, off

    def wall(self) -> int:
        return self.t + self.off

    def mono(self) -> int:
        return self.t + 123_456_789


class Mirror:
    """Feeds the paper run to a core and to an offline ObserverPredictor, the latter at the
    step the daemon's clock says (its wall clock, steps never going back)."""

    def __init__(self, tmp_path, host: HostClock, steps: int = 140) -> None:
        self.bus = InMemoryBus()
        self.col = Collector().attach(self.bus.transport())
        self.cli = self.bus.transport()
        self.host = host
        self.clock = StepClock(host.wall, host.mono)
        self.core = ServiceCore(self.bus.transport(), Settings(instance="a"),
                                store=SpecStore(tmp_path / "a"), now_ns=self.clock,
                                mono_ns=host.mono, run_clock_ns=lambda: 0,
                                spawn=lambda fn: fn())
        self.core.start()
        self.spec = paper_spec("s1", epoch_ns=EPOCH_NS)
        run = simulate_paper(steps, np.random.default_rng(5), loss=0.1)
        self.arrivals: dict[int, list] = {}
        for smp in run.samples:
            if smp.arrival is not None:
                self.arrivals.setdefault(smp.arrival, []).append((smp.sensor, smp.step, smp.z))
        x0, P0 = paper_prior()
        self.offline = ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0,
                                         lead=self.spec.lead, max_delay=self.spec.max_delay)
        self.k_daemon: int | None = None
        self.compared = 0
        self.seq = 0

    def set_true(self, step: float) -> None:
        self.host.t = EPOCH_NS + int(round(step * PERIOD_NS))

    def daemon_step(self) -> int:
        # the step clock's reading (tests/service/test_step_clock.py checks it against the
        # host clocks: the wall clock's, or caught up at half speed after a small step back)
        k = (self.clock() - EPOCH_NS) // PERIOD_NS
        self.k_daemon = k if self.k_daemon is None else max(self.k_daemon, k)
        return self.k_daemon

    def configure(self) -> None:
        self.set_true(-0.5)
        self.cli.put(keys.config_key("s1"), encode(self.spec))
        self.core.run_once()

    def step(self, k: int) -> None:
        s, lead = "s1", self.spec.lead
        self.set_true(k + 0.1)
        kd = self.daemon_step()
        u = paper_command(k + lead)
        self.cli.put(keys.command_key(s), cmd_bytes(s, k + lead, u, seq=k))
        self.offline.add_command(k + lead, np.array([u]), now=kd if kd >= 0 else None)
        for sensor, stamp, z in self.arrivals.get(k, []):
            self.seq += 1
            self.cli.put(keys.sensor_key(s, sensor), meas_bytes(s, sensor, stamp, z, self.seq))
            if kd >= 0:
                self.offline.add_measurement(sensor, stamp, z, now=kd)
        self._run()
        self.set_true(k + 0.6)
        self._run()

    def _run(self) -> None:
        before = len(self.col.predictions["s1"])
        self.core.run_once()
        kd = self.daemon_step()
        for p in self.col.predictions["s1"][before:]:
            exp = self.offline.predict(kd)
            assert p.step == exp.step == kd + self.spec.lead
            np.testing.assert_allclose(p.x, exp.x, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(p.P, exp.P, rtol=1e-9, atol=1e-12)
            self.compared += 1

    def service(self) -> ServiceStatus:
        return decode(self.cli.get(keys.service_status_key("a"))[0].payload, ServiceStatus)


@pytest.mark.parametrize("step_ns", [1_000_000_000, -1_000_000_000, HOUR_NS],
                         ids=["+1s", "-1s", "+1h"])
def test_a_wrong_host_clock_stepped_right(tmp_path, step_ns):
    """The daemon's host clock is off by -step and an NTP correction steps it by +step
    (+1 h: a dead RTC). Re-anchored once, counted; the sessions keep predicting, every
    prediction equals the offline mirror's, and one window after the step they predict at
    the senders' step again."""
    host = HostClock(0, off=-step_ns)
    m = Mirror(tmp_path, host)
    m.configure()
    for k in range(40):
        m.step(k)
    host.off = 0  # the step
    before = len(m.col.predictions["s1"])
    end = 80 + m.spec.max_delay  # the catch-up (2 s for a second back), then one window
    for k in range(40, end):
        m.step(k)
    # one prediction per step; a backward step of a second: one per step of the step clock,
    # caught up at half speed for 2 s (40 steps of the senders, 20 of its own)
    slow = 20 if step_ns < 0 else 0
    assert len(m.col.predictions["s1"]) - before >= end - 40 - slow - 1
    assert m.col.predictions["s1"][-1].step == end - 1 + m.spec.lead  # the senders' step
    st = m.service()
    assert st.counters["clock_steps"] == 1
    assert st.clock_stepped_ns == step_ns
    assert m.compared >= end - 40 - slow - 1  # each compared with the mirror


def test_a_host_clock_step_away_from_the_senders(tmp_path):
    """A host clock stepped 1 s back while the senders' stay: the step clock catches it up
    at half speed, the sessions keep predicting (never going back); what the step makes
    look late or new is counted as ``clock_step``, not ``late``/``future``; a forward step
    of an hour: the sessions leap to it (the prediction over an hour without data is one
    long jump) and keep predicting."""
    host = HostClock(0)
    m = Mirror(tmp_path, host)
    m.configure()
    for k in range(40):
        m.step(k)
    c0 = dict(m.service().counters)
    host.off = -1_000_000_000
    n_back = len(m.col.predictions["s1"])
    for k in range(40, 80):
        m.step(k)
    c1 = m.service().counters
    assert c1["clock_steps"] == 1
    assert len(m.col.predictions["s1"]) - n_back >= 20 - 1  # predicting at half speed, then at full
    assert c1.get("clock_step", 0) + c1.get("commands_clock_step", 0) > 0
    for reason in ("late", "future", "commands_late", "commands_future"):
        assert c1.get(reason, 0) == c0.get(reason, 0), reason
    assert m.col.predictions["s1"][-1].step == m.k_daemon + m.spec.lead
    host.off += HOUR_NS
    n = len(m.col.predictions["s1"])
    for k in range(80, 90):
        m.step(k)
    assert len(m.col.predictions["s1"]) - n >= 10
    assert m.col.predictions["s1"][-1].step == m.k_daemon + m.spec.lead
    assert m.service().counters["clock_steps"] == 2
