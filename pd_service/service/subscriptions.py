"""The data subscriptions of one instance: they follow the partitions it owns.

Per owned partition k, two subscriptions: ``pd/p<k>/*/sensor/*`` and ``pd/p<k>/*/cmd``
(``keys.partition_sensors``, ``keys.partition_commands``), so Zenoh's routers deliver the
instance only its partitions' samples. An instance that owns every partition (alone, or
the only live one) subscribes to the two wildcards ``pd/*/*/sensor/*`` and ``pd/*/*/cmd``
instead: two subscriptions, not 2 x P. All of them are members of one drain group
(:meth:`Transport.drain_group`): the worker takes their samples in batches, and one watcher
thread per instance hands the first one over while the worker is idle, however many
partitions it owns. On a membership change :meth:`DataSubscriptions.follow` declares the
subscriptions of the gained partitions and closes those of the lost ones; the partitions
kept keep theirs (their sessions see no gap).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection

from pd_service.transport import DrainGroup, DrainMember, Sample, Transport
from pd_service.wire import keys

#: Most samples taken from a subscription per look while emptying the queues at a switch.
_TAKE = 4096

#: Key of the wildcard pair (every partition) in :attr:`DataSubscriptions.by_partition`.
ALL = -1

#: How long after a switch between the wildcard pair and per-partition pairs a sample the
#: old subscriptions delivered is still dropped when the new ones deliver it again (ns).
OVERLAP_NS = 1_000_000_000


def data_keyexprs(owned: Collection[int], p: int) -> dict[int, tuple[str, str]]:
    """The (sensors, commands) key expressions to subscribe for the ``owned`` partitions of
    ``p``: one pair per partition, or the wildcard pair (key :data:`ALL`) if it owns all."""
    if len(owned) == p:
        return {ALL: (keys.ALL_SENSORS, keys.ALL_COMMANDS)}
    return {k: (keys.partition_sensors(k), keys.partition_commands(k)) for k in sorted(owned)}


class SwitchOverlap:
    """A switch between the wildcard pair and per-partition pairs, where the old and the new
    subscriptions overlap: the new ones are declared before the old ones close, so nothing
    arriving in between is lost, and a sample both deliver reaches dispatch once (the second
    copy would be refused as a duplicate and reported to its sender).

    The old subscriptions record what they deliver from the switch on, as (key, payload);
    the new ones drop a sample recorded so (once), until ``OVERLAP_NS`` after the switch,
    then go back to the plain callbacks. (A sender that really sends the same bytes twice
    within that second has its second copy dropped quietly instead of reported.)"""

    def __init__(self, until_mono_ns: int) -> None:
        """``until_mono_ns``: the end of the overlap, on the samples' ``recv_mono_ns`` clock."""
        self.until = until_mono_ns
        self.seen: set[tuple[str, bytes]] = set()
        #: the new members and the plain callbacks they go back to
        self.members: list[tuple[DrainMember, Callable[[Sample], None]]] = []

    def recording(self, plain: Callable[[Sample], None]) -> Callable[[Sample], None]:
        seen = self.seen

        def record(s: Sample) -> None:
            seen.add((s.key, s.payload))
            plain(s)
        return record

    def filtering(self, plain: Callable[[Sample], None]) -> Callable[[Sample], None]:
        seen = self.seen

        def drop_seen(s: Sample) -> None:
            if s.recv_mono_ns > self.until:
                self.end()
            else:
                k = (s.key, s.payload)
                if k in seen:
                    seen.discard(k)
                    return
            plain(s)
        return drop_seen

    def end(self) -> None:
        for m, plain in self.members:
            m.callback = plain
        self.members.clear()
        self.seen.clear()


class DataSubscriptions:
    """The drained sensor and command subscriptions of the owned partitions."""

    def __init__(self, transport: Transport, on_sensor: Callable[[Sample], None],
                 on_command: Callable[[Sample], None], wake: Callable[[], None],
                 partitions: int) -> None:
        self._on_sensor, self._on_command = on_sensor, on_command
        self.partitions = partitions
        #: the instance's one drain group: the worker drains and arms it
        self.group: DrainGroup = transport.drain_group(wake)
        #: partition (or ALL) -> its (sensors, commands) members
        self.by_partition: dict[int, tuple[DrainMember, DrainMember]] = {}
        #: the last switch's overlap (tests read it)
        self.overlap: SwitchOverlap | None = None

    def follow(self, owned: Collection[int]) -> tuple[int, int]:
        """Subscribe to the ``owned`` partitions' data, unsubscribe from the others'.
        Returns (declared, closed) partition pairs. Worker thread only.

        What a closed subscription still holds goes to dispatch, as in a round. From the
        wildcard pair to per-partition pairs (a second member joined) the new pairs are
        declared before the wildcards close: nothing arriving in between is lost, and
        :class:`SwitchOverlap` drops the second copies. The other way (the instance is
        left alone) the per-partition pairs close before the wildcards are declared: with
        Zenoh 1.10 a wildcard declared beside narrower subscriptions that then close
        sometimes stopped receiving altogether (docs/service.md, "Scale-out"), so this
        switch loses what is sent in between (microseconds)."""
        want = data_keyexprs(owned, self.partitions)
        have = self.by_partition
        gone = [k for k in have if k not in want]
        new = [k for k in want if k not in have]
        on_sensor, on_command = self._on_sensor, self._on_command
        ov: SwitchOverlap | None = None
        if ALL in gone:
            # what the queues hold first, through the previous switch's filters (its second
            # copies are in there): then that switch is over
            while self.group.drain(_TAKE):
                pass
            if self.overlap is not None:
                self.overlap.end()
            ov = self.overlap = SwitchOverlap(time.monotonic_ns() + OVERLAP_NS)
            sm, cm = have[ALL]  # recording before the new ones exist: no copy escapes it
            sm.callback, cm.callback = ov.recording(on_sensor), ov.recording(on_command)
            on_sensor, on_command = ov.filtering(on_sensor), ov.filtering(on_command)
        else:
            self._close(gone)
        add = self.group.add
        for k in new:
            sensors, commands = want[k]
            pair = have[k] = (add(sensors, on_sensor), add(commands, on_command))
            if ov is not None:
                ov.members += [(pair[0], self._on_sensor), (pair[1], self._on_command)]
        if ov is not None:
            self._close(gone)
        return len(new), len(gone)

    def _close(self, gone: list[int]) -> None:
        for k in gone:
            for m in self.by_partition.pop(k):
                m.close()

    def close(self) -> None:
        self.group.close()
        self.by_partition.clear()
