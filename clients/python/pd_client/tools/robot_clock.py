"""An emulated robot clock (issue 43): offset, drift and step changes against the session's
clock, for ``pd-robot-sim`` and the tests.

``robot(t) = t + offset + drift (t - t0) + sum of the steps whose time has come`` (ns; drift in
s/s, a step ``(at_s, size_s)`` moves the clock by ``size_s`` from ``t0 + at_s`` on: an NTP
correction). :meth:`RobotClock.at` maps a time on the session's clock (e.g. a sample's true
time) to the robot's reading; calling the object reads the robot clock now.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field


@dataclass
class RobotClock:
    """A robot clock ``offset_s`` off the ``base`` clock, drifting ``drift_ppm``, with step
    changes ``steps`` ((at_s since ``t0_ns``, size_s), ...); ``t0_ns`` defaults to the base
    clock's reading at construction."""

    offset_s: float = 0.0
    drift_ppm: float = 0.0
    steps: Sequence[tuple[float, float]] = ()
    base: Callable[[], int] = time.time_ns
    t0_ns: int | None = None
    _steps_ns: list[tuple[int, int]] = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.t0_ns is None:
            self.t0_ns = self.base()
        self._steps_ns = sorted((self.t0_ns + round(a * 1e9), round(s * 1e9))
                                for a, s in self.steps)

    def offset_ns(self, t_ns: int) -> int:
        """The robot clock minus the base clock at base time ``t_ns`` (ns)."""
        assert self.t0_ns is not None
        off = self.offset_s * 1e9 + self.drift_ppm * 1e-6 * (t_ns - self.t0_ns)
        return round(off) + sum(s for at, s in self._steps_ns if t_ns >= at)

    def at(self, t_ns: int) -> int:
        """The robot clock's reading at base time ``t_ns``."""
        return t_ns + self.offset_ns(t_ns)

    def __call__(self) -> int:
        return self.at(self.base())


def add_clock_flags(ap: argparse.ArgumentParser) -> None:
    """``--clock-offset-s``, ``--clock-drift-ppm``, ``--clock-step AT_S:SIZE_S`` (repeatable)
    and ``--apply-on-arrival``."""
    g = ap.add_argument_group("robot clock (emulation of an unsynchronised robot)")
    g.add_argument("--clock-offset-s", type=float, default=0.0,
                   help="the robot clock's offset from the session's clock (s)")
    g.add_argument("--clock-drift-ppm", type=float, default=0.0,
                   help="the robot clock's drift (ppm)")
    g.add_argument("--clock-step", action="append", default=[], metavar="AT_S:SIZE_S",
                   type=_step, help="a step change of the robot clock by SIZE_S seconds, AT_S "
                                    "seconds after start (an NTP correction); repeatable")
    g.add_argument("--apply-on-arrival", action="store_true",
                   help="apply each command when it arrives (as a ROS base controller does) "
                        "and echo it; default: at its apply step")


def _step(text: str) -> tuple[float, float]:
    try:
        at, size = text.split(":")
        return float(at), float(size)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not AT_S:SIZE_S") from None


def clock_from_args(args: argparse.Namespace) -> RobotClock | None:
    """The robot clock of the command line; None when it is the session's clock."""
    if not (args.clock_offset_s or args.clock_drift_ppm or args.clock_step):
        return None
    return RobotClock(args.clock_offset_s, args.clock_drift_ppm, list(args.clock_step))
