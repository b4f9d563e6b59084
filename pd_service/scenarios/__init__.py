"""Simulated robots, step by step, each able to give its SessionSpec.

A :class:`Scenario` holds a robot's model, sensors, command profile and session settings;
:class:`ScenarioSim` simulates it one step at a time (ground truth and sensor samples; no
clock, no network, no filter). The scenarios: :mod:`.paper` (Liang et al. 2017),
:mod:`.maneuver` (a 2-D robot on legs and turns), :mod:`.omni` (the three-wheel
omnidirectional robot), :mod:`.diffdrive` (a differential-drive robot with ROS 2 topics),
:mod:`.asynchronous` (that robot with sensors off the step grid, simulated in continuous time) and
:mod:`.tracking` (the UIF-IMM paper's range-bearing tracking,
vectorised over Monte-Carlo runs). :mod:`.filter_runs` drives estimators through simulated
runs. This package sits above :mod:`pd_service.wire` and :mod:`pd_service.estimation`.
"""

from __future__ import annotations

from .asynchronous import AsyncSim, TimedSample, async_scenario, simulate_async
from .diffdrive import diffdrive_scenario
from .maneuver import maneuver_scenario
from .omni import omni_scenario
from .paper import NOISE_SETTINGS, paper_scenario
from .simulator import Detection, Scenario, ScenarioSim, SensorDef

SCENARIOS = ("paper", "maneuver", "omni", "diffdrive", "diffdrive-stationary", "async")


def get_scenario(name: str, noise: str = "journal") -> Scenario:
    """A scenario by name: ``paper`` (``noise`` journal|english), ``maneuver``, ``omni``,
    ``diffdrive``, ``diffdrive-stationary`` or ``async`` (sensors off the step grid)."""
    if name == "paper":
        return paper_scenario(noise)
    if name == "maneuver":
        return maneuver_scenario()
    if name == "omni":
        return omni_scenario()
    if name in ("diffdrive", "diffdrive-stationary"):
        return diffdrive_scenario(stationary_robot=name == "diffdrive-stationary")
    if name == "async":
        return async_scenario()
    raise ValueError(f"scenario: expected one of {', '.join(SCENARIOS)}, got {name!r}")


__all__ = [
    "NOISE_SETTINGS",
    "SCENARIOS",
    "AsyncSim",
    "Detection",
    "Scenario",
    "ScenarioSim",
    "SensorDef",
    "TimedSample",
    "async_scenario",
    "diffdrive_scenario",
    "get_scenario",
    "maneuver_scenario",
    "omni_scenario",
    "paper_scenario",
    "simulate_async",
]
