"""compose.yml's two routers, meshed on loopback: partitioned keys routed across the mesh and
the access control enforced on both routers.

Two Python Zenoh sessions in router mode stand in for router-a and router-b of compose.yml:
each opened with deploy/zenoh/router.json5 under the Zenoh id compose gives it (``--id``),
router-b connected to router-a (``--connect``), and logged in there as the file's mesh user.
Clients connect to either router with their role files.  Synchronisation as in
test_router_acl: events, bounded polling, one bounded negative wait.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest

from pd_service.transport import ZenohTransport
from pd_service.wire import keys

from ._support import compose_routers, free_port, open_client, open_router, wait_for
from .test_router_acl import (
    CASES,
    NEGATIVE_WAIT_S,
    ROUNDS,
    TIMEOUT_S,
    Collector,
    publish_race,
)

pytestmark = pytest.mark.integration


@contextlib.contextmanager
def mesh(acl: bool = True, tables: dict[str, ZenohTransport] | None = None
         ) -> Iterator[dict[str, str]]:
    """router-a and router-b as compose.yml runs them (ids, who connects to whom), on
    loopback; yields {router name: its client endpoint}.  With ``tables`` (a dict, filled
    with {router name: its session}) the routers' admin spaces are readable."""
    routers = compose_routers()
    endpoints = {name: f"tcp/127.0.0.1:{free_port()}" for name in routers}
    with contextlib.ExitStack() as stack:
        # routers that connect to others start after those (compose: depends_on)
        for name in sorted(routers, key=lambda n: len(routers[n].connect)):
            connect = [endpoints[ep.split("/")[1].split(":")[0]] for ep in routers[name].connect]
            r = stack.enter_context(open_router(endpoints[name], acl=acl, zid=routers[name].id,
                                                connect=connect, admin_read=tables is not None))
            if tables is not None:
                tables[name] = r
        yield endpoints


def routing_table(router: ZenohTransport, zid: str, kind: str) -> list[str]:
    """The key expressions of one table (``subscriber``, ``publisher``) of a router, read
    from its admin space (``@/<zid>/router/<kind>/<key expr>``), sorted."""
    prefix = f"@/{zid}/router/{kind}/"
    return sorted(str(r.ok.key_expr)[len(prefix):] for r in router.session.get(
        f"{prefix}**", timeout=TIMEOUT_S) if r.ok is not None)


def sessions_in_two_partitions() -> tuple[str, str]:
    """Two session names in different partitions (of this process's P)."""
    first = "s0"
    other = next(f"s{i}" for i in range(1, 1000)
                 if keys.partition_of(f"s{i}") != keys.partition_of(first))
    return first, other


def test_partition_wildcard_receives_its_partition_only_across_the_mesh() -> None:
    """A link on router-a publishes a layout-2 sensor key of two sessions in two partitions;
    on router-b a daemon's subscription to one partition's wildcard receives that partition's
    samples and none of the other's, while a subscription to every partition (the control)
    receives both."""
    mine, theirs = sessions_in_two_partitions()
    k = keys.partition_of(mine)
    with mesh() as ep, open_client("link", ep["router-a"]) as link, \
            open_client("service", ep["router-b"]) as part_t, \
            open_client("service", ep["router-b"]) as all_t:
        part, every = Collector(), Collector()
        part_t.subscribe(keys.partition_sensors(k), part)
        all_t.subscribe(keys.ALL_SENSORS, every)

        def synced() -> bool:
            link.put(keys.sensor_key(mine, "camera"), b"sync")
            link.put(keys.sensor_key(theirs, "camera"), b"sync-theirs")
            return part.wait_count(b"sync", 1, 0.05) and every.wait_count(b"sync-theirs", 1, 0.05)
        wait_for(synced, TIMEOUT_S, "both subscriptions to be known across the mesh")
        for i in range(ROUNDS):
            link.put(keys.sensor_key(theirs, "camera"), b"theirs-%d" % i)
            link.put(keys.sensor_key(mine, "camera"), b"mine-%d" % i)
        assert every.wait_count(b"theirs-", ROUNDS, TIMEOUT_S), "control: the other partition"
        assert every.wait_count(b"mine-", ROUNDS, TIMEOUT_S)
        assert part.wait_count(b"mine-", ROUNDS, TIMEOUT_S), "its own partition's samples"
        part.wait_count(b"theirs-", 1, NEGATIVE_WAIT_S)
        assert part.count(b"theirs-") == 0 and part.count(b"sync-theirs") == 0
        assert part.count(b"mine-") == ROUNDS


@pytest.mark.parametrize("sub_on", ["router-a", "router-b"])
@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("acl", [True, False], ids=["acl-on", "control-acl-off"])
def test_only_the_authorised_user_publishes_across_the_mesh(case: str, acl: bool,
                                                            sub_on: str) -> None:
    """test_router_acl's cases with the subscriber on one router and both publishers on the
    other: the refused user's puts are stopped by its own router, the allowed user's cross
    the mesh (control: access control off on both, the refused user's arrive too)."""
    sub_role, sub_key, key, allowed_role, other_role = CASES[case]
    pub_on = "router-b" if sub_on == "router-a" else "router-a"
    with mesh(acl) as ep, open_client(sub_role, ep[sub_on]) as sub_t, \
            open_client(allowed_role, ep[pub_on]) as allowed, \
            open_client(other_role, ep[pub_on]) as other:
        sub = Collector()
        sub_t.subscribe(sub_key, sub)
        leaked = publish_race(sub, key, allowed, other, expect_other=not acl)
    assert leaked == (0 if acl else ROUNDS), f"{other_role}'s puts on {key}"


def test_queries_and_liveliness_cross_the_mesh() -> None:
    """A daemon on router-a is seen (liveliness) and answers (status query) an operator on
    router-b; the robot on router-b still may not query the link's statistics on router-a."""
    with mesh() as ep, open_client("service", ep["router-a"]) as service, \
            open_client("link", ep["router-a"]) as link, \
            open_client("operator", ep["router-b"]) as operator, \
            open_client("robot", ep["router-b"]) as robot:
        service.declare_token(keys.service_token_key("pd-a"))
        service.queryable(keys.ALL_STATUS, lambda q: q.reply(q.key, b"status"))
        link.queryable(keys.link_stats_key("paper"),
                       lambda q: q.reply(keys.link_stats_key("paper"), b"stats"))
        alive = wait_for(lambda: operator.get_liveliness(keys.ALL_SERVICES, timeout=1.0),
                         TIMEOUT_S, "the daemon's token across the mesh")
        assert alive == [keys.service_token_key("pd-a")]
        got = wait_for(lambda: [r.payload for r in operator.get(keys.status_key("paper"),
                                                                timeout=1.0) if r.ok],
                       TIMEOUT_S, "the operator's status query to be answered")
        assert got == [b"status"]
        got = wait_for(lambda: [r.payload for r in operator.get(keys.link_stats_key("paper"),
                                                                timeout=1.0) if r.ok],
                       TIMEOUT_S, "the operator's stats query to be answered")
        assert got == [b"stats"]
        assert [r for r in robot.get(keys.link_stats_key("paper"), timeout=NEGATIVE_WAIT_S)
                if r.ok] == []




def test_routing_tables_grow_with_partitions_not_sessions() -> None:
    """A daemon instance on router-a owning 8 partitions declares 2 wildcards per partition;
    senders on router-b declare a publisher per session.  Both routers' subscriber tables hold
    exactly the 16 wildcards, with 10 sessions and with 40; router-b's publisher table holds
    its own clients' publishers (one per session), router-a's none: per-session entries stay
    at the sender's router (deploy/README.md, "Routed deployment")."""
    ids = {name: a.id for name, a in compose_routers().items()}
    owned = range(8)
    wildcards = sorted([keys.partition_sensors(k) for k in owned]
                       + [keys.partition_commands(k) for k in owned])
    tables: dict[str, ZenohTransport] = {}
    with mesh(tables=tables) as ep, open_client("service", ep["router-a"]) as daemon, \
            open_client("link", ep["router-b"]) as sender:
        got = Collector()
        for w in wildcards:
            daemon.subscribe(w, got)
        names = [f"s{i}" for i in range(1000) if keys.partition_of(f"s{i}") in owned]
        publishers = []
        for n in (10, 40):
            while len(publishers) < n:
                name = names[len(publishers)]
                publishers.append(sender.session.declare_publisher(keys.sensor_key(name, "x")))

            def learnt(n: int = n) -> bool:  # every publisher knows the daemon's wildcard
                return all(p.matching_status.matching for p in publishers[:n])
            wait_for(learnt, TIMEOUT_S, "the publishers to learn of the daemon's subscribers")
            for name in ("router-a", "router-b"):
                subs = routing_table(tables[name], ids[name], "subscriber")
                assert subs == wildcards, (name, n)
            assert routing_table(tables["router-a"], ids["router-a"], "publisher") == []
            want = sorted(keys.sensor_key(s, "x") for s in names[:n])

            def declared(want: list[str] = want) -> bool:  # declarations reach the router
                return routing_table(tables["router-b"], ids["router-b"], "publisher") == want
            # a publisher's declaration reaches its router after the publisher has learnt of
            # the subscribers (the other direction): wait for it, then compare exactly
            wait_for(declared, TIMEOUT_S, "router-b to hold the publishers' declarations")
            assert routing_table(tables["router-b"], ids["router-b"], "publisher") == want
        publishers[0].put(b"x")
        assert got.wait_count(b"x", 1, TIMEOUT_S)
        for p in publishers:
            p.undeclare()
