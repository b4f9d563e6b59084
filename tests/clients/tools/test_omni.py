"""The omnidirectional robot in the simulated robot: a whole in-memory chain (sim -> link ->
MiniDaemon, with the scripted operator's torques) tracks it through the Q x100 jump."""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
import pytest

from pd_client import Admin, Operator, Prediction, Truth
from pd_client.tools import pd_operator, pd_robot_sim
from pd_service.estimation.nonlinear import wrap_angle
from pd_service.estimation.nonlinear.models_omni import OMNI_Q0
from pd_service.scenarios import ScenarioSim, get_scenario
from pd_service.scenarios.omni import omni_torque
from pd_service.wire import Command, decode, encode, keys

from ..conftest import EPOCH_NS, Collector, MemLink
from ..mini_daemon import MiniDaemon


def test_omni_chain_tracks_the_truth_and_adapts_q(bus):
    """13 s of the scenario (the jump at 10 s): the robot applies each torque at its apply
    step, the daemon's adaptive UKF predicts x(now + lead) within millimetres of the truth
    while the robot travels metres, and its q of (vx, vy) rises towards 100 Q0 after the
    jump."""
    sc = get_scenario("omni")
    steps, seed, name = 1300, 8, "omni"
    spec = sc.spec(name, EPOCH_NS)
    daemon = MiniDaemon(bus.transport())
    bus.transport().put(keys.config_key(name), encode(spec))
    assert name in daemon.sessions and not daemon.errors
    link = MemLink(bus, {s.name: s.delay for s in sc.sensors}, uplink=sc.lead)
    preds = Collector(bus, keys.prediction_key(name))
    truths = Collector(bus, keys.truth_key(name))
    robot = pd_robot_sim.RobotSim(bus.transport(), sc, [spec], seed=seed)
    op = Operator(bus.transport(), name, spec=spec)
    true_x = []
    q_before = None
    for k in range(steps + 1):
        daemon.now = link.now = k
        true_x.append(robot.tick(k).copy())
        link.release(k)
        op.send(sc.command(k + sc.lead), step=k + sc.lead)
        daemon.tick()
        if k == 990:
            q_before = daemon.sessions[name].est.q.copy()
    robot.close()
    op.close()
    assert not daemon.errors
    assert robot.schedule.late == 0 and robot.schedule.stale == 0

    # The robot applied u(k) = omni_torque(k) from step lead on (nothing arrives earlier).
    ref = ScenarioSim(sc, seed=seed)
    for k in range(steps):
        ref.sample()
        ref.advance(sc.command(k) if k >= sc.lead else np.zeros(3))
    np.testing.assert_array_equal(true_x[-1], ref.x)

    # Truth is published with theta wrapped, as the estimator reports it.
    tr = [decode(p, Truth) for p in truths.payloads()]
    assert [t.step for t in tr] == list(range(steps + 1))
    assert tr[0].names == ["x", "y", "theta", "vx", "vy", "omega"]
    X = np.array(true_x)
    got = np.array([t.x for t in tr])
    np.testing.assert_allclose(got[:, 2], wrap_angle(X[:, 2]), atol=1e-12)
    np.testing.assert_array_equal(got[:, [0, 1, 3, 4, 5]], X[:, [0, 1, 3, 4, 5]])

    # Predictions of x(now + lead), once samples and commands flow (target >= 50).
    pr = [decode(p, Prediction) for p in preds.payloads()]
    assert len(pr) == steps + 1 and pr[-1].step == steps + sc.lead
    rows = [(p.step, p.x) for p in pr if 50 <= p.step <= steps]
    err = np.array([x[:2] - X[s, :2] for s, x in rows])
    dth = np.array([wrap_angle(x[2] - X[s, 2]) for s, x in rows])
    steps_of = np.array([s for s, _ in rows])
    pos_err = np.hypot(err[:, 0], err[:, 1])
    travel = float(np.sum(np.hypot(*np.diff(X[:, :2], axis=0).T)))
    assert travel > 2.0  # m
    before, after = steps_of < 1000, steps_of >= 1100  # after: once q has adapted
    rms_before = float(np.sqrt(np.mean(pos_err[before] ** 2)))
    rms_after = float(np.sqrt(np.mean(pos_err[after] ** 2)))
    # 0.1 s ahead plus the 30 ms pose delay: about 1 mm before the jump, 8 mm after (the
    # process noise over 13 steps, which no filter can predict).
    assert rms_before < 2e-3 and rms_after < 1.5e-2  # m
    assert rms_after < 1e-2 * travel
    assert np.sqrt(np.mean(dth[before] ** 2)) < 5e-3  # rad
    assert np.sqrt(np.mean(dth[after] ** 2)) < 4e-2
    # The predicted covariance matches the errors, before the jump and once q has adapted.
    sig = np.array([np.sqrt(np.diag(p.P)[:2]) for p in pr if 50 <= p.step <= steps])
    for w in (before, after):
        ratio = np.sqrt(np.mean(err[w] ** 2, axis=0) / np.mean(sig[w] ** 2, axis=0))
        assert np.all((0.5 < ratio) & (ratio < 2.0)), ratio
        assert np.mean(np.abs(err[w]) <= 3 * sig[w]) > 0.95

    # MIT adaptation runs in the daemon: q of (vx, vy) near Q0 before the jump, ~100 Q0 after.
    q_after = daemon.sessions[name].est.q
    assert q_before is not None
    assert np.all(q_before[:2] < 5 * np.array(OMNI_Q0[3:5]))
    assert np.all(q_after[:2] > 20 * np.array(OMNI_Q0[3:5]))
    daemon.close()


def test_operator_tool_sends_the_torque_profile(bus):
    """``pd-operator --scenario omni`` accepts the unscented session (its command dimension
    comes from the registered model) and sends omni_torque(j) for apply step j."""
    sc = get_scenario("omni")
    # 1 ms steps starting 0.3 s from now: the tool normally starts sending from step 0 (it
    # joins later on a slow machine, which only shortens the run).
    spec = sc.spec("omni", time.time_ns() + 300_000_000, time_scale=10.0)
    cmds = Collector(bus, keys.command_key("omni"))
    steps = sc.lead + 200
    stop, result = threading.Event(), []
    with Admin(bus.transport()) as admin:
        admin.replace_session(spec, wait=False)  # serves the spec, no service needed
        args = argparse.Namespace(spec_timeout=5.0, progress=0.0)
        worker = threading.Thread(target=lambda: result.append(
            pd_operator._run(bus.transport(), sc, ["omni"], steps, args, stop)))
        worker.start()
        worker.join(30.0)
        stop.set()  # only matters if the tool hung
        worker.join(5.0)
    assert result == [0]
    got = [decode(p, Command) for p in cmds.payloads()]
    assert got and got[-1].step == steps
    for c in got:
        np.testing.assert_array_equal(c.u, omni_torque(c.step))


@pytest.mark.parametrize("parser", [pd_robot_sim.build_parser, pd_operator.build_parser])
def test_tools_accept_the_omni_scenario(parser):
    assert parser().parse_args(["--scenario", "omni"]).scenario == "omni"


def test_robot_sim_refuses_a_linear_session_for_the_omni_robot(bus):
    sc = get_scenario("omni")
    with pytest.raises(ValueError, match="model"):
        pd_robot_sim.RobotSim(bus.transport(), sc, [get_scenario("paper").spec("a", EPOCH_NS)])
