"""Every Zenoh key expression pd-service uses, built and parsed in one place.

Nothing else in the project formats a key by hand: call these functions.

Key layout 2 (protocol.md §3): every per-session key carries the session's **partition**
``p<k>`` before the session, ``k = partition_of(session)``, so that an instance subscribes
with one wildcard per partition it owns and Zenoh's routers deliver it only those samples.

Operator side (what the daemon reads and writes)::

    pd/p<k>/<session>/config          SessionSpec put (create/replace) or delete (remove)
    pd/p<k>/<session>/sensor/<name>   Measurement, after the downlink
    pd/p<k>/<session>/cmd             Command, published by the operator
    pd/p<k>/<session>/prediction      Prediction, published by the daemon
    pd/p<k>/<session>/path            PredictedPath, by the daemon if the spec asks (path)
    pd/p<k>/<session>/error           ErrorReport, published by the daemon
    pd/p<k>/<session>/status          queryable: SessionStatus
    pd/p<k>/<session>/echo            CommandEcho, after the downlink (robot's clock)
    pd/@service/<instance>            liveliness token of one daemon instance
    pd/@service/<instance>/status     queryable: ServiceStatus

Robot side (what the link emulator bridges)::

    robot/p<k>/<session>/sensor/<name>  Measurement, as the robot publishes it
    robot/p<k>/<session>/cmd            Command, after the uplink
    robot/p<k>/<session>/truth          ground truth (simulators only, for evaluation)
    robot/p<k>/<session>/echo           CommandEcho, as the robot publishes it
    robot/p<k>/<session>/clock          queryable: ClockProbe -> ClockProbeReply (the robot)
    robot/p<k>/<session>/camera         CameraFrame (a robot's video; pd-link bridges it to
                                        pd/p<k>/<session>/camera, with its own delay rule)

Link emulator::

    pd/@link/<instance>/rules    queryable: get or replace the rule set
    pd/@link/<instance>/stats    queryable: per-rule statistics

ROS 2 bridge (``pd-ros2``)::

    pd/@ros2/<instance>/status   queryable: per-session counters (JSON)

The partition: ``k = FNV-1a-32(UTF-8 bytes of the session name) mod P`` (:func:`partition_of`),
with P the deployment's partition count (:func:`partitions`: the environment variable
``PD_PARTITIONS``, default 64, read once by every party at start; every process of one
deployment must see the same value).

Key layout 1 (before partitions: ``pd/<session>/config`` and so on) is recognised only to
refuse it with a clear reason (:data:`LEGACY_CONFIGS`, :data:`LEGACY_STATUS`, :func:`is_legacy_key`).

Chunks starting with ``@`` are *verbatim* in Zenoh 1.x: ``*`` and ``**`` never match
them, so a session wildcard such as ``pd/*/*/cmd`` can never catch a service key, and a
session id (which may not start with ``@``) can never collide with one.
"""

from __future__ import annotations

import os
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

#: The key layout this build speaks (protocol.md §3).
KEY_LAYOUT = 2
#: The environment variable that sets the deployment's partition count, and its default.
PARTITIONS_ENV = "PD_PARTITIONS"
DEFAULT_PARTITIONS = 64
#: Bounds of the partition count (a partition chunk is ``p0`` .. ``p4095``).
MAX_PARTITIONS = 4096
_PART_RE = re.compile(r"p(0|[1-9][0-9]{0,3})")

StreamKind = Literal["config", "sensor", "cmd", "prediction", "path", "error", "status",
                     "truth", "echo", "clock", "camera"]


class KeyError_(ValueError):
    """A key expression that is not one of ours, or a name that is not valid."""


def check_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it matches ``[a-z0-9][a-z0-9_-]{0,63}``, else raise KeyError_."""
    if not isinstance(name, str) or _NAME_RE.fullmatch(name) is None:
        raise KeyError_(f"{what} {name!r} must match {NAME_PATTERN}")
    return name


# --- partitions ------------------------------------------------------------------------

def check_partitions(value: object, what: str = PARTITIONS_ENV) -> int:
    """A partition count: an integer 1..MAX_PARTITIONS (a string of one is accepted);
    KeyError_ naming ``what`` otherwise."""
    try:
        n = int(str(value).strip()) if not isinstance(value, int) else value
    except ValueError:
        n = 0
    if isinstance(value, bool) or not 1 <= n <= MAX_PARTITIONS:
        raise KeyError_(f"{what} must be an integer from 1 to {MAX_PARTITIONS}, got {value!r}")
    return n


def _partitions_from_env() -> int:
    raw = os.environ.get(PARTITIONS_ENV)
    return DEFAULT_PARTITIONS if raw is None or raw == "" else check_partitions(raw)


_partitions = _partitions_from_env()


def partitions() -> int:
    """The deployment's partition count P (``PD_PARTITIONS``, default 64)."""
    return _partitions


def set_partitions(n: int) -> None:
    """Set P for this process (a tool's ``--partitions`` flag, tests); every party of a
    deployment must use the same P."""
    global _partitions
    _partitions = check_partitions(n, "partitions")


def fnv1a32(data: bytes) -> int:
    """32-bit FNV-1a: h = 2166136261; for each byte: h = ((h XOR byte) * 16777619) mod 2^32."""
    h = 0x811C9DC5
    for b in data:
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h


def partition_of(session: str, n: int | None = None) -> int:
    """The partition of ``session``: FNV-1a-32 of its UTF-8 bytes mod P (``n``, default
    :func:`partitions`). Test vectors in protocol.md §3."""
    return fnv1a32(check_name(session, "session").encode()) % (partitions() if n is None else n)


def partition_chunk(k: int) -> str:
    """The key chunk of partition ``k``: ``p<k>`` (decimal, no leading zeros)."""
    return f"p{k}"


def parse_partition(chunk: str) -> int:
    """The partition index of a chunk ``p<k>``; KeyError_ if it is not one."""
    if _PART_RE.fullmatch(chunk) is None:
        raise KeyError_(f"{chunk!r} is not a partition chunk p<k>")
    return int(chunk[1:])


def _prefix(root: str, session: str) -> str:
    return f"{root}/p{partition_of(session)}/{session}"


# --- operator side ---------------------------------------------------------------------

def session_prefix(session: str) -> str:
    """``pd/p<k>/<session>``: every operator-side key of the session starts with it."""
    return _prefix(OPERATOR_ROOT, session)


def config_key(session: str) -> str:
    return f"{session_prefix(session)}/config"


def sensor_key(session: str, sensor: str) -> str:
    return f"{session_prefix(session)}/sensor/{check_name(sensor, 'sensor')}"


def sensors_of(session: str) -> str:
    """Wildcard of every sensor of one session: ``pd/p<k>/<session>/sensor/*``."""
    return f"{session_prefix(session)}/sensor/*"


def command_key(session: str) -> str:
    return f"{session_prefix(session)}/cmd"


def prediction_key(session: str) -> str:
    return f"{session_prefix(session)}/prediction"


def path_key(session: str) -> str:
    return f"{session_prefix(session)}/path"


def error_key(session: str) -> str:
    return f"{session_prefix(session)}/error"


def status_key(session: str) -> str:
    return f"{session_prefix(session)}/status"


def echo_key(session: str) -> str:
    return f"{_prefix(OPERATOR_ROOT, session)}/echo"


def service_token_key(instance: str) -> str:
    return f"{OPERATOR_ROOT}/{SERVICE_CHUNK}/{check_name(instance, 'instance')}"


def service_status_key(instance: str) -> str:
    return f"{service_token_key(instance)}/status"


# Wildcards over every partition: one subscriber per stream class, dispatch on the parsed key.
ALL_CONFIGS = f"{OPERATOR_ROOT}/*/*/config"
ALL_SENSORS = f"{OPERATOR_ROOT}/*/*/sensor/*"
ALL_COMMANDS = f"{OPERATOR_ROOT}/*/*/cmd"
ALL_PREDICTIONS = f"{OPERATOR_ROOT}/*/*/prediction"
#: Every session's predicted path (sessions whose spec asks for it).
ALL_PATHS = f"{OPERATOR_ROOT}/*/*/path"
ALL_ERRORS = f"{OPERATOR_ROOT}/*/*/error"
ALL_STATUS = f"{OPERATOR_ROOT}/*/*/status"
ALL_SERVICES = f"{OPERATOR_ROOT}/{SERVICE_CHUNK}/*"
ALL_ECHOES = f"{OPERATOR_ROOT}/*/*/echo"


def partition_sensors(k: int) -> str:
    """Every sensor sample of partition ``k``: ``pd/p<k>/*/sensor/*``."""
    return f"{OPERATOR_ROOT}/{partition_chunk(k)}/*/sensor/*"


def partition_commands(k: int) -> str:
    """Every command of partition ``k``: ``pd/p<k>/*/cmd``."""
    return f"{OPERATOR_ROOT}/{partition_chunk(k)}/*/cmd"


def all_service_status() -> str:
    return f"{OPERATOR_ROOT}/{SERVICE_CHUNK}/*/status"


# Key layout 1, recognised only to refuse it (an old client's spec put, status query).
LEGACY_CONFIGS = f"{OPERATOR_ROOT}/*/config"
LEGACY_STATUS = f"{OPERATOR_ROOT}/*/status"


def is_legacy_key(key: str) -> bool:
    """Whether ``key`` is a key-layout-1 session key (``pd/<session>/<stream>``, three
    chunks, the second a session name): an old client's."""
    parts = str(key).split("/")
    return (len(parts) == 3 and parts[0] == OPERATOR_ROOT and _NAME_RE.fullmatch(parts[1])
            is not None and parts[2] in ("config", "status", "cmd", "prediction", "error"))


def legacy_reason(key: str) -> str:
    """What an old client is told: where its session's keys are now."""
    session = str(key).split("/")[1]
    return (f"key {key!r} is of key layout 1; this service speaks key layout {KEY_LAYOUT}: "
            f"a session's keys carry its partition, e.g. {config_key(session)!r} "
            f"(partition = FNV-1a-32(name) mod {partitions()}, protocol.md §3): upgrade the client")


def error_key_beside(key: str) -> str:
    """The error key next to a config or status key, whatever its layout or partition
    (``pd/p<k>/<s>/config`` -> ``pd/p<k>/<s>/error``, ``pd/<s>/config`` -> ``pd/<s>/error``):
    where the client that used ``key`` listens, when the daemon refuses the key itself."""
    return f"{str(key).rsplit('/', 1)[0]}/error"


# --- robot side ------------------------------------------------------------------------

def robot_sensor_key(session: str, sensor: str) -> str:
    return f"{_prefix(ROBOT_ROOT, session)}/sensor/{check_name(sensor, 'sensor')}"


def robot_command_key(session: str) -> str:
    return f"{_prefix(ROBOT_ROOT, session)}/cmd"


def truth_key(session: str) -> str:
    return f"{_prefix(ROBOT_ROOT, session)}/truth"


def robot_echo_key(session: str) -> str:
    return f"{_prefix(ROBOT_ROOT, session)}/echo"


def robot_clock_key(session: str) -> str:
    """The robot's probe queryable (the daemon queries it directly: pd-link relays samples,
    not queries)."""
    return f"{_prefix(ROBOT_ROOT, session)}/clock"


def robot_camera_key(session: str) -> str:
    return f"{_prefix(ROBOT_ROOT, session)}/camera"


def camera_key(session: str) -> str:
    """The camera frames after the downlink (pd-link bridges robot/.../camera here)."""
    return f"{session_prefix(session)}/camera"


ROBOT_ALL_SENSORS = f"{ROBOT_ROOT}/*/*/sensor/*"
ROBOT_ALL_ECHOES = f"{ROBOT_ROOT}/*/*/echo"
ROBOT_ALL_COMMANDS = f"{ROBOT_ROOT}/*/*/cmd"
ALL_TRUTHS = f"{ROBOT_ROOT}/*/*/truth"
ROBOT_ALL_CAMERAS = f"{ROBOT_ROOT}/*/*/camera"
ALL_CAMERAS = f"{OPERATOR_ROOT}/*/*/camera"


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
    """A key split into its parts. ``side`` is "operator" (``pd/``) or "robot" (``robot/``);
    ``partition`` the index of its partition chunk (checked against the session's)."""

    side: Literal["operator", "robot"]
    session: str
    kind: StreamKind
    sensor: str | None = None
    partition: int = 0


_KINDS_OPERATOR = {"config", "cmd", "prediction", "path", "error", "status", "echo", "camera"}
_KINDS_ROBOT = {"cmd", "truth", "echo", "clock", "camera"}


def parse_key(key: str) -> ParsedKey:
    """Parse a concrete per-session key (``<root>/p<k>/<session>/<stream>[/<sensor>]``);
    raise KeyError_ with a readable reason if it is not one, names a partition other than
    the session's, or is of key layout 1."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] not in (OPERATOR_ROOT, ROBOT_ROOT):
        raise KeyError_(f"key {key!r} is not a pd-service session key")
    if is_legacy_key(key):
        raise KeyError_(legacy_reason(key))
    side: Literal["operator", "robot"] = "operator" if parts[0] == OPERATOR_ROOT else "robot"
    if len(parts) < 4:
        raise KeyError_(f"key {key!r} is not a pd-service session key "
                        "(<root>/p<k>/<session>/<stream>)")
    part = parse_partition(parts[1])
    session = check_name(parts[2], "session")
    want = partition_of(session)
    if part != want:
        raise KeyError_(f"key {key!r}: session {session!r} is in partition p{want} of "
                        f"{partitions()}, not {parts[1]} (is {PARTITIONS_ENV} the same for "
                        "every party?)")
    kind = parts[3]
    if kind == "sensor":
        if len(parts) != 5:
            raise KeyError_(f"key {key!r}: a sensor key is <root>/p<k>/<session>/sensor/<name>")
        return ParsedKey(side, session, "sensor", check_name(parts[4], "sensor"), part)
    allowed = _KINDS_OPERATOR if side == "operator" else _KINDS_ROBOT
    if len(parts) != 4 or kind not in allowed:
        raise KeyError_(f"key {key!r}: unknown stream {kind!r} for the {side} side")
    return ParsedKey(side, session, kind, None, part)  # type: ignore[arg-type]


def session_of(key: str) -> str | None:
    """The session chunk of a per-session key (``<root>/p<k>/<session>/...``), unchecked:
    the hot path's split; None if the key has too few chunks."""
    parts = key.split("/", 3)
    return parts[2] if len(parts) == 4 else None


def to_operator_side(key: str) -> str:
    """Map a robot-side key to its operator-side twin (``robot/p<k>/s/sensor/x`` ->
    ``pd/p<k>/s/sensor/x``)."""
    p = parse_key(key)
    if p.kind == "sensor":
        return sensor_key(p.session, p.sensor or "")
    if p.kind == "cmd":
        return command_key(p.session)
    if p.kind == "echo":
        return echo_key(p.session)
    if p.kind == "camera":
        return camera_key(p.session)
    raise KeyError_(f"key {key!r} has no operator-side twin")


def to_robot_side(key: str) -> str:
    """Map an operator-side key to its robot-side twin (``pd/p<k>/s/cmd`` ->
    ``robot/p<k>/s/cmd``)."""
    p = parse_key(key)
    if p.kind == "sensor":
        return robot_sensor_key(p.session, p.sensor or "")
    if p.kind == "cmd":
        return robot_command_key(p.session)
    raise KeyError_(f"key {key!r} has no robot-side twin")
