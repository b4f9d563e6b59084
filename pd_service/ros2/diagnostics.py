"""``/diagnostics`` of pd-ros2: one ``diagnostic_msgs/DiagnosticStatus`` per bridged session,
published once a second as a ``diagnostic_msgs/DiagnosticArray`` (what ``rqt_robot_monitor``
and the ``diagnostic_aggregator`` read), CDR through the rosbags typestore.

Per session, from two of the daemon's ``SessionStatus`` one interval apart (counters are
cumulative: the rates are of the interval) and the bridge's own input arrivals:

==================  ==================================================  ====================
check               value                                               WARN / ERROR at
==================  ==================================================  ====================
late rate           Δlate / Δ(accepted + late + future)                 > 5 % / > 25 %
future rate         Δfuture / Δ(accepted + late + future)               > 5 % / > 25 %
silent sensors      bound sensor topics with no message for ``silent_s``  any / all
clock               |daemon's now_step - the bridge's step of now|      > 1 / > max_delay steps
NEES consistency    not in SessionStatus: reported "not available"      never
status              no SessionStatus reply from the daemon              ERROR
==================  ==================================================  ====================

The session's level is the worst of its checks. Pure: no transport, no clock read (times
are passed in).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from rosbags.typesys.stores.ros2_jazzy import (
    diagnostic_msgs__msg__DiagnosticArray as DiagnosticArray,
)
from rosbags.typesys.stores.ros2_jazzy import (
    diagnostic_msgs__msg__DiagnosticStatus as DiagnosticStatus,
)
from rosbags.typesys.stores.ros2_jazzy import (
    diagnostic_msgs__msg__KeyValue as KeyValue,
)

from pd_service.ros2.messages import header, typestore
from pd_service.wire import SessionSpec, SessionStatus

#: diagnostic_msgs/DiagnosticStatus levels.
OK, WARN, ERROR = 0, 1, 2
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
DIAGNOSTICS_TOPIC = "/diagnostics"
#: Rate thresholds (fraction of the interval's samples): WARN, ERROR.
RATE_WARN, RATE_ERROR = 0.05, 0.25


@dataclass(frozen=True, slots=True)
class Check:
    """One line of a session's diagnostics: its level, a short message and its value."""

    name: str
    level: int
    message: str
    value: str


def _rate(prev: Mapping[str, int], cur: Mapping[str, int], name: str) -> tuple[float, int]:
    """(the interval's share of ``name`` among the samples judged, samples judged)."""
    def delta(k: str) -> int:
        return max(0, int(cur.get(k, 0)) - int(prev.get(k, 0)))

    judged = delta("accepted") + delta("late") + delta("future")
    return (delta(name) / judged if judged else 0.0), judged


def session_checks(spec: SessionSpec, prev: SessionStatus | None, cur: SessionStatus | None,
                   last_input_ns: Mapping[str, int | None], now_ns: int,
                   silent_s: float) -> list[Check]:
    """The checks of the module docstring for one session: ``prev`` / ``cur`` its statuses
    one interval apart (None: no reply), ``last_input_ns`` the last arrival (ns, the bridge's
    clock; None: never) of each bound sensor topic, ``now_ns`` the bridge's wall clock."""
    if cur is None:
        return [Check("status", ERROR, "no SessionStatus from the daemon", "none")]
    out: list[Check] = []
    before = prev.counters if prev is not None else {}
    for name in ("late", "future"):
        share, judged = _rate(before, cur.counters, name)
        level = ERROR if share > RATE_ERROR else WARN if share > RATE_WARN else OK
        out.append(Check(f"{name} rate", level, f"{100 * share:.1f} % of {judged} samples",
                         f"{share:.4f}"))
    silent = sorted(s for s, t in last_input_ns.items()
                    if t is None or now_ns - t > silent_s * 1e9)
    if last_input_ns:
        level = OK if not silent else ERROR if len(silent) == len(last_input_ns) else WARN
        out.append(Check("silent sensors", level,
                         f"silent for {silent_s:g} s: {', '.join(silent)}" if silent
                         else "every bound sensor heard", ",".join(silent)))
    offset = cur.now_step - spec.step_of(now_ns)
    level = ERROR if abs(offset) > spec.max_delay else WARN if abs(offset) > 1 else OK
    out.append(Check("clock", level, f"daemon's step minus the bridge's: {offset}",
                     str(offset)))
    out.append(Check("NEES consistency", OK, "not available (not in SessionStatus)", "n/a"))
    return out


def diagnostic_array(stamp_ns: int, node: str,
                     sessions: Sequence[tuple[str, list[Check]]]) -> bytes:
    """CDR bytes of the DiagnosticArray: one status per session (name ``<node>: <session>``,
    level the worst check's, message the worst checks' messages, values every check's)."""
    statuses = []
    for session, checks in sessions:
        level = max((c.level for c in checks), default=OK)
        worst = [f"{c.name}: {c.message}" for c in checks if c.level == level and level > OK]
        values = [KeyValue(key=c.name, value=c.value) for c in checks]
        values += [KeyValue(key=f"{c.name} level", value=str(c.level)) for c in checks]
        statuses.append(DiagnosticStatus(
            level=level, name=f"{node}: {session}",
            message="; ".join(worst) if worst else "OK", hardware_id=session, values=values))
    msg = DiagnosticArray(header=header(stamp_ns, ""), status=statuses)
    return bytes(typestore().serialize_cdr(msg, DIAGNOSTICS_TYPE))


def decode_diagnostic_array(payload: bytes) -> DiagnosticArray:
    """The DiagnosticArray of CDR ``payload`` (for tests and tools)."""
    msg = typestore().deserialize_cdr(payload, DIAGNOSTICS_TYPE)
    assert isinstance(msg, DiagnosticArray)
    return msg
