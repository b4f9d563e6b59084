"""``pd-robot-sim``: a simulated robot that runs a scenario in real time.

    pd-robot-sim --scenario paper --noise journal --session paper --create-session
    pd-robot-sim --scenario paper --session paper --session paper-cam:camera --create-session
    pd-robot-sim --scenario maneuver --session rover --time-scale 2 --steps 600
    pd-robot-sim --scenario omni --session omni --create-session   # adaptive UKF session
    pd-robot-sim --scenario diffdrive --session bot --create-session --ros2   # a ROS 2 robot
    pd-robot-sim --scenario async --session bot --create-session   # sensors off the grid

Every step k (wall time ``epoch_ns + k * period_ns``; the period is the scenario's divided by
``--time-scale``) it moves the true state with the command in force for step k - 1, then
publishes the truth x(k) on ``robot/p<j>/<s>/truth`` and each sensor's sample of x(k),
stamped with step k, on ``robot/p<j>/<s>/sensor/<name>`` (``p<j>``: the session's partition,
protocol.md §3; the link emulator carries them to the service; ``--direct`` publishes on
``pd/p<j>/<s>/sensor/<name>`` instead). Commands are read from ``robot/p<j>/<s>/cmd``
(``pd/p<j>/<s>/cmd`` with ``--direct``) of the first session and apply from their
apply step, holding the last one; a command that arrives after its apply step applies on
arrival. The transition k-1 -> k is computed at the start of step k, so a command has up to
one period of slack after its apply step begins.

``--scenario async``: the sensors sample off the step grid, each at its own rate, phase and
jitter, and the truth moves in continuous time (:class:`pd_service.scenarios.AsyncSim`). At
step k the robot moves x(k-1) -> x(k) with u(k-1) through the samples taken in between, and
publishes each sample stamped with the time it was taken (``t_ns`` at full resolution,
``epoch_ns`` + its model time scaled by ``--time-scale``) at the first step at or after that
time plus the sensor's own delay (the pose fix's 300 ms); the truth x(k) as above.

``--ros2`` (one session, whose spec has ROS 2 bindings, e.g. ``--scenario diffdrive``): the
robot is a ROS 2 node ``robot_sim`` in rmw_zenoh's format instead. Each bound sensor's sample
is a ROS message (CDR, rmw_zenoh attachment, header.stamp = the step's time) on
``robot/<rmw_zenoh key>`` (pd-link's ``deploy/link-ros2.toml`` maps it to the plain key;
``--direct``: the plain key), its liveliness tokens are declared for ``--domain-id`` and
``--namespace``, and Twist commands on ``robot/<cmd_vel key>`` apply from the step they
arrive in (see docs/ros2.md). The truth stays native.

An unsynchronised robot (issue 43): ``--clock-offset-s``, ``--clock-drift-ppm`` and
``--clock-step AT_S:SIZE_S`` give the robot a clock of its own (:mod:`.robot_clock`): its
samples are stamped with ``t_ns`` on it (with ``--ros2``: header.stamp), its echoes and probe
answers read it; ``--apply-on-arrival`` applies each command in the step it arrives in and
echoes it (with ``--ros2``: each Twist, by its rmw_zenoh sequence number, as ``pd-ros2 --role
robot`` does, which then need not run: it reads the computer's clock, not the emulated one).

Several ``--session NAME[:sensor,...]`` run the same robot (same truth and samples) for
several sessions, each with its own sensor subset. ``--create-session`` puts the sessions'
SessionSpecs (epoch = now, once the service answers) and answers spec queries while
running; otherwise the specs are read from the config keys (whoever created the sessions
must serve them).
Progress lines go to stderr. Exit codes: 0 done or stopped by SIGINT/SIGTERM, 1 runtime
error (e.g. no service acknowledged the session), 2 bad command line.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pd_service.backends import command_dim
from pd_service.scenarios import (
    NOISE_SETTINGS,
    SCENARIOS,
    AsyncSim,
    Scenario,
    ScenarioSim,
    TimedSample,
    get_scenario,
)
from pd_service.transport import Transport
from pd_service.wire import Command, SessionSpec, WireError, encode, keys
from pd_service.wire.messages import PathSpec

from ..admin import Admin
from ..errors import PdClientError
from ..robot import CommandSchedule, Robot
from . import common
from .robot_clock import RobotClock, add_clock_flags, clock_from_args
from .web_feed import position_layout

if TYPE_CHECKING:
    from .ros2_robot import Ros2Options, Ros2RobotNode

TOOL = "pd-robot-sim"
log = logging.getLogger(__name__)


@dataclass
class SimSession:
    """One session the simulated robot serves: its spec, sensor subset and Robot."""

    spec: SessionSpec
    sensors: set[str]
    robot: Robot


class RobotSim:
    """The networked simulated robot (the stepping logic; :func:`main` adds the clock).

    ``specs``: one SessionSpec per session, all on the same clock (epoch and period); the
    first session's commands drive the robot. Call :meth:`tick` with k = 0, 1, 2, ... (or
    starting later), one per step.

    ``ros2``: be a ROS 2 robot (one session, whose spec has ``ros2`` bindings): the bound
    sensors are published as ROS messages by :attr:`ros` (a
    :class:`~.ros2_robot.Ros2RobotNode`), stamped with the step's time, and its Twist
    commands drive the robot from the step they arrive in: u(j) on, j = the session's step at
    ``clock()`` (wall clock, ns) on arrival; a sensor without a binding stays native.
    """

    def __init__(self, transport: Transport, scenario: Scenario, specs: Sequence[SessionSpec],
                 *, seed: int | None = 0, direct: bool = False,
                 ros2: Ros2Options | None = None,
                 clock: Callable[[], int] = time.time_ns, camera_every: int = 0,
                 camera_view: str = "top", robot_clock: RobotClock | None = None,
                 apply_on_arrival: bool = False) -> None:
        if not specs:
            raise ValueError("specs: at least one session is required")
        names = list(scenario.state_names)
        if camera_every and not {"x", "y"} <= set(names):
            raise ValueError(f"--camera: scenario {scenario.name!r} has no planar x, y to "
                             "film (use omni or diffdrive)")
        if camera_every < 0:
            raise ValueError(f"--camera: must be >= 0, got {camera_every}")
        if camera_every:
            try:
                import PIL  # noqa: F401
            except ImportError:
                raise ValueError("--camera needs Pillow: pip install 'pd-client[viz]'") from None
        #: A camera frame every this many steps (0: no camera), its view (camera_view.VIEWS)
        #: and its pose's state indices.
        self.camera_every = camera_every
        self.camera_view = camera_view
        self._pose_idx = (names.index("x") if "x" in names else 0,
                          names.index("y") if "y" in names else 0,
                          next((names.index(h) for h in ("theta", "yaw") if h in names), None))
        self._transport = transport
        self._direct = direct
        self.frames_published = 0
        if ros2 is not None:
            if len(specs) != 1:
                raise ValueError("--ros2: the ROS 2 robot serves exactly one session")
            if specs[0].ros2 is None:
                raise ValueError(f"session {specs[0].session!r} has no ROS 2 bindings "
                                 "(its spec's ros2 is unset)")
        first = specs[0]
        for spec in specs:
            if (spec.epoch_ns, spec.period_ns) != (first.epoch_ns, first.period_ns):
                raise ValueError(f"session {spec.session!r} is on another clock than "
                                 f"{first.session!r} (epoch_ns/period_ns differ)")
            try:
                r = command_dim(spec)  # a nonlinear model's is its registered model's
            except WireError as exc:
                raise ValueError(f"session {spec.session!r}: {exc.reason}") from None
            if spec.n != scenario.n or r != scenario.nu:
                raise ValueError(f"session {spec.session!r}: model is {spec.n} states / "
                                 f"{r} inputs, scenario {scenario.name!r} has "
                                 f"{scenario.n} / {scenario.nu}")
            if spec.model.kind != scenario.kind:
                raise ValueError(f"session {spec.session!r}: model kind {spec.model.kind!r}, "
                                 f"scenario {scenario.name!r} is {scenario.kind!r}")
            unknown = {s.name for s in spec.sensors} - set(scenario.sensor_names)
            if unknown:
                raise ValueError(f"session {spec.session!r}: sensors {sorted(unknown)} are not "
                                 f"in scenario {scenario.name!r}")
        self.scenario = scenario
        self.sim = ScenarioSim(scenario, seed)
        # sensors off the grid: the continuous-time simulation, samples held until they arrive
        self.async_sim = AsyncSim(scenario, seed) if scenario.timing is not None else None
        self._held: list[TimedSample] = []
        self.schedule = CommandSchedule(scenario.nu)
        self.sessions: list[SimSession] = []
        try:
            for spec in specs:
                # a ROS 2 robot applies Twists, not Commands: it echoes those (_on_ros_command)
                robot = Robot(transport, spec.session, spec=spec, direct=direct,
                              clock=robot_clock or clock,
                              apply_on_arrival=apply_on_arrival and ros2 is None,
                              stamp_clock=robot_clock.at if robot_clock else None)
                self.sessions.append(SimSession(spec, {s.name for s in spec.sensors}, robot))
        except BaseException:
            self.close()
            raise
        self._clock = clock
        self._stamp = robot_clock.at if robot_clock is not None else (lambda t: t)
        self._echo_twists = apply_on_arrival
        self.ros: Ros2RobotNode | None = None
        if ros2 is None:
            self.sessions[0].robot.on_command(self._on_command)
        else:
            from .ros2_robot import Ros2RobotNode

            bindings = specs[0].ros2
            assert bindings is not None
            try:
                self.ros = Ros2RobotNode(transport, bindings,
                                         {s.name: s.R for s in scenario.sensors},
                                         options=ros2, on_command=self._on_ros_command)
            except BaseException:
                self.close()
                raise
        self.commands_invalid = 0
        self.last_u = np.zeros(scenario.nu)
        self.samples_published = 0
        self._started = False

    @property
    def spec(self) -> SessionSpec:
        return self.sessions[0].spec

    def _on_command(self, cmd: Command) -> None:
        robot = self.sessions[0].robot
        try:  # on arrival: in force from the step it arrives in (the session's clock)
            step = (max(0, self.spec.step_of(self._clock())) if robot.apply_on_arrival
                    else robot.apply_step(cmd))
            self.schedule.add(step, cmd.u)
        except (PdClientError, ValueError) as exc:
            self.commands_invalid += 1
            log.warning("ignoring command seq %s: %s", cmd.seq, exc)

    def _on_ros_command(self, u: np.ndarray, seq: int | None) -> None:
        """A Twist's u = (v, yaw_rate): in force from the step it arrives in; with
        ``apply_on_arrival`` echoed (its rmw_zenoh sequence number ``seq``, as pd-ros2 --role
        robot does) at its arrival on the robot's clock."""
        self.schedule.add(max(0, self.spec.step_of(self._clock())), u)
        if self._echo_twists and seq is not None:
            robot = self.sessions[0].robot
            robot.echo(Command(session=robot.session, seq=seq, step=0, u=u), robot.clock())

    def tick(self, k: int) -> np.ndarray:
        """Run step k: move x(k-1) -> x(k) with u(k-1), then publish truth and samples of
        x(k). Returns x(k) (the simulated state; the published truth has the scenario's
        angles wrapped to [-pi, pi)). Steps must increase by one after the first call."""
        if self.async_sim is not None:
            return self._tick_async(k)
        if not self._started:
            self._started = True
            self.sim.k = k  # the first step (0, or later when joining a running session)
        else:
            if k != self.sim.k + 1:
                raise ValueError(f"tick: expected step {self.sim.k + 1}, got {k}")
            self.last_u = self.schedule.u_at(k - 1)
            self.sim.advance(self.last_u)
        x = self.sim.x
        names = self.scenario.state_names
        truth = self.scenario.truth_view(x)
        samples = self.sim.sample()
        for s in self.sessions:
            s.robot.publish_truth(k, truth, names=names, angles=self.scenario.angles)
            for d in samples:
                if d.sensor not in s.sensors:
                    continue
                if self.ros is not None and self.ros.binds(d.sensor):
                    self.ros.publish(d.sensor, d.z, stamp_ns=self._stamp(s.spec.time_of(k)))
                else:
                    s.robot.publish(d.sensor, d.z, step=k)
                self.samples_published += 1
        self._film(k, truth)  # after the step's pose: what places a ROS 2 frame
        return x

    def _tick_async(self, k: int) -> np.ndarray:
        """:meth:`tick` of a scenario with sensors off the grid (see the module docstring)."""
        sim = self.async_sim
        assert sim is not None
        if not self._started:
            self._started = True
            sim.start_at(k)
        else:
            if k != sim.k + 1:
                raise ValueError(f"tick: expected step {sim.k + 1}, got {k}")
            self.last_u = self.schedule.u_at(k - 1)
            self._held.extend(sim.step(self.last_u))
        T = self.scenario.period_s
        due = [d for d in self._held if d.arrival_s <= k * T + 1e-12]
        self._held = [d for d in self._held if d.arrival_s > k * T + 1e-12]
        truth = self.scenario.truth_view(sim.x)
        self._film(k, truth)
        for s in self.sessions:
            s.robot.publish_truth(k, truth, names=self.scenario.state_names,
                                  angles=self.scenario.angles)
            for d in due:
                if d.sensor not in s.sensors:
                    continue
                t_ns = self._stamp(s.spec.epoch_ns + round(d.t_s / T * s.spec.period_ns))
                if self.ros is not None and self.ros.binds(d.sensor):
                    self.ros.publish(d.sensor, d.z, stamp_ns=t_ns)
                else:
                    s.robot.publish(d.sensor, d.z, t_ns=t_ns)
                self.samples_published += 1
        return sim.x

    def _film(self, k: int, truth: np.ndarray) -> None:
        """Every ``camera_every``-th step: the camera frame of the true pose, captured at
        step k's time, on each session's camera key (robot side, or the service's with
        --direct: then without the link's delay)."""
        if not self.camera_every or k % self.camera_every:
            return
        from .camera_view import render_view

        ix, iy, ih = self._pose_idx
        yaw = float(truth[ih]) if ih is not None else 0.0
        for s in self.sessions:
            if self.ros is not None and self.ros.films:  # a ROS 2 camera: the chase view
                self.ros.publish_frame(render_view("chase", s.spec.session, self.frames_published,
                                                   s.spec.time_of(k), float(truth[ix]),
                                                   float(truth[iy]), yaw))
                continue
            frame = render_view(self.camera_view, s.spec.session, self.frames_published,
                                s.spec.time_of(k), float(truth[ix]), float(truth[iy]), yaw)
            key = (keys.camera_key if self._direct else keys.robot_camera_key)(s.spec.session)
            self._transport.put(key, encode(frame))
        self.frames_published += 1

    def close(self) -> None:
        ros = getattr(self, "ros", None)
        if ros is not None:
            ros.close()
        for s in self.sessions:
            s.robot.close()


def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scenario", default="paper", choices=SCENARIOS,
                    help="the simulated robot and its sensors (default paper)")
    ap.add_argument("--noise", default="journal", choices=NOISE_SETTINGS,
                    help="noise setting of the paper scenario (default: journal)")
    ap.add_argument("--session", action="append", metavar="NAME[:SENSORS]",
                    help="session to serve, optionally with a sensor subset "
                         "(e.g. paper-cam:camera); repeatable; default: the scenario's name")
    ap.add_argument("--steps", type=int, default=None,
                    help="run steps 0..N, then stop (default: the scenario's length; 0: run "
                         "until stopped)")
    ap.add_argument("--time-scale", type=float, default=1.0,
                    help="run this many times faster than real time (default 1)")
    ap.add_argument("--seed", type=int, default=0,
                    help="random seed of the simulation's noise (default 0)")
    ap.add_argument("--create-session", action="store_true",
                    help="put the SessionSpec(s) (epoch = now, once the service answers) and "
                         "serve them while running")
    ap.add_argument("--create-only", action="store_true",
                    help="with --create-session: create the session(s), wait for the service's "
                         "answer and exit (run as the admin user where only admins may create)")
    ap.add_argument("--close-on-exit", action="store_true",
                    help="with --create-session: delete the session(s) on exit")
    ap.add_argument("--no-wait-service", action="store_true",
                    help="with --create-session: do not wait for a service to acknowledge")
    ap.add_argument("--service-timeout", type=float, default=15.0,
                    help="seconds to wait for the service or for the spec (default 15)")
    ap.add_argument("--lead", type=int, help="override the scenario's lead (steps)")
    ap.add_argument("--max-delay", type=int, help="override the scenario's max_delay (steps)")
    ap.add_argument("--publish-every", type=int, default=1, metavar="N",
                    help="with --create-session: the daemon publishes every N-th step's "
                         "prediction (default 1: every step)")
    ap.add_argument("--path", type=int, default=0, metavar="N",
                    help="with --create-session: the daemon publishes the predicted path (the "
                         "position and heading components) with every N-th prediction "
                         "(default 0: never)")
    ap.add_argument("--camera", type=int, default=0, metavar="N",
                    help="publish a camera frame (JPEG, stamped with its capture time) every N "
                         "steps on robot/p<k>/<s>/camera (default 0: no camera; planar "
                         "scenarios: omni, diffdrive, async)")
    ap.add_argument("--camera-view", default="top", choices=("top", "chase"),
                    help="the camera: top (a top-down view following the robot, default) or "
                         "chase (a perspective camera on the robot, behind and above it)")
    add_clock_flags(ap)
    ap.add_argument("--direct", action="store_true",
                    help="publish on the service's keys (no link emulator in between)")
    common.add_ros2_args(ap, "be a ROS 2 robot in rmw_zenoh's format (needs the ros2 extra and a "
                             "spec with ROS 2 bindings, e.g. --scenario diffdrive)")
    common.add_progress_arg(ap)


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        scenario = get_scenario(args.scenario, args.noise)
        sessions = [common.parse_session_arg(v) for v in (args.session or [scenario.name])]
        for _, sensors in sessions:
            scenario.select(sensors)
        scenario.period_ns(args.time_scale)
        ros2 = ros2_options(args, prefix=None if args.direct else "robot")
    except ValueError as exc:
        ap.error(str(exc))
    steps = scenario.default_steps if args.steps is None else args.steps
    if steps < 0:
        ap.error("--steps must be >= 0")
    return common.run_on_transport(
        TOOL, args, lambda transport: _run(args, scenario, sessions, steps, transport, stop, ros2),
        stop=stop)


def _run(args: argparse.Namespace, scenario: Scenario,
         sessions: list[tuple[str, list[str] | None]], steps: int,
         transport: Transport, stop: threading.Event, ros2: Ros2Options | None = None) -> int:
    with Admin(transport) as admin:
        if args.create_session:
            try:  # checked before waiting: a bad command line fails at once
                specs = _new_specs(args, scenario, sessions, time.time_ns())
            except ValueError as exc:
                return common.fail(TOOL, exc, 2)
            if not args.no_wait_service:
                common.progress(TOOL, "waiting for pd-service ...")
                admin.wait_for_service(args.service_timeout)
            # Step 0 is now, when the service is there and the robot is about to start:
            # the steps that elapse before the first tick are published at once, and the
            # service refuses those older than max_delay (a slow start cost the warm-up).
            specs = _new_specs(args, scenario, sessions, time.time_ns())
            if args.create_only:
                _create(admin, specs, args)
                return 0
        else:
            specs = []
            for name, _ in sessions:
                common.progress(TOOL, f"waiting for the spec of session {name} ...")
                specs.append(admin.wait_for_spec(name, args.service_timeout))
        robot_clock = clock_from_args(args)
        try:
            sim = RobotSim(transport, scenario, specs, seed=args.seed, direct=args.direct,
                           camera_every=args.camera, camera_view=args.camera_view,
                           ros2=ros2, robot_clock=robot_clock,
                           apply_on_arrival=args.apply_on_arrival)
        except ValueError as exc:
            return common.fail(TOOL, exc, 2)
        if robot_clock is not None:  # its t0: what an outside check of the offset needs
            common.progress(TOOL, f"robot clock {robot_clock.offset_s:+g} s, "
                                  f"{robot_clock.drift_ppm:g} ppm, steps "
                                  f"{list(robot_clock.steps)} from t0_ns={robot_clock.t0_ns}")
        try:
            if args.create_session:  # the robot listens for commands before they can come
                _create(admin, specs, args)
        except BaseException:
            sim.close()
            raise
        if sim.ros is not None:
            keys = [sim.ros.key_of(n) for n in sim.ros.endpoints]
            common.progress(TOOL, f"ROS 2 node {sim.ros.node.name} (domain "
                                f"{sim.ros.node.domain_id}, namespace {sim.ros.node.namespace}) "
                                f"publishing on {', '.join(keys)}; commands from "
                                f"{sim.ros.command_key}")
        try:
            _loop(sim, steps, args.progress, stop, from_zero=args.create_session)
        finally:
            sim.close()
            if args.create_session and args.close_on_exit:
                for spec in specs:
                    try:
                        admin.close_session(spec.session, timeout=2.0)
                    except PdClientError as exc:
                        common.progress(TOOL, f"closing {spec.session}: {exc}")
    return 0


def _new_specs(args: argparse.Namespace, scenario: Scenario,
               sessions: list[tuple[str, list[str] | None]], epoch: int) -> list[SessionSpec]:
    """The sessions' SessionSpecs with step 0 at ``epoch`` (ns); ValueError for bad settings."""
    path = None
    if args.path:  # the positions, and the heading if there is one (a nav_msgs/Path's yaw)
        names = list(scenario.state_names)
        heading = [names.index(h) for h in ("theta", "yaw") if h in names][:1]
        path = PathSpec(indices=position_layout(names, len(names))[1] + heading,
                        every=args.path)
    specs = [scenario.spec(name, epoch, time_scale=args.time_scale, sensors=sensors,
                           lead=args.lead, max_delay=args.max_delay,
                           publish_every=args.publish_every, path=path)
             for name, sensors in sessions]
    if args.ros2 and args.camera:
        specs = [with_ros2_camera(s) for s in specs]
    return specs


def with_ros2_camera(spec: SessionSpec) -> SessionSpec:
    """``spec`` with its ROS 2 camera bound (``ros2.camera``): the chase camera's mount, the
    robot placed by its first bound sensor with x, y and yaw; ValueError without one."""
    from pd_service.wire.ros2 import CameraBinding

    from .camera_view import CHASE_MOUNT

    b = spec.ros2
    pose = next((n for n, tb in (b.sensors.items() if b else ())
                 if {"x", "y", "yaw"} <= set(tb.fields)), None)
    if b is None or pose is None:
        raise ValueError("--ros2 --camera: the spec binds no sensor with x, y and yaw to place "
                         "the camera")
    return spec.model_copy(update={"ros2": b.model_copy(update={
        "camera": CameraBinding(pose_sensor=pose, mount=CHASE_MOUNT)})})


def _create(admin: Admin, specs: list[SessionSpec], args: argparse.Namespace) -> None:
    """Put the sessions' specs (waiting for the service's acknowledgement unless
    ``--no-wait-service``) and say so."""
    for spec in specs:
        admin.replace_session(spec, wait=not args.no_wait_service, timeout=args.service_timeout)
        common.progress(TOOL, f"session {spec.session} created (model {_model_label(spec)}, "
                            f"sensors {', '.join(s.name for s in spec.sensors)}, period "
                            f"{spec.period_ns / 1e6:g} ms, lead {spec.lead})")


def ros2_options(args: argparse.Namespace, prefix: str | None) -> Ros2Options | None:
    """The ROS 2 settings of the command line (``--ros2``, ``--domain-id``, ``--namespace``;
    None without --ros2) with the key ``prefix``; ValueError for a domain id or namespace
    ROS 2 refuses, or without the ros2 extra."""
    if not args.ros2:
        return None
    try:
        from .ros2_robot import Ros2Options
    except ImportError as exc:
        raise ValueError(f"--ros2 needs the ros2 extra (pip install 'pd-service[ros2]'): "
                         f"{exc}") from None
    from pd_service.ros2.keys import check_namespace, domain_id

    domain = domain_id(args.domain_id)
    if not 0 <= domain <= 232:
        raise ValueError(f"--domain-id: {domain} is outside 0..232")
    check_namespace(args.namespace)
    return Ros2Options(domain_id=domain, namespace=args.namespace, prefix=prefix)


def _model_label(spec: SessionSpec) -> str:
    """e.g. "linear" or "unscented omni3, adapt mit [3, 4, 5]"."""
    model = spec.model
    label: str = model.kind
    name = getattr(model, "model", None)
    if isinstance(name, str):
        label += f" {name}"
    adapt = getattr(model, "adapt", None)
    if adapt is not None:
        label += f", adapt {adapt.method} {adapt.indices}"
    return label


def _loop(sim: RobotSim, steps: int, every_s: float, stop: threading.Event,
          from_zero: bool = False) -> None:
    """Tick in real time from step 0 (``from_zero``: we created the session just now, so any
    steps already elapsed are caught up at once) or from the current step (joining)."""
    spec = sim.spec
    k = 0 if from_zero else max(0, spec.step_of(time.time_ns()))
    if k > 0:
        common.progress(TOOL, f"joining session {spec.session} at step {k}")
    last_report = time.monotonic()
    end = f"/{steps}" if steps else ""
    while not stop.is_set() and (steps == 0 or k <= steps):
        if not common.wait_until(spec.time_of(k), stop):
            break
        x = sim.tick(k)
        if every_s and time.monotonic() - last_report >= every_s:
            last_report = time.monotonic()
            behind = spec.step_of(time.time_ns()) - k
            common.progress(TOOL, f"step {k}{end} x={common.fmt_vec(x)} u={common.fmt_vec(sim.last_u)} "
                                f"samples {sim.samples_published} commands "
                                f"{sim.schedule.received} (late {sim.schedule.late}, stale "
                                f"{sim.schedule.stale})" + (f" behind {behind}" if behind > 1 else ""))
        k += 1
    common.progress(TOOL, f"{'stopped' if stop.is_set() else 'done'} at step {k - 1}: samples "
                        f"{sim.samples_published}, commands {sim.schedule.received} (late "
                        f"{sim.schedule.late}, stale {sim.schedule.stale}, invalid "
                        f"{sim.commands_invalid})")


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
