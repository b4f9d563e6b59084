"""``pd-operator``: a scripted operator that sends a scenario's command profile.

    pd-operator --scenario paper --session paper --session paper-cam
    pd-operator --scenario omni --session omni      # wheel torques of the omni robot
    pd-operator --scenario diffdrive --session bot --ros2   # Twist on cmd_vel (rmw_zenoh)

At each step k of the session clock (wall time ``epoch_ns + k * period_ns``) it sends, to
every session, the scenario's command for apply step k + lead: the step at which a command
sent now reaches the robot over an uplink of ``lead`` steps. The session specs are read
from their config keys (the service and ``pd-robot-sim --create-session`` serve them); when
a session is re-created (a new SessionSpec put), it follows the new clock. With ``--steps N``
it stops after sending the command for apply step N. Progress lines go to stderr.
``--ros2`` (one session, whose spec binds a command topic, e.g. ``--scenario diffdrive``): the
operator is a ROS 2 node ``operator`` that publishes the same commands as ``geometry_msgs/Twist``
(or the bound TwistStamped) on the bound topic in rmw_zenoh's format (``--domain-id``,
``--namespace``), without an apply step: pd-ros2 forwards it to the service, which applies it
from the arrival step + lead, and pd-link carries it to ``pd-robot-sim --ros2``, which applies
it on arrival (docs/ros2.md).
Exit codes: 0 done or stopped by SIGINT/SIGTERM, 1 runtime error, 2 bad command line.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from typing import TYPE_CHECKING

from pd_service.backends import command_dim
from pd_service.scenarios import NOISE_SETTINGS, SCENARIOS, Scenario, get_scenario
from pd_service.transport import Sample, Transport
from pd_service.wire import SessionSpec, WireError, keys

from .._base import try_decode
from ..admin import Admin
from ..operator import Operator
from . import common
from .pd_robot_sim import ros2_options

if TYPE_CHECKING:
    from .ros2_operator import Ros2OperatorNode
    from .ros2_robot import Ros2Options

TOOL = "pd-operator"


def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scenario", default="paper", choices=SCENARIOS,
                    help="whose command profile to send (default paper)")
    ap.add_argument("--noise", default="journal", choices=NOISE_SETTINGS,
                    help=argparse.SUPPRESS)
    ap.add_argument("--session", action="append", metavar="NAME",
                    help="session to command (repeatable; default: the scenario's name)")
    ap.add_argument("--steps", type=int, default=None,
                    help="stop after the command for apply step N (default: the scenario's "
                         "length; 0: run until stopped)")
    ap.add_argument("--spec-timeout", type=float, default=30.0,
                    help="seconds to wait for the session specs (default 30)")
    common.add_ros2_args(ap, "send Twist messages on the session's bound command topic in "
                             "rmw_zenoh's format (needs the ros2 extra and ROS 2 bindings)")
    common.add_progress_arg(ap)


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        scenario = get_scenario(args.scenario, args.noise)
    except ValueError as exc:
        ap.error(str(exc))
    steps = scenario.default_steps if args.steps is None else args.steps
    names = args.session or [scenario.name]
    try:
        ros2 = ros2_options(args, prefix=None)
    except ValueError as exc:
        ap.error(str(exc))
    if ros2 is not None and len(names) != 1:
        ap.error("--ros2: exactly one --session")
    return common.run_on_transport(
        TOOL, args, lambda transport: _run(transport, scenario, names, steps, args, stop, ros2),
        stop=stop)


class _Followed:
    """The current spec of each session: replaced when a new SessionSpec is put on its
    config key (e.g. a simulator re-creating the session with a new epoch)."""

    def __init__(self, transport: Transport, specs: list[SessionSpec]) -> None:
        self.specs = {s.session: s for s in specs}
        self.lock = threading.Lock()
        self.changed = threading.Event()
        self.handles = [transport.subscribe(keys.config_key(s.session), self._on_config)
                        for s in specs]

    def _on_config(self, sample: Sample) -> None:
        if sample.kind != "put":
            return
        spec = try_decode(sample, SessionSpec)
        if spec is None or spec.session not in self.specs:
            return
        with self.lock:
            if spec != self.specs[spec.session]:
                self.specs[spec.session] = spec
                self.changed.set()

    def close(self) -> None:
        for h in self.handles:
            h.close()


def _run(transport: Transport, scenario: Scenario, names: list[str], steps: int,
         args: argparse.Namespace, stop: threading.Event, ros2: Ros2Options | None = None
         ) -> int:
    specs: list[SessionSpec] = []
    with Admin(transport) as admin:
        for name in names:
            common.progress(TOOL, f"waiting for the spec of session {name} ...")
            spec = admin.wait_for_spec(name, args.spec_timeout)
            try:
                r = command_dim(spec)  # a nonlinear model's is its registered model's
            except WireError as exc:
                return common.fail(TOOL, f"session {name}: {exc.reason}", 2)
            if r != scenario.nu:
                return common.fail(TOOL, f"session {name}: {r} inputs, scenario "
                                       f"{scenario.name!r} has {scenario.nu}", 2)
            if ros2 is not None and (spec.ros2 is None or spec.ros2.commands is None):
                return common.fail(TOOL, f"session {name}: --ros2 needs a spec whose ROS 2 "
                                       "bindings have a command topic", 2)
            specs.append(spec)
    ros_node: Ros2OperatorNode | None = None
    if ros2 is not None:
        from .ros2_operator import Ros2OperatorNode

        assert specs[0].ros2 is not None and specs[0].ros2.commands is not None
        ros_node = Ros2OperatorNode(transport, specs[0].ros2.commands, options=ros2)
        common.progress(TOOL, f"ROS 2 node {ros_node.node.name} publishing "
                            f"{ros_node.binding.msg_type} on {ros_node.key}")
    followed = _Followed(transport, specs)
    ops = {s.session: Operator(transport, s.session, spec=s) for s in specs}
    finished: dict[str, bool] = dict.fromkeys(ops, False)
    sent = 0
    try:
        k: int | None = None
        clock = specs[0]
        last_report = time.monotonic()
        while not stop.is_set():
            if k is None or followed.changed.is_set():
                followed.changed.clear()
                with followed.lock:
                    for name, op in ops.items():
                        if op.spec is not followed.specs[name]:
                            if k is not None:
                                common.progress(TOOL, f"session {name} was replaced: "
                                                    "following its new clock")
                            op.spec = followed.specs[name]
                            finished[name] = False
                new_clock = ops[names[0]].spec
                assert new_clock is not None
                if k is None or (new_clock.epoch_ns, new_clock.period_ns) != (
                        clock.epoch_ns, clock.period_ns):
                    k = max(0, new_clock.step_of(time.time_ns()))
                clock = new_clock
            if not common.wait_until(clock.time_of(k), stop):
                break
            for name, op in ops.items():
                assert op.spec is not None
                j = op.spec.step_of(clock.time_of(k)) + op.spec.lead
                if steps == 0 or j <= steps:
                    if ros_node is not None:  # no apply step: it applies on arrival
                        ros_node.send(scenario.command(j))
                    else:
                        op.send(scenario.command(j), step=j)
                    sent += 1
                    finished[name] = j == steps
            if args.progress and time.monotonic() - last_report >= args.progress:
                last_report = time.monotonic()
                j = k + clock.lead
                late = "" if steps == 0 or j <= steps else \
                    f" (past --steps {steps}: waiting for the session to be re-created)"
                common.progress(TOOL, f"step {k}: sent {sent} commands, u(step {j})="
                                    f"{common.fmt_vec(scenario.command(j))}{late}")
            if steps and all(finished.values()):
                break
            k += 1
        common.progress(TOOL, f"{'stopped' if stop.is_set() else 'done'}: sent {sent} commands")
    finally:
        followed.close()
        if ros_node is not None:
            ros_node.close()
        for op in ops.values():
            op.close()
    return 0


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
