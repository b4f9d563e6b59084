"""The robot's answer to a clock probe (protocol.md section 9), one rule for every robot side
(the SDK's ``Robot``, ``pd-ros2 --role robot``)."""

from __future__ import annotations

from .codec import decode
from .errors import WireError
from .messages import ClockProbe, ClockProbeReply


def answer_probe(payload: bytes | None, session: str, t2_ns: int, t3_ns: int) -> ClockProbeReply:
    """The reply to a probe query's ``payload`` received at ``t2_ns`` and answered at
    ``t3_ns`` (the robot's clock, ns; t3 is raised to t2 if the clock stepped back between the
    two reads). WireError if the payload is not a ClockProbe of ``session``."""
    probe = decode(payload or b"", ClockProbe)
    if probe.session != session:
        raise WireError(f"ClockProbe.session: {probe.session!r}, not {session!r}")
    return ClockProbeReply(session=session, probe=probe.probe, t1_ns=probe.t1_ns, t2_ns=t2_ns,
                           t3_ns=max(t2_ns, t3_ns))
