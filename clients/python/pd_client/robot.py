"""Robot side: publish measurements stamped with their sample time, receive commands.

Example::

    with Robot(transport, "s1") as robot:
        robot.publish("camera", [1.2, 5.3], step=k)         # or t_ns=time.time_ns()
        robot.on_command(lambda cmd: print(cmd.step, cmd.u))  # or: for cmd in robot.commands():
        robot.echo(cmd)              # when cmd took effect (robot clock); apply_on_arrival=True
                                     # echoes each command as it arrives

A robot answers time probes (``robot/p<k>/<session>/clock``, :class:`ClockProbe` ->
:class:`ClockProbeReply`) on its own ``clock`` unless ``answer_probes=False``: with its echoes
and stamps the daemon estimates the robot clock's offset (spec ``robot_clock: estimated``).
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from pd_service.transport import DEFAULT_SENDER_CACHE, Query, Sample, Transport
from pd_service.wire import (
    Command,
    CommandEcho,
    Measurement,
    SessionSpec,
    WireError,
    encode,
    keys,
)
from pd_service.wire.clock_probe import answer_probe
from pd_service.wire.convert import check_measurement, command_step

from ._base import ClientBase, as_array, build, session_name, try_decode
from ._queue import Inbox
from .errors import InvalidMessage, Timeout
from .truth import Truth

log = logging.getLogger("pd_client.robot")

CommandCallback = Callable[[Command], None]


class Robot(ClientBase):
    """The robot's end of a session.

    Measurements go to ``robot/p<k>/<session>/sensor/<name>`` (the link emulator carries them to
    the service); commands are read from ``robot/p<k>/<session>/cmd``. With ``direct=True`` the
    operator-side keys (``pd/p<k>/<session>/...``) are used instead: no link emulator between.

    ``spec`` (optional): the session's SessionSpec. With it, measurements are checked
    against the session (known sensor, dimension) before they are sent, truth gets its
    ``t_ns`` from the step, and :meth:`apply_step` can resolve commands stamped with
    ``issued_ns``.

    ``cache``: each sensor's publisher keeps its last ``cache`` samples (0: none), which a
    restarted service reads back (direct mode; through the link emulator, pd-link's own
    publishers keep them): samples sent while no service ran are not lost. In direct mode
    with ``spec``, every sensor's publisher is declared at once (its cache answers empty
    until it sends); otherwise at its first sample.

    ``clock``: the robot's clock (ns), for echoes and probe answers; ``apply_on_arrival``:
    echo every command when it arrives (a robot that applies commands on arrival, as ROS
    base controllers do); ``answer_probes``: declare the probe queryable; ``stamp_clock``
    (emulation of an unsynchronised robot, with ``spec``): a sample published by ``step`` is
    sent with ``t_ns = stamp_clock(spec.time_of(step))``, the robot clock's reading then.
    """

    def __init__(self, transport: Transport, session: str, *, spec: SessionSpec | None = None,
                 direct: bool = False, queue_size: int = 1024,
                 cache: int = DEFAULT_SENDER_CACHE, clock: Callable[[], int] = time.time_ns,
                 apply_on_arrival: bool = False, answer_probes: bool = True,
                 stamp_clock: Callable[[int], int] | None = None) -> None:
        super().__init__(transport)
        self.cache = cache
        self.session = session_name(session, spec)
        self.spec = spec
        self.direct = direct
        self._seq: dict[str, int] = {}
        self._inbox: Inbox[Command] = Inbox(queue_size)
        self._callbacks: list[CommandCallback] = []
        self.commands_received = 0
        self.commands_invalid = 0
        self.published = 0
        self.clock = clock
        self.apply_on_arrival = apply_on_arrival
        if stamp_clock is not None and spec is None:
            raise InvalidMessage("stamp_clock needs the session spec (the steps' times)")
        self.stamp_clock = stamp_clock
        self.echoes = 0
        self.probes_answered = 0
        self.probes_invalid = 0
        cmd_key = keys.command_key(session) if direct else keys.robot_command_key(session)
        self._echo_key = keys.echo_key(session) if direct else keys.robot_echo_key(session)
        self._subscribe(cmd_key, self._on_sample)
        if direct and spec is not None and cache > 0:
            # every sensor's cache present from now on, empty or not: a restarted or
            # taking-over service waits for each one's answer (a sensor that has not sent
            # yet would otherwise hold its first prediction for 2 x recover_timeout_s)
            for sensor in spec.sensors:
                self._sender(self.sensor_key(sensor.name), cache)
        if answer_probes:
            self._handles.append(transport.queryable(keys.robot_clock_key(self.session),
                                                     self._on_probe))

    # --- measurements ------------------------------------------------------------------

    def sensor_key(self, sensor: str) -> str:
        return (keys.sensor_key if self.direct else keys.robot_sensor_key)(self.session, sensor)

    def publish(self, sensor: str, z: Sequence[float] | np.ndarray | float, *,
                step: int | None = None, t_ns: int | None = None,
                R: np.ndarray | Sequence[Sequence[float]] | None = None) -> Measurement:
        """Send one sample of ``sensor`` taken at ``step`` (or at time ``t_ns``, ns on the
        shared clock): exactly one of the two. ``R``: this sample's noise covariance (m x m)
        if it differs from the sensor's. The per-sensor ``seq`` counts up from 0.

        Raises InvalidMessage (a ValueError) for a bad field, without sending anything.
        """
        try:
            key = self.sensor_key(sensor)
        except keys.KeyError_ as exc:
            raise InvalidMessage(str(exc)) from None
        if self.stamp_clock is not None and step is not None and t_ns is None:
            assert self.spec is not None
            t_ns = self.stamp_clock(self.spec.time_of(step))
            step = None
        fields: dict[str, object] = {"session": self.session, "sensor": sensor,
                        "seq": self._seq.get(sensor, 0), "step": step, "t_ns": t_ns,
                        "z": as_array(z, "z", 1)}
        if R is not None:
            fields["R"] = as_array(R, "R", 2)
        msg = build(Measurement, **fields)
        if self.spec is not None:
            # a robot clock the daemon estimates: its stamps meet the epoch once it maps them
            own = self.spec.robot_clock == "estimated" and msg.t_ns is not None
            try:
                check_measurement(msg.model_copy(update={"t_ns": None}) if own else msg,
                                  self.spec)
            except WireError as exc:
                raise InvalidMessage(exc.reason) from None
        self._sender(key, self.cache).put(encode(msg))
        self._seq[sensor] = msg.seq + 1
        self.published += 1
        return msg

    def publish_truth(self, step: int, x: Sequence[float] | np.ndarray, *,
                      t_ns: int | None = None, names: Sequence[str] = (),
                      angles: Sequence[int] = ()) -> Truth:
        """Publish the true state x(step) on ``robot/p<k>/<session>/truth`` (simulators only:
        used by recorders and displays for evaluation, never by the service). ``t_ns``
        defaults to the step's time when the spec is known."""
        if t_ns is None:
            if self.spec is None:
                raise InvalidMessage("publish_truth: t_ns is required when the spec is unknown")
            t_ns = self.spec.time_of(step)
        msg = build(Truth, session=self.session, step=step, t_ns=t_ns,
                    x=as_array(x, "x", 1), names=list(names), angles=list(angles))
        self.transport.put(keys.truth_key(self.session), encode(msg))
        return msg

    # --- commands ----------------------------------------------------------------------

    def _on_sample(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        arrived = self.clock()
        cmd = try_decode(sample, Command)
        if cmd is None or cmd.session != self.session:
            self.commands_invalid += 1
            return
        self.commands_received += 1
        if self.apply_on_arrival:
            self.echo(cmd, arrived)
        self._inbox.push(cmd)
        for cb in list(self._callbacks):
            try:
                cb(cmd)
            except Exception:
                log.exception("command callback failed")

    def on_command(self, callback: CommandCallback) -> None:
        """Call ``callback(cmd)`` for every command received, on the transport's thread
        (it must return quickly)."""
        self._callbacks.append(callback)

    def next_command(self, timeout: float | None = None) -> Command:
        """The oldest command not yet taken; raises Timeout after ``timeout`` seconds."""
        cmd = self._inbox.pop(timeout)
        if cmd is None:
            raise Timeout(f"no command for session {self.session!r} within {timeout} s")
        return cmd

    def commands(self, timeout: float | None = None) -> Iterator[Command]:
        """Iterate over received commands; stops after ``timeout`` seconds without one
        (None: wait forever) or when the robot is closed."""
        return self._inbox.iterate(timeout)

    def pending_commands(self) -> list[Command]:
        """Every command received and not yet taken, oldest first (does not wait)."""
        return self._inbox.drain()

    def apply_step(self, cmd: Command) -> int:
        """The step from which ``cmd`` applies: ``cmd.step``, or, for a command stamped with
        ``issued_ns``, ``step_of(issued_ns) + lead`` (needs the spec)."""
        if cmd.step is not None:
            return cmd.step
        if self.spec is None:
            raise InvalidMessage("a command stamped with issued_ns needs the session spec")
        return command_step(cmd, self.spec)

    # --- echoes and probes (the daemon's view of the robot's time) ----------------------

    def echo(self, cmd: Command, applied_ns: int | None = None) -> CommandEcho:
        """Tell the daemon that ``cmd`` took effect at ``applied_ns`` (the robot's clock;
        default: now), on ``robot/p<k>/<session>/echo``."""
        sent = self.clock()
        msg = build(CommandEcho, session=self.session, seq=cmd.seq,
                    applied_ns=sent if applied_ns is None else applied_ns, sent_ns=sent)
        self._sender(self._echo_key, 0).put(encode(msg))
        self.echoes += 1
        return msg

    def _on_probe(self, query: Query) -> None:
        t2 = self.clock()  # first: the probe's receipt
        try:
            reply = answer_probe(query.payload, self.session, t2, self.clock())
        except WireError as exc:
            self.probes_invalid += 1
            query.reply_err(f"not a ClockProbe of {self.session}: {exc.reason}"[:512].encode())
            return
        try:
            query.reply(keys.robot_clock_key(self.session), encode(reply))
            self.probes_answered += 1
        except Exception as exc:  # the query may have been dropped meanwhile
            log.debug("probe reply failed: %s", exc)

    def close(self) -> None:
        self._inbox.close()
        super().close()


class CommandSchedule:
    """Commands by apply step, with zero-order hold: ``u_at(k)`` is the u of the command
    with the greatest apply step <= k received so far (zeros before any).

    This is how a robot applies commands "at their apply step, hold last": a command that
    arrives after its apply step takes effect on arrival (it is then the newest one <= k),
    and one older than the command already in force never takes effect (counted ``stale``).
    Thread-safe: ``add`` may be called from a transport callback.
    """

    def __init__(self, nu: int, keep: int = 4096) -> None:
        if nu < 1:
            raise ValueError(f"nu: must be >= 1, got {nu}")
        self.nu = nu
        self._steps: list[int] = []
        self._u: dict[int, np.ndarray] = {}
        self._keep = keep
        self._lock = threading.Lock()
        self._applied_step = -1  # apply step of the command in force at the last u_at
        self.received = 0
        self.stale = 0
        self.late = 0
        self._last_k = -1

    def add(self, step: int, u: Sequence[float] | np.ndarray) -> None:
        """Record that ``u`` applies from ``step`` on (a later command for the same step
        replaces the earlier one)."""
        uv = np.asarray(u, dtype=np.float64).reshape(-1)
        if uv.shape != (self.nu,):
            raise ValueError(f"u: expected {self.nu} values, got {uv.shape[0]}")
        with self._lock:
            self.received += 1
            if step < self._applied_step:
                self.stale += 1
                return
            if step <= self._last_k:
                self.late += 1  # takes effect at the next u_at, later than stamped
            if step not in self._u:
                bisect.insort(self._steps, step)
            self._u[step] = uv
            if len(self._steps) > self._keep:
                old = self._steps.pop(0)
                del self._u[old]

    def u_at(self, k: int) -> np.ndarray:
        """u(k): the newest command whose apply step is <= k (zeros before the first)."""
        with self._lock:
            self._last_k = max(self._last_k, k)
            i = bisect.bisect_right(self._steps, k)
            if i == 0:
                return np.zeros(self.nu)
            step = self._steps[i - 1]
            self._applied_step = max(self._applied_step, step)
            # Forget commands superseded by the one in force.
            if i > 1:
                for s in self._steps[: i - 1]:
                    del self._u[s]
                del self._steps[: i - 1]
            return self._u[step].copy()
