"""Operator side: send commands stamped with the step at which they apply.

Example::

    with Operator(transport, "s1") as op:
        op.send([0.5], step=now_step + lead)      # u applies from that step on
        op.send([0.0], issued_ns=time.time_ns())  # or: the service adds the session's lead
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pd_service.backends import command_dim
from pd_service.transport import DEFAULT_SENDER_CACHE, Transport
from pd_service.wire import Command, SessionSpec, WireError, encode, keys
from pd_service.wire.convert import check_command

from ._base import ClientBase, as_array, build, session_name
from .errors import InvalidMessage


class Operator(ClientBase):
    """Sends Commands on ``pd/p<k>/<session>/cmd`` (the service reads them there, and the link
    emulator carries them to the robot). ``seq`` counts up from 0.

    ``spec`` (optional): the session's SessionSpec; with it, ``u`` is checked against the
    model's input dimension before sending, and :meth:`now_step` / :meth:`send_now` work.

    ``cache``: the command publisher keeps its last ``cache`` commands (0: none), which a
    restarted service reads back: commands sent while no service ran are not lost. It is
    declared at once (its cache answers empty until the first command).
    """

    def __init__(self, transport: Transport, session: str, *,
                 spec: SessionSpec | None = None, cache: int = DEFAULT_SENDER_CACHE) -> None:
        super().__init__(transport)
        self.cache = cache
        self.session = session_name(session, spec)
        self.spec = spec
        #: the model's input dimension, read from the spec at the first send
        self._nu: int | None = None
        self._key = keys.command_key(session)
        self.seq = 0
        if cache > 0:  # its cache present from now on, as the Robot's (a service waits for it)
            self._sender(self._key, cache)

    def send(self, u: Sequence[float] | np.ndarray | float, *, step: int | None = None,
             issued_ns: int | None = None) -> Command:
        """Send command ``u`` that applies from ``step`` on, or stamp it with the time it was
        issued (``issued_ns``, ns on the shared clock; the service then applies it at
        ``step_of(issued_ns) + lead``). Exactly one of the two.

        Raises InvalidMessage (a ValueError) for a bad field, without sending anything.
        """
        msg = build(Command, session=self.session, seq=self.seq, step=step, issued_ns=issued_ns,
                    u=as_array(u, "u", 1))
        if self.spec is not None:
            try:
                if self._nu is None:  # a nonlinear model's is its registered model's
                    self._nu = command_dim(self.spec)
                check_command(msg, self.spec, self._nu)
            except WireError as exc:
                raise InvalidMessage(exc.reason) from None
        self._sender(self._key, self.cache).put(encode(msg))
        self.seq += 1
        return msg

    def now_step(self, t_ns: int) -> int:
        """The session's step at time ``t_ns``: floor((t_ns - epoch_ns) / period_ns)."""
        if self.spec is None:
            raise InvalidMessage("now_step needs the session spec")
        return self.spec.step_of(t_ns)

    def send_now(self, u: Sequence[float] | np.ndarray | float, t_ns: int) -> Command:
        """Send ``u`` to apply at ``step_of(t_ns) + lead``: the step at which a command sent
        now reaches the robot over the uplink (needs the spec)."""
        if self.spec is None:
            raise InvalidMessage("send_now needs the session spec")
        return self.send(u, step=self.spec.step_of(t_ns) + self.spec.lead)
