"""Which instance serves which session.

Two policies, both pure functions of names (every instance computes the same answer):

- **Rendezvous** (highest random weight, the default): the owner of session ``s`` among the
  live instances ``I`` is ``argmax_{i in I} h(i, s)`` with ``h`` a 64-bit BLAKE2b of
  ``"<i>/<s>"``. When an instance leaves, only its sessions move (each to the survivor with
  the next-highest weight); when one joins, it takes about 1/|I| of the sessions.
- **Static shards** ``i/N``: instance i serves the sessions with ``h(s) mod N == i``. No
  coordination, no takeover: if shard i is down, its sessions are not served.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable


def stable_hash(text: str) -> int:
    """64-bit BLAKE2b of ``text`` (UTF-8) as an unsigned int: same value in every process."""
    return int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "big")


def rendezvous_owner(session: str, instances: Iterable[str]) -> str | None:
    """The instance with the highest weight h(instance/session); ties broken by name."""
    best: tuple[int, str] | None = None
    for inst in instances:
        w = (stable_hash(f"{inst}/{session}"), inst)
        if best is None or w > best:
            best = w
    return None if best is None else best[1]


def shard_of(session: str, n: int) -> int:
    """Static shard of a session: h(session) mod n."""
    return stable_hash(session) % n


class Ownership:
    """The current ownership view of one instance: itself plus the live peers it has seen."""

    def __init__(self, instance: str, shard: tuple[int, int] | None = None) -> None:
        self.instance = instance
        self.shard = shard
        self.members: set[str] = {instance}

    def owner(self, session: str) -> str | None:
        """Owning instance, or None when it is unknown (another static shard)."""
        if self.shard is not None:
            i, n = self.shard
            return self.instance if shard_of(session, n) == i else None
        return rendezvous_owner(session, self.members)

    def successor(self, session: str) -> str | None:
        """Who would own ``session`` if this instance went away (rendezvous only): the
        next instance in its rendezvous order. None with static shards or alone."""
        if self.shard is not None:
            return None
        return rendezvous_owner(session, self.members - {self.instance})

    def owns(self, session: str) -> bool:
        return self.owner(session) == self.instance

    def join(self, instance: str) -> bool:
        """Record a live instance; True if the membership changed."""
        if instance in self.members:
            return False
        self.members.add(instance)
        return True

    def leave(self, instance: str) -> bool:
        """Record an instance that went away (never ourselves); True if it changed."""
        if instance == self.instance or instance not in self.members:
            return False
        self.members.discard(instance)
        return True

    def describe(self) -> str:
        if self.shard is not None:
            return f"{self.shard[0]}/{self.shard[1]}"
        return f"rendezvous:{len(self.members)}"
