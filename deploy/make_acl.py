#!/usr/bin/env python3
"""Generate the Zenoh router configuration (access control scoped by session) of a pd-service
deployment from a short list of sessions and users.

    python deploy/make_acl.py deploy/sessions.toml > deploy/zenoh/router.json5
    python deploy/make_acl.py deploy/sessions.toml --check deploy/zenoh/router.json5
    python deploy/make_acl.py deploy/sessions.toml --partitions 256 > ...   # P (else
                                                            # PD_PARTITIONS, else 64)

Keys are of key layout 2 (protocol.md §2): a session's keys carry its partition,
``pd/p<k>/<s>/...`` and ``robot/p<k>/<s>/...`` with ``k = FNV-1a-32(s) mod P``; P is the
deployment's partition count, the same for every party (``PD_PARTITIONS``), and is written into
the generated file's header.  Below, ``<s>`` stands for ``p<k>/<s>``.

The input (TOML; every list of users may name several users, a user may have several roles)::

    admins = ["admin"]        # create, replace, delete ANY session: pd/p<k>/<s>/config
    link_admins = ["admin"]   # read and replace pd-link's rules: pd/@link/<i>/rules
    services = ["service"]    # the pd-service daemon instances (pd/@service/** is theirs only)
    links = ["link"]          # the link emulator (bridges robot/p<k>/<s>/... <-> pd/p<k>/<s>/...)
    displays = ["display"]    # read-only: predictions, errors, statuses, specs, truth, stats
    users_file = "/etc/zenoh/users.txt"   # optional (router's path of the user:password list)
    listen = ["tcp/[::]:7447"]            # optional (default tls/[::]:7447 with [tls])

    [tls]                     # optional: TLS with mutual authentication instead of passwords
    ca = "/etc/zenoh/certs/ca.pem"                 # paths on the router's host
    certificate = "/etc/zenoh/certs/router.pem"    # (deploy/make_certs.py makes them)
    private_key = "/etc/zenoh/certs/router-key.pem"
    # a client is then known by its certificate's common name (cert_common_names), which is
    # its role's user name below; only tls/ listeners (no plaintext port); no users_file

    [mesh]                    # optional: several routers meshed, each with this configuration
    zids = ["a1a1", "b2b2"]   # every router's Zenoh id (zenohd -i <zid>): they trust each other
    user = "router"           # the user a router logs in with to the router it connects to
    password = "..."          # (must be in users.txt)
    # with [tls] instead: common_names = ["router-a", "router-b"] (their certificates' CNs:
    # mutual TLS between the routers; a Zenoh id is only claimed, a certificate is proven)

    [[session]]
    name = "paper"
    robot = "robot"           # puts robot/paper/{sensor/*,truth,camera,echo}; gets robot/paper/cmd;
                              # answers probes on robot/paper/clock
    operator = "operator"     # puts pd/paper/cmd; reads pd/paper/{prediction,path,error,status,
                              # config,camera}
    direct = true             # optional: the robot also puts pd/paper/{sensor/*,camera}, gets
                              # pd/paper/cmd (no link emulator in between)
    robot_creates = true      # optional: the robot may create/replace/delete THIS session's
                              # spec (pd-robot-sim --create-session); default: admins only

Sender caches (zenoh-ext advanced publishers: a queryable and a liveliness token on
``<key>/@adv/pub/**``): a direct robot and an operator may serve them on their sessions'
``pd/p<k>/<s>/sensor/*`` and ``pd/p<k>/<s>/cmd``, links on every session's; only services may query them
and watch their tokens (deploy/README.md, "Sender caches").

Key layout 1 (``pd/<s>/config``, ``pd/<s>/status``, ``pd/<s>/error``: clients before
partitions) passes only where the daemon refuses it with a reason: services subscribe and
answer there, admins and a session's operator (and a ``robot_creates`` robot) reach it.

Routers of a mesh recognise each other by Zenoh id (the router that connects out sees the
other without a user name, so a user alone cannot match it) and relay between them whatever
any rule allows a client; each router enforces its own clients' rules (deploy/README.md).

Only stdlib; the output is JSON (valid JSON5) behind a comment header.  Rules come in the pairs
of Zenoh's model: what a client may send in (``ingress``: put, declare_subscriber, query,
declare_queryable, reply, liveliness_token) and what the router may deliver to it (``egress``).
Exit status 2 with a message for a bad input file; with ``--check FILE``, 1 if FILE differs
from what would be generated.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

try:  # one session-name rule: the daemon's, where pd-service is installed (venv, image)
    from pd_service.wire.keys import NAME_PATTERN
except ImportError:  # standalone: the same pattern (tests/deploy/test_make_acl.py: equal)
    NAME_PATTERN = r"[a-z0-9][a-z0-9_-]{0,63}"
_NAME = re.compile(NAME_PATTERN)
_USER = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_ZID = re.compile(r"[1-9a-f][0-9a-f]{0,31}")  # Zenoh: lowercase hex, no leading zero
_ROLE_LISTS = ("admins", "link_admins", "services", "links", "displays")
_TOP = {*_ROLE_LISTS, "users_file", "listen", "mesh", "session", "tls"}
_SESSION = {"name", "robot", "operator", "direct", "robot_creates"}
_MESH = {"zids", "user", "password"}
_TLS = {"ca", "certificate", "private_key"}
RESULTS = ("prediction", "path", "error", "status")
#: every session of every partition (key layout 2): pd/p<k>/<s>, robot/p<k>/<s>
PD = "pd/*/*"
ROBOT = "robot/*/*"
#: key layout 1 (before partitions), let through only to be refused by the daemon
LEGACY = "pd/*"
PARTITIONS_ENV = "PD_PARTITIONS"  # pd_service.wire.keys: the same variable, default, bounds
DEFAULT_PARTITIONS = 64
MAX_PARTITIONS = 4096
#: zenoh-ext 1.10's advanced publisher on K keeps its cache behind a queryable and a liveliness
#: token on K/@adv/pub/<zid>/<eid>/<meta>; "@adv" is a verbatim chunk, which no wildcard matches
ADV = "@adv/pub/**"


def _cache(key: str) -> str:
    """The key expression of the sender caches of the publishers on ``key``."""
    return f"{key}/{ADV}"


class InputError(ValueError):
    """The sessions file is not valid (the message names the field)."""


def fnv1a32(data: bytes) -> int:
    """32-bit FNV-1a (protocol.md §2); equal to pd_service.wire.keys.fnv1a32 (tested), kept
    here so that this script needs only the standard library."""
    h = 0x811C9DC5
    for b in data:
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h


def check_partitions(value: object, what: str) -> int:
    """A partition count 1..MAX_PARTITIONS (an integer or its decimal string)."""
    try:
        n = int(str(value).strip())
    except ValueError:
        n = 0
    if isinstance(value, bool) or not 1 <= n <= MAX_PARTITIONS:
        raise InputError(f"{what}: an integer from 1 to {MAX_PARTITIONS}, got {value!r}")
    return n


def partitions_from_env() -> int:
    """P from ``PD_PARTITIONS`` (default 64), as every party of the deployment reads it."""
    raw = os.environ.get(PARTITIONS_ENV, "")
    return DEFAULT_PARTITIONS if raw == "" else check_partitions(raw, PARTITIONS_ENV)


def session_path(session: str, partitions: int) -> str:
    """``p<k>/<session>``: the chunks that name a session in its keys (key layout 2)."""
    return f"p{fnv1a32(session.encode()) % partitions}/{session}"


def _users(doc: dict[str, Any], field: str) -> list[str]:
    value = doc.get(field, [])
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(u, str) for u in value):
        raise InputError(f"{field}: expected a list of user names")
    for u in value:
        if not _USER.fullmatch(u):
            raise InputError(f"{field}: bad user name {u!r}")
    return value


def read_sessions(doc: dict[str, Any]) -> dict[str, Any]:
    """Check a decoded sessions file; returns it normalised (lists, booleans, defaults)."""
    unknown = set(doc) - _TOP
    if unknown:
        raise InputError(f"unknown field(s) {sorted(unknown)} (known: {sorted(_TOP)})")
    out: dict[str, Any] = {f: _users(doc, f) for f in _ROLE_LISTS}
    if not out["services"]:
        raise InputError("services: at least one user (the pd-service daemon)")
    out["tls"] = _read_tls(doc.get("tls"))
    if out["tls"] is not None and "users_file" in doc:
        raise InputError("users_file: not with [tls] (the client certificate is the identity)")
    out["users_file"] = doc.get("users_file", "/etc/zenoh/users.txt")
    listen = doc.get("listen", ["tls/[::]:7447"] if out["tls"] else ["tcp/[::]:7447"])
    out["listen"] = [listen] if isinstance(listen, str) else listen
    if not isinstance(out["listen"], list) or not all(isinstance(e, str) for e in out["listen"]):
        raise InputError("listen: a list of Zenoh endpoints")
    tls_eps = [e for e in out["listen"] if e.startswith("tls/")]
    if tls_eps and out["tls"] is None:
        raise InputError(f"listen: {tls_eps[0]!r} needs a [tls] table ({sorted(_TLS)})")
    if out["tls"] is not None and len(tls_eps) != len(out["listen"]):
        raise InputError("listen: with [tls], tls/ endpoints only (no plaintext port)")
    out["mesh"] = _read_mesh(doc.get("mesh"), tls=out["tls"] is not None)
    sessions = doc.get("session", [])
    if not isinstance(sessions, list) or not sessions:
        raise InputError("session: at least one [[session]] table")
    seen: set[str] = set()
    out["session"] = []
    for i, s in enumerate(sessions):
        where = f"session[{i}]"
        if not isinstance(s, dict):
            raise InputError(f"{where}: expected a table")
        if set(s) - _SESSION:
            raise InputError(f"{where}: unknown field(s) {sorted(set(s) - _SESSION)}")
        name = s.get("name")
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise InputError(f"{where}.name: a session name ({_NAME.pattern}, no wildcard), "
                             f"got {name!r}")
        if name in seen:
            raise InputError(f"{where}.name: {name!r} listed twice")
        seen.add(name)
        entry = {"name": name, "robot": _users(s, "robot"), "operator": _users(s, "operator"),
                 "direct": s.get("direct", False), "robot_creates": s.get("robot_creates", False)}
        for flag in ("direct", "robot_creates"):
            if not isinstance(entry[flag], bool):
                raise InputError(f"{where}.{flag}: true or false")
        out["session"].append(entry)
    return out


def _read_tls(tls: object) -> dict[str, str] | None:
    """``[tls]``: the router's CA, certificate and key (paths on the router's host)."""
    if tls is None:
        return None
    if not isinstance(tls, dict) or set(tls) != _TLS or not all(
            isinstance(v, str) and v for v in tls.values()):
        raise InputError(f"tls: a table with exactly {sorted(_TLS)} (paths on the router)")
    return dict(tls)


def _read_mesh(mesh: object, tls: bool = False) -> dict[str, Any] | None:
    if mesh is None:
        return None
    if tls:  # routers authenticate each other by their certificates' common names
        names = mesh.get("common_names") if isinstance(mesh, dict) else None
        if not isinstance(mesh, dict) or set(mesh) != {"common_names"} or not isinstance(
                names, list) or len(names) < 2 or not all(
                isinstance(n, str) and _USER.fullmatch(n) for n in names):
            raise InputError("mesh: with [tls], a table with exactly common_names = [the "
                             "routers' certificate common names, two or more]")
        return {"common_names": list(names)}
    if not isinstance(mesh, dict) or set(mesh) != _MESH:
        raise InputError(f"mesh: a table with exactly {sorted(_MESH)}")
    zids = mesh["zids"]
    if not isinstance(zids, list) or len(zids) < 2 or len(set(zids)) != len(zids) or not all(
            isinstance(z, str) and _ZID.fullmatch(z) for z in zids):
        raise InputError("mesh.zids: two or more distinct Zenoh ids (lowercase hex, no "
                         f"leading zero), got {zids!r}")
    if not isinstance(mesh["user"], str) or not _USER.fullmatch(mesh["user"]):
        raise InputError(f"mesh.user: bad user name {mesh['user']!r}")
    if not isinstance(mesh["password"], str) or not mesh["password"]:
        raise InputError("mesh.password: a non-empty string")
    return dict(mesh)


def _rule(rid: str, flows: Iterable[str], messages: Iterable[str], key_exprs: Iterable[str]
          ) -> dict[str, Any]:
    return {"id": rid, "permission": "allow", "flows": list(flows), "messages": list(messages),
            "key_exprs": sorted(set(key_exprs))}


# rules every deployment has (not scoped by session): (id, flows, messages, key_exprs)
_FIXED: dict[str, tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]] = {
    # A Zenoh 1.x client with a declared publisher drops a put locally while it knows of no
    # matching subscriber; it learns of subscribers through declarations that cross the router
    # as egress "declare_subscriber".  Reveals key expressions, never data.
    "learn-subscribers": (("egress",), ("declare_subscriber",), ("pd/**", "robot/**")),
    # admins: create = put, remove = delete; serve the spec to queries; follow the result
    # (and an old client's spec put on layout 1, which the daemon answers with a refusal)
    "admin-specs-in": (("ingress",), ("put", "delete", "declare_subscriber", "query",
                                      "declare_queryable", "reply"),
                       (f"{PD}/config", f"{LEGACY}/config")),
    "admin-specs-out": (("egress",), ("put", "delete", "query", "reply"),
                        (f"{PD}/config", f"{LEGACY}/config")),
    "admin-results-ask": (("ingress",), ("declare_subscriber", "query"),
                          (*(f"{PD}/{r}" for r in RESULTS), f"{LEGACY}/error",
                           f"{LEGACY}/status")),
    "admin-results-get": (("egress",), ("put", "delete", "reply"),
                          (*(f"{PD}/{r}" for r in RESULTS), f"{LEGACY}/error",
                           f"{LEGACY}/status")),
    # which daemon instances are alive and their status (read-only for everybody but services)
    "watch-services-ask": (("ingress",), ("declare_liveliness_subscriber", "liveliness_query",
                                          "query"), ("pd/@service/*", "pd/@service/*/status")),
    "watch-services-get": (("egress",), ("liveliness_token", "reply"),
                           ("pd/@service/*", "pd/@service/*/status")),
    "read-link-stats-ask": (("ingress",), ("query",), ("pd/@link/*/stats",)),
    "read-link-stats-get": (("egress",), ("reply",), ("pd/@link/*/stats",)),
    # a query on .../rules with a payload replaces pd-link's rules: link admins only
    "admin-link-rules-ask": (("ingress",), ("query", "put"), ("pd/@link/*/rules",)),
    "admin-link-rules-get": (("egress",), ("reply",), ("pd/@link/*/rules",)),
    # the daemon: every session of every partition (it serves them all); on key layout 1 it
    # hears specs and status queries and puts errors only to refuse them
    "service-write": (("ingress",), ("put", "delete"),
                      (*(f"{PD}/{r}" for r in RESULTS), f"{LEGACY}/error")),
    "service-retire-specs": (("ingress",), ("delete",), (f"{PD}/config",)),
    "service-ask": (("ingress",), ("declare_subscriber", "query", "declare_queryable", "reply"),
                    (f"{PD}/config", f"{PD}/sensor/*", f"{PD}/cmd", f"{PD}/status",
                     f"{PD}/echo", f"{ROBOT}/clock", f"{LEGACY}/config", f"{LEGACY}/status")),
    "service-get": (("egress",), ("put", "delete", "reply", "query"),
                    (f"{PD}/config", f"{PD}/sensor/*", f"{PD}/cmd", f"{PD}/status",
                     f"{PD}/echo", f"{ROBOT}/clock", f"{LEGACY}/config", f"{LEGACY}/status")),
    # daemon instances among themselves: liveliness tokens (session membership), status,
    # peer queries, replicated state.  ONLY services: a token here takes sessions over.
    "service-coordination": (("ingress", "egress"), (
        "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
        "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"),
        ("pd/@service/**",)),
    # sender caches (zenoh-ext advanced publishers) read back by the daemon after a restart,
    # a takeover, or when a sender appears: it watches their liveliness tokens and queries each
    # on its token's key; the replies carry the cached samples' own keys
    # (pd/p<k>/<s>/sensor/<name>, pd/p<k>/<s>/cmd), which "service-get" already lets out to it
    "service-recover-ask": (("ingress",), ("query", "declare_liveliness_subscriber",
                                           "liveliness_query"),
                            (_cache(f"{PD}/sensor/*"), _cache(f"{PD}/cmd"))),
    "service-recover-get": (("egress",), ("liveliness_token",),
                            (_cache(f"{PD}/sensor/*"), _cache(f"{PD}/cmd"))),
    # the link emulator: every session
    "link-ask": (("ingress",), ("declare_subscriber",),
                 (f"{ROBOT}/sensor/*", f"{ROBOT}/camera", f"{ROBOT}/echo", f"{PD}/cmd")),
    "link-get": (("egress",), ("put", "delete"),
                 (f"{ROBOT}/sensor/*", f"{ROBOT}/camera", f"{ROBOT}/echo", f"{PD}/cmd")),
    "link-write": (("ingress",), ("put", "delete"),
                   (f"{PD}/sensor/*", f"{PD}/camera", f"{PD}/echo", f"{ROBOT}/cmd")),
    "link-serve-in": (("ingress",), ("declare_queryable", "reply"),
                      ("pd/@link/*/rules", "pd/@link/*/stats")),
    "link-serve-out": (("egress",), ("query",), ("pd/@link/*/rules", "pd/@link/*/stats")),
    # the caches of its outputs to the daemon (pd-link --cache N); see _cache_rules
    "link-cache-in": (("ingress",), ("declare_queryable", "liveliness_token"),
                      (_cache(f"{PD}/sensor/*"), _cache(f"{PD}/cmd"))),
    "link-cache-reply": (("ingress",), ("reply",), (f"{PD}/sensor/*", f"{PD}/cmd")),
    "link-cache-out": (("egress",), ("query",),
                       (_cache(f"{PD}/sensor/*"), _cache(f"{PD}/cmd"))),
    # displays: read-only, every session
    "display-ask": (("ingress",), ("declare_subscriber", "query"),
                    (*(f"{PD}/{r}" for r in RESULTS), f"{PD}/config", f"{PD}/camera",
                     f"{ROBOT}/truth")),
    "display-get": (("egress",), ("put", "delete", "reply"),
                    (*(f"{PD}/{r}" for r in RESULTS), f"{PD}/config", f"{PD}/camera",
                     f"{ROBOT}/truth")),
    # routers of a mesh ([mesh]) relay to each other every message, both ways, on every key
    # some rule above grants a client: each router enforces its own clients' rules, the mesh
    # carries what one router let in to where another may let it out.  "**" never matches a
    # verbatim chunk (@service, @link, @adv): those are named.
    "mesh": (("ingress", "egress"), (
        "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
        "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"),
        ("pd/**", "robot/**", "pd/@service/**", "pd/@link/**", _cache(f"{PD}/sensor/*"),
         _cache(f"{PD}/cmd"))),
}

_ROLE_RULES = {
    "admins": ("admin-specs-in", "admin-specs-out", "admin-results-ask", "admin-results-get",
               "watch-services-ask", "watch-services-get"),
    "link_admins": ("admin-link-rules-ask", "admin-link-rules-get",
                    "read-link-stats-ask", "read-link-stats-get"),
    "services": ("service-write", "service-retire-specs", "service-ask", "service-get",
                 "service-coordination", "service-recover-ask", "service-recover-get"),
    "links": ("link-ask", "link-get", "link-write", "link-serve-in", "link-serve-out",
              "link-cache-in", "link-cache-reply", "link-cache-out", "read-link-stats-ask",
              "read-link-stats-get"),
    "displays": ("display-ask", "display-get", "watch-services-ask", "watch-services-get",
                 "read-link-stats-ask", "read-link-stats-get"),
}


def _session_rules(user: str, robot_of: list[dict[str, Any]], operator_of: list[dict[str, Any]],
                   partitions: int) -> tuple[list[dict[str, Any]], list[str]]:
    """The rules of one user scoped to its sessions, and the fixed rules it also needs.
    Keys name a session as ``p<k>/<s>`` (key layout 2); a layout-1 key (``pd/<s>/...``) only
    where the daemon answers an old client with a refusal (status, error; a spec put)."""
    rules: list[dict[str, Any]] = []
    fixed: list[str] = []
    if robot_of:
        names = [session_path(s["name"], partitions) for s in robot_of]
        direct = [session_path(s["name"], partitions) for s in robot_of if s["direct"]]
        creates = [s["name"] for s in robot_of if s["robot_creates"]]
        rules += [
            _rule(f"robot-{user}-write", ["ingress"], ["put", "delete"],
                  [*(f"robot/{s}/{k}" for s in names
                     for k in ("sensor/*", "truth", "camera", "echo")),
                   *(f"pd/{s}/{k}" for s in direct for k in ("sensor/*", "camera", "echo"))]),
            # its clock, probed by the daemon (issue 43's field clocks)
            _rule(f"robot-{user}-clock-in", ["ingress"], ["declare_queryable", "reply"],
                  [f"robot/{s}/clock" for s in names]),
            _rule(f"robot-{user}-clock-out", ["egress"], ["query"],
                  [f"robot/{s}/clock" for s in names]),
            _rule(f"robot-{user}-ask", ["ingress"], ["declare_subscriber", "query"],
                  [*(f"robot/{s}/cmd" for s in names), *(f"pd/{s}/cmd" for s in direct),
                   *(f"pd/{s}/config" for s in names)]),
            _rule(f"robot-{user}-get", ["egress"], ["put", "delete", "reply"],
                  [*(f"robot/{s}/cmd" for s in names), *(f"pd/{s}/cmd" for s in direct),
                   *(f"pd/{s}/config" for s in names)]),
        ]
        if direct:  # the caches of its sensor publishers, read back by the daemon
            rules += _cache_rules(f"robot-{user}", [f"pd/{s}/sensor/*" for s in direct])
        if creates:
            paths = [session_path(s, partitions) for s in creates]
            specs = [*(f"pd/{s}/config" for s in paths), *(f"pd/{s}/config" for s in creates)]
            results = [*(f"pd/{s}/{r}" for s in paths for r in RESULTS),
                       *(f"pd/{s}/{r}" for s in creates for r in ("error", "status"))]
            rules += [  # put/delete/serve its sessions' specs; follow the daemon's answer
                _rule(f"robot-{user}-create-in", ["ingress"],
                      ["put", "delete", "declare_queryable", "reply"], specs),
                _rule(f"robot-{user}-create-out", ["egress"], ["query"], specs),
                _rule(f"robot-{user}-results-ask", ["ingress"], ["declare_subscriber", "query"],
                      results),
                _rule(f"robot-{user}-results-get", ["egress"], ["put", "delete", "reply"],
                      results),
            ]
            fixed += ["watch-services-ask", "watch-services-get"]
    if operator_of:
        plain = [s["name"] for s in operator_of]
        names = [session_path(s, partitions) for s in plain]
        readable = [*(f"pd/{s}/{r}" for s in names for r in (*RESULTS, "config", "camera")),
                    *(f"pd/{s}/{r}" for s in plain for r in ("error", "status"))]
        rules += [
            _rule(f"operator-{user}-write", ["ingress"], ["put", "delete"],
                  [f"pd/{s}/cmd" for s in names]),
            _rule(f"operator-{user}-ask", ["ingress"], ["declare_subscriber", "query"], readable),
            _rule(f"operator-{user}-get", ["egress"], ["put", "delete", "reply"], readable),
        ]
        rules += _cache_rules(f"operator-{user}", [f"pd/{s}/cmd" for s in names])
        fixed += ["watch-services-ask", "watch-services-get", "read-link-stats-ask",
                  "read-link-stats-get"]
    return rules, fixed


def _cache_rules(prefix: str, keys: list[str]) -> list[dict[str, Any]]:
    """A scoped user's sender caches on ``keys`` (keys it publishes): declare their
    queryables and liveliness tokens (``<key>/@adv/pub/**``), receive the daemon's queries on
    them, reply with the cached samples.  The router checks a reply against the key of the
    sample it carries (``keys``), a query against the key it was sent on: the daemon queries
    each cache on its own key, so no rule needs a wildcard across sessions."""
    caches = [_cache(k) for k in keys]
    return [
        _rule(f"{prefix}-cache-in", ["ingress"], ["declare_queryable", "liveliness_token"],
              caches),
        _rule(f"{prefix}-cache-reply", ["ingress"], ["reply"], keys),
        _rule(f"{prefix}-cache-out", ["egress"], ["query"], caches),
    ]


def build(sessions: dict[str, Any], partitions: int | None = None) -> dict[str, Any]:
    """The router configuration (a dict) for a checked sessions description and ``partitions``
    (P; default: ``PD_PARTITIONS``, else 64)."""
    n = partitions_from_env() if partitions is None else check_partitions(partitions,
                                                                          "partitions")
    per_user_fixed: dict[str, list[str]] = {}
    for role, rule_ids in _ROLE_RULES.items():
        for u in sessions[role]:
            per_user_fixed.setdefault(u, []).extend(rule_ids)
    robot_of: dict[str, list[dict[str, Any]]] = {}
    operator_of: dict[str, list[dict[str, Any]]] = {}
    for s in sessions["session"]:
        for u in s["robot"]:
            robot_of.setdefault(u, []).append(s)
        for u in s["operator"]:
            operator_of.setdefault(u, []).append(s)
    users = sorted({*per_user_fixed, *robot_of, *operator_of})
    scoped: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for u in users:
        rules, fixed = _session_rules(u, robot_of.get(u, []), operator_of.get(u, []), n)
        scoped += rules
        wanted = ["learn-subscribers", *per_user_fixed.get(u, []), *fixed]
        ids = list(dict.fromkeys([*wanted, *(r["id"] for r in rules)]))
        policies.append({"id": f"user-{u}", "subjects": [f"user-{u}"], "rules": ids})
    tls = sessions.get("tls")
    # who a client is: its certificate's common name with [tls], else its user name
    who = "cert_common_names" if tls else "usernames"
    subjects: list[dict[str, Any]] = [{"id": f"user-{u}", who: [u]} for u in users]
    usrpwd: dict[str, str] = {"dictionary_file": sessions["users_file"]}
    mesh = sessions.get("mesh")
    if mesh and tls:
        # mutual TLS between the routers: a router proves its name with its certificate (a
        # Zenoh id is only claimed, so anybody may claim another router's)
        subjects.append({"id": "routers", "cert_common_names": list(mesh["common_names"])})
        policies.append({"id": "routers", "subjects": ["routers"], "rules": ["mesh"]})
    elif mesh:
        # a router that connected out sees its peer without a user name (user/password
        # authenticates one way only): the routers are matched by their Zenoh ids
        subjects.append({"id": "routers", "zids": list(mesh["zids"])})
        policies.append({"id": "routers", "subjects": ["routers"], "rules": ["mesh"]})
        usrpwd.update(user=mesh["user"], password=mesh["password"])
    used = {rid for p in policies for rid in p["rules"]}
    all_rules = [_rule(rid, *spec) for rid, spec in _FIXED.items() if rid in used] + scoped
    transport: dict[str, Any] = {"auth": {"usrpwd": usrpwd}}
    if tls:
        transport = {"link": {"protocols": ["tls"], "tls": {
            "root_ca_certificate": tls["ca"], "enable_mtls": True,
            "listen_certificate": tls["certificate"], "listen_private_key": tls["private_key"],
            # the same pair when this router connects to another one of the mesh
            "connect_certificate": tls["certificate"], "connect_private_key": tls["private_key"],
            "verify_name_on_connect": True}}}
    return {
        "mode": "router",
        "listen": {"endpoints": sessions["listen"]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": transport,
        "adminspace": {"enabled": False, "permissions": {"read": False, "write": False}},
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": all_rules,
            "subjects": subjects,
            "policies": policies,
        },
    }


HEADER = """\
// Zenoh router (zenohd) of a pd-service deployment: authentication (user/password, or TLS
// client certificates with a [tls] table) and access control scoped by session.
// GENERATED by deploy/make_acl.py from {source}; do not edit: change the sessions file and run
//     python deploy/make_acl.py {source} --partitions {partitions} > router.json5
// Key layout 2 with P = {partitions} partitions: a session's keys are pd/p<k>/<s>/... and
// robot/p<k>/<s>/..., k = FNV-1a-32(s) mod {partitions}; every party of the deployment must
// run with PD_PARTITIONS={partitions} (protocol.md §2).
// Zenoh 1.10.x syntax.  Deny by default; a message crosses the router only if a rule allows it
// for the SENDER's user on the way in (ingress) AND for the RECEIVER's user on the way out
// (egress).  Access control applies only to traffic THROUGH this router: every process must
// connect to it as a client (deploy/README.md, "Security model").  Keys: pd_service/wire/keys.py.
"""


def render(sessions: dict[str, Any], source: str, partitions: int | None = None) -> str:
    n = partitions_from_env() if partitions is None else partitions
    return (HEADER.format(source=source, partitions=n)
            + json.dumps(build(sessions, n), indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="make_acl.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("sessions", help="the sessions file (.toml)")
    ap.add_argument("--check", metavar="FILE",
                    help="exit 1 if FILE differs from the generated configuration")
    ap.add_argument("--partitions", metavar="P",
                    help=f"the deployment's partition count (default: ${PARTITIONS_ENV}, "
                         f"else {DEFAULT_PARTITIONS})")
    args = ap.parse_args(argv)
    path = Path(args.sessions)
    try:
        n = (partitions_from_env() if args.partitions is None
             else check_partitions(args.partitions, "--partitions"))
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
        text = render(read_sessions(doc), path.as_posix(), n)
    except (OSError, tomllib.TOMLDecodeError, InputError) as e:
        print(f"make_acl.py: {path}: {e}", file=sys.stderr)
        return 2
    if args.check:
        same = Path(args.check).read_text(encoding="utf-8") == text
        if not same:
            print(f"make_acl.py: {args.check} is not what {path} generates", file=sys.stderr)
        return 0 if same else 1
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
