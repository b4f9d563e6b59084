"""Dispatch: a message is judged late or on time at the earliest it may have arrived, not at
the time a busy or stalled worker took it (pd_service.intake.judged_step); one late at its
arrival is still refused, one stamped after the current step still "future"."""

from __future__ import annotations

import time

import numpy as np

from pd_service.backends import build
from pd_service.transport import InMemoryBus, Sample
from pd_service.wire import Command, Measurement, encode, keys

from .helpers import PERIOD_NS, Clock, Collector, cmd_bytes, meas_bytes, paper_spec
from .test_core import make_core

#: The paper's ranger arrives 12 steps after it is sampled; a window of 16 leaves it 4.
WINDOW = 16


def _fed(tmp_path, steps: int):
    """One core serving s1 (window WINDOW), fed ``steps`` steps as a robot and an operator
    would (each step's inputs handled when they come, then the step's tick), mirrored on an
    offline estimator fed each input at its send step."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    core = make_core(bus, clock, tmp_path)
    spec = paper_spec("s1", max_delay=WINDOW)
    cli.put(keys.config_key("s1"), encode(spec))
    core.run_once()
    ref = build(spec).est
    rng = np.random.default_rng(5)

    def put(k: int) -> None:
        """Step k's command (for k + lead), ranger sample of k - 12, camera sample of k - 10,
        in that order, sent at (k + 0.1) periods."""
        clock.t = int((k + 0.1) * PERIOD_NS)
        u, zr, zc = rng.standard_normal(1), rng.standard_normal(1) + 5, rng.standard_normal(2)
        cli.put(keys.command_key("s1"), cmd_bytes("s1", k + spec.lead, u, seq=k))
        ref.add_command(k + spec.lead, u, now=k)
        if k >= 12:
            cli.put(keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", k - 12, zr, k))
            ref.add_measurement("ranger", k - 12, zr, now=k)
        if k >= 10:
            cli.put(keys.sensor_key("s1", "camera"), meas_bytes("s1", "camera", k - 10, zc, k))
            ref.add_measurement("camera", k - 10, zc, now=k)

    for k in range(steps):
        put(k)
        core.run_once()
        clock.t = int((k + 0.6) * PERIOD_NS)
        core.run_once()
    return core, clock, col, cli, ref, put


def _exact(col, ref, k: int) -> None:
    pred = col.predictions["s1"][-1]
    want = ref.predict(k)
    assert pred.step == want.step
    np.testing.assert_allclose(pred.x, want.x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(pred.P, want.P, rtol=1e-9, atol=1e-9)


def test_inputs_that_waited_for_a_stalled_worker_are_judged_at_their_arrival(tmp_path):
    """Step 30's inputs arrive on time (the ranger 12 steps late, inside the window of 16),
    but the worker gets to them only 5.5 steps later (it stalled): they are judged at their
    arrival, accepted, and the estimate stays that of the estimator that got each input at
    its send step."""
    core, clock, col, _, ref, put = _fed(tmp_path, 30)
    put(30)  # arrives at 30.1 ...
    clock.t = int(35.6 * PERIOD_NS)  # ... taken at 35.6: at step 35 the ranger of 18 is late
    core.run_once()
    c = core.counters
    assert c["late"] == 0 and c["refused"] == 0
    assert c["accepted"] == 2 * 30 - 12 - 10 + 2 and c["commands_accepted"] == 31
    _exact(col, ref, 35)


def test_an_input_late_at_its_arrival_is_still_refused_and_a_future_one_too(tmp_path):
    """Judged at its arrival: a ranger sample older than the window then is late, one stamped
    after the step the worker took it at is "future"; a sample stamped between its arrival
    and that step is accepted (it may have been sent just before it was taken)."""
    core, clock, col, cli, ref, _ = _fed(tmp_path, 30)
    clock.t = int(30.1 * PERIOD_NS)
    ranger = keys.sensor_key("s1", "ranger")
    cli.put(ranger, meas_bytes("s1", "ranger", 30 - WINDOW - 1, [5.0], 100))  # late at 30
    cli.put(ranger, meas_bytes("s1", "ranger", 36, [5.0], 101))  # future at 35 as at 30
    cli.put(ranger, meas_bytes("s1", "ranger", 33, [5.0], 102))  # after 30, before 35
    clock.t = int(35.6 * PERIOD_NS)
    core.run_once()
    c = core.counters
    assert c["late"] == 1 and c["future"] == 1 and c["refused"] == 2
    assert c["accepted"] == 2 * 30 - 12 - 10 + 1


def test_a_drained_sample_is_judged_at_the_previous_look_at_its_queue(tmp_path):
    """Over Zenoh the worker takes samples from queues: one that waited there while the
    worker was busy carries the time of the previous look at the queue (``recv_mono_ns``,
    the monotonic clock), before which it was not there; it is judged at that time. A look
    within LOOK_SLACK_NS is the hand-off itself: judged when handed over."""
    core, clock, col, _, ref, _ = _fed(tmp_path, 30)
    d = core.dispatch
    rng = np.random.default_rng(9)
    u, zr, zc = rng.standard_normal(1), rng.standard_normal(1) + 5, rng.standard_normal(2)
    clock.t = int(35.6 * PERIOD_NS)  # taken at 35.6 ...
    looked = time.monotonic_ns() - int(5.5 * PERIOD_NS)  # ... the queue last looked at 30.1
    for key, payload in ((keys.command_key("s1"), cmd_bytes("s1", 30 + 10, u, seq=30)),
                         (keys.sensor_key("s1", "ranger"), meas_bytes("s1", "ranger", 18, zr)),
                         (keys.sensor_key("s1", "camera"), meas_bytes("s1", "camera", 20, zc))):
        on = d.on_command_sample if key.endswith("/cmd") else d.on_sensor_sample
        on(Sample(key, payload, "put", clock.t, looked))
    ref.add_command(40, u, now=30)
    ref.add_measurement("ranger", 18, zr, now=30)
    ref.add_measurement("camera", 20, zc, now=30)
    core.run_once()
    c = core.counters
    assert c["late"] == 0 and c["refused"] == 0
    _exact(col, ref, 35)
    # looked at just now: judged at the hand-over, where 19 is older than the window of 36
    clock.t = int(36.6 * PERIOD_NS)
    d.on_sensor_sample(Sample(keys.sensor_key("s1", "ranger"),
                              meas_bytes("s1", "ranger", 19, [5.0]), "put", clock.t,
                              time.monotonic_ns()))
    core.run_once()
    assert c["late"] == 1


def test_a_read_back_is_handled_in_slices(tmp_path):
    """A read-back of many messages (a heal or a takeover of many sessions) is handled
    READ_BACK_SLICE at a time, one slice per loop of run_once (its ticks between them), in
    order; nothing is lost."""
    from pd_service.service.dispatch import READ_BACK_SLICE

    core, clock, col, _, ref, _ = _fed(tmp_path, 30)
    d = core.dispatch
    clock.t = int(30.1 * PERIOD_NS)
    rng = np.random.default_rng(2)
    n = READ_BACK_SLICE + 100
    camera = keys.sensor_key("s1", "camera")
    for i in range(n):  # sample steps 15..29 at offsets inside the step: all new
        payload = encode(Measurement(session="s1", sensor="camera", seq=1000 + i, step=None,
                                     t_ns=int((15 + i % 15 + (1 + i // 15) * 0.01) * PERIOD_NS),
                                     z=rng.standard_normal(2)))
        d.on_read_back_sensor(Sample(camera, payload, "put", clock.t, time.monotonic_ns(),
                                     recovered=True))
    touched: list = []
    assert d.process_read_back(clock.t, touched) == READ_BACK_SLICE
    assert len(d.read_back) == n - READ_BACK_SLICE and core.has_work()
    core.run_once()
    assert not d.read_back
    c = core.counters
    assert c["recovered_accepted"] + c["recovered_refused"] == n


def test_the_stamp_of_a_held_input_is_read_without_decoding_it():
    """stamp_step reads a message's stamp from its msgpack map: the sample step, else the
    step of t_ns; a command's apply step - lead, else the step of issued_ns; anything
    unreadable: the default."""
    from pd_service.service.dispatch import stamp_step
    from pd_service.service.session import COMMAND, READ_BACK, SENSOR

    spec = paper_spec("s1", max_delay=WINDOW)

    def item(stream, payload):
        return (stream, "k", payload, 0, "put", 0, 0)

    t = int(17.3 * PERIOD_NS)
    assert stamp_step(spec, item(SENSOR, meas_bytes("s1", "ranger", 12, [1.0])), -1) == 12
    m = encode(Measurement(session="s1", sensor="ranger", seq=0, step=None, t_ns=t,
                           z=np.array([1.0])))
    assert stamp_step(spec, item(SENSOR + READ_BACK, m), -1) == spec.sample_at(t)[0] == 17
    assert stamp_step(spec, item(COMMAND, cmd_bytes("s1", 30, [0.5])), -1) == 30 - spec.lead
    c = encode(Command(session="s1", seq=0, step=None, issued_ns=t, u=np.array([0.5])))
    assert stamp_step(spec, item(COMMAND + READ_BACK, c), -1) == 17
    for bad in (b"", b"\xc1", b"\x93\x01\x02\x03", meas_bytes("s1", "ranger", 12, [1.0])[:-3]):
        assert stamp_step(spec, item(SENSOR, bad), -7) == -7
