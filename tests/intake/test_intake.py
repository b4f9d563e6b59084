"""The intake's supersede rule (pd_service.intake, module docstring): of two commands that land
on one open apply step the newer (later issued_ns, then higher seq) replaces the older; a repeat
or an older one is a duplicate; a final step is never changed."""

from __future__ import annotations

import numpy as np

from pd_service.backends import build
from pd_service.intake import Intake
from pd_service.wire import keys
from tests.service.helpers import cmd_bytes, cmd_now_bytes, paper_spec

SPEC = paper_spec("s1", epoch_ns=0)
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
    assert len(it.command_order) <= 4096
