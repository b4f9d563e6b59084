"""Zenoh key expressions and liveliness tokens of ROS 2 entities, as rmw_zenoh_cpp (ROS 2 Jazzy)
and zenoh-bridge-ros2dds build them.

Sources (docs/ros2.md has the details): ros2/rmw_zenoh ``docs/design.md`` sections "Topic and
Service name mapping to Zenoh key expressions" and "Graph Cache", and
``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` / ``qos.cpp`` (the versions with type hashes and
the compact QoS chunk, as released in Jazzy 0.2.x); zenoh-plugin-ros2dds
``src/ros2_utils.rs::ros2_name_to_key_expr``.

rmw_zenoh formats::

    data key:        <domain_id>/<fq_name without leading '/'>/<dds_type>/<type_hash>
    node token:      @ros2_lv/<domain_id>/<zid>/<node_id>/<node_id>/NN/<enclave%>/<namespace%>/<node>
    endpoint token:  @ros2_lv/<domain_id>/<zid>/<node_id>/<entity_id>/<MP|MS|SS|SC>/<enclave%>/
                     <namespace%>/<node>/<fq_name%>/<dds_type>/<type_hash>/<qos>

where ``x%`` is ``x`` with every ``/`` replaced by ``%`` (``/`` itself becomes ``%``), ``zid`` the
Zenoh session id in lowercase hex, and ``dds_type`` e.g. ``std_msgs::msg::dds_::String_``.

zenoh-bridge-ros2dds: the key is the fully qualified name without its leading ``/``, prefixed by
the bridge's namespace (also without leading ``/``) when one is configured: ``/cmd_vel`` ->
``cmd_vel``, or ``bot1/cmd_vel`` with ``namespace: "/bot1"``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from typing import Literal

from pd_service.errors import ConfigError
from pd_service.ros2.errors import Ros2DecodeError
from pd_service.wire.ros2 import check_topic_name

#: Prefix of every rmw_zenoh liveliness token (a Zenoh hermetic namespace).
ADMIN_SPACE = "@ros2_lv"
#: rmw_zenoh's replacement for ``/`` inside one key chunk.
SLASH_REPLACEMENT = "%"

EntityKind = Literal["NN", "MP", "MS", "SS", "SC"]
EndpointKind = Literal["MP", "MS"]

#: One ROS 2 name token: a letter or underscore, then letters, digits, underscores.
_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_NAME = re.compile(rf"^/?{_TOKEN}(/{_TOKEN})*$")
_NAMESPACE = re.compile(rf"^/({_TOKEN}(/{_TOKEN})*)?$")
_ROS_TYPE = re.compile(rf"^({_TOKEN})/(msg|srv)/({_TOKEN})$")
_TYPE_HASH = re.compile(r"^RIHS01_[0-9a-f]{64}$")
_ZID = re.compile(r"^[0-9a-f]{1,32}$")


def check_namespace(namespace: str) -> str:
    """Return ``namespace`` if it is an absolute ROS 2 namespace (``/`` or ``/a/b``)."""
    if not _NAMESPACE.match(namespace):
        raise ValueError(f"{namespace!r} is not an absolute ROS 2 namespace ('/' or '/a/b')")
    return namespace


def domain_id(given: int | None) -> int:
    """The ROS domain id: ``given``, else ``$ROS_DOMAIN_ID``, else 0 (ROS 2's rule). Raises
    ConfigError (a ValueError) when the variable is not a number."""
    if given is not None:
        return given
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    try:
        return int(env) if env else 0
    except ValueError:
        raise ConfigError(f"ROS_DOMAIN_ID={env!r} is not a number") from None


def fully_qualified_name(namespace: str, name: str) -> str:
    """The fully qualified topic name: an absolute ``name`` as is, a relative one under
    ``namespace`` (ROS 2 name resolution without ``~`` and remapping)."""
    check_namespace(namespace)
    check_topic_name(name)
    if name.startswith("/"):
        return name
    return f"/{name}" if namespace == "/" else f"{namespace}/{name}"


def mangle(name: str) -> str:
    """rmw_zenoh ``mangle_name``: every ``/`` replaced by ``%`` (``/`` -> ``%``,
    ``/robot1/chatter`` -> ``%robot1%chatter``)."""
    return name.replace("/", SLASH_REPLACEMENT)


def demangle(chunk: str) -> str:
    """rmw_zenoh ``demangle_name``: every ``%`` replaced by ``/``."""
    return chunk.replace(SLASH_REPLACEMENT, "/")


def dds_type_name(ros_type: str) -> str:
    """The DDS (CDR) type name rmw_zenoh puts in keys: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    m = _ROS_TYPE.match(ros_type)
    if not m:
        raise ValueError(f"{ros_type!r} is not a ROS 2 interface type 'pkg/msg/Name'")
    pkg, kind, name = m.groups()
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_type: str) -> str:
    """Inverse of :func:`dds_type_name`."""
    m = re.match(rf"^({_TOKEN})::(msg|srv)::dds_::({_TOKEN})_$", dds_type)
    if not m:
        raise ValueError(f"{dds_type!r} is not a DDS type name 'pkg::msg::dds_::Name_'")
    pkg, kind, name = m.groups()
    return f"{pkg}/{kind}/{name}"


def _check_domain(domain_id: int) -> None:
    # ROS_DOMAIN_ID: rmw_zenoh accepts any size_t; DDS vendors 0..232. We keep 0..232.
    if not 0 <= domain_id <= 232:
        raise ValueError(f"ROS domain id {domain_id} is outside 0..232")


def topic_keyexpr(domain_id: int, fq_name: str, ros_type: str, type_hash: str) -> str:
    """rmw_zenoh data key ``<domain_id>/<fq_name>/<dds_type>/<type_hash>`` (``TopicInfo``:
    the name with its leading and trailing ``/`` stripped)."""
    _check_domain(domain_id)
    check_topic_name(fq_name)
    if not _TYPE_HASH.match(type_hash):
        raise ValueError(f"{type_hash!r} is not a RIHS01 type hash")
    return f"{domain_id}/{fq_name.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


def bridge_keyexpr(fq_name: str, bridge_namespace: str = "/") -> str:
    """zenoh-bridge-ros2dds data key: ``fq_name`` without its leading ``/``, under the bridge's
    ``namespace`` setting (``ros2_name_to_key_expr``)."""
    check_namespace(bridge_namespace)
    check_topic_name(fq_name)
    if not fq_name.startswith("/"):
        raise ValueError(f"{fq_name!r} is not fully qualified (no leading '/')")
    if bridge_namespace == "/":
        return fq_name[1:]
    return f"{bridge_namespace[1:]}/{fq_name[1:]}"


# ---------------------------------------------------------------------------------------------
# QoS chunk of endpoint tokens (liveliness_utils.cpp qos_to_keyexpr / keyexpr_to_qos)
# ---------------------------------------------------------------------------------------------

Reliability = Literal["reliable", "best_effort"]
Durability = Literal["volatile", "transient_local"]
History = Literal["keep_last", "keep_all"]

# rmw/types.h enum values, written as decimal in the token ("" = rmw_zenoh default,
# "0" = SYSTEM_DEFAULT, which rmw_zenoh resolves to the default too).
_RELIABILITY_CODE: dict[str, int] = {"reliable": 1, "best_effort": 2}
_DURABILITY_CODE: dict[str, int] = {"transient_local": 1, "volatile": 2}
_HISTORY_CODE: dict[str, int] = {"keep_last": 1, "keep_all": 2}
_RELIABILITY_BY_CODE: dict[str, Reliability] = {
    "": "reliable",
    "0": "reliable",
    "1": "reliable",
    "2": "best_effort",
}
_DURABILITY_BY_CODE: dict[str, Durability] = {
    "": "volatile",
    "0": "volatile",
    "1": "transient_local",
    "2": "volatile",
}
_HISTORY_BY_CODE: dict[str, History] = {"": "keep_last", "0": "keep_last", "1": "keep_last", "2": "keep_all"}
#: rmw_zenoh's defaults (qos.cpp, Jazzy >= 0.2.3): an empty component means this value.
DEFAULT_DEPTH = 42


@dataclass(frozen=True)
class QoS:
    """The QoS of one endpoint, as far as pd-service sets it. Deadline, lifespan and liveliness
    are always the defaults (infinite, AUTOMATIC), which the token writes as empty components."""

    reliability: Reliability = "reliable"
    durability: Durability = "volatile"
    history: History = "keep_last"
    depth: int = DEFAULT_DEPTH

    def __post_init__(self) -> None:
        if self.depth < 0:
            raise ValueError(f"QoS depth {self.depth} is negative")

    def keyexpr(self) -> str:
        """The compact form
        ``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>``
        with each component left empty when it equals rmw_zenoh's default (reliable, volatile,
        keep_last, depth 42, infinite durations, AUTOMATIC). Depth 0 is written as 0 (rmw_zenoh
        replaces it with 42 before building the token; so should a caller)."""
        rel = "" if self.reliability == "reliable" else str(_RELIABILITY_CODE[self.reliability])
        dur = "" if self.durability == "volatile" else str(_DURABILITY_CODE[self.durability])
        hist = "" if self.history == "keep_last" else str(_HISTORY_CODE[self.history])
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{rel}:{dur}:{hist},{depth}:,:,:,,"


def parse_qos(chunk: str) -> QoS:
    """Parse the QoS chunk of an endpoint token. Deadline/lifespan/liveliness components are
    accepted and ignored; empty or SYSTEM_DEFAULT (0) means the default. Raises Ros2DecodeError."""
    parts = chunk.split(":")
    if len(parts) < 6:
        raise Ros2DecodeError(f"QoS chunk {chunk!r}: expected 6 ':'-separated parts")
    hist_parts = parts[2].split(",")
    if len(hist_parts) < 2:
        raise Ros2DecodeError(f"QoS chunk {chunk!r}: history part needs '<kind>,<depth>'")
    reliability = _RELIABILITY_BY_CODE.get(parts[0])
    durability = _DURABILITY_BY_CODE.get(parts[1])
    history = _HISTORY_BY_CODE.get(hist_parts[0])
    if reliability is None or durability is None or history is None:
        raise Ros2DecodeError(f"QoS chunk {chunk!r}: unsupported reliability/durability/history")
    try:
        depth = int(hist_parts[1]) if hist_parts[1] else DEFAULT_DEPTH
    except ValueError:
        raise Ros2DecodeError(f"QoS chunk {chunk!r}: depth {hist_parts[1]!r} is not a number") from None
    if depth < 0:
        raise Ros2DecodeError(f"QoS chunk {chunk!r}: negative depth")
    return QoS(reliability=reliability, durability=durability, history=history, depth=depth)


# ---------------------------------------------------------------------------------------------
# Liveliness tokens
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NodeIdentity:
    """A ROS 2 node as rmw_zenoh announces it.

    ``session_id`` is the Zenoh session id as ``zenoh::Id::to_string`` prints it (lowercase hex);
    ``node_id`` is the context-wide entity counter value the node got. ``enclave`` and
    ``namespace`` are absolute (``/`` when unset, mangled to ``%``).
    """

    domain_id: int
    session_id: str
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def __post_init__(self) -> None:
        _check_domain(self.domain_id)
        if not _ZID.match(self.session_id):
            raise ValueError(f"session id {self.session_id!r} is not a lowercase hex Zenoh id")
        if self.node_id < 0:
            raise ValueError(f"node id {self.node_id} is negative")
        if not re.match(rf"^{_TOKEN}$", self.name):
            raise ValueError(f"{self.name!r} is not a ROS 2 node name")
        check_namespace(self.namespace)
        check_namespace(self.enclave)

    def _prefix(self, entity_id: int, kind: EntityKind) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.session_id}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}"
        )

    def token(self) -> str:
        """The node's liveliness token (``NN``; the node id is written twice)."""
        return self._prefix(self.node_id, "NN")

    def resolve(self, topic: str) -> str:
        """``topic`` resolved against this node's namespace."""
        return fully_qualified_name(self.namespace, topic)


@dataclass(frozen=True)
class TopicEndpoint:
    """A publisher (``MP``) or subscription (``MS``) of ``node`` on a fully qualified topic."""

    node: NodeIdentity
    entity_id: int
    kind: EndpointKind
    topic: str
    ros_type: str
    type_hash: str
    qos: QoS = QoS()

    def __post_init__(self) -> None:
        if self.entity_id < 0:
            raise ValueError(f"entity id {self.entity_id} is negative")
        check_topic_name(self.topic)
        if not self.topic.startswith("/"):
            raise ValueError(f"topic {self.topic!r} is not fully qualified (use node.resolve)")
        dds_type_name(self.ros_type)
        if not _TYPE_HASH.match(self.type_hash):
            raise ValueError(f"{self.type_hash!r} is not a RIHS01 type hash")

    def token(self) -> str:
        """The endpoint's liveliness token."""
        return (
            f"{self.node._prefix(self.entity_id, self.kind)}/{mangle(self.topic)}/"
            f"{dds_type_name(self.ros_type)}/{self.type_hash}/{self.qos.keyexpr()}"
        )

    def keyexpr(self) -> str:
        """The data key expression the endpoint publishes on or subscribes to."""
        return topic_keyexpr(self.node.domain_id, self.topic, self.ros_type, self.type_hash)

    def gid(self) -> bytes:
        """The endpoint's 16-byte GID, as rmw_zenoh derives it from its token (see
        :func:`entity_gid`); the publisher GID of the attachment."""
        return entity_gid(self.token())


def entity_gid(token: str) -> bytes:
    """rmw_zenoh's GID of an entity: XXH3-128 (seed 0) of the liveliness token, stored as the
    low 64 bits then the high 64 bits, each in host order (little-endian on x86-64 and arm64).

    ``liveliness_utils.cpp`` uses ``simplified_XXH3_128bits``, stated in its source to be the
    portable path of stock XXH3 (xxHash commit 8ffd354); here the ``xxhash`` package computes it.
    """
    import xxhash

    value = xxhash.xxh3_128_intdigest(token.encode("utf-8"))
    low, high = value & 0xFFFF_FFFF_FFFF_FFFF, value >> 64
    return low.to_bytes(8, "little") + high.to_bytes(8, "little")


@dataclass(frozen=True)
class ParsedToken:
    """The parts of an rmw_zenoh liveliness token (names demangled). Endpoint fields are None
    for a node token."""

    domain_id: int
    session_id: str
    node_id: int
    entity_id: int
    kind: EntityKind
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None
    qos: QoS | None = None


_KINDS: dict[str, EntityKind] = {"NN": "NN", "MP": "MP", "MS": "MS", "SS": "SS", "SC": "SC"}


def parse_token(token: str) -> ParsedToken:
    """Split an rmw_zenoh liveliness token (``Entity::make(keyexpr)``). Raises Ros2DecodeError."""
    parts = token.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        raise Ros2DecodeError(f"liveliness token {token!r}: not '{ADMIN_SPACE}/...' with 9+ parts")
    kind = _KINDS.get(parts[5])
    if kind is None:
        raise Ros2DecodeError(f"liveliness token {token!r}: unknown entity kind {parts[5]!r}")
    try:
        domain_id, node_id, entity_id = int(parts[1]), int(parts[3]), int(parts[4])
    except ValueError:
        raise Ros2DecodeError(f"liveliness token {token!r}: domain/node/entity ids must be numbers") from None
    expected = 9 if kind == "NN" else 13
    if len(parts) != expected:
        raise Ros2DecodeError(f"liveliness token {token!r}: a {kind} token has {expected} parts")
    topic = ros_type = type_hash = None
    qos = None
    if kind != "NN":
        try:
            ros_type = ros_type_name(demangle(parts[10]))
        except ValueError as exc:
            raise Ros2DecodeError(f"liveliness token {token!r}: {exc}") from None
        topic, type_hash, qos = demangle(parts[9]), demangle(parts[11]), parse_qos(parts[12])
    return ParsedToken(
        domain_id=domain_id,
        session_id=parts[2],
        node_id=node_id,
        entity_id=entity_id,
        kind=kind,
        enclave=demangle(parts[6]),
        namespace=demangle(parts[7]),
        node_name=demangle(parts[8]),
        topic=topic,
        ros_type=ros_type,
        type_hash=type_hash,
        qos=qos,
    )
