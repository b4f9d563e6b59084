"""ObserverPredictor's contract: validation, window semantics, counters, bounded memory."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.estimation.inputs import InputBuffer
from pd_service.scenarios.paper import paper_model, paper_prior, paper_sensors


def make(lead: int = 10, max_delay: int = 12, hold: str = "hold") -> ObserverPredictor:
    x0, P0 = paper_prior()
    return ObserverPredictor(paper_model(), paper_sensors(), x0, P0, lead=lead,
                             max_delay=max_delay, command_hold=hold)


def snapshot(op: ObserverPredictor, now: int):
    p = op.predict(now=now)
    return p.x.copy(), p.P.copy(), op.counters


def test_textbook_kalman_filter_with_zero_delay() -> None:
    """Zero delay, one sensor: the textbook predict / update cycle."""
    rng = np.random.default_rng(0)
    A = np.array([[1.0, 0.1], [0.0, 1.0]])
    B = np.array([[0.005], [0.1]])
    Q = np.diag([1e-4, 1e-3])
    H, R = np.array([[1.0, 0.0]]), np.array([[0.04]])
    op = ObserverPredictor(LinearModel(A=A, B=B, Q=Q), [Sensor("pos", H, R)],
                           x0=[0, 0], P0=np.eye(2), lead=0, max_delay=0)
    x, P = np.zeros(2), np.eye(2)
    for k in range(50):
        z = rng.normal(size=1)
        u = np.array([np.sin(k / 5)])
        assert op.add_measurement("pos", step=k, z=z, now=k)
        # update: K = P H^T (H P H^T + R)^-1; x += K (z - H x); P = (I - K H) P
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        x = x + K @ (z - H @ x)
        P = (np.eye(2) - K @ H) @ P
        pred = op.predict(now=k)
        np.testing.assert_allclose(pred.x, x, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(pred.P, P, rtol=1e-10, atol=1e-12)
        assert op.add_command(step=k, u=u)
        # predict: x = A x + B u; P = A P A^T + Q
        x, P = A @ x + B @ u, A @ P @ A.T + Q


def test_window_refusals_are_counted_and_change_nothing() -> None:
    op = make()
    z = np.array([1.0, 5.0])
    assert op.add_measurement("camera", step=20, z=z, now=30)
    before = snapshot(op, 30)
    assert not op.add_measurement("camera", step=31, z=z, now=30)  # future
    assert not op.add_measurement("camera", step=17, z=z, now=30)  # late: 30 - 12 = 18
    assert not op.add_measurement("camera", step=20, z=z, now=30)  # duplicate
    assert not op.add_measurement("camera", step=-1, z=z, now=30)  # before step 0
    after = snapshot(op, 30)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
    c = op.counters
    assert (c["accepted"], c["future"], c["late"], c["duplicate"]) == (1, 1, 2, 1)
    assert op.add_measurement("camera", step=18, z=z, now=30)  # edge of the window
    assert op.add_measurement("camera", step=30, z=z, now=30)  # sampled now


def test_commands_for_final_steps_are_refused() -> None:
    op = make()
    op.predict(now=40)  # steps < 28 are final
    assert not op.add_command(step=27, u=[1.0])
    assert op.add_command(step=28, u=[1.0])
    assert not op.add_command(step=28, u=[2.0])
    assert not op.add_command(step=40 + 10 + 12 + 2, u=[1.0])
    c = op.counters
    assert (c["commands_late"], c["commands_accepted"], c["commands_duplicate"],
            c["commands_future"]) == (1, 1, 1, 1)


def test_a_command_superseded_on_an_open_step_moves_the_prediction_like_the_newer_alone() -> None:
    op, ref = make(), make()
    op.predict(now=40)  # steps < 28 are final
    ref.predict(now=40)
    assert op.add_command(step=30, u=[1.0]) and op.add_command(step=33, u=[-1.0])
    assert op.supersede_command(30, np.array([2.0]), now=41)
    assert ref.add_command(step=30, u=[2.0]) and ref.add_command(step=33, u=[-1.0])
    a, b = op.predict(now=41), ref.predict(now=41)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
    assert not op.supersede_command(31, np.array([5.0]))  # nothing stored for step 31
    op.predict(now=60)  # step 30 is final now
    assert not op.supersede_command(30, np.array([5.0]))
    c = op.counters
    assert (c["commands_accepted"], c["commands_superseded"]) == (2, 1)


@pytest.mark.parametrize("hold", ["hold", "zero"])
@pytest.mark.parametrize("withdrawn", [30, 33])
def test_a_withdrawn_command_leaves_the_estimate_of_the_others_alone(hold: str,
                                                                     withdrawn: int) -> None:
    op, ref = make(hold=hold), make(hold=hold)
    op.predict(now=40)
    ref.predict(now=40)
    for k, u in ((30, 1.0), (33, -1.0), (36, 0.5)):
        assert op.add_command(step=k, u=[u])
        if k != withdrawn:
            assert ref.add_command(step=k, u=[u])
    assert op.withdraw_command(withdrawn, now=41)
    a, b = op.predict(now=41), ref.predict(now=41)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)
    assert not op.withdraw_command(withdrawn)  # gone
    op.predict(now=60)  # 36 is final now
    assert not op.withdraw_command(36)
    assert op.counters["commands_withdrawn"] == 1


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda op: op.add_measurement("lidar", 1, [1.0], now=3), "sensor"),
        (lambda op: op.add_measurement("camera", 1, [1.0], now=3), "z"),
        (lambda op: op.add_measurement("camera", 1, [1.0, np.nan], now=3), "z"),
        (lambda op: op.add_measurement("camera", 1, [1.0, 2.0], now=3, R=np.ones((3, 3))), "R"),
        (lambda op: op.add_measurement("camera", 1, [1.0, 2.0], now=3,
                                       R=np.array([[1.0, 2.0], [2.0, 1.0]])), "R"),
        (lambda op: op.add_measurement("camera", 1, [1.0, 2.0], now=3,
                                       R=np.array([[1.0, 0.5], [0.0, 1.0]])), "R"),
        (lambda op: op.add_measurement("camera", 1.5, [1.0, 2.0], now=3), "step"),
        (lambda op: op.add_measurement("camera", 1, [1.0, 2.0], now=1), "now"),
        (lambda op: op.add_command(step=5, u=[1.0, 2.0]), "u"),
        (lambda op: op.add_command(step=5, u=[np.inf]), "u"),
        (lambda op: op.predict(now=1), "now"),
    ],
)
def test_bad_input_raises_naming_the_field_and_leaves_state(call, field) -> None:
    op = make()
    op.add_measurement("camera", 2, [0.5, 5.0], now=3)
    before = snapshot(op, 3)
    with pytest.raises(ValueError, match=rf"^{field}\b"):
        call(op)
    after = snapshot(op, 3)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
    assert before[2] == after[2]


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"A": np.ones((2, 3))}, "A"),
        ({"Q": -np.eye(4)}, "Q"),
        ({"B": np.ones((3, 1))}, "B"),
    ],
)
def test_bad_model_raises(kwargs, field) -> None:
    m = paper_model()
    args = {"A": m.A, "B": m.B, "Q": m.Q} | kwargs
    with pytest.raises(ValueError, match=rf"^{field}\b"):
        LinearModel(**args)


def test_bad_constructor_arguments() -> None:
    x0, P0 = paper_prior()
    with pytest.raises(ValueError, match="^x0"):
        ObserverPredictor(paper_model(), paper_sensors(), [0, 0], P0, lead=1, max_delay=1)
    with pytest.raises(ValueError, match="^P0"):
        ObserverPredictor(paper_model(), paper_sensors(), x0, -P0, lead=1, max_delay=1)
    with pytest.raises(ValueError, match="H"):
        ObserverPredictor(paper_model(), [Sensor("a", np.ones((1, 3)), np.eye(1))], x0, P0, 1, 1)
    with pytest.raises(ValueError, match="^lead"):
        ObserverPredictor(paper_model(), paper_sensors(), x0, P0, lead=-1, max_delay=1)
    with pytest.raises(ValueError, match="duplicate"):
        ObserverPredictor(paper_model(), paper_sensors() * 2, x0, P0, lead=1, max_delay=1)


def test_memory_is_bounded_by_the_window() -> None:
    op = make(lead=10, max_delay=12)
    rng = np.random.default_rng(1)
    for k in range(3000):
        op.add_command(step=k + 10, u=[0.1], now=k)
        op.add_measurement("camera", k - 10, rng.normal(size=2), now=k)
        op.add_measurement("ranger", k - 12, rng.normal(size=1), now=k)
        op.predict(now=k)
        assert len(op._packets) <= 13 and len(op._chk) <= 13
    assert op._inputs.capacity < 100


def test_long_silence_then_packets() -> None:
    """A session with no packets for many windows rolls its base forward in bounded chunks."""
    op = make(lead=3, max_delay=4)
    op.add_command(step=0, u=[0.2])
    p1 = op.predict(now=10_000)
    assert p1.step == 10_003 and np.all(np.isfinite(p1.P))
    assert op.add_measurement("camera", 9_998, [1.0, 2.0], now=10_000)
    assert op.predict(now=10_000).P[0, 0] < p1.P[0, 0]


def test_input_buffer_hold_and_zero() -> None:
    hold = InputBuffer(nu=1, capacity=8, hold=True)
    hold.set(2, np.array([1.0]))
    hold.set(5, np.array([2.0]))
    hold.set(3, np.array([3.0]))  # inserted between: holds until step 5
    assert hold.slice(0, 8)[:, 0].tolist() == [0, 0, 1, 3, 3, 2, 2, 2]
    hold.advance(4)
    assert hold.slice(4, 8)[:, 0].tolist() == [3, 2, 2, 2, 2, 2, 2, 2]
    zero = InputBuffer(nu=1, capacity=8, hold=False)
    zero.set(2, np.array([1.0]))
    assert zero.slice(0, 8)[:, 0].tolist() == [0, 0, 1, 0, 0, 0, 0, 0]
    zero.advance(20)
    assert zero.slice(20, 8)[:, 0].tolist() == [0] * 8
    with pytest.raises(IndexError):
        zero.slice(19, 2)


def _recorded(commands: dict[int, np.ndarray], t: int, nu: int, hold: bool) -> np.ndarray:
    """u(t) from every command ever given: hold, the last one at or before t; zero, the one
    at t; else zeros."""
    if not hold:
        return commands.get(t, np.zeros(nu))
    past = [j for j in commands if j <= t]
    return commands[max(past)] if past else np.zeros(nu)


@pytest.mark.parametrize("hold", [True, False])
def test_input_buffer_equals_a_plain_record_of_commands(hold: bool) -> None:
    """Random commands and window moves (by 0, 1, 2, capacity - 1, capacity, more; across
    the buffer's end, where the window moves back to row 0), and exports restored into a
    fresh buffer: every u(t) in the window is what a plain record of every command gives
    (hold: the last command at or before t, else 0; zero: the command at t, else 0)."""
    rng = np.random.default_rng(11 if hold else 12)
    for _ in range(40):
        cap, nu = int(rng.integers(1, 10)), int(rng.integers(1, 3))
        buf = InputBuffer(nu=nu, capacity=cap, hold=hold)
        commands: dict[int, np.ndarray] = {}
        origin = 0


        for _ in range(120):
            r = rng.random()
            if r < 0.5:
                free = [t for t in range(origin, origin + cap) if t not in commands]
                if free:
                    t = int(rng.choice(free))
                    commands[t] = rng.normal(size=nu)
                    buf.set(t, commands[t])
            elif r < 0.9:
                origin += int(rng.choice([0, 1, 1, 2, max(cap - 1, 0), cap, cap + 3]))
                buf.advance(origin)
            else:
                o, u0, cmds = buf.export()
                assert o == origin
                buf = InputBuffer(nu=nu, capacity=cap, hold=hold)
                buf.restore(o, u0, cmds)
            got = buf.slice(origin, cap)
            assert np.array_equal(got, np.array([_recorded(commands, t, nu, hold)
                                                 for t in range(origin, origin + cap)]))


@pytest.mark.parametrize("cls", ["ObserverPredictor", "AugmentedStateKF", "ConventionalPredictor"])
def test_every_linear_estimator_checks_its_sensors(cls) -> None:
    """A sensor whose H does not fit the model is refused by name, by every estimator."""
    import pd_service.estimation as est
    import pd_service.research as research

    x0, P0 = paper_prior()
    bad = Sensor("lidar", np.ones((1, 3)), np.eye(1))
    arg = bad if cls == "ConventionalPredictor" else [bad]
    with pytest.raises(ValueError, match="sensor 'lidar' H: expected 4 columns"):
        module = est if cls == "ObserverPredictor" else research
        getattr(module, cls)(paper_model(), arg, x0, P0, lead=1, max_delay=1)


def test_a_command_moved_inside_its_step_or_withdrawn_at_the_origin_keeps_the_record_exact() -> None:
    """An echo moves a command to another instant of the same step (supersede with an
    offset) or takes it back at the window's origin: u(t) and the cuts are what a buffer
    given only the final commands holds (u_before at the origin)."""
    buf, ref = InputBuffer(nu=1, capacity=8, hold=True), InputBuffer(nu=1, capacity=8, hold=True)
    buf.set(2, np.array([1.0]), 0.01)
    buf.set(4, np.array([2.0]), 0.02)
    buf.replace(4, np.array([2.0]), 0.035)  # moved inside its step
    buf.replace(2, np.array([1.0]))  # moved to its step's start: no cut left
    ref.set(2, np.array([1.0]))
    ref.set(4, np.array([2.0]), 0.035)
    assert buf.cut_offsets == ref.cut_offsets == {4: 0.035} and buf.cuts(0, 7) == ref.cuts(0, 7)
    buf.advance(2)
    ref.advance(2)
    buf.remove(2)  # at the origin: u(2..3) falls back to u(1), the zeros before it
    assert np.array_equal(buf.slice(2, 2), np.zeros((2, 1)))
    buf.remove(4)
    assert buf.cut_offsets == {} and buf.cuts(2, 9) is None
    assert np.array_equal(buf.slice(2, 8), np.zeros((8, 1)))
