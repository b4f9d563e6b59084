"""The intake (pd_service.intake): the instant each message is applied at, on both read
paths (the C fast read where compiled, the full decode for a message with its own R); the
supersede rule: of two commands that land on one open apply step the newer (later issued_ns,
then higher seq) replaces the older; a repeat or an older one is a duplicate; a final step is
never changed."""

from __future__ import annotations

import numpy as np

from pd_service.backends import build
from pd_service.estimation import ObserverPredictor
from pd_service.intake import Intake
from pd_service.wire import encode, keys
from tests.service.helpers import cmd_bytes, cmd_now_bytes
from tests.service.helpers import paper_spec as service_paper_spec
from tests.wire.factories import PERIOD_NS, command, measurement, paper_continuous_spec, paper_spec

EPOCH = 1_700_000_000_000_000_000


def intake_of(spec) -> tuple[Intake, ObserverPredictor]:  # type: ignore[no-untyped-def]
    built = build(spec)
    assert isinstance(built.est, ObserverPredictor)
    return Intake(spec, built.est, built.nu), built.est


def test_a_continuous_spec_applies_each_sample_at_its_own_time() -> None:
    intake, est = intake_of(paper_continuous_spec(epoch_ns=EPOCH))
    k = 20
    key = "pd/p0/s1/sensor/camera"
    for i, (extra, R) in enumerate([(12_345_678, None), (40_000_001, np.eye(2))]):
        msg = measurement(step=None, t_ns=EPOCH + k * PERIOD_NS + extra, seq=i, R=R)
        assert intake.measurement(key, encode(msg), k) is None
    offsets = [p.offset for p in est._packets[k]]
    assert offsets == [0.012345678, 0.040000001]  # full resolution, fast and full paths
    # the same instant twice: a duplicate; a step stamp: the step's start
    again = measurement(step=None, t_ns=EPOCH + k * PERIOD_NS + 12_345_678, seq=5)
    refusal = intake.measurement(key, encode(again), k)
    assert refusal is not None and refusal.reason == "duplicate"
    assert intake.measurement(key, encode(measurement(step=k, seq=6)), k) is None
    assert [p.offset for p in est._packets[k]] == [0.0, 0.012345678, 0.040000001]
    # a command acts from exactly issued_ns + lead * period
    issued = EPOCH + k * PERIOD_NS + 7_000_000
    assert intake.command("pd/p0/s1/cmd", encode(command(step=None, issued_ns=issued)), k) is None
    assert est._inputs.cut_offsets == {k + est.lead: 0.007}


def test_a_discrete_spec_rounds_to_the_nearest_step_but_never_past_the_current_one() -> None:
    intake, est = intake_of(paper_spec(epoch_ns=EPOCH))
    k = 20
    key = "pd/p0/s1/sensor/camera"
    late_half = EPOCH + (k - 3) * PERIOD_NS + PERIOD_NS // 2 + 1  # nearest: step k - 2
    now_half = EPOCH + k * PERIOD_NS + PERIOD_NS // 2 + 1  # nearest: k + 1, after now
    for i, t in enumerate((late_half, now_half)):
        assert intake.measurement(key, encode(measurement(step=None, t_ns=t, seq=i)), k) is None
    assert sorted(est._packets) == [k - 2, k]
    assert all(p.offset == 0.0 for b in est._packets.values() for p in b)
    # a stamp after the current step is still refused as future
    future = EPOCH + (k + 1) * PERIOD_NS + 1
    refusal = intake.measurement(key, encode(measurement(step=None, t_ns=future, seq=9)), k)
    assert refusal is not None and refusal.reason == "future"


def test_a_nonlinear_model_on_its_own_period_gets_the_same_fraction_of_its_step() -> None:
    """A session run at another pace than its model (pd-robot-sim --time-scale): an offset
    is the same fraction of the model's step, not the same number of seconds."""
    from pd_service.scenarios import get_scenario

    scen = get_scenario("async")
    spec = scen.spec("s1", EPOCH, time_scale=2.0)  # steps of 25 ms, the model's of 50 ms
    built = build(spec)
    intake = Intake(spec, built.est, built.nu)
    model_s = built.est.period_s  # type: ignore[attr-defined]
    assert model_s == 2 * spec.period_ns / 1e9
    sensor = spec.sensors[0].name
    k = 20
    z = np.zeros(spec.sensors[0].m)
    from pd_service.wire import Measurement

    for i, frac in enumerate((0.25, 0.999999)):
        t = EPOCH + k * spec.period_ns + round(frac * spec.period_ns)
        msg = Measurement(session="s1", sensor=sensor, seq=i, t_ns=t, z=z)
        key = f"pd/p0/s1/sensor/{sensor}"
        assert intake.measurement(key, encode(msg), k) is None
    offsets = [p.offset for p in built.est._packets[k]]  # type: ignore[attr-defined]
    assert offsets[0] == 0.25 * model_s
    assert 0.999 * model_s < offsets[1] < model_s


SPEC = service_paper_spec("s1", epoch_ns=0)
P = SPEC.period_ns
KEY = keys.command_key("s1")


def make() -> Intake:
    built = build(SPEC)
    return Intake(SPEC, built.est, built.nu)


def test_a_newer_twist_on_the_same_apply_step_supersedes_the_older() -> None:
    it = make()
    now = 40
    # two Twists 10 ms apart inside one step: one apply step, the second is the newer
    assert it.command(KEY, cmd_now_bytes("s1", now * P + 1_000_000, (1.0,), seq=1), now) is None
    assert not it.superseded
    assert it.command(KEY, cmd_now_bytes("s1", now * P + 11_000_000, (2.0,), seq=2), now) is None
    assert it.superseded
    # the older one arriving again (reordered or repeated): a duplicate, not applied
    r = it.command(KEY, cmd_now_bytes("s1", now * P + 1_000_000, (1.0,), seq=1), now)
    assert r is not None and r.reason == "commands_duplicate"
    c = it.est.counters
    assert (c["commands_accepted"], c["commands_superseded"], c["commands_duplicate"]) == (1, 1, 1)
    ref = make()
    assert ref.command(KEY, cmd_now_bytes("s1", now * P + 11_000_000, (2.0,), seq=2), now) is None
    a, b = it.est.predict(now + 1), ref.est.predict(now + 1)
    np.testing.assert_array_equal(a.x, b.x)


def test_explicit_steps_supersede_by_seq_and_final_steps_never() -> None:
    it = make()
    assert it.command(KEY, cmd_bytes("s1", 45, (1.0,), seq=5), 40) is None
    r = it.command(KEY, cmd_bytes("s1", 45, (3.0,), seq=4), 40)  # lower seq: older
    assert r is not None and r.reason == "commands_duplicate"
    assert it.command(KEY, cmd_bytes("s1", 45, (3.0,), seq=6), 40) is None and it.superseded
    it.est.predict(45 + SPEC.max_delay + 5)  # step 45 final
    r = it.command(KEY, cmd_bytes("s1", 45, (4.0,), seq=7), 45 + SPEC.max_delay + 5)
    assert r is not None and r.reason == "commands_late"
    assert it.est.counters["commands_superseded"] == 1


def test_the_order_memory_is_bounded() -> None:
    it = make()
    for k in range(0, 20_000, 1):
        it.command(KEY, cmd_bytes("s1", k + 1, (0.0,), seq=k), k)
        assert len(it.command_order) <= max(64, 2 * (k - it.est.committed_step + 2))
    assert min(it.command_order) >= it.est.committed_step - 64  # final steps are forgotten


def test_a_message_that_waited_is_judged_at_the_earliest_step_it_may_have_arrived_at() -> None:
    """``first_step`` < ``now_step``: the message arrived between them (it waited for the
    worker). Judged at max(first, min(stamp, now), the estimator's newest step): a sample
    inside the window at its arrival is accepted although it is outside it now; one outside
    at its arrival is late; a stamp after now is future; a command is judged at its send
    step (apply step - lead) alike; the estimator is never taken back."""
    from pd_service.intake import judged_step

    assert judged_step(5, 8, 12, None) == 8  # older than its arrival: judged there
    assert judged_step(10, 8, 12, None) == 10  # stamped after it arrived: at its stamp
    assert judged_step(15, 8, 12, None) == 12  # after now: at now (future)
    assert judged_step(5, 8, 12, 11) == 11  # never before the estimator's newest step
    intake, est = intake_of(paper_spec(epoch_ns=EPOCH))  # max_delay 12
    key = "pd/p0/s1/sensor/ranger"
    first = encode(measurement(sensor="ranger", step=5, z=np.array([1.0])))
    assert intake.measurement(key, first, 20, 17) is None  # inside [5, 17] when it arrived
    assert est.now == 17  # judged there: the estimator was not moved to 20
    refusal = intake.measurement(key, encode(measurement(sensor="ranger", step=4, seq=2,
                                                         z=np.array([1.0]))), 20, 17)
    assert refusal is not None and refusal.reason == "late"
    # a command sent at step 19 (apply step 19 + lead) that arrived at 18: judged at 19
    lead = paper_spec().lead
    cmd = encode(command(step=19 + lead, u=np.array([0.5])))
    assert intake.command("pd/p0/s1/cmd", cmd, 22, 18) is None and est.now == 19
    refusal = intake.measurement(key, encode(measurement(sensor="ranger", step=21, seq=3,
                                                         z=np.array([1.0]))), 20, 17)
    assert refusal is not None and refusal.reason == "future" and est.now == 20
    # the estimator is at 20 now: a sample that arrived at 18 is judged there (came after)
    refusal = intake.measurement(key, encode(measurement(sensor="ranger", step=7, seq=4,
                                                         z=np.array([1.0]))), 22, 18)
    assert refusal is not None and refusal.reason == "late"


def test_a_sample_late_only_by_the_clocks_slack_goes_in_at_its_latest_instant() -> None:
    intake, est = intake_of(paper_spec(epoch_ns=EPOCH))
    slack = [0]
    intake.stamp_map = lambda t: t  # stamps already on the daemon's timeline
    intake.stamp_slack = lambda: slack[0]
    k = 40
    oldest = k - est.max_delay
    key = "pd/p0/s1/sensor/camera"

    def offer(step: int, seq: int, **kw):  # type: ignore[no-untyped-def]
        msg = measurement(step=None, t_ns=EPOCH + step * PERIOD_NS, seq=seq, **kw)
        return intake.measurement(f"pd/p0/s1/sensor/{msg.sensor}", encode(msg), k)

    for seq, s in enumerate((0, PERIOD_NS)):  # no slack, or too little: late
        slack[0] = s
        refusal = offer(oldest - 2, seq)
        assert refusal is not None and refusal.reason == "late" and not intake.remapped
        assert f"sample step {oldest - 2} is older" in refusal.text  # its own step
    slack[0] = 3 * PERIOD_NS  # late by 2 steps, the estimate moved by 3 while it flew
    assert offer(oldest - 2, 5) is None and intake.remapped
    assert sorted(est._packets) == [oldest + 1]  # t_ns + slack: never as current
    assert intake.last_t_ns == EPOCH + (oldest + 1) * PERIOD_NS
    # a second one of that sensor at that instant: late; the full decode path (its own R)
    assert offer(oldest - 2, 6) is not None and not intake.remapped
    assert offer(oldest - 2, 7, sensor="ranger", z=np.array([0.1]), R=np.eye(1)) is None
    assert intake.remapped and len(est._packets[oldest + 1]) == 2
    # a step-stamped sample carries no clock error: late whatever the slack
    refusal = intake.measurement(key, encode(measurement(step=oldest - 1, seq=8)), k)
    assert refusal is not None and refusal.reason == "late"
