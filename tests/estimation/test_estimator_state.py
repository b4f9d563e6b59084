"""export_state / restore_state: an estimator restored from another's state, fed the same
inputs afterwards, predicts what the uninterrupted one predicts (property test on the random
systems of test_equivalence, checked against the batch re-filter too), for the linear, the
unscented (plain and adaptive) and the IMM estimators; bad states are refused, unchanged."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pd_service.estimation import ObserverPredictor, StateError
from pd_service.estimation.imm.factory import make_imm
from pd_service.estimation.nonlinear import UnscentedObserverPredictor, make_adapter

from .imm.test_observer import MODES, TRANSITION, _traffic
from .imm.test_observer import P0 as IMM_P0
from .imm.test_observer import SENSORS as IMM_SENSORS
from .imm.test_observer import X0 as IMM_X0
from .nonlinear.test_replay_adaptive import ADAPT, _scenario
from .nonlinear.test_replay_adaptive import SENSORS as UKF_SENSORS
from .reference import batch_predict
from .test_equivalence import random_case, spd

TOL = 1e-12


def linear_events(seed: int, ticks: int):
    """Per tick: the calls (("c", step, u) / ("m", sensor, stamp, z, R)) of test_equivalence's
    random traffic, and the case."""
    rng, model, sensors, meta, max_delay, lead, x0, P0, hold = random_case(seed)
    events: dict[int, list] = {}
    for idx, (interval, delay) in enumerate(meta):
        s = sensors[idx]
        for stamp in range(int(rng.integers(0, interval)), ticks, interval):
            if rng.random() < 0.2:
                continue
            d = delay + int(rng.geometric(0.4)) - 1 if rng.random() < 0.7 else int(rng.integers(0, 40))
            z = rng.standard_normal(s.m) * 2
            R = spd(rng, s.m, 0.01, 1.0) if rng.random() < 0.2 else None
            events.setdefault(stamp + d, []).append(("m", s.name, stamp, z, R))
            if rng.random() < 0.05:
                events.setdefault(stamp + d + 1, []).append(("m", s.name, stamp, z, R))
    for k in range(ticks):
        if model.nu and rng.random() < 0.6:
            events.setdefault(k, []).insert(0, ("c", k + int(rng.integers(-3, lead + 3)),
                                                rng.standard_normal(model.nu)))
    for v in events.values():
        rng.shuffle(v)
    return (model, sensors, max_delay, lead, x0, P0, hold), events


def feed(est, calls, now):
    out = []
    for ev in calls:
        if ev[0] == "c":
            out.append(("c", ev[1], ev[2], est.add_command(ev[1], ev[2], now=now)))
        else:
            out.append(("m", ev[1], ev[2], ev[3], ev[4],
                        est.add_measurement(ev[1], ev[2], ev[3], now=now, R=ev[4])))
    return out


def run_split(make, events, ticks, cut, check=None):
    """Run one estimator through; another exported at ``cut`` and restored into a fresh one.
    Predictions, counters and acceptance must agree at every tick after the cut."""
    a, b = make(), make()
    for k in range(ticks):
        if k == cut:
            state = b.export_state()
            b = make()
            b.restore_state(copy.deepcopy(state))
        ra = feed(a, events.get(k, []), k)
        rb = feed(b, events.get(k, []), k)
        assert [r[-1] for r in ra] == [r[-1] for r in rb]
        if k >= cut:
            pa, pb = a.predict(k), b.predict(k)
            assert pa.step == pb.step and pa.newest_step == pb.newest_step
            np.testing.assert_allclose(pb.x, pa.x, rtol=TOL, atol=TOL)
            np.testing.assert_allclose(pb.P, pa.P, rtol=TOL, atol=TOL)
            if check is not None:
                check(k, pb, ra)
    assert a.counters == b.counters
    return a, b


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1), cut=st.integers(0, 59))
def test_linear_restore_continues_exactly(seed: int, cut: int) -> None:
    ticks = 60
    (model, sensors, max_delay, lead, x0, P0, hold), events = linear_events(seed, ticks)
    mode = "hold" if hold else "zero"
    commands: dict[int, np.ndarray] = {}
    accepted: list = []
    names = [s.name for s in sensors]

    def make():
        return ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay,
                                 command_hold=mode)

    def check(k, pred, results):
        for r in results:
            if r[0] == "c" and r[-1]:
                commands[r[1]] = r[2]
            elif r[0] == "m" and r[-1]:
                accepted.append((names.index(r[1]), r[2], r[3], r[4]))
        if k % 7 == 3 or k == ticks - 1:
            x, P = batch_predict(model.A, model.B, model.Q, [(s.H, s.R) for s in sensors],
                                 x0, P0, commands, accepted, k + lead, hold=hold)
            scale = max(1.0, float(np.max(np.abs(P))))
            np.testing.assert_allclose(pred.x, x, atol=1e-9 * max(1.0, np.max(np.abs(x))))
            np.testing.assert_allclose(pred.P, P, atol=1e-9 * scale)

    # the reference needs every accepted input, also those before the cut
    a = make()
    for k in range(cut):
        check(-1, None, feed(a, events.get(k, []), k))
    run_split(make, events, ticks, cut, check)


def test_restore_of_an_idle_estimator_and_of_a_fresh_one() -> None:
    (model, sensors, max_delay, lead, x0, P0, hold), events = linear_events(7, 80)

    def make():
        return ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay)

    run_split(make, events, 80, 0)
    quiet = {k: v for k, v in events.items() if not 10 <= k < 60}  # base rolls forward
    run_split(make, quiet, 80, 55)


@pytest.mark.parametrize("method", list(ADAPT))
def test_unscented_restore_continues_exactly(method) -> None:
    max_delay, lead, steps = 6, 4, 130
    model, samples, commands = _scenario(21, steps, max_delay)
    x0 = np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    P0 = np.diag([1e-4, 1e-4, 1e-3, 1e-2, 1e-2, 1e-1])
    dims = [model.sensors[s].m for s in UKF_SENSORS]
    events: dict[int, list] = {}
    for i, k, z, arr in samples:
        events.setdefault(arr, []).append(("m", UKF_SENSORS[i], k, z, None))
    for j, u, arr in commands:
        events.setdefault(arr, []).append(("c", j, u))

    def make():
        return UnscentedObserverPredictor(model, x0, P0, lead, max_delay, "hold",
                                          sensors=UKF_SENSORS,
                                          adapter=make_adapter(ADAPT[method], model.Q, dims))

    for cut in (3, 40, 77, 100):  # after adaptation started (window 4..6 innovations)
        a, b = run_split(make, events, steps, cut)
        np.testing.assert_array_equal(a.Q, b.Q)


@pytest.mark.parametrize("variant", ["single", "imm1", "imm2"])
def test_imm_restore_continues_exactly(variant) -> None:
    steps, max_delay, lead = 60, 8, 3

    def make():
        return make_imm(MODES, TRANSITION, IMM_SENSORS, variant, IMM_X0, IMM_P0, lead=lead,
                        max_delay=max_delay, node=1)

    events: dict[int, list] = {}
    for name, s, z, arr in _traffic(steps, max_delay, seed=11, filt=make().filter):
        events.setdefault(arr, []).append(("m", name, s, z, None))
    for cut in (5, 31):
        a, b = run_split(make, events, steps + 1, cut)
        np.testing.assert_allclose(b.predict_modes(steps).mu, a.predict_modes(steps).mu,
                                   rtol=TOL, atol=TOL)


def _fed():
    (model, sensors, max_delay, lead, x0, P0, hold), events = linear_events(3, 40)

    def make():
        return ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay)

    est = make()
    for k in range(30):
        feed(est, events.get(k, []), k)
    return make, est


@pytest.mark.parametrize("mutate, msg", [
    (lambda s: setattr(s, "version", 2), "version"),
    (lambda s: setattr(s, "kind", "ImmObserverPredictor"), "kind"),
    (lambda s: setattr(s, "n", s.n + 1), "kind"),
    (lambda s: s.base.__setitem__("x", np.zeros(99)), "base.x"),
    (lambda s: s.base.__setitem__("P", np.full_like(s.base["P"], np.nan)), "base.P"),
    (lambda s: s.base.pop("P"), "base.P"),
    (lambda s: setattr(s, "committed_step", s.committed_step + 1), "now"),
    (lambda s: setattr(s, "base_step", s.committed_step + 1), "steps"),
    (lambda s: s.packets.append((s.committed_step - 1, s.packets[0][1], s.packets[0][2], None, 0.0)),
     "packets"),
    (lambda s: s.packets.append((s.packets[0][0], "nosuch", s.packets[0][2], None, 0.0)), "packets"),
    (lambda s: s.packets.append(s.packets[0]), "packets"),
    (lambda s: s.counters.__setitem__("bogus", 1), "counters"),
    (lambda s: s.extras.__setitem__("Q", np.eye(2)), "extras"),
])
def test_a_state_that_does_not_fit_is_refused_and_changes_nothing(mutate, msg) -> None:
    make, est = _fed()
    state = est.export_state()
    assert state.packets, "the case needs packets in the window"
    mutate(state)
    target = make()
    before = target.predict(0)
    with pytest.raises(StateError, match=msg):
        target.restore_state(state)
    after = target.predict(0)
    np.testing.assert_array_equal(before.x, after.x)
    assert target.now == 0 and target.committed_step == 0


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1))
def test_checked_entry_points_equal_the_checking_ones(seed: int) -> None:
    """add_checked_measurement / add_checked_command (the intake fast path's: its values
    are already fresh finite float64 arrays of the right size) give the very verdicts,
    counters and bits of add_measurement / add_command."""
    (model, sensors, max_delay, lead, x0, P0, hold), events = linear_events(seed, 80)

    def make() -> ObserverPredictor:
        return ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay,
                                 command_hold="hold" if hold else "zero")

    a, b = make(), make()
    for k in range(80):
        for ev in events.get(k, []):
            if ev[0] == "c":
                ra = a.add_command(ev[1], ev[2], now=k)
                rb = b.add_checked_command(ev[1], np.array(ev[2], dtype=float), k)
            elif ev[4] is None:  # the fast path takes only samples without their own R
                ra = a.add_measurement(ev[1], ev[2], ev[3], now=k)
                rb = b.add_checked_measurement(ev[1], ev[2], np.array(ev[3], dtype=float), k)
            else:
                ra = a.add_measurement(ev[1], ev[2], ev[3], now=k, R=ev[4])
                rb = b.add_measurement(ev[1], ev[2], ev[3], now=k, R=ev[4])
            assert ra == rb
        pa, pb = a.predict(k), b.predict(k)
        assert pa.step == pb.step and pa.newest_step == pb.newest_step
        np.testing.assert_array_equal(pb.x, pa.x)
        np.testing.assert_array_equal(pb.P, pa.P)
    assert a.counters == b.counters
