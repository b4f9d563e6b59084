"""Samples taken inside a step (a packet's offset) in the unscented and IMM backends.

References: a sequential filter run directly over the events in time order (no window, no
replay; the package's single-step functions), and, on a linear model where the UKF is the
Kalman filter, the same filter run on a grid fine enough to hold every sample time.
"""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.imm import ImmFilter, ImmObserverPredictor
from pd_service.estimation.imm.models import imm_ct, imm_cv
from pd_service.estimation.nonlinear import UnscentedObserverPredictor, make_model
from pd_service.estimation.nonlinear.events import segments, split_packets
from pd_service.estimation.nonlinear.registry import MeasurementModel, NonlinearModel, batched
from pd_service.estimation.nonlinear.sigma import SigmaWeights
from pd_service.estimation.nonlinear.unscented import (
    ModelOps,
    UKFState,
    measurement_update,
    time_step,
)
from pd_service.estimation.replay import Packet

T = 0.05  # s, the step


def _events(rng, steps, sensors, dims, grid_only=False, fine=None):
    """Random samples: (step, offset, sensor index, z), with at most one per sensor and
    instant; offsets on ``fine`` sub-steps if given."""
    out = []
    for k in range(steps):
        for i, _ in enumerate(sensors):
            for _ in range(rng.integers(0, 3)):
                if grid_only:
                    off = 0.0
                elif fine is not None:
                    off = T * int(rng.integers(0, fine)) / fine
                else:
                    off = float(rng.choice([0.0, rng.uniform(0.0, T)]))
                out.append((k, off, i, rng.normal(size=dims[i]) * 0.3))
    uniq = {(k, off, i): (k, off, i, z) for k, off, i, z in out}
    return list(uniq.values())


def _drive(op, events, commands, steps, delay, rng):
    """Commands at their step; every sample arrives up to ``delay`` steps late, shuffled.
    Returns the prediction at the last step and the samples that arrived by then."""
    arrive: dict[int, list] = {}
    for ev in events:
        arrive.setdefault(ev[0] + int(rng.integers(0, delay + 1)), []).append(ev)
    names = op.sensor_names
    got = []
    for now in range(steps):
        op.add_command(now, commands[now], now=now)
        batch = arrive.get(now, [])
        rng.shuffle(batch)
        for k, off, i, z in batch:
            assert op.add_measurement(names[i], k, z, now=now, offset=off)
            got.append((k, off, i, z))
    return op.predict(steps - 1), got


def _ukf_reference(model, names, x0, P0, events, commands, target):
    """The UKF run directly over the events in time order, to x(target)."""
    ops, w = ModelOps(model, names), SigmaWeights.make(model.n)
    st = UKFState(np.array(x0, float), np.array(P0, float))
    by_step: dict[int, list] = {}
    for k, off, i, z in events:
        by_step.setdefault(k, []).append(Packet(i, z, None, off))
    for k in range(target):
        u = commands[min(k, len(commands) - 1)]  # the last command holds
        pk = sorted(by_step.get(k, []), key=lambda p: p.sensor)
        start, inside = split_packets(pk, True)
        if start:
            st = measurement_update(ops, w, st, k, start)[0]
        if not inside:
            st = time_step(ops, w, model.Q, st, u, k)
            continue
        for _, tau, group in segments(inside, T):
            st = time_step(ops, w, model.Q * (tau / T), st, u, k, tau=tau)
            if group:
                st = measurement_update(ops, w, st, k, group)[0]
    head = [p for p in sorted(by_step.get(target, []), key=lambda p: p.sensor) if p.offset == 0]
    if head:  # lead 0: the target step's samples at its start count, those inside it not yet
        st = measurement_update(ops, w, st, target, head)[0]
    return st


@pytest.mark.parametrize(("seed", "lead"), [(0, 3), (1, 3), (2, 0), (3, 0), (4, 1)])
def test_ukf_equals_sequential_reference_over_event_times(seed, lead):
    rng = np.random.default_rng(seed)
    model = make_model("unicycle", period_s=T)
    names = ["odom_twist", "imu", "pose"]
    steps = 30
    commands = [np.array([rng.uniform(0, 1), rng.uniform(-0.5, 0.5)]) for _ in range(steps)]
    events = _events(rng, steps, names, [2, 1, 3])
    op = UnscentedObserverPredictor(model, np.zeros(5), 0.01 * np.eye(5), lead=lead,
                                    max_delay=8, sensors=names)
    pred, events = _drive(op, events, commands, steps, 6, rng)
    ref = _ukf_reference(model, names, np.zeros(5), 0.01 * np.eye(5), events, commands,
                         steps - 1 + lead)
    np.testing.assert_allclose(pred.x, ref.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pred.P, ref.P, rtol=0, atol=1e-9)


def test_ukf_grid_aligned_is_bit_for_bit_unchanged():
    """Offsets 0.0 take exactly the path of packets without an offset, and that path is
    the per-step UKF (update at x(k), one whole step of f)."""
    rng = np.random.default_rng(7)
    model = make_model("unicycle", period_s=T)
    names = ["odom_twist", "imu", "pose"]
    steps, lead = 25, 2
    commands = [np.array([rng.uniform(0, 1), rng.uniform(-0.5, 0.5)]) for _ in range(steps)]
    events = _events(rng, steps, names, [2, 1, 3], grid_only=True)
    op = UnscentedObserverPredictor(model, np.zeros(5), 0.01 * np.eye(5), lead=lead,
                                    max_delay=8, sensors=names)
    pred, events = _drive(op, events, commands, steps, 6, np.random.default_rng(1))
    ref = _ukf_reference(model, names, np.zeros(5), 0.01 * np.eye(5), events, commands,
                         steps - 1 + lead)
    assert np.array_equal(pred.x, ref.x) and np.array_equal(pred.P, ref.P)


def _linear_model(period_s, kind):
    """[p, v] with a position sensor and its exact flow: a linear model, on which the UKF is
    the Kalman filter. ``kind`` "cv": constant velocity without process noise (the flow's
    timing alone); "walk": two random walks, Q = 0.2 tau I over tau (noise increments that
    add up over any split, so a split step and the fine grid agree exactly)."""
    def A(t):
        return np.array([[1.0, t], [0.0, 1.0]]) if kind == "cv" else np.eye(2)

    Q = np.zeros((2, 2)) if kind == "cv" else 0.2 * period_s * np.eye(2)
    pos = MeasurementModel("pos", batched(lambda X: X[:, :1].copy()), np.array([[0.04]]),
                           vectorized=True)
    return NonlinearModel(
        name="lin", n=2, nu=0, f=batched(lambda X, u, k: X @ A(period_s).T), Q=Q,
        sensors={"pos": pos}, vectorized=True,
        flow=lambda t: batched(lambda X, u: X @ A(t).T), period_s=period_s)


@pytest.mark.parametrize("kind", ["cv", "walk"])
def test_ukf_offsets_equal_the_same_filter_on_a_fine_grid(kind):
    """Samples at multiples of T/8: the 50 ms-step filter with offsets equals the filter on
    the T/8 grid to rounding."""
    fine = 8
    rng = np.random.default_rng(3)
    coarse_m, fine_m = _linear_model(T, kind), _linear_model(T / fine, kind)
    steps, lead = 30, 2
    events = _events(rng, steps, ["pos"], [1], fine=fine)
    x0, P0 = np.array([0.0, 1.0]), np.diag([0.1, 0.1])
    op = UnscentedObserverPredictor(coarse_m, x0, P0, lead=lead, max_delay=5)
    pred, events = _drive(op, events, [np.zeros(0)] * steps, steps, 4, rng)
    op_f = UnscentedObserverPredictor(fine_m, x0, P0, lead=lead * fine, max_delay=steps * fine)
    for k, off, _, z in events:
        assert op_f.add_measurement("pos", k * fine + round(off / T * fine), z,
                                    now=(steps - 1) * fine)
    pf = op_f.predict((steps - 1) * fine)
    np.testing.assert_allclose(pred.x, pf.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pred.P, pf.P, rtol=0, atol=1e-9)


def test_offsets_are_refused_where_the_model_has_no_flow():
    model = make_model("linear", A=[[1.0]], B=None, Q=[[0.01]],
                       sensors={"s": {"H": [[1.0]], "R": [[0.1]]}})
    op = UnscentedObserverPredictor(model, [0.0], [[1.0]], lead=1, max_delay=2)
    assert op.add_measurement("s", 0, [1.0], now=0, offset=0.0)
    with pytest.raises(ValueError, match="offset"):
        op.add_measurement("s", 0, [1.0], now=0, offset=0.02)
    flowing = UnscentedObserverPredictor(make_model("unicycle", period_s=T), np.zeros(5),
                                         np.eye(5), lead=1, max_delay=2)
    with pytest.raises(ValueError, match="below the step period"):
        flowing.add_measurement("imu", 0, [0.0], now=0, offset=T)


def _imm_reference(filt, events, target):
    """The IMM run directly over the events in time order, to x(target)."""
    st = filt.initial_state(np.zeros(5), np.eye(5))
    by_step: dict[int, list] = {}
    for k, off, i, z in events:
        by_step.setdefault(k, []).append(Packet(i, z, None, off))
    for k in range(target):
        pk = sorted(by_step.get(k, []), key=lambda p: p.sensor)
        start, inside = split_packets(pk, True)
        if start:
            st = filt.update(st, [(p.sensor, p.z, p.R) for p in start])
        if not inside:
            st = filt.predict(st, k)
            continue
        first = True
        for _, tau, group in segments(inside, T):
            st = filt.predict(st, k, tau=tau, interact=first)
            first = False
            if group:
                st = filt.update(st, [(p.sensor, p.z, p.R) for p in group])
    return filt.output(st)


@pytest.mark.parametrize("seed", range(3))
def test_imm_equals_sequential_reference_over_event_times(seed):
    rng = np.random.default_rng(seed)
    pos = MeasurementModel("pos", batched(lambda X: X[:, [0, 2]].copy()), 0.05 * np.eye(2),
                           vectorized=True)
    filt = ImmFilter([imm_cv(period_s=T), imm_ct(period_s=T)], [[0.95, 0.05], [0.05, 0.95]],
                     [pos], variant="imm2")
    steps, lead = 20, 2
    events = [(k, off, i, z + np.array([k * T, k * T])) for k, off, i, z in
              _events(rng, steps, ["pos"], [2])]
    op = ImmObserverPredictor(filt, np.zeros(5), np.eye(5), lead=lead, max_delay=6)
    pred, events = _drive(op, events, [np.zeros(0)] * steps, steps, 5, rng)
    x, P = _imm_reference(filt, events, steps - 1 + lead)
    np.testing.assert_allclose(pred.x, x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pred.P, P, rtol=0, atol=1e-9)


def test_segments_split_a_step_in_time_order():
    pk = [Packet(0, np.zeros(1), None, o) for o in (0.01, 0.01, 0.03)]
    segs = [(round(t0, 12), round(t, 12), len(g)) for t0, t, g in segments(pk, T)]
    assert segs == [(0.0, 0.01, 2), (0.01, 0.02, 1), (0.03, 0.02, 0)]
    cut = [(round(t0, 12), round(t, 12), len(g)) for t0, t, g in segments(pk, T, cut=0.02)]
    assert cut == [(0.0, 0.01, 2), (0.01, 0.01, 0), (0.02, 0.01, 1), (0.03, 0.02, 0)]
    start, inside = split_packets([Packet(1, np.zeros(1), None, 0.02),
                                   Packet(0, np.zeros(1), None, 0.0)], True)
    assert [p.sensor for p in start] == [0] and [p.sensor for p in inside] == [1]


def test_a_command_taking_effect_inside_a_step_switches_the_input_there():
    """Where the core reports a command's cut inside a step with inner samples (inputs_at),
    the step runs on the input before it until the cut, then on u(k)."""
    model = make_model("unicycle", period_s=T)
    op = UnscentedObserverPredictor(model, np.zeros(5), 0.01 * np.eye(5), lead=1, max_delay=3,
                                    sensors=["imu", "pose"])
    backend = op._backend
    u_new, u_old = np.array([1.0, 0.3]), np.array([0.2, -0.1])
    backend.inputs_at = lambda k: (u_new, (0.02, u_old))
    st = UKFState(np.zeros(5), 0.01 * np.eye(5))
    pk = [Packet(0, np.array([0.1]), None, 0.01), Packet(1, np.array([0.0, 0.0, 0.0]), None, 0.035)]
    got = backend.update(st, 4, pk)
    ops, w = ModelOps(model, ["imu", "pose"]), SigmaWeights.make(5)
    ref = time_step(ops, w, model.Q * 0.2, st, u_old, 4, tau=0.01)
    ref = measurement_update(ops, w, ref, 4, pk[:1])[0]
    ref = time_step(ops, w, model.Q * 0.2, ref, u_old, 4, tau=0.01)   # up to the cut at 20 ms
    ref = time_step(ops, w, model.Q * 0.3, ref, u_new, 4, tau=0.015)  # the new command
    ref = measurement_update(ops, w, ref, 4, pk[1:])[0]
    ref = time_step(ops, w, model.Q * 0.3, ref, u_new, 4, tau=0.015)
    np.testing.assert_allclose(got.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.P, ref.P, rtol=0, atol=1e-12)
