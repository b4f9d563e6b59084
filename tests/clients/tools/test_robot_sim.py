"""The simulated robot on the in-memory bus, and the whole chain sim -> link -> service ->
recorder with the MiniDaemon standing in for the service, driven step by step."""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import numpy as np
import pytest

from pd_client import Measurement, Operator, Truth
from pd_client.tools.pd_record import Recorder
from pd_client.tools.pd_robot_sim import RobotSim
from pd_client.tools.record_csv import summarize
from pd_service.scenarios import ScenarioSim, get_scenario
from pd_service.wire import Command, decode, encode, keys

from ..conftest import EPOCH_NS, Collector, MemLink
from ..mini_daemon import MiniDaemon


def test_tick_publishes_truth_and_stamped_samples_per_session(bus):
    sc = get_scenario("paper")
    specs = [sc.spec("full", EPOCH_NS), sc.spec("cam", EPOCH_NS, sensors=["camera"])]
    sink = Collector(bus, "robot/**")
    sim = RobotSim(bus.transport(), sc, specs, seed=1)
    for k in range(4):
        sim.tick(k)
    by_key = defaultdict(list)
    for s in sink.samples:
        by_key[s.key].append(s.payload)
    truth = [decode(p, Truth) for p in by_key[keys.truth_key("full")]]
    assert [t.step for t in truth] == [0, 1, 2, 3] and truth[0].names == ["p1", "v1", "p2", "v2"]
    np.testing.assert_array_equal(truth[0].x, sc.x0_true)
    cam_truth = [decode(p, Truth) for p in by_key[keys.truth_key("cam")]]
    assert [(t.step, t.x.tolist()) for t in cam_truth] == [(t.step, t.x.tolist()) for t in truth]
    cams = [decode(p, Measurement) for p in by_key[keys.robot_sensor_key("full", "camera")]]
    assert [(m.step, m.seq) for m in cams] == [(0, 0), (2, 1)]  # every 2 steps
    assert keys.robot_sensor_key("cam", "ranger") not in by_key  # the camera-only session
    assert [decode(p, Measurement).step for p in by_key[keys.robot_sensor_key("cam", "camera")]] == [0, 2]
    with pytest.raises(ValueError, match="expected step 4"):
        sim.tick(6)
    sim.close()


def test_camera_frames_film_the_true_pose_at_their_capture_step(bus):
    """--camera 3 on the omni robot: a frame every 3 steps on the robot side, stamped with
    the step's time, its view centred on the true position then, the robot drawn there."""
    import io

    from PIL import Image

    from pd_service.wire.camera import CameraFrame

    sc = get_scenario("omni")
    spec = sc.spec("o", EPOCH_NS)
    sink = Collector(bus, "robot/**")
    sim = RobotSim(bus.transport(), sc, [spec], seed=1, camera_every=3)
    for k in range(7):
        sim.tick(k)
    sim.close()
    truth = {t.step: t for t in (decode(s.payload, Truth) for s in sink.samples
                                 if s.key == keys.truth_key("o"))}
    frames = [decode(s.payload, CameraFrame) for s in sink.samples
              if s.key == keys.robot_camera_key("o")]
    assert [f.t_ns for f in frames] == [spec.time_of(k) for k in (0, 3, 6)]
    for f, k in zip(frames, (0, 3, 6), strict=True):
        assert (f.center_x, f.center_y) == (truth[k].x[0], truth[k].x[1])
        img = Image.open(io.BytesIO(f.image()))
        assert img.size == (f.width, f.height) and img.format == "JPEG"
        # the robot's body (light) at the centre, the background (dark) in a corner
        assert sum(img.getpixel((f.width // 2, f.height // 2))) > 500
        assert sum(img.getpixel((2, 2))) < 200
    with pytest.raises(ValueError, match="planar"):
        RobotSim(bus.transport(), get_scenario("paper"), [get_scenario("paper").spec("p", 0)],
                 camera_every=2)


def test_sessions_must_share_a_clock_and_fit_the_scenario(bus):
    sc = get_scenario("paper")
    with pytest.raises(ValueError, match="clock"):
        RobotSim(bus.transport(), sc, [sc.spec("a", EPOCH_NS), sc.spec("b", EPOCH_NS + 1)])
    with pytest.raises(ValueError, match="model"):
        RobotSim(bus.transport(), sc, [get_scenario("maneuver").spec("a", EPOCH_NS)])


def test_commands_apply_at_their_step_and_late_ones_on_arrival(bus):
    sc = get_scenario("paper")
    spec = sc.spec("s1", EPOCH_NS)
    sim = RobotSim(bus.transport(), sc, [spec], seed=2)
    uplink = bus.transport()

    def send(seq, step, u):
        uplink.put(keys.robot_command_key("s1"),
                   encode(Command(session="s1", seq=seq, step=step, u=np.array([u]))))

    ref = ScenarioSim(sc, seed=2)
    ref.sample()
    sim.tick(0)
    send(0, 3, 1.0)  # ahead of time: applies at step 3
    us = []
    for k in range(1, 8):
        if k == 6:
            send(1, 4, -1.0)  # late: stamped 4, arrives during step 6 -> applies from 6
        sim.tick(k)
        us.append(sim.last_u[0])
    assert us == [0.0, 0.0, 0.0, 1.0, 1.0, -1.0, -1.0]  # u(0..6)
    for u in us:
        ref.advance([u])
        ref.sample()
    np.testing.assert_array_equal(sim.sim.x, ref.x)
    assert sim.schedule.late == 1
    sim.close()


def run_chain(bus, tmp_path, sc, specs, steps, seed):
    """Drive sim -> link (each sensor's nominal delay, uplink = lead) -> MiniDaemon ->
    recorder, one step at a time, with the scripted operator's commands."""
    daemon = MiniDaemon(bus.transport())
    setup = bus.transport()
    for spec in specs:
        setup.put(keys.config_key(spec.session), encode(spec))
    link = MemLink(bus, {s.name: s.delay for s in sc.sensors}, uplink=sc.lead)
    sim = RobotSim(bus.transport(), sc, specs, seed=seed)
    ops = [Operator(bus.transport(), s.session, spec=s) for s in specs]
    rec = Recorder(bus.transport(), [s.session for s in specs], tmp_path)
    for k in range(steps + 1):
        daemon.now = link.now = k
        sim.tick(k)
        link.release(k)
        for op in ops:
            op.send(sc.command(k + sc.lead), step=k + sc.lead)
        daemon.tick()
        rec.poll()
    rec.close()
    sim.close()
    assert not daemon.errors
    return sim


def test_chain_sim_link_service_recorder(bus, tmp_path):
    """The paper's scenario with its delays (camera 10, ranger 12, uplink 10), two sessions
    (with the range finder and camera only), the operator's commands, the MiniDaemon, and
    the recorder's CSV and summary."""
    sc = get_scenario("paper")
    steps, seed = 240, 4
    specs = [sc.spec("full", EPOCH_NS), sc.spec("cam", EPOCH_NS, sensors=["camera"])]
    sim = run_chain(bus, tmp_path, sc, specs, steps, seed)

    # The robot applied each command exactly at its apply step: the truth equals an offline
    # run with u(k) = command(k) from step lead on (no command reaches it earlier).
    ref = ScenarioSim(sc, seed=seed)
    for k in range(steps):
        ref.sample()
        ref.advance(sc.command(k) if k >= sc.lead else np.zeros(1))
    np.testing.assert_array_equal(sim.sim.x, ref.x)
    assert sim.schedule.late == 0 and sim.schedule.stale == 0

    full, cam = summarize(tmp_path / "full.csv"), summarize(tmp_path / "cam.csv")
    assert full["states"] == ["p1", "v1", "p2", "v2"]
    assert full["rows"] == steps + 1 - 40 - 0  # target steps 40..240 have truth
    assert full["first_step"] == 40 and full["last_step"] == steps
    # Accuracy in the paper's range (its Figs. 7-8: errors of a few tenths, variance of
    # p2 about 0.06 with the camera only, about 0.02 once the range finder reports) ...
    for s in (full, cam):
        assert s["rms_p1"] < 0.5 and s["rms_p2"] < 0.5
        assert 0.005 < s["mean_var_p2"] < 0.2
        assert s["within_3sigma"] > 0.95  # errors consistent with the predicted covariance
    # ... and the range finder lowers the predicted variance of both positions.
    assert full["mean_var_p1"] < cam["mean_var_p1"]
    assert full["mean_var_p2"] < cam["mean_var_p2"]


def test_chain_maneuvering_robot(bus, tmp_path):
    """The 2-D robot's legs and turns are tracked by the linear constant-velocity model."""
    sc = get_scenario("maneuver")
    run_chain(bus, tmp_path, sc, [sc.spec("rover", EPOCH_NS)], steps=400, seed=9)
    s = summarize(tmp_path / "rover.csv")
    assert s["states"] == ["px", "py", "vx", "vy"] and s["rows"] == 400 + 1 - 40
    assert s["rms_px"] < 0.1 and s["rms_py"] < 0.1  # m, over turns of 90-180 degrees
    assert s["rms_vx"] < 0.05 and s["rms_vy"] < 0.05  # m/s
    assert s["within_3sigma"] > 0.95


def test_async_scenario_publishes_samples_at_their_true_time_after_their_delay(bus):
    """--scenario async: each sample stamped t_ns = its true sample time (full resolution,
    off the grid), published at the first step at or after that time plus its delay."""
    from pd_service.scenarios import simulate_async

    sc = get_scenario("async")
    spec = sc.spec("bot", EPOCH_NS)
    sink = Collector(bus, "robot/**")
    sim = RobotSim(bus.transport(), sc, [spec], seed=4)
    for k in range(21):
        sim.tick(k)  # no commands: u = 0 throughout
    ref = simulate_async(dataclasses.replace(sc, command=lambda k: np.zeros(2)), 20, seed=4)
    T = sc.period_s
    sent = {}
    for s in sink.samples:
        if "/sensor/" in s.key:
            m = decode(s.payload, Measurement)
            assert m.step is None
            sent[(m.sensor, m.t_ns)] = m.z
    expect = {(d.sensor, EPOCH_NS + round(d.t_s / T * spec.period_ns)): d.z
              for d in ref.samples if d.arrival_s <= 20 * T + 1e-12}
    assert sent.keys() == expect.keys()
    assert all(np.array_equal(sent[key], expect[key]) for key in expect)
    assert sum(1 for (_, t) in sent if (t - EPOCH_NS) % spec.period_ns) > 0.95 * len(sent)
    assert any(d.sensor == "pose" and d.arrival_s > 20 * T for d in ref.samples)  # held back
    sim.close()
