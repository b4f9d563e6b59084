"""Key layout 2 in the daemon: an instance subscribes to the data of the partitions it owns
and receives nothing of the others; its subscriptions move on a join and a leave; an old
client's (layout 1) config put and status query, and a config on another partition than
the session's, are refused with the reason."""

from __future__ import annotations

import pytest

from pd_service.service.subscriptions import ALL
from pd_service.transport import InMemoryBus
from pd_service.wire import ErrorReport, ServiceStatus, decode, encode, keys

from .helpers import Clock, Collector, meas_bytes, paper_spec
from .test_core import PAIR, make_core, settle

TRIO = [*PAIR, "inst-c"]


def data_subscriptions(bus: InMemoryBus) -> list[str]:
    """The key expressions of every sensor subscription on the bus (the daemons')."""
    return [ke for ke, _ in bus.subs if ke.endswith("/sensor/*")]


def owned_by(core, names: list[str]) -> list[str]:
    mine = core.ownership.owned_partitions()
    return [s for s in names if keys.partition_of(s) in mine]


def test_an_instance_receives_only_its_partitions_data(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR)
    settle(a, b)
    names = [f"s{i:02d}" for i in range(40)]
    for s in names:
        cli.put(keys.config_key(s), encode(paper_spec(s)))
    settle(a, b)
    pa, pb = a.ownership.owned_partitions(), b.ownership.owned_partitions()
    assert len(pa) == len(pb) == keys.partitions() // 2 and pa.isdisjoint(pb)
    assert set(a.subs.by_partition) == pa and set(b.subs.by_partition) == pb
    assert sorted(data_subscriptions(bus)) == sorted(keys.partition_sensors(k)
                                                     for k in range(keys.partitions()))
    clock.t = 5 * 50_000_000
    for s in names:
        cli.put(keys.sensor_key(s, "ranger"), meas_bytes(s, "ranger", 3, [1.0]))
    # a session nobody configured, in one of b's partitions: a never hears of it
    ghost = next(f"g{i}" for i in range(1000) if keys.partition_of(f"g{i}") in pb)
    cli.put(keys.sensor_key(ghost, "ranger"), meas_bytes(ghost, "ranger", 3, [1.0]))
    settle(a, b)
    sa, sb = a.service_status(), b.service_status()
    assert sa.counters["samples_received"] == len(owned_by(a, names))
    assert sb.counters["samples_received"] == len(owned_by(b, names)) + 1
    assert sa.counters["accepted"] == sa.counters["samples_received"]
    assert "unknown_session" not in sa.counters and sb.counters["unknown_session"] == 1
    assert sorted(sa.sessions) == owned_by(a, names)
    for st, owned in ((sa, pa), (sb, pb)):
        assert (st.partitions, st.key_layout, st.owned_partitions) == \
            (keys.partitions(), keys.KEY_LAYOUT, len(owned))


def test_subscriptions_follow_a_join_and_a_leave(tmp_path):
    """Alone, the instance holds the two wildcards; a second one joins: each holds one pair
    per owned partition, the two halves disjoint; it leaves: back to the wildcards. The
    partitions kept keep their subscriptions (the same drains)."""
    bus, clock = InMemoryBus(), Clock(0)
    a = make_core(bus, clock, tmp_path, "inst-a", peers=TRIO)
    assert list(a.subs.by_partition) == [ALL]
    assert data_subscriptions(bus) == [keys.ALL_SENSORS]
    b = make_core(bus, clock, tmp_path, "inst-b", peers=TRIO)
    settle(a, b)
    kept = dict(a.subs.by_partition)
    assert set(kept) == a.ownership.owned_partitions()
    assert len(data_subscriptions(bus)) == keys.partitions()
    c = make_core(bus, clock, tmp_path, "inst-c", peers=TRIO)
    settle(a, b, c)
    owned = [x.ownership.owned_partitions() for x in (a, b, c)]
    assert sum(map(len, owned)) == keys.partitions() and set().union(*owned) == \
        set(range(keys.partitions()))
    for k in a.ownership.owned_partitions():  # the partitions a kept: the same drains
        assert a.subs.by_partition[k] is kept[k]
    assert len(data_subscriptions(bus)) == keys.partitions()
    c.close()
    b.close()
    settle(a)
    assert list(a.subs.by_partition) == [ALL]
    assert data_subscriptions(bus) == [keys.ALL_SENSORS]


def test_a_layout1_config_put_and_status_query_are_refused(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    col = Collector()
    legacy_errors: list[ErrorReport] = []
    cli.subscribe("pd/*/error", lambda s: legacy_errors.append(decode(s.payload, ErrorReport)))
    a = make_core(bus, clock, tmp_path, "inst-a", peers=PAIR)
    b = make_core(bus, clock, tmp_path, "inst-b", peers=PAIR)
    col.attach(cli)
    settle(a, b)
    cli.put("pd/s1/config", encode(paper_spec("s1")))  # an old client's spec
    settle(a, b)
    assert a.known_specs() == b.known_specs() == {}
    assert len(legacy_errors) == 1  # reported once, by the name's owner
    rep = legacy_errors[0]
    assert rep.session == "s1" and rep.key == "pd/s1/config"
    assert rep.reason == keys.legacy_reason("pd/s1/config") and "key layout 1" in rep.reason
    assert keys.config_key("s1") in rep.reason
    for core in (a, b):
        assert core.service_status().counters["legacy_keys"] == 1
    replies = cli.get("pd/s1/status")
    assert [r.ok for r in replies] == [False]  # one error reply, from the owner
    err = decode(replies[0].payload, ErrorReport)
    assert err.session == "s1" and err.reason == keys.legacy_reason("pd/s1/status")
    owner = a if a.ownership.owns("s1") else b
    assert owner.service_status().counters["legacy_keys"] == 2
    # a wildcard query of layout 1 names no session: counted, not answered
    assert cli.get("pd/*/status") == []
    assert col.errors == {}  # nothing on layout-2 keys


def test_layout1_refusals_are_rate_limited(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    got: list[bytes] = []
    cli.subscribe("pd/*/error", lambda s: got.append(s.payload))
    a = make_core(bus, clock, tmp_path, "inst-a", error_rate=1.0, error_burst=2)
    for i in range(10):  # (each config of its own session: within the config rate)
        assert [r.ok for r in cli.get("pd/s1/status")] in ([False], [])
        cli.put(f"pd/s2-{i}/config", encode(paper_spec(f"s2-{i}")))
    settle(a)
    c = a.service_status().counters
    assert c["legacy_keys"] == 20
    assert c["errors_sent"] == 2 and c["errors_suppressed"] > 0  # the error budget's burst


def test_a_config_on_another_partition_is_refused(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a = make_core(bus, clock, tmp_path, "inst-a")
    p = keys.partitions()
    wrong = (keys.partition_of("s1") + 1) % p
    key = f"pd/{keys.partition_chunk(wrong)}/s1/config"  # a client with another P
    seen: list[ErrorReport] = []
    cli.subscribe(keys.error_key_beside(key), lambda s: seen.append(decode(s.payload,
                                                                             ErrorReport)))
    cli.put(key, encode(paper_spec("s1")))
    settle(a)
    assert a.known_specs() == {}
    assert a.service_status().counters["wrong_partition"] == 1
    assert len(seen) == 1 and seen[0].key == key
    with pytest.raises(keys.KeyError_) as exc:
        keys.parse_key(key)
    assert seen[0].reason == str(exc.value) and keys.PARTITIONS_ENV in seen[0].reason


def test_the_error_key_beside_a_key():
    assert keys.error_key_beside(keys.config_key("s1")) == keys.error_key("s1")
    assert keys.error_key_beside("pd/s1/config") == "pd/s1/error"
    assert keys.error_key_beside("pd/p9/s1/status") == "pd/p9/s1/error"


def test_service_status_of_key_layout_1_decodes_with_the_defaults():
    st = ServiceStatus(instance="old", sessions=[], latency_p50_us=0.0, latency_p99_us=0.0,
                       uptime_s=1.0)
    assert (st.partitions, st.key_layout, st.owned_partitions) == (1, 1, 0)
