"""The data subscriptions of one instance: they follow the partitions it owns.

Per owned partition k, two drained subscriptions: ``pd/p<k>/*/sensor/*`` and ``pd/p<k>/*/cmd``
(``keys.partition_sensors``, ``keys.partition_commands``), so Zenoh's routers deliver the
instance only its partitions' samples. An instance that owns every partition (alone, or
the only live one) subscribes to the two wildcards ``pd/*/*/sensor/*`` and ``pd/*/*/cmd``
instead: two subscriptions, not 2 x P. On a membership change :meth:`DataSubscriptions.follow`
declares the subscriptions of the gained partitions and closes those of the lost ones; the
partitions kept keep theirs (their sessions see no gap).
"""

from __future__ import annotations

from collections.abc import Callable, Collection

from pd_service.transport import Drain, Sample, Transport
from pd_service.wire import keys

#: Most samples taken from a subscription per call while emptying it before its close.
_TAKE = 4096

#: Key of the wildcard pair (every partition) in :attr:`DataSubscriptions.by_partition`.
ALL = -1


def data_keyexprs(owned: Collection[int], p: int) -> dict[int, tuple[str, str]]:
    """The (sensors, commands) key expressions to subscribe for the ``owned`` partitions of
    ``p``: one pair per partition, or the wildcard pair (key :data:`ALL`) if it owns all."""
    if len(owned) == p:
        return {ALL: (keys.ALL_SENSORS, keys.ALL_COMMANDS)}
    return {k: (keys.partition_sensors(k), keys.partition_commands(k)) for k in sorted(owned)}


class DataSubscriptions:
    """The drained sensor and command subscriptions of the owned partitions."""

    def __init__(self, transport: Transport, on_sensor: Callable[[Sample], None],
                 on_command: Callable[[Sample], None], wake: Callable[[], None],
                 partitions: int) -> None:
        self.t = transport
        self._on_sensor, self._on_command, self._wake = on_sensor, on_command, wake
        self.partitions = partitions
        #: partition (or ALL) -> its (sensors, commands) drains
        self.by_partition: dict[int, tuple[Drain, Drain]] = {}
        #: every drain, in the order the worker takes them
        self.drains: list[Drain] = []

    def follow(self, owned: Collection[int]) -> tuple[int, int]:
        """Subscribe to the ``owned`` partitions' data, unsubscribe from the others'.
        Returns (declared, closed) partition pairs.

        Between the wildcard pair and per-partition pairs (one member <-> two) the old pair
        is closed before the new one is declared: a sample in between is lost (the
        estimator takes losses), where both at once would deliver it twice and the second
        copy would be reported to its sender as a duplicate. A closed subscription is
        emptied first (what it holds goes to dispatch, as in a round). Worker thread only."""
        want = data_keyexprs(owned, self.partitions)
        have = self.by_partition
        gone = [k for k in have if k not in want]
        for k in gone:
            for dr in have.pop(k):
                while dr.drain(_TAKE):  # what it holds still reaches dispatch
                    pass
                dr.close()
        new = [k for k in want if k not in have]
        t = self.t
        for k in new:
            sensors, commands = want[k]
            have[k] = (t.subscribe_drained(sensors, self._on_sensor, self._wake),
                       t.subscribe_drained(commands, self._on_command, self._wake))
        self.drains = [dr for pair in have.values() for dr in pair]
        return len(new), len(gone)

    def close(self) -> None:
        for pair in self.by_partition.values():
            for dr in pair:
                dr.close()
        self.by_partition.clear()
        self.drains = []
