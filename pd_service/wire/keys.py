"""Every Zenoh key expression pd-service uses, built and parsed in one place.

Nothing else in the project formats a key by hand: call these functions.

Operator side (what the daemon reads and writes)::

    pd/<session>/config          SessionSpec put (create/replace) or delete (remove)
    pd/<session>/sensor/<name>   Measurement, after the downlink
    pd/<session>/cmd             Command, published by the operator
    pd/<session>/prediction      Prediction, published by the daemon
    pd/<session>/error           ErrorReport, published by the daemon
    pd/<session>/status          queryable: SessionStatus
    pd/@service/<instance>       liveliness token of one daemon instance
    pd/@service/<instance>/status queryable: ServiceStatus

Robot side (what the link emulator bridges)::

    robot/<session>/sensor/<name>  Measurement, as the robot publishes it
    robot/<session>/cmd            Command, after the uplink
    robot/<session>/truth          ground truth (simulators only, for evaluation)

Link emulator::

    pd/@link/<instance>/rules    queryable: get or replace the rule set
    pd/@link/<instance>/stats    queryable: per-rule statistics

ROS 2 bridge (``pd-ros2``)::

    pd/@ros2/<instance>/status   queryable: per-session counters (JSON)

Chunks starting with ``@`` are *verbatim* in Zenoh 1.x: ``*`` and ``**`` never match
them, so a session wildcard such as ``pd/*/cmd`` can never catch a service key, and a
session id (which may not start with ``@``) can never collide with one.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

NAME_PATTERN = r"[a-z0-9][a-z0-9_-]{0,63}"
_NAME_RE = re.compile(NAME_PATTERN)

OPERATOR_ROOT = "pd"
ROBOT_ROOT = "robot"
SERVICE_CHUNK = "@service"
LINK_CHUNK = "@link"
ROS2_CHUNK = "@ros2"

StreamKind = Literal["config", "sensor", "cmd", "prediction", "error", "status", "truth"]


class KeyError_(ValueError):
    """A key expression that is not one of ours, or a name that is not valid."""


def check_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it matches ``[a-z0-9][a-z0-9_-]{0,63}``, else raise KeyError_."""
    if not isinstance(name, str) or _NAME_RE.fullmatch(name) is None:
        raise KeyError_(f"{what} {name!r} must match {NAME_PATTERN}")
    return name


# --- operator side ---------------------------------------------------------------------

def config_key(session: str) -> str:
    return f"{OPERATOR_ROOT}/{check_name(session, 'session')}/config"


def sensor_key(session: str, sensor: str) -> str:
    return f"{OPERATOR_ROOT}/{check_name(session, 'session')}/sensor/{check_name(sensor, 'sensor')}"


def command_key(session: str) -> str:
    return f"{OPERATOR_ROOT}/{check_name(session, 'session')}/cmd"


def prediction_key(session: str) -> str:
    return f"{OPERATOR_ROOT}/{check_name(session, 'session')}/prediction"


def error_key(session: str) -> str:
    return f"{OPERATOR_ROOT}/{check_name(session, 'session')}/error"


def status_key(session: str) -> str:
    return f"{OPERATOR_ROOT}/{check_name(session, 'session')}/status"


def service_token_key(instance: str) -> str:
    return f"{OPERATOR_ROOT}/{SERVICE_CHUNK}/{check_name(instance, 'instance')}"


def service_status_key(instance: str) -> str:
    return f"{service_token_key(instance)}/status"


# Wildcards: one subscriber per stream class, dispatch on the parsed key.
ALL_CONFIGS = f"{OPERATOR_ROOT}/*/config"
ALL_SENSORS = f"{OPERATOR_ROOT}/*/sensor/*"
ALL_COMMANDS = f"{OPERATOR_ROOT}/*/cmd"
ALL_PREDICTIONS = f"{OPERATOR_ROOT}/*/prediction"
ALL_ERRORS = f"{OPERATOR_ROOT}/*/error"
ALL_STATUS = f"{OPERATOR_ROOT}/*/status"
ALL_SERVICES = f"{OPERATOR_ROOT}/{SERVICE_CHUNK}/*"


def all_service_status() -> str:
    return f"{OPERATOR_ROOT}/{SERVICE_CHUNK}/*/status"


# --- robot side ------------------------------------------------------------------------

def robot_sensor_key(session: str, sensor: str) -> str:
    return f"{ROBOT_ROOT}/{check_name(session, 'session')}/sensor/{check_name(sensor, 'sensor')}"


def robot_command_key(session: str) -> str:
    return f"{ROBOT_ROOT}/{check_name(session, 'session')}/cmd"


def truth_key(session: str) -> str:
    return f"{ROBOT_ROOT}/{check_name(session, 'session')}/truth"


ROBOT_ALL_SENSORS = f"{ROBOT_ROOT}/*/sensor/*"
ROBOT_ALL_COMMANDS = f"{ROBOT_ROOT}/*/cmd"


# --- link emulator ---------------------------------------------------------------------

def link_rules_key(instance: str) -> str:
    return f"{OPERATOR_ROOT}/{LINK_CHUNK}/{check_name(instance, 'instance')}/rules"


def link_stats_key(instance: str) -> str:
    return f"{OPERATOR_ROOT}/{LINK_CHUNK}/{check_name(instance, 'instance')}/stats"


# --- ROS 2 bridge ----------------------------------------------------------------------

def ros2_status_key(instance: str) -> str:
    return f"{OPERATOR_ROOT}/{ROS2_CHUNK}/{check_name(instance, 'instance')}/status"


# --- parsing ---------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class ParsedKey:
    """A key split into its parts. ``side`` is "operator" (``pd/``) or "robot" (``robot/``)."""

    side: Literal["operator", "robot"]
    session: str
    kind: StreamKind
    sensor: str | None = None


_KINDS_OPERATOR = {"config", "cmd", "prediction", "error", "status"}
_KINDS_ROBOT = {"cmd", "truth"}


def parse_key(key: str) -> ParsedKey:
    """Parse a concrete per-session key; raise KeyError_ with a readable reason if it is not one."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] not in (OPERATOR_ROOT, ROBOT_ROOT):
        raise KeyError_(f"key {key!r} is not a pd-service session key")
    side: Literal["operator", "robot"] = "operator" if parts[0] == OPERATOR_ROOT else "robot"
    session = check_name(parts[1], "session")
    kind = parts[2]
    if kind == "sensor":
        if len(parts) != 4:
            raise KeyError_(f"key {key!r}: a sensor key is <root>/<session>/sensor/<name>")
        return ParsedKey(side, session, "sensor", check_name(parts[3], "sensor"))
    allowed = _KINDS_OPERATOR if side == "operator" else _KINDS_ROBOT
    if len(parts) != 3 or kind not in allowed:
        raise KeyError_(f"key {key!r}: unknown stream {kind!r} for the {side} side")
    return ParsedKey(side, session, kind)  # type: ignore[arg-type]


def to_operator_side(key: str) -> str:
    """Map a robot-side key to its operator-side twin (``robot/s/sensor/x`` -> ``pd/s/sensor/x``)."""
    p = parse_key(key)
    if p.kind == "sensor":
        return sensor_key(p.session, p.sensor or "")
    if p.kind == "cmd":
        return command_key(p.session)
    raise KeyError_(f"key {key!r} has no operator-side twin")


def to_robot_side(key: str) -> str:
    """Map an operator-side key to its robot-side twin (``pd/s/cmd`` -> ``robot/s/cmd``)."""
    p = parse_key(key)
    if p.kind == "sensor":
        return robot_sensor_key(p.session, p.sensor or "")
    if p.kind == "cmd":
        return robot_command_key(p.session)
    raise KeyError_(f"key {key!r} has no robot-side twin")
