"""A 2-D robot driving straight legs and turns, with a linear constant-velocity model the
linear service can track exactly::

    x = [px, py, vx, vy],  u = [ax, ay] (m/s^2),  d = step period (s)
    A = [[I, d I], [0, I]],  B = [[d^2/2 I], [d I]],  w = B a,  a ~ N(0, sigma_a^2 I)
    gnss:     z = [px, py] + v,  every 4 steps, delay 8, std 0.2 m
    odometry: z = [vx, vy] + v,  every step,    delay 3, std 0.05 m/s
    lead 6 (uplink 0.3 s)

The robot rests for 20 steps (so that the first commands, which apply from step lead on,
are all delivered), accelerates along +x for 40 steps to 0.5 m/s, then repeats a pattern of
legs and turns. A turn is open-loop centripetal acceleration: with nominal speed s and
heading theta(k), u(k) = s ([cos, sin](theta(k) + omega d) - [cos, sin](theta(k))) / d,
which rotates the nominal velocity by omega d per step exactly.
"""

from __future__ import annotations

import math

import numpy as np

from .simulator import Scenario, SensorDef

MANEUVER_PERIOD_S = 0.05
MANEUVER_SPEED = 0.5  # m/s, cruise speed
MANEUVER_REST_STEPS = 20  # steps at rest first (longer than the lead: every command arrives)
MANEUVER_ACCEL_STEPS = 40  # steps of constant acceleration from rest to cruise speed
MANEUVER_SIGMA_A = 0.05  # m/s^2, acceleration noise
#: The repeating pattern after the start: ("leg", steps) or ("turn", degrees, steps).
MANEUVER_PATTERN: tuple[tuple, ...] = (
    ("leg", 80), ("turn", 90.0, 60), ("leg", 60), ("turn", -90.0, 60),
    ("leg", 80), ("turn", 180.0, 100), ("leg", 40), ("turn", -90.0, 40),
)


def _pattern_total() -> tuple[int, float]:
    steps = sum(seg[-1] for seg in MANEUVER_PATTERN)
    degrees = sum(seg[1] for seg in MANEUVER_PATTERN if seg[0] == "turn")
    return steps, degrees


def maneuver_heading(k: int, d: float = MANEUVER_PERIOD_S) -> tuple[float, float]:
    """Nominal (heading at step k in radians, turn rate omega in rad/s during step k)."""
    start = MANEUVER_REST_STEPS + MANEUVER_ACCEL_STEPS
    if k < start:
        return 0.0, 0.0
    cycle_steps, cycle_deg = _pattern_total()
    j = k - start
    n_cycles, j = divmod(j, cycle_steps)
    heading = math.radians(cycle_deg) * n_cycles
    for seg in MANEUVER_PATTERN:
        steps = seg[-1]
        if seg[0] == "leg":
            if j < steps:
                return heading, 0.0
        else:
            omega = math.radians(seg[1]) / (steps * d)
            if j < steps:
                return heading + omega * d * j, omega
            heading += math.radians(seg[1])
        j -= steps
    raise AssertionError("unreachable")  # pragma: no cover


def maneuver_command(k: int, d: float = MANEUVER_PERIOD_S) -> np.ndarray:
    """u(k) = [ax, ay], m/s^2: rest, accelerate along +x, then legs (u = 0) and turns."""
    if k < MANEUVER_REST_STEPS:
        return np.zeros(2)
    if k < MANEUVER_REST_STEPS + MANEUVER_ACCEL_STEPS:
        return np.array([MANEUVER_SPEED / (MANEUVER_ACCEL_STEPS * d), 0.0])
    theta, omega = maneuver_heading(k, d)
    if omega == 0.0:
        return np.zeros(2)
    # u = s (e(theta + omega d) - e(theta)) / d: rotates the nominal velocity by omega d.
    a = theta + omega * d
    return MANEUVER_SPEED * np.array([math.cos(a) - math.cos(theta),
                                      math.sin(a) - math.sin(theta)]) / d


def maneuver_scenario() -> Scenario:
    """The scenario (see the module docstring); endless (default_steps 0)."""
    d = MANEUVER_PERIOD_S
    eye, zero = np.eye(2), np.zeros((2, 2))
    A = np.block([[eye, d * eye], [zero, eye]])
    B = np.vstack([0.5 * d * d * eye, d * eye])
    G = MANEUVER_SIGMA_A * B  # w = B a, a ~ N(0, sigma_a^2 I)
    Q = G @ G.T
    return Scenario(
        name="maneuver",
        description="2-D robot: straight legs and turns, constant-velocity model",
        period_s=d, A=A, B=B, Q=Q,
        sensors=(
            SensorDef("gnss", np.hstack([eye, zero]), 0.2 * eye, delay=8, interval=4),
            SensorDef("odometry", np.hstack([zero, eye]), 0.05 * eye, delay=3, interval=1),
        ),
        x0_true=np.zeros(4), x0=np.zeros(4), P0=np.diag([1.0, 1.0, 0.1, 0.1]),
        lead=6, max_delay=12,
        state_names=("px", "py", "vx", "vy"),
        command=maneuver_command,
        default_steps=0,
        G=G,
    )
