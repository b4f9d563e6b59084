"""Ground truth of a simulated robot (``robot/p<k>/<session>/truth``), for evaluation only.

The daemon never reads it; pd-web, pd-viz, pd-record and the display draw or record it. It is
encoded with the same msgpack codec as the protocol's messages (:func:`pd_service.wire.encode`
/ ``decode``), described in docs/protocol.md section 4 and ``docs/schemas/Truth.json``, so that
a simulator in any language can publish it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, StringConstraints

from .arrays import Vector
from .messages import Int64, Message, Name, NonNegInt

StateName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_.-]{1,32}$")]


class Truth(Message):
    """True state x(step) of a simulated robot.

    ``names`` (optional, n entries) label the state components, e.g. ``["p1", "v1", "p2",
    "v2"]``; recorders and displays use them as column and axis names. ``angles`` lists the
    components that are angles, so that an error across +-pi is wrapped, not 2 pi.
    """

    session: Name = Field(description="Session id.")
    step: NonNegInt = Field(description="Step k of the session's grid.")
    t_ns: Int64 = Field(description="Time of step k, ns: epoch_ns + k * period_ns.")
    x: Vector = Field(description="True state x(k), n values.")
    names: Annotated[list[StateName], Field(max_length=64)] = Field(
        default_factory=list, description="Names of the n state components (or empty).")
    angles: Annotated[list[Annotated[int, Field(ge=0, le=63)]], Field(max_length=64)] = Field(
        default_factory=list,
        description="Indices of the components that are angles (rad): errors are wrapped.")
