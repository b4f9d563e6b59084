"""The replay's covariance reuse and the fast kernels of LinearBackend.

A replay that only commands triggered keeps every covariance and gain (the same objects) and
recomputes means; a packet that joins a step keeps the update of the step's earlier packets;
both must give the very bits a full recompute gives. Covariances stay exactly symmetric, and
a long run stays on the batch re-filter (a covariance recursion that lets antisymmetric
rounding grow drifts away only after hundreds of steps).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.linear import _REPLAY, Gaussian, LinearBackend, _chol_inv, read_stages
from pd_service.scenarios.paper import paper_model, paper_prior, paper_sensors

from .reference import batch_predict
from .test_estimator_state import feed, linear_events

RTOL = 1e-9


class StepwiseBackend(LinearBackend):
    """LinearBackend without its C replay loop: the replay calls advance step by step."""

    def advance_run(self, state, a, steps, buf, off, packets, chk, noreuse, cut_view):  # type: ignore[no-untyped-def]
        return state, a, 0


class CountingBackend(StepwiseBackend):
    """LinearBackend that counts reused covariances, or (``reuse=False``) never reuses
    (stepwise: every step through its advance, which the C loop would bypass)."""

    def __init__(self, *args: object, reuse: bool = True) -> None:
        super().__init__(*args)  # type: ignore[arg-type]
        self.reuse = reuse
        self.offered = self.hits = 0

    def advance(self, state, m, U, packets, old):  # type: ignore[no-untyped-def]
        out = super().advance(state, m, U, packets, old if self.reuse else None)
        if old is not None:
            self.offered += 1
            self.hits += self.reuse and out.P is old.P
        return out


class RunCountingBackend(LinearBackend):
    """LinearBackend counting the steps its C replay loop made."""

    made = 0

    def advance_run(self, state, a, steps, buf, off, packets, chk, noreuse, cut_view):  # type: ignore[no-untyped-def]
        got = super().advance_run(state, a, steps, buf, off, packets, chk, noreuse, cut_view)
        self.made += got[2]
        return got


def command_heavy(seed: int, ticks: int):
    """test_estimator_state's random traffic plus, in most ticks, a command for a past step inside
    the window: replays that a command alone triggers reuse covariances."""
    case, events = linear_events(seed, ticks)
    rng = np.random.default_rng(seed)
    max_delay, nu = case[2], case[0].nu
    out: dict[int, list] = {}
    for k in range(ticks):
        calls = list(events.get(k, []))
        if nu and rng.random() < 0.8:
            calls.append(("c", k - int(rng.integers(0, max_delay + 1)), rng.standard_normal(nu)))
        out[k] = calls
    return case, out


def with_backend(op: ObserverPredictor, reuse: bool) -> ObserverPredictor:
    op._backend = CountingBackend(op.model, op.sensors, op._inputs.capacity, reuse=reuse)
    return op


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1))
def test_reused_covariances_give_the_bits_of_a_full_recompute(seed: int) -> None:
    """Random traffic with commands for past steps: predictions with reuse equal those
    without, bit for bit, at every tick."""
    ticks = 50
    (model, sensors, max_delay, lead, x0, P0, hold), events = command_heavy(seed, ticks)
    mode = "hold" if hold else "zero"
    a, b = (with_backend(ObserverPredictor(model, sensors, x0, P0, lead=lead,
                                           max_delay=max_delay, command_hold=mode), reuse)
            for reuse in (True, False))
    for k in range(ticks):
        ra, rb = feed(a, events.get(k, []), k), feed(b, events.get(k, []), k)
        assert ra == rb or [r[-1] for r in ra] == [r[-1] for r in rb]
        pa, pb = a.predict(k), b.predict(k)
        assert np.array_equal(pa.x, pb.x) and np.array_equal(pa.P, pb.P), k


def test_reuse_happens_for_late_commands() -> None:
    """The property above is not vacuous: its traffic does reuse covariances."""
    hits = 0
    for seed in range(20):
        (model, sensors, max_delay, lead, x0, P0, hold), events = command_heavy(seed, 50)
        op = with_backend(ObserverPredictor(model, sensors, x0, P0, lead=lead,
                                            max_delay=max_delay), True)
        for k in range(50):
            feed(op, events.get(k, []), k)
            op.predict(k)
        hits += op._backend.hits  # type: ignore[attr-defined]
    assert hits > 30


def paper_op(lead: int = 10, max_delay: int = 12) -> ObserverPredictor:
    x0, P0 = paper_prior()
    return ObserverPredictor(paper_model(), paper_sensors(), x0, P0, lead=lead,
                             max_delay=max_delay)


def drive(op: ObserverPredictor, ticks: int, rng: np.random.Generator,
          commands: dict[int, np.ndarray], accepted: list, cmd_every: int = 1) -> None:
    """The bench's paper traffic: camera every 2nd step at delay 10, ranger at delay 12,
    a command for now + 10 every ``cmd_every`` steps."""
    for k in range(ticks):
        if k % cmd_every == 0:
            u = rng.standard_normal(1) * 0.1
            assert op.add_command(step=k + 10, u=u, now=k)
            commands[k + 10] = u
        for idx, name, delay, every in ((0, "camera", 10, 2), (1, "ranger", 12, 1)):
            s = k - delay
            if s >= 0 and s % every == 0:
                z = rng.standard_normal(2 if idx == 0 else 1)
                assert op.add_measurement(name, step=s, z=z, now=k)
                accepted.append((idx, s, z, None))
        op.predict(now=k)


def reference(op: ObserverPredictor, commands, accepted, target):
    m = op.model
    x0, P0 = paper_prior()
    return batch_predict(m.A, m.B, m.Q, [(s.H, s.R) for s in op.sensors], x0, P0, commands,
                         accepted, target)


def close(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(np.abs(a - b) <= RTOL * max(1.0, float(np.max(np.abs(b))))))


def test_a_command_only_change_keeps_every_covariance_and_gain() -> None:
    op = paper_op()
    commands: dict[int, np.ndarray] = {}
    accepted: list = []
    drive(op, 40, np.random.default_rng(1), commands, accepted, cmd_every=3)
    now = 39
    # a packet at now - 1 so that the window holds measured steps after the command
    assert op.add_measurement("camera", step=38, z=[0.5, 5.0], now=now)
    accepted.append((0, 38, np.array([0.5, 5.0]), None))
    pred0 = op.predict(now)
    before = {s: op._chk[s] for s in op._steps}
    j = op.committed_step  # 27: no command there (commands at multiples of 3, + 10)
    u = np.array([0.7])
    assert op.add_command(step=j, u=u)
    commands[j] = u
    pred = op.predict(now)
    assert [s for s in op._steps if s > j]
    for s in op._steps:
        new, old = op._chk[s], before[s]
        assert new.P is old.P and new.stages is old.stages  # the same objects: not recomputed
        assert (new is old) == (s <= j)  # posteriors after the command's step are new
        assert s <= j or not np.array_equal(new.x, old.x)
    assert pred.P is pred0.P  # the predicted covariance too
    assert not np.array_equal(pred.x, pred0.x)
    want_x, want_P = reference(op, commands, accepted, now + op.lead)
    assert close(pred.x, want_x) and close(pred.P, want_P)
    # a restored copy recomputes every posterior from the base: the same to 1e-12
    again = paper_op()
    again.restore_state(op.export_state())
    p2 = again.predict(now)
    assert p2.P is not pred.P
    np.testing.assert_allclose(p2.x, pred.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(p2.P, pred.P, rtol=0, atol=1e-12)


def test_a_packet_renews_covariances_from_its_step_on() -> None:
    op = paper_op()
    drive(op, 40, np.random.default_rng(2), {}, [])  # now 39: steps 27 (ranger), 28 (camera)
    assert op.add_measurement("camera", step=36, z=[0.3, 5.0], now=39)
    op.predict(39)
    before = {s: op._chk[s].P for s in op._steps}
    assert sorted(before) == [27, 28, 36]
    assert op.add_measurement("ranger", step=28, z=[4.0], now=39)  # ranger stamps <= 27 in
    pred = op.predict(39)
    for s, P in before.items():
        assert (op._chk[s].P is P) == (s < 28), s
    assert pred.newest_step == 36


def test_long_run_stays_on_the_batch_refilter_and_symmetric() -> None:
    op = paper_op()
    commands: dict[int, np.ndarray] = {}
    accepted: list = []
    rng = np.random.default_rng(3)
    for chunk in range(4):
        for k in range(chunk * 500, chunk * 500 + 500):
            u = rng.standard_normal(1) * 0.1
            op.add_command(step=k + 10, u=u, now=k)
            commands[k + 10] = u
            for idx, name, delay, every in ((0, "camera", 10, 2), (1, "ranger", 12, 1)):
                s = k - delay
                if s >= 0 and s % every == 0:
                    z = rng.standard_normal(2 if idx == 0 else 1)
                    op.add_measurement(name, step=s, z=z, now=k)
                    accepted.append((idx, s, z, None))
            pred = op.predict(now=k)
        for s in op._steps:
            P = op._chk[s].P
            assert np.array_equal(P, P.T)
        want_x, want_P = reference(op, commands, accepted, k + op.lead)
        assert close(pred.x, want_x), (k, pred.x, want_x)
        assert close(pred.P, want_P), (k, pred.P, want_P)


@pytest.mark.parametrize("r", [2, 3])
def test_closed_form_cholesky_inverse(r: int) -> None:
    rng = np.random.default_rng(r)
    for _ in range(200):
        L = rng.standard_normal((r, r))
        S = L @ L.T + 1e-3 * np.eye(r)
        Li = _chol_inv(S)
        assert Li is not None
        assert np.array_equal(Li, np.tril(Li))
        np.testing.assert_allclose(Li @ S @ Li.T, np.eye(r), atol=1e-8)
    assert _chol_inv(np.zeros((r, r))) is None
    v = rng.standard_normal(r)
    assert _chol_inv(np.outer(v, v)) is None  # rank one
    assert _chol_inv(np.eye(4)) is None and _chol_inv(np.eye(1)) is None


def test_unit_row_and_general_row_sensors_agree() -> None:
    """One scalar sensor given as a unit row (the fast path) and as a general row that is
    numerically the same row scaled by -1 (with z negated): the same estimate."""
    model = paper_model()
    x0, P0 = paper_prior()
    unit = [Sensor("p", np.array([[0.0, 0, 1.0, 0]]), np.array([[0.04]]))]
    neg = [Sensor("p", np.array([[0.0, 0, -1.0, 0]]), np.array([[0.04]]))]
    a = ObserverPredictor(model, unit, x0, P0, lead=3, max_delay=5)
    b = ObserverPredictor(model, neg, x0, P0, lead=3, max_delay=5)
    assert a._backend._single[0][0] == 1 and b._backend._single[0][0] == 2  # type: ignore[attr-defined]
    rng = np.random.default_rng(4)
    for k in range(60):
        z = rng.standard_normal(1)
        a.add_measurement("p", step=k - 2, z=z, now=k)
        b.add_measurement("p", step=k - 2, z=-z, now=k)
        pa, pb = a.predict(k), b.predict(k)
        np.testing.assert_allclose(pa.x, pb.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(pa.P, pb.P, rtol=1e-12, atol=1e-12)


def test_zero_innovation_variance_leaves_the_state() -> None:
    """s = h P h^T + r = 0 (r = 0, P known in that direction): K = 0 (the LMMSE gain)."""
    model = LinearModel(A=np.eye(2), B=np.zeros((2, 0)), Q=np.zeros((2, 2)))
    op = ObserverPredictor(model, [Sensor("p", np.array([[1.0, 0.0]]), np.zeros((1, 1)))],
                           x0=[1.0, 2.0], P0=np.diag([0.0, 1.0]), lead=0, max_delay=2)
    assert op.add_measurement("p", step=0, z=[5.0], now=0)
    pred = op.predict(0)
    assert np.array_equal(pred.x, [1.0, 2.0]) and np.array_equal(pred.P, np.diag([0.0, 1.0]))
    assert isinstance(op._chk[0], Gaussian)


def test_a_packet_joining_a_step_pays_only_its_own_update() -> None:
    """The ranger sample joins a step whose camera sample is already applied: the camera's
    update (covariance and gain) is kept, and the result has the bits of a recompute."""
    ops = [with_backend(paper_op(), reuse) for reuse in (True, False)]
    for op in ops:
        drive(op, 40, np.random.default_rng(5), {}, [])
    old = ops[0]._chk[28]
    assert old.sensors == (0,)  # the camera sample of step 28 (ranger stamps <= 27 so far)
    for op in ops:
        assert op.add_measurement("ranger", step=28, z=[4.0], now=39)
    pa, pb = ops[0].predict(39), ops[1].predict(39)
    new = ops[0]._chk[28]
    assert new.sensors == (0, 1)
    assert new.stages.startswith(old.stages) and len(new.stages) > len(old.stages)  # old's kept
    assert np.array_equal(pa.x, pb.x) and np.array_equal(pa.P, pb.P)
    # a sample of a lower sensor index than those applied: recomputed from the prior
    assert ops[0].add_measurement("camera", step=27, z=[0.1, 5.0], now=39)
    before = ops[0]._chk[27]
    assert before.sensors == (1,)
    ops[0].predict(39)
    after = ops[0]._chk[27]
    def gains(g: Gaussian) -> list[np.ndarray]:
        return [st[5] for st in read_stages(g.stages, g.x.shape[0])]

    assert after.sensors == (0, 1)  # the ranger's gain recomputed after the camera's update
    assert not np.array_equal(gains(after)[1], gains(before)[0])


def replay_pair(seed: int, ticks: int) -> int:
    """The same random traffic (commands for past steps included) through an estimator
    whose replay uses the C loop and one whose replay calls advance step by step: asserts
    the same predictions, bit for bit, at every tick; returns the steps the C loop made."""
    (model, sensors, max_delay, lead, x0, P0, hold), events = command_heavy(seed, ticks)
    mode = "hold" if hold else "zero"
    ops = []
    for cls in (RunCountingBackend, StepwiseBackend):
        op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay,
                               command_hold=mode)
        op._backend = cls(op.model, op.sensors, op._inputs.capacity)
        ops.append(op)
    a, b = ops
    for k in range(ticks):
        ra, rb = feed(a, events.get(k, []), k), feed(b, events.get(k, []), k)
        assert ra == rb or [r[-1] for r in ra] == [r[-1] for r in rb]
        pa, pb = a.predict(k), b.predict(k)
        assert np.array_equal(pa.x, pb.x) and np.array_equal(pa.P, pb.P), k
    return a._backend.made  # type: ignore[attr-defined]


needs_kernel = pytest.mark.skipif(_REPLAY is None, reason="the C kernel is not built (pure Python)")


@needs_kernel
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1))
def test_the_kernels_replay_loop_gives_the_bits_of_the_step_by_step_loop(seed: int) -> None:
    """``_kalman.replay`` (LinearBackend.advance_run: the replay's steps in one C call)
    against the replay's own loop of advance calls, with and without reuse."""
    replay_pair(seed, 50)


@needs_kernel
def test_the_kernels_replay_loop_is_used() -> None:
    """The property above is not vacuous: the C loop makes most replayed steps."""
    assert sum(replay_pair(seed, 50) for seed in range(10)) > 100


def event_time_pair(seed: int, ticks: int) -> int:
    """As :func:`replay_pair` for a continuous-time model with samples at their own times
    and commands taking effect inside steps: the C loop's split steps (``_kalman.replay``
    calling its split walk) against the replay's loop of advance calls (``_kalman.split``
    per step), bit for bit; returns the steps the C loop made."""
    rng = np.random.default_rng([seed, 7])
    n, T = 4, 0.05
    F = np.zeros((n, n))
    F[0, 2] = F[1, 3] = 1.0
    F[2:, 2:] = rng.standard_normal((2, 2)) * 0.3
    G = rng.standard_normal((n, 2))
    model = LinearModel.continuous(F, G, np.diag([0.0, 0.0, 0.05, 0.05]), T)
    sensors = [Sensor("pos", np.eye(n)[:2], 0.01 * np.eye(2)),
               Sensor("vel", np.eye(n)[2:], 0.04 * np.eye(2))]
    lead, max_delay = int(rng.integers(0, 4)), int(rng.integers(2, 8))
    ops = []
    for cls in (RunCountingBackend, StepwiseBackend):
        op = ObserverPredictor(model, sensors, np.zeros(n), np.eye(n), lead=lead,
                               max_delay=max_delay)
        op._backend = cls(op.model, op.sensors, op._inputs.capacity)
        ops.append(op)
    a, b = ops
    for k in range(ticks):
        for _ in range(int(rng.integers(0, 4))):
            name = sensors[int(rng.integers(0, 2))].name
            s = k - int(rng.integers(0, max_delay + 2))
            off = 0.0 if rng.random() < 0.2 else float(rng.uniform(0, T))
            z = rng.standard_normal(2)
            assert a.add_measurement(name, s, z, k, offset=off) == b.add_measurement(
                name, s, z, k, offset=off)
        if rng.random() < 0.7:
            j = k + int(rng.integers(-2, lead + 2))
            off = 0.0 if rng.random() < 0.3 else float(rng.uniform(0, T))
            u = rng.standard_normal(2)
            assert a.add_command(j, u, k, offset=off) == b.add_command(j, u, k, offset=off)
        pa, pb = a.predict(k), b.predict(k)
        assert np.array_equal(pa.x, pb.x) and np.array_equal(pa.P, pb.P), k
    return a._backend.made  # type: ignore[attr-defined]


@needs_kernel
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(seed=st.integers(min_value=0, max_value=2**32 - 1))
def test_the_kernels_replay_loop_takes_steps_with_events_inside_them(seed: int) -> None:
    event_time_pair(seed, 40)


@needs_kernel
def test_the_kernels_replay_loop_makes_split_steps() -> None:
    """The property above is not vacuous: the C loop makes most of those steps."""
    assert sum(event_time_pair(seed, 40) for seed in range(5)) > 100
