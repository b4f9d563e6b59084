"""Which instance serves which session: ownership by *partition* (key layout 2).

A session belongs to partition ``k = keys.partition_of(session)`` (0 <= k < P, P =
``keys.partitions()``); an instance owns partitions, and with them every session in them. It
subscribes to the data of its partitions only (``pd/p<k>/*/sensor/*``, ``pd/p<k>/*/cmd``), so
Zenoh's routers deliver it only those samples. Two policies, both pure functions of names
(every instance computes the same answer from the same member list):

- **Bounded-load rendezvous** (the default, :func:`assign_partitions`): partitions
  k = 0..P-1 in order, each to its highest-weight member (weight ``h("<instance>/p<k>")``, a
  64-bit BLAKE2b) that still has room; room: fewer than ``floor(P/N)`` partitions, or
  ``floor(P/N)`` while fewer than ``P mod N`` members hold ``ceil(P/N)``. Every member owns
  ``floor(P/N)`` or ``ceil(P/N)`` partitions. On a join or a leave a share of the partitions
  near 1/N changes owner (somewhat more than plain rendezvous, whose loads are uneven:
  measured in tests/service/test_ownership.py, reported in docs/service.md).
- **Static shards** ``i/N``: instance i owns the partitions with ``k mod N == i``. No
  coordination, no takeover: if shard i is down, its sessions are not served.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable

from pd_service.wire import keys


def stable_hash(text: str) -> int:
    """64-bit BLAKE2b of ``text`` (UTF-8) as an unsigned int: same value in every process."""
    return int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "big")


def assign_partitions(members: Iterable[str], p: int) -> list[str]:
    """The owner of each partition 0..p-1 among ``members`` (bounded-load rendezvous, see the
    module's docstring); a list of p instance names, [] without members."""
    ms = sorted(set(members))
    if not ms:
        return []
    floor, extra = divmod(p, len(ms))
    count = dict.fromkeys(ms, 0)
    at_ceil = 0  # members holding floor + 1 partitions (at most ``extra`` of them)
    out: list[str] = []
    for k in range(p):
        order = sorted(((stable_hash(f"{m}/{keys.partition_chunk(k)}"), m) for m in ms),
                       reverse=True)
        for _, m in order:
            c = count[m]
            if c < floor or (c == floor and at_ceil < extra):
                at_ceil += c == floor
                count[m] = c + 1
                out.append(m)
                break
    return out


def shard_partitions(i: int, n: int, p: int) -> frozenset[int]:
    """The partitions of static shard ``i`` of ``n``: those with k mod n == i."""
    return frozenset(range(i, p, n))


class Ownership:
    """The current ownership view of one instance: itself plus the live peers it has seen.

    The partition table is recomputed on each membership change (P x N hashes); a lookup is a
    partition hash and a list index."""

    def __init__(self, instance: str, shard: tuple[int, int] | None = None,
                 partitions: int | None = None) -> None:
        self.instance = instance
        self.shard = shard
        self.partitions = keys.partitions() if partitions is None else partitions
        self.members: set[str] = {instance}
        self._table: list[str | None] = []
        self._successors: list[str | None] = []
        self._recompute()

    def _recompute(self) -> None:
        p = self.partitions
        if self.shard is not None:
            mine = shard_partitions(self.shard[0], self.shard[1], p)
            self._table = [self.instance if k in mine else None for k in range(p)]
            self._successors = [None] * p
            return
        self._table = list(assign_partitions(self.members, p))
        others = self.members - {self.instance}
        self._successors = list(assign_partitions(others, p)) if others else [None] * p

    def owner_of_partition(self, k: int) -> str | None:
        """Owning instance of partition ``k``, or None when unknown (another static shard)."""
        return self._table[k]

    def owner(self, session: str) -> str | None:
        """Owning instance of ``session``, or None when unknown (another static shard)."""
        return self._table[keys.partition_of(session, self.partitions)]

    def owners(self) -> list[str | None]:
        """A copy of the partition table (owner of each partition): the view before a
        membership change, to tell who served a session that moves."""
        return list(self._table)

    def successor(self, session: str) -> str | None:
        """Who would own ``session`` if this instance went away (rendezvous only). None with
        static shards or alone."""
        return self._successors[keys.partition_of(session, self.partitions)]

    def owns(self, session: str) -> bool:
        return self.owner(session) == self.instance

    def owned_partitions(self) -> frozenset[int]:
        """The partitions this instance owns now."""
        me = self.instance
        return frozenset(k for k, m in enumerate(self._table) if m == me)

    def join(self, instance: str) -> bool:
        """Record a live instance; True if the membership changed."""
        if instance in self.members:
            return False
        self.members.add(instance)
        self._recompute()
        return True

    def leave(self, instance: str) -> bool:
        """Record an instance that went away (never ourselves); True if it changed."""
        if instance == self.instance or instance not in self.members:
            return False
        self.members.discard(instance)
        self._recompute()
        return True

    def describe(self) -> str:
        if self.shard is not None:
            return f"{self.shard[0]}/{self.shard[1]}"
        return f"rendezvous:{len(self.members)}"


# ====================================================================== fencing ========
#
# An ownership *term* fences the output of two owners of one session (a partition between
# instances: each side takes the other's sessions over). term = generation << TERM_TAG_BITS
# | tag, with tag = the low TERM_TAG_BITS bits of stable_hash(instance) (ties between two
# instances that start a generation at the same time broken by instance, the same way in
# every reader) and generation = max(previous generation + 1, now in ms). The previous
# term is the one a resumed state carries (replica, hand-over, checkpoint) or the replaced
# session's: a taker's term is newer than the term of the owner it took from, whatever
# the clocks; a session started from nothing (prior, a new spec) still gets a term newer
# than any earlier incarnation's as long as the hosts' clocks agree to a millisecond.

#: Bits of a term that hold the instance's tag (the rest: the generation).
TERM_TAG_BITS = 16


def term_tag(instance: str) -> int:
    """The instance's tag: the low TERM_TAG_BITS bits of its stable_hash."""
    return stable_hash(instance) & ((1 << TERM_TAG_BITS) - 1)


def term_generation(term: int) -> int:
    """The generation part of ``term`` (ms since the epoch when it began, or later)."""
    return term >> TERM_TAG_BITS


def next_term(previous: int, instance: str, now_ns: int) -> int:
    """The term ``instance`` publishes a session with when it starts serving it at wall
    time ``now_ns``, after ``previous`` (0: none known): generation
    max(generation(previous) + 1, now_ns // 1e6), then the instance's tag. Always >
    ``previous`` (int64 holds generations up to 2^47 ms, year 6429)."""
    gen = max(term_generation(previous) + 1, now_ns // 1_000_000)
    return (gen << TERM_TAG_BITS) | term_tag(instance)
