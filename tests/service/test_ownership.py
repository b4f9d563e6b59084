"""Ownership by partition: bounded-load rendezvous (balance, determinism, what moves on a
join and a leave) and static shards."""

from __future__ import annotations

import math

import pytest

from pd_service.service.ownership import (
    Ownership,
    assign_partitions,
    shard_partitions,
    stable_hash,
)
from pd_service.wire import keys


def members(n: int, tag: str = "") -> list[str]:
    return [f"inst{tag}-{i}" for i in range(n)]


def moved(a: list[str], b: list[str]) -> float:
    """Share of the partitions whose owner differs between two assignments."""
    return sum(x != y for x, y in zip(a, b, strict=True)) / len(a)


@pytest.mark.parametrize("p", [1, 7, 64, 256])
@pytest.mark.parametrize("n", [1, 2, 3, 5, 10])
def test_every_member_owns_floor_or_ceil_of_p_over_n(p, n):
    table = assign_partitions(members(n), p)
    assert len(table) == p
    counts = [table.count(m) for m in members(n)]
    assert min(counts) >= p // n and max(counts) <= math.ceil(p / n)
    assert sum(counts) == p


def test_the_assignment_is_a_function_of_the_member_set():
    a = assign_partitions(["x", "y", "z"], 64)
    assert a == assign_partitions(["z", "x", "y", "y"], 64)  # order and repeats do not count
    assert stable_hash("abc") == stable_hash("abc")
    assert assign_partitions([], 64) == []
    assert assign_partitions(["x"], 64) == ["x"] * 64


def share_moved(p: int, n: int, trials: int = 4) -> tuple[float, float]:
    """Mean share of the partitions that change owner when one member joins n members, and
    when one of n + 1 leaves, over ``trials`` sets of names (each leave of every member)."""
    joins, leaves = [], []
    for t in range(trials):
        ms = members(n, f"t{t}")
        before = assign_partitions(ms, p)
        after = assign_partitions([*ms, f"new{t}"], p)
        joins.append(moved(before, after))
        for m in ms + [f"new{t}"]:
            leaves.append(moved(after, assign_partitions([x for x in [*ms, f"new{t}"]
                                                          if x != m], p)))
    return sum(joins) / len(joins), sum(leaves) / len(leaves)


@pytest.mark.parametrize("p", [64, 256])
def test_a_join_or_a_leave_moves_about_one_share(p, capsys):
    """A join to n members, or a leave from n + 1, must move at least 1/(n+1) of the
    partitions (the newcomer's share, or the leaver's); bounded load moves more (a member
    that fills up sends the next partitions to their second choice, and a change of the
    member count shifts where that happens). Printed for docs/service.md; asserted: at most
    twice the minimum plus one partition."""
    rows = []
    for n in range(2, 11):
        join, leave = share_moved(p, n)
        least = 1 / (n + 1)
        rows.append(f"P={p:3d} N={n:2d}->{n + 1:2d}: join {join:.3f}, leave {leave:.3f} "
                    f"(minimum {least:.3f})")
        assert least - 1e-9 <= join <= 2 * least + 1 / p
        assert least - 1e-9 <= leave <= 2 * least + 1 / p
    with capsys.disabled():
        print("\n" + "\n".join(rows))


def test_ownership_follows_the_members_and_gives_the_successor():
    o = Ownership("a", partitions=64)
    assert o.owned_partitions() == frozenset(range(64))
    assert o.successor("s1") is None
    assert o.join("b") and not o.join("b") and not o.leave("a")
    mine = o.owned_partitions()
    assert len(mine) == 32
    names = [f"s{i}" for i in range(200)]
    for s in names:
        k = keys.partition_of(s, 64)
        assert o.owner(s) == o.owner_of_partition(k) == ("a" if k in mine else "b")
        assert o.owns(s) == (k in mine)
        # the successor: who owns it in the table without this instance
        assert o.successor(s) == "b"
    b = Ownership("b", partitions=64)
    b.join("a")
    assert b.owned_partitions() == frozenset(range(64)) - mine  # both compute the same
    assert o.leave("b") and o.owned_partitions() == frozenset(range(64))


def test_static_shards_own_every_nth_partition():
    assert shard_partitions(1, 3, 10) == {1, 4, 7}
    shards = [Ownership("a", (i, 3), partitions=64) for i in range(3)]
    owned = [s.owned_partitions() for s in shards]
    assert set().union(*owned) == set(range(64)) and sum(map(len, owned)) == 64
    s = shards[0]
    name = next(n for n in (f"s{i}" for i in range(100)) if keys.partition_of(n, 64) % 3 == 1)
    assert s.owner(name) is None and not s.owns(name) and s.successor(name) is None
    assert s.join("b") and s.owned_partitions() == owned[0]  # no coordination


def test_a_term_is_newer_than_the_one_it_follows_whatever_the_clock():
    from pd_service.service.ownership import TERM_TAG_BITS, next_term, term_generation, term_tag

    now = 1_800_000_000_000_000_000  # ns
    t0 = next_term(0, "inst-a", now)
    assert term_generation(t0) == now // 1_000_000 and t0 & 0xFFFF == term_tag("inst-a")
    # a taker resumes from the owner's state: newer even with its clock an hour behind
    t1 = next_term(t0, "inst-b", now - 3_600 * 10**9)
    assert t1 > t0 and term_generation(t1) == term_generation(t0) + 1
    # a fresh start later (no state: the prior) is newer by the clock alone
    assert next_term(0, "inst-a", now + 10**6) > t0
    # the same millisecond on two instances: ordered by their tags, the same in every reader
    a, b = next_term(t0, "inst-a", now), next_term(t0, "inst-b", now)
    assert (a > b) == (term_tag("inst-a") > term_tag("inst-b")) and a != b
    assert next_term(t0, "x", now) < 2**63 and TERM_TAG_BITS == 16
