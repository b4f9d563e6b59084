"""Robot: measurements stamped with their sample time, commands received, CommandSchedule."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from pd_client import Command, InvalidMessage, Measurement, Robot, Timeout, Truth
from pd_client.robot import CommandSchedule
from pd_service.wire import decode, encode, keys

from .conftest import EPOCH_NS, Collector


def test_publish_stamps_step_and_counts_seq_per_sensor(bus):
    sink = Collector(bus, keys.ROBOT_ALL_SENSORS)
    with Robot(bus.transport(), "s1") as robot:
        robot.publish("camera", [1.0, 5.0], step=4)
        robot.publish("camera", np.array([1.1, 5.1]), step=6)
        robot.publish("ranger", 3.9, step=6)
    msgs = [(s.key, decode(s.payload, Measurement)) for s in sink.samples]
    assert [k for k, _ in msgs] == [keys.robot_sensor_key("s1", "camera")] * 2 + [
        keys.robot_sensor_key("s1", "ranger")]
    assert [(m.sensor, m.seq, m.step, m.t_ns) for _, m in msgs] == [
        ("camera", 0, 4, None), ("camera", 1, 6, None), ("ranger", 0, 6, None)]
    np.testing.assert_array_equal(msgs[2][1].z, [3.9])


def test_publish_with_t_ns_and_own_R(bus):
    sink = Collector(bus, keys.ROBOT_ALL_SENSORS)
    with Robot(bus.transport(), "s1") as robot:
        m = robot.publish("camera", [1.0, 2.0], t_ns=EPOCH_NS + 123, R=[[0.1, 0], [0, 0.2]])
    got = decode(sink.payloads()[0], Measurement)
    assert got == m and got.t_ns == EPOCH_NS + 123 and got.step is None
    np.testing.assert_array_equal(got.R, [[0.1, 0], [0, 0.2]])


def test_direct_mode_uses_service_keys(bus):
    sink = Collector(bus, keys.sensors_of("s1"))
    with Robot(bus.transport(), "s1", direct=True) as robot:
        robot.publish("camera", [1.0, 2.0], step=0)
    assert [s.key for s in sink.samples] == [keys.sensor_key("s1", "camera")]


@pytest.mark.parametrize("kwargs, needle", [
    ({"step": 1, "t_ns": 5}, "exactly one of step / t_ns"),
    ({}, "exactly one of step / t_ns"),
    ({"step": -1}, "step"),
    ({"step": 1, "R": [[1.0, 2.0], [3.0, 4.0]]}, "symmetric"),
])
def test_bad_measurement_is_refused_and_not_sent(bus, kwargs, needle):
    sink = Collector(bus, "robot/**")
    with Robot(bus.transport(), "s1") as robot:
        with pytest.raises(InvalidMessage, match=needle):
            robot.publish("camera", [1.0, 2.0], **kwargs)
        with pytest.raises(InvalidMessage, match="finite"):
            robot.publish("camera", [np.nan, 2.0], step=1)
        with pytest.raises(InvalidMessage, match="sensor"):
            robot.publish("Bad Name", [1.0], step=1)
        with pytest.raises(ValueError):  # InvalidMessage is a ValueError
            robot.publish("camera", [[1.0]], step=1)
        assert robot.published == 0
    assert sink.samples == []


def test_spec_checks_sensor_and_dimension(bus, spec):
    with Robot(bus.transport(), "s1", spec=spec) as robot:
        with pytest.raises(InvalidMessage, match="unknown sensor 'lidar'"):
            robot.publish("lidar", [1.0], step=0)
        with pytest.raises(InvalidMessage, match="expected 2 values"):
            robot.publish("camera", [1.0, 2.0, 3.0], step=0)
        robot.publish("camera", [1.0, 2.0], step=0)
    with pytest.raises(InvalidMessage, match="session"):
        Robot(bus.transport(), "other", spec=spec)
    with pytest.raises(InvalidMessage, match="session"):
        Robot(bus.transport(), "Not Valid")


def test_a_stamp_before_the_epoch_is_refused_unless_the_robot_clock_is_estimated(bus, spec):
    """A robot clock 10 s behind the daemon's stamps the session's first seconds before its
    epoch: the daemon maps them (spec robot_clock "estimated"); with a shared clock they are
    refused as before."""
    from pd_service.wire import SessionSpec

    sink = Collector(bus, keys.robot_sensor_key("s1", "camera"))
    with Robot(bus.transport(), "s1", spec=spec) as robot:
        with pytest.raises(InvalidMessage, match="before the session epoch"):
            robot.publish("camera", [1.0, 2.0], t_ns=EPOCH_NS - 10 * 10**9)
    own = SessionSpec.model_validate({**spec.model_dump(), "robot_clock": "estimated"})
    with Robot(bus.transport(), "s1", spec=own) as robot:
        robot.publish("camera", [1.0, 2.0], t_ns=EPOCH_NS - 10 * 10**9)
        with pytest.raises(InvalidMessage, match="expected 2 values"):  # the rest still checked
            robot.publish("camera", [1.0], t_ns=EPOCH_NS - 10 * 10**9)
    (m,) = [decode(p, Measurement) for p in sink.payloads()]
    assert m.t_ns == EPOCH_NS - 10 * 10**9


def test_truth_gets_time_from_spec(bus, spec):
    sink = Collector(bus, keys.truth_key("s1"))
    with Robot(bus.transport(), "s1", spec=spec) as robot:
        robot.publish_truth(3, [0.0, 1.0, 2.0, 3.0], names=["p1", "v1", "p2", "v2"])
        with pytest.raises(InvalidMessage):
            Robot(bus.transport(), "s1").publish_truth(3, [0.0])
    t = decode(sink.payloads()[0], Truth)
    assert t.step == 3 and t.t_ns == spec.time_of(3) and t.names == ["p1", "v1", "p2", "v2"]


def _cmd(seq, step=None, issued_ns=None, u=(0.5,), session="s1"):
    return encode(Command(session=session, seq=seq, step=step, issued_ns=issued_ns,
                          u=np.array(u)))


def test_commands_callback_iterator_and_timeout(bus):
    op_side = bus.transport()
    seen = []
    with Robot(bus.transport(), "s1") as robot:
        robot.on_command(seen.append)
        op_side.put(keys.robot_command_key("s1"), _cmd(0, step=10))
        op_side.put(keys.robot_command_key("s1"), _cmd(1, step=11, u=(0.0,)))
        op_side.put(keys.command_key("s1"), _cmd(2, step=12))  # operator side: not for robot
        assert [c.seq for c in seen] == [0, 1]
        assert robot.next_command(timeout=0).seq == 0
        assert [c.seq for c in robot.commands(timeout=0.01)] == [1]
        with pytest.raises(Timeout):
            robot.next_command(timeout=0.01)
        assert robot.commands_received == 2


def test_invalid_commands_are_counted_not_raised(bus):
    op_side = bus.transport()
    with Robot(bus.transport(), "s1") as robot:
        op_side.put(keys.robot_command_key("s1"), b"\x00garbage")
        op_side.put(keys.robot_command_key("s1"), _cmd(0, step=1, session="s2"))
        assert robot.commands_invalid == 2 and robot.pending_commands() == []


def test_iterator_ends_when_robot_closes(bus):
    robot = Robot(bus.transport(), "s1")
    out = []
    th = threading.Thread(target=lambda: out.extend(robot.commands()))
    th.start()
    robot.close()
    th.join(5)
    assert not th.is_alive() and out == []


def test_apply_step_of_issued_ns_needs_spec(bus, spec):
    cmd = decode(_cmd(0, issued_ns=spec.time_of(7) + 1), Command)
    with Robot(bus.transport(), "s1", spec=spec) as robot:
        assert robot.apply_step(cmd) == 7 + spec.lead
    with Robot(bus.transport(), "s1") as robot:
        with pytest.raises(InvalidMessage):
            robot.apply_step(cmd)
        assert robot.apply_step(decode(_cmd(0, step=4), Command)) == 4


def test_command_schedule_holds_last_command():
    s = CommandSchedule(1)
    np.testing.assert_array_equal(s.u_at(0), [0.0])  # zeros before any command
    s.add(10, [0.5])
    s.add(20, [0.0])
    assert [s.u_at(k)[0] for k in (9, 10, 15, 19, 20, 30)] == [0, 0.5, 0.5, 0.5, 0.0, 0.0]


def test_command_schedule_late_and_stale():
    s = CommandSchedule(1)
    s.add(5, [1.0])
    assert s.u_at(8)[0] == 1.0
    s.add(7, [2.0])  # arrived after its apply step 7 (now 8): applies on arrival
    assert s.late == 1 and s.u_at(9)[0] == 2.0
    s.add(6, [3.0])  # older than the command in force (7): never applies
    assert s.stale == 1 and s.u_at(10)[0] == 2.0
    s.add(12, [4.0])
    s.add(12, [5.0])  # same step again: the later one replaces it
    assert s.u_at(12)[0] == 5.0
    with pytest.raises(ValueError):
        s.add(13, [1.0, 2.0])


def test_connect_classmethod_owns_its_transport(bus, monkeypatch):
    import pd_client._base as base

    opened = []

    def fake_connect(endpoint, mode):
        opened.append((endpoint, mode))
        return bus.transport()

    monkeypatch.setattr(base, "connect", fake_connect)
    with Robot.connect("s1", endpoint="tcp/127.0.0.1:1", mode="peer") as robot:
        assert robot.session == "s1" and not robot.transport._closed
    assert opened == [("tcp/127.0.0.1:1", "peer")] and robot.transport._closed
    shared = bus.transport()
    Robot(shared, "s1").close()
    assert not shared._closed  # a shared transport stays open


def test_robot_and_operator_keep_their_last_samples_for_a_restarted_service(bus):
    from pd_client import Operator
    t = bus.transport()
    with Robot(t, "s1", direct=True, cache=2) as robot, Operator(t, "s1", cache=3) as op:
        for k in range(4):
            robot.publish("camera", [1.0, float(k)], step=k)
            op.send([float(k)], step=k + 10)
        got: list = []
        bus.transport().read_back(keys.ALL_SENSORS, got.append, max_samples=100)
        assert [decode(s.payload, Measurement).step for s in got] == [2, 3]
        got.clear()
        bus.transport().read_back(keys.ALL_COMMANDS, got.append, max_samples=100)
        assert [decode(s.payload, Command).step for s in got] == [11, 12, 13]
    got.clear()  # closed with the clients: nothing kept
    bus.transport().read_back("pd/**", got.append, max_samples=100)
    assert got == []
    with Robot(t, "s2", direct=True, cache=0) as robot:  # cache=0: plain publishers
        robot.publish("camera", [1.0, 2.0], step=1)
        bus.transport().read_back(keys.ALL_SENSORS, got.append, max_samples=100)
        assert got == []


def test_caches_are_present_before_the_first_sample(bus):
    """A restarted or taking-over service waits for the cache of each sensor of the spec
    and of the commands: with the spec (direct), the Robot's caches answer, empty, before
    a sensor sent anything (the paper's ranger is silent while out of range), and so does
    the Operator's."""
    from pd_client import Operator
    from pd_service.scenarios.paper import paper_scenario
    spec = paper_scenario().spec("s1", EPOCH_NS)
    answered: list[str] = []
    t = bus.transport()
    with Robot(t, "s1", spec=spec, direct=True), Operator(t, "s1"):
        bus.transport().read_back("pd/**", lambda s: None, max_samples=10,
                                  answered=answered.append)
    assert sorted(answered) == sorted([keys.command_key("s1")] + [
        keys.sensor_key("s1", x.name) for x in spec.sensors])
    answered.clear()
    with Robot(t, "s2", spec=spec.model_copy(update={"session": "s2"})), \
            Robot(t, "s3", direct=True), Operator(t, "s3", cache=0):
        bus.transport().read_back("pd/**", lambda s: None, max_samples=10,
                                  answered=answered.append)
    assert answered == []  # through the link, without the spec, or without a cache: none


# --- echoes and probes -------------------------------------------------------------------

class _StepClock:
    """A robot clock 10 s ahead of the bus' time that advances 5 µs per read."""

    def __init__(self) -> None:
        self.t = 10_000_000_000 + EPOCH_NS

    def __call__(self) -> int:
        self.t += 5_000
        return self.t


def test_a_robot_applying_on_arrival_echoes_each_command_on_its_own_clock(bus):
    from pd_service.wire import CommandEcho

    sink = Collector(bus, keys.robot_echo_key("s1"))
    clock = _StepClock()
    with Robot(bus.transport(), "s1", clock=clock, apply_on_arrival=True) as robot:
        t = bus.transport()
        for seq in (3, 4):
            t.put(keys.robot_command_key("s1"),
                  encode(Command(session="s1", seq=seq, step=7, u=np.array([0.5]))))
        assert robot.echoes == 2
    echoes = [decode(p, CommandEcho) for p in sink.payloads()]
    assert [e.seq for e in echoes] == [3, 4]
    first = 10_000_000_000 + EPOCH_NS + 5_000  # the first read: the first command's arrival
    assert echoes[0].applied_ns == first and echoes[0].sent_ns is not None
    assert echoes[0].sent_ns > echoes[0].applied_ns and echoes[1].applied_ns > echoes[0].sent_ns


def test_a_robot_answers_probes_with_its_clock_and_refuses_bad_ones(bus):
    from pd_service.wire import ClockProbe, ClockProbeReply

    clock = _StepClock()
    with Robot(bus.transport(), "s1", clock=clock) as robot:
        t = bus.transport()
        (r,) = t.get(keys.robot_clock_key("s1"),
                     payload=encode(ClockProbe(session="s1", probe=9, t1_ns=123)))
        assert r.ok
        reply = decode(r.payload, ClockProbeReply)
        assert (reply.probe, reply.t1_ns) == (9, 123)
        assert reply.t2_ns == 10_000_000_000 + EPOCH_NS + 5_000 and reply.t3_ns > reply.t2_ns
        (bad,) = t.get(keys.robot_clock_key("s1"), payload=b"\x00garbage")
        (other,) = t.get(keys.robot_clock_key("s1"),
                         payload=encode(ClockProbe(session="s2", probe=1, t1_ns=1)))
        assert not bad.ok and not other.ok
        assert (robot.probes_answered, robot.probes_invalid) == (1, 2)
