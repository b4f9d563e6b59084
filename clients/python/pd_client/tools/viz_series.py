"""pd-viz's numeric series as ROS 2 messages (``cdr`` encoding, ``ros2msg`` schema).

PlotJuggler's Foxglove WebSocket client (3.16+) lists only channels with encoding ``cdr`` and
schema encoding ``ros2msg`` and a non-empty schema, schema name and topic
(plotjuggler_plugins/DataStreamFoxgloveBridge/foxglove_client.cpp, ``canUseChannel``); it
parses each message with the definition the channel advertises, so the type need not exist
in any ROS installation. A :class:`SeriesType` is one flat message made for a session: a
``builtin_interfaces/Time stamp`` (the prediction's target time), int64 fields, then float64
fields, each named for what it holds (``x_0``, ``sd_0``, ``err_2``: per state index).

CDR (XCDR1, little endian): the 4-byte encapsulation header ``00 01 00 00``, then each field
at an offset (from the end of the header) aligned to its size: ``sec`` int32 at 0,
``nanosec`` uint32 at 4, then every int64 and float64 at 8, 16, ... (all aligned).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass

_CDR_LE = b"\x00\x01\x00\x00"
_SEPARATOR = "=" * 80
_TIME = "int32 sec\nuint32 nanosec\n"


def type_name(session: str, kind: str) -> str:
    """``pd_viz_msgs/msg/<Session><Kind>``: one message type per session and kind (a
    session's state size sets its fields)."""
    camel = "".join(part.capitalize() for part in re.split(r"[^A-Za-z0-9]+", session) if part)
    return f"pd_viz_msgs/msg/{camel or 'Session'}{kind}"


@dataclass(frozen=True)
class SeriesType:
    """One flat ROS 2 message type: stamp, ``ints`` (int64), ``floats`` (float64)."""

    name: str
    ints: tuple[str, ...]
    floats: tuple[str, ...]

    def definition(self) -> str:
        """The ``ros2msg`` schema: the message's definition, then its one dependency."""
        lines = ["builtin_interfaces/Time stamp", *(f"int64 {f}" for f in self.ints),
                 *(f"float64 {f}" for f in self.floats)]
        return "\n".join(lines) + f"\n\n{_SEPARATOR}\nMSG: builtin_interfaces/Time\n{_TIME}"

    def encode(self, t_ns: int, ints: Sequence[int], floats: Sequence[float]) -> bytes:
        """The CDR bytes of one message stamped ``t_ns`` (ns, >= 0)."""
        if len(ints) != len(self.ints) or len(floats) != len(self.floats):
            raise ValueError(f"{self.name}: {len(self.ints)} ints and {len(self.floats)} floats")
        sec, nsec = divmod(t_ns, 1_000_000_000)
        return _CDR_LE + struct.pack(f"<iI{len(ints)}q{len(floats)}d", sec, nsec, *ints,
                                     *floats)
