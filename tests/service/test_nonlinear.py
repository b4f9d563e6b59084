"""The daemon serves the nonlinear model kinds next to linear sessions.

One ServiceCore on the in-memory bus with an injected clock serves three sessions at once:
the paper's linear example ("lin"), an unscented session on
the registered omni-robot model with MIT-rule adaptation ("u1") and an IMM session
tracking a turning target from three range-bearing stations ("i1"). Every
published prediction must equal the offline estimator built by the backend's own factory
and fed the same accepted packets; bad nonlinear specs are refused with a readable reason
and leave the others untouched.
"""

from __future__ import annotations

import math

import numpy as np

from pd_service.estimation.imm.factory import make_imm
from pd_service.estimation.nonlinear.factory import make_unscented
from pd_service.service import ServiceCore, Settings, SpecStore
from pd_service.transport import InMemoryBus
from pd_service.wire import SensorSpec, SessionSpec, decode, encode, keys
from pd_service.wire.messages import (
    AdaptSpec,
    ImmModelSpec,
    ModeSpec,
    SigmaSpec,
    UnscentedModelSpec,
)

from .helpers import PERIOD_NS, Clock, Collector, cmd_bytes, meas_bytes

T = PERIOD_NS / 1e9  # step, s
LEAD, MAX_DELAY = 8, 12

# --- unscented session: the omni robot (state x, y, theta, vx, vy, omega; pose sensor) ---
OMNI_PARAMS = {"period_s": T, "mass": 10, "Q": [1e-10, 1e-10, 1e-10, 4e-6, 4e-6, 2.5e-5]}
OMNI_ADAPT = {"method": "mit", "indices": [3, 4, 5], "window": 10, "eta": 0.1}
OMNI_SIGMA = {"alpha": 1.0, "beta": 2.0, "kappa": 0.0}
OMNI_R = 1e-6 * np.eye(3)
OMNI_P0 = np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3])

# --- IMM session: CV / CT modes, three range-bearing stations ---------------------------
MODES = [{"model": "imm_cv", "params": {"period_s": T, "sigma_accel": 0.003}},
         {"model": "imm_ct", "params": {"period_s": T, "sigma_accel": 0.0016,
                                        "sigma_turn_step": 0.00349}}]
TRANSITION = [[0.99, 0.01], [0.01, 0.99]]
STATIONS = [(9.5, -8.5), (25.1, 18.5), (-6.1, 18.5)]
SIGMA_RANGE, SIGMA_BEARING = 0.25, 0.0625  # squares and their roots are exact in float64
IMM_X0 = np.array([0.0, 0.3, 0.0, 0.0, 0.0])
IMM_P0 = np.diag([0.25, 0.0025, 0.25, 0.0025, math.radians(1.0) ** 2])


def omni_spec(session: str = "u1", **model) -> SessionSpec:
    m = dict(model="omni3", params=OMNI_PARAMS, adapt=AdaptSpec(**OMNI_ADAPT),
             sigma=SigmaSpec(**OMNI_SIGMA))
    m.update(model)
    x0 = m.pop("x0", np.zeros(6))
    return SessionSpec(
        session=session, period_ns=PERIOD_NS, epoch_ns=0, model=UnscentedModelSpec(**m),
        x0=x0, P0=OMNI_P0[: x0.shape[0], : x0.shape[0]],
        sensors=[SensorSpec(name="pose", kind="model", R=OMNI_R, delay=2, interval=1)],
        lead=LEAD, max_delay=MAX_DELAY)


def omni_offline():
    return make_unscented("omni3", OMNI_PARAMS, x0=np.zeros(6), P0=OMNI_P0, lead=LEAD,
                          max_delay=MAX_DELAY, command_hold="hold", adapt=OMNI_ADAPT,
                          sigma=OMNI_SIGMA, sensors=["pose"], sensor_R={"pose": OMNI_R})


def imm_spec(session: str = "i1", modes=MODES) -> SessionSpec:
    return SessionSpec(
        session=session, period_ns=PERIOD_NS, epoch_ns=0,
        model=ImmModelSpec(modes=[ModeSpec(**m) for m in modes],
                           transition=np.array(TRANSITION), variant="imm2"),
        x0=IMM_X0, P0=IMM_P0,
        sensors=[SensorSpec(name=f"st{i + 1}", kind="range_bearing", station=np.array(st),
                            R=np.diag([SIGMA_RANGE**2, SIGMA_BEARING**2]), delay=3, interval=1)
                 for i, st in enumerate(STATIONS)],
        lead=LEAD, max_delay=MAX_DELAY)


def imm_offline():
    sensors = [{"name": f"st{i + 1}", "kind": "range_bearing", "station": list(st),
                "sigma_range": SIGMA_RANGE, "sigma_bearing": SIGMA_BEARING}
               for i, st in enumerate(STATIONS)]
    return make_imm(MODES, TRANSITION, sensors, "imm2", x0=IMM_X0, P0=IMM_P0, lead=LEAD,
                    max_delay=MAX_DELAY)


def linear_spec() -> SessionSpec:
    from .helpers import paper_spec

    return paper_spec("lin", lead=LEAD, max_delay=MAX_DELAY)


def linear_offline():
    from pd_service.estimation import ObserverPredictor
    from pd_service.scenarios.paper import paper_model, paper_prior, paper_sensors

    x0, P0 = paper_prior()
    return ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0, lead=LEAD,
                             max_delay=MAX_DELAY)


# ---------------------------------------------------------------- synthetic packets ------

def _arrivals(rng, steps, samples_of, loss=0.1, max_late=4):
    """arrival step -> [(sensor, stamp, z)]: each sample delayed 0..max_late steps, lost with
    probability ``loss``; now and then a duplicate and an over-late copy (both refused)."""
    out: dict[int, list] = {}
    for s in range(steps):
        for sensor, z in samples_of(s):
            if rng.random() < loss:
                continue
            out.setdefault(s + int(rng.integers(0, max_late + 1)), []).append((sensor, s, z))
            if s % 23 == 5:
                out.setdefault(s + MAX_DELAY + 2, []).append((sensor, s, z))  # too late
                out.setdefault(s + max_late + 1, []).append((sensor, s, z))  # duplicate
    return out


def omni_samples(rng):
    def samples(s):
        t = s * T
        pose = np.array([0.4 * math.sin(0.5 * t), 0.3 * (1 - math.cos(0.5 * t)), 0.2 * t])
        return [("pose", pose + 1e-3 * rng.standard_normal(3))]
    return samples


def imm_samples(rng):
    def samples(s):
        t = s * T  # straight at 0.3 m/s for 2 s, then a left turn at 0.3 rad/s
        if t <= 2.0:
            xi, eta = 0.3 * t, 0.0
        else:
            a = 0.3 * (t - 2.0)
            xi, eta = 0.6 + math.sin(a), 1.0 - math.cos(a)
        out = []
        for i, (sx, sy) in enumerate(STATIONS):
            rng_, brg = math.hypot(xi - sx, eta - sy), math.atan2(eta - sy, xi - sx)
            rng_ += SIGMA_RANGE * rng.standard_normal()
            brg = (brg + SIGMA_BEARING * rng.standard_normal() + math.pi) % (2 * math.pi) - math.pi
            out.append((f"st{i + 1}", np.array([rng_, brg])))
        return out
    return samples


class Feed:
    """One session's packets, sent to the daemon and mirrored on an offline estimator."""

    def __init__(self, cli, col, spec, offline, arrivals, command=None, exact=True):
        self.cli, self.col, self.spec, self.offline = cli, col, spec, offline
        self.exact = exact
        self.s = spec.session
        self.arrivals = arrivals
        self.command = command
        self.seen = 0
        self.compared = 0
        self.seq = 0

    def put(self, k: int) -> None:
        s = self.s
        if self.command is not None:
            u = self.command(k + LEAD)
            self.cli.put(keys.command_key(s), cmd_bytes(s, k + LEAD, u, seq=k))
            assert self.offline.add_command(k + LEAD, u, now=k)
        for sensor, stamp, z in self.arrivals.get(k, []):
            self.seq += 1
            self.cli.put(keys.sensor_key(s, sensor), meas_bytes(s, sensor, stamp, z, self.seq))
            self.offline.add_measurement(sensor, stamp, z, now=k)

    def check(self, k: int) -> None:
        """Every prediction published since the last check (during step k) equals the
        offline estimator's predict(k): bit for bit (``exact``), else to rounding."""
        new = self.col.predictions[self.s][self.seen:]
        self.seen += len(new)
        for p in new:
            exp = self.offline.predict(k)
            assert p.step == exp.step == k + LEAD
            assert p.newest_step == exp.newest_step
            if self.exact:
                np.testing.assert_array_equal(p.x, exp.x)
                np.testing.assert_array_equal(p.P, exp.P)
            else:
                np.testing.assert_allclose(p.x, exp.x, rtol=1e-9, atol=1e-12)
                np.testing.assert_allclose(p.P, exp.P, rtol=1e-9, atol=1e-12)
            assert p.counters["accepted"] == self.offline.counters["accepted"]
            self.compared += 1


def at(step: float) -> int:
    return int(round(step * PERIOD_NS))


def make_core(bus, clock, path, **kw) -> ServiceCore:
    core = ServiceCore(bus.transport(), Settings(instance="a", **kw),
                       store=SpecStore(path), now_ns=clock, spawn=lambda fn: fn())
    core.start()
    return core


def test_nonlinear_sessions_next_to_a_linear_one(tmp_path):
    bus = InMemoryBus()
    clock = Clock(at(0) - 1)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    core = make_core(bus, clock, tmp_path / "a")
    steps = 60
    rng = np.random.default_rng(11)
    from pd_service.scenarios.paper import paper_command, simulate_paper

    run = simulate_paper(steps, np.random.default_rng(4), loss=0.1)
    lin_arrivals: dict[int, list] = {}
    for smp in run.samples:
        if smp.arrival is not None:
            lin_arrivals.setdefault(smp.arrival, []).append((smp.sensor, smp.step, smp.z))
    feeds = [
        Feed(cli, col, linear_spec(), linear_offline(), lin_arrivals,
             lambda j: np.array([paper_command(j)])),
        Feed(cli, col, omni_spec(), omni_offline(), _arrivals(rng, steps, omni_samples(rng)),
             lambda j: 0.2 * np.array([math.sin(0.1 * j), math.cos(0.1 * j), 0.1])),
        Feed(cli, col, imm_spec(), imm_offline(), _arrivals(rng, steps, imm_samples(rng))),
    ]
    for f in feeds:
        cli.put(keys.config_key(f.s), encode(f.spec))
    core.run_once()
    assert core.served_sessions() == ["i1", "lin", "u1"]
    assert {f.s: col.statuses[f.s][-1].detail for f in feeds} == \
        {"lin": "created", "u1": "created", "i1": "created"}
    assert {s: type(core._routes[s].sess.est).__name__ for s in ("lin", "u1", "i1")} == {
        "lin": "ObserverPredictor",
        "u1": "UnscentedObserverPredictor", "i1": "ImmObserverPredictor"}

    for k in range(steps):
        clock.t = at(k + 0.1)
        for f in feeds:
            f.put(k)
        if k == 20:  # bad nonlinear specs: refused, nothing else changes
            cli.put(keys.config_key("bad1"), encode(omni_spec("bad1", model="no-such-model")))
            cli.put(keys.config_key("bad2"), encode(omni_spec("bad2", adapt=None,
                                                              x0=np.zeros(5))))
            cli.put(keys.config_key("u1"), encode(imm_spec("u1", modes=[
                MODES[0], {"model": "imm_turn", "params": {}}])))  # a bad replacement
            cli.put(keys.command_key("i1"), cmd_bytes("i1", k + LEAD, 1.0))  # no inputs
        core.run_once()
        for f in feeds:
            f.check(k)
        clock.t = at(k + 0.6)
        core.run_once()
        for f in feeds:
            f.check(k)

    for f in feeds:
        assert f.compared >= steps, f.s  # at least one prediction per step, all compared
        counters = core.session_status(f.s).counters
        off = f.offline.counters
        for name in ("accepted", "late", "duplicate", "commands_accepted"):
            assert counters.get(name, 0) == off[name], (f.s, name)
        assert off["accepted"] > 20, f.s
        if f.s != "lin":  # the injected refusals were exercised
            assert off["accepted"] > 40 and off["late"] > 0 and off["duplicate"] > 0, f.s

    # the refusals: readable reasons, on the sessions' error keys
    assert core.served_sessions() == ["i1", "lin", "u1"]
    assert core.session_status("u1").counters["config_refused"] == 1
    # bad1 and bad2 (new sessions) and u1's bad replacement: each counted once service-wide
    assert core.service_status().counters["config_refused"] == 3
    [bad1] = col.errors["bad1"]
    assert bad1.reason.startswith("SessionSpec.model: refused by the estimator: model: unknown "
                                  "model 'no-such-model' (registered: ")
    [bad2] = col.errors["bad2"]
    assert bad2.reason == "SessionSpec.x0: refused by the estimator: x0: expected length 6, got 5"
    u1_errors = [e.reason for e in col.errors["u1"] if e.key == keys.config_key("u1")]
    assert len(u1_errors) == 1 and u1_errors[0].startswith(
        "SessionSpec.model: refused by the estimator: model: unknown model 'imm_turn' (registered: ")
    assert core._routes["u1"].sess.spec == omni_spec()  # the running session was kept
    i1_cmd = [e.reason for e in col.errors["i1"] if e.key == keys.command_key("i1")]
    assert i1_cmd == ["Command.u: session 'i1' takes no commands (its model has no inputs)"]
    assert core.session_status("i1").counters["commands_wrong_dims"] == 1

    # the specs were persisted: a restarted daemon serves the nonlinear sessions again
    bus2 = InMemoryBus()
    col2 = Collector().attach(bus2.transport())
    core2 = make_core(bus2, clock, tmp_path / "a", recover_samples=0)  # no sender caches
    assert core2.served_sessions() == ["i1", "lin", "u1"]
    assert core2._routes["i1"].sess.spec == imm_spec()
    clock.t = at(steps + 0.6)
    core2.run_once()
    for s in ("i1", "lin", "u1"):
        [p] = col2.predictions[s]
        assert p.step == steps + LEAD
    core.close()
    core2.close()


def test_nonlinear_spec_replaces_a_linear_session(tmp_path):
    """The same session name switches kinds: the estimator is rebuilt from the new spec."""
    bus = InMemoryBus()
    clock = Clock(at(0.1))
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    core = make_core(bus, clock, tmp_path / "a")
    spec = linear_spec().model_copy(update={"session": "s1"})
    cli.put(keys.config_key("s1"), encode(spec))
    core.run_once()
    cli.put(keys.config_key("s1"), encode(omni_spec("s1")))
    core.run_once()
    assert col.statuses["s1"][-1].detail.startswith("replaced")
    est = core._routes["s1"].sess.est
    assert type(est).__name__ == "UnscentedObserverPredictor"
    cli.put(keys.sensor_key("s1", "pose"), meas_bytes("s1", "pose", 0, [0.0, 0.0, 0.0]))
    cli.put(keys.sensor_key("s1", "camera"), meas_bytes("s1", "camera", 0, [0.0, 0.0]))
    core.run_once()
    assert col.predictions["s1"][-1].x.shape == (6,)
    assert col.errors["s1"][-1].reason.startswith("Measurement.sensor: unknown sensor 'camera'")
    assert decode(encode(core._routes["s1"].sess.spec), SessionSpec) == omni_spec("s1")
    core.close()


def test_a_nonlinear_spec_with_an_epoch_far_in_the_past_is_refused(tmp_path):
    """An unscented model would propagate its prior step by step from the epoch: an epoch
    more than MAX_PRIOR_STEPS steps ago is refused (counted, reported); a linear spec with
    the same epoch is served (its first prediction is one closed-form jump)."""
    from pd_service.backends import MAX_PRIOR_STEPS

    from .helpers import paper_spec
    bus = InMemoryBus()
    far = (MAX_PRIOR_STEPS + 10) * PERIOD_NS  # the clock; both specs' epoch is 0
    clock = Clock(far)
    col = Collector().attach(bus.transport())
    cli = bus.transport()
    core = ServiceCore(bus.transport(), Settings(instance="a"), store=SpecStore(tmp_path / "a"),
                       now_ns=clock, run_clock_ns=lambda: 0, spawn=lambda fn: fn())
    core.start()
    cli.put(keys.config_key("u1"), encode(omni_spec("u1")))
    cli.put(keys.config_key("p1"), encode(paper_spec("p1")))
    core.run_once()
    assert core._routes.get("u1") is None or core._routes["u1"].sess is None
    [err] = col.errors["u1"]
    assert err.reason.startswith("SessionSpec.epoch_ns:") and str(MAX_PRIOR_STEPS) in err.reason
    assert core.counters["epoch_too_old"] == 1 and core.counters["config_refused"] == 1
    clock.t += PERIOD_NS // 2
    core.run_once()
    assert col.predictions["p1"] and not col.predictions["u1"]
    assert core._routes["p1"].sess.est.long_jumps == 1
    clock.t = MAX_PRIOR_STEPS * PERIOD_NS  # an epoch just inside the bound: served
    cli.put(keys.config_key("u2"), encode(omni_spec("u2")))
    core.run_once()
    assert not col.errors["u2"] and core.counters["epoch_too_old"] == 1
