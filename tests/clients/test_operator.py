"""Operator: commands stamped with their apply step (or issue time)."""

from __future__ import annotations

import numpy as np
import pytest

from pd_client import Command, InvalidMessage, Operator
from pd_service.wire import decode, keys

from .conftest import Collector


def test_send_step_and_issued_ns(bus, spec):
    sink = Collector(bus, keys.command_key("s1"))
    with Operator(bus.transport(), "s1") as op:
        a = op.send([0.5], step=12)
        b = op.send(0.0, issued_ns=spec.time_of(3))
    got = [decode(p, Command) for p in sink.payloads()]
    assert got == [a, b]
    assert (got[0].seq, got[0].step, got[0].issued_ns) == (0, 12, None)
    assert (got[1].seq, got[1].step, got[1].issued_ns) == (1, None, spec.time_of(3))
    np.testing.assert_array_equal(got[1].u, [0.0])


def test_bad_commands_are_refused_and_not_sent(bus, spec):
    sink = Collector(bus, "pd/**")
    with Operator(bus.transport(), "s1", spec=spec) as op:
        with pytest.raises(InvalidMessage, match="exactly one of step / issued_ns"):
            op.send([0.5], step=1, issued_ns=2)
        with pytest.raises(InvalidMessage, match="exactly one"):
            op.send([0.5])
        with pytest.raises(InvalidMessage, match="expected 1 values"):
            op.send([0.5, 1.0], step=3)
        with pytest.raises(InvalidMessage, match="apply step"):
            op.send([0.5], issued_ns=spec.epoch_ns - 10**12)
        assert op.seq == 0
    assert sink.samples == []


def test_send_now_uses_lead(bus, spec):
    sink = Collector(bus, keys.command_key("s1"))
    with Operator(bus.transport(), "s1", spec=spec) as op:
        assert op.now_step(spec.time_of(40) + 5) == 40
        op.send_now([0.5], t_ns=spec.time_of(40) + 5)
    assert decode(sink.payloads()[0], Command).step == 40 + spec.lead
    with Operator(bus.transport(), "s1") as op, pytest.raises(InvalidMessage):
        op.send_now([0.5], t_ns=0)
