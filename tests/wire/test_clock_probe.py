"""The robot's answer to a clock probe: the probe's number and t1 echoed, t3 never before t2,
anything but a ClockProbe of the session refused."""

from __future__ import annotations

import pytest

from pd_service.wire import ClockProbe, WireError, encode
from pd_service.wire.clock_probe import answer_probe


def test_the_reply_echoes_the_probe_and_keeps_t3_after_t2() -> None:
    r = answer_probe(encode(ClockProbe(session="s1", probe=4, t1_ns=-5)), "s1", 100, 90)
    assert (r.session, r.probe, r.t1_ns, r.t2_ns, r.t3_ns) == ("s1", 4, -5, 100, 100)


@pytest.mark.parametrize("payload", [None, b"", b"\xc1", encode(ClockProbe(session="s2", probe=1,
                                                                            t1_ns=0))])
def test_bad_probes_are_refused(payload) -> None:
    with pytest.raises(WireError):
        answer_probe(payload, "s1", 1, 2)
