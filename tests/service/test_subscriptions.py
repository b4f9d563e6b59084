"""DataSubscriptions: one drain group per instance, and the switch between the wildcard pair
and per-partition pairs that loses nothing and delivers nothing twice."""

from __future__ import annotations

import threading
import time

import pytest

from pd_service.service.subscriptions import ALL, DataSubscriptions, SwitchOverlap
from pd_service.transport import InMemoryBus, Sample
from pd_service.wire import keys
from tests.transport.test_transport import drain_watchers, listener_and_client

P = 8


def _sample(key: str, payload: bytes, mono: int = 0) -> Sample:
    return Sample(key, payload, "put", 0, mono)


def test_the_overlap_drops_the_second_copy_once_and_ends() -> None:
    out: list[bytes] = []
    ov = SwitchOverlap(until_mono_ns=100)
    old, new = ov.recording(lambda s: out.append(b"old " + s.payload)), \
        ov.filtering(lambda s: out.append(b"new " + s.payload))
    old(_sample("k", b"1"))
    old(_sample("k", b"2"))
    new(_sample("k", b"2", 10))  # both had it: dropped
    new(_sample("k", b"3", 10))
    new(_sample("k", b"2", 10))  # the sender sent it again: once dropped, now delivered
    assert out == [b"old 1", b"old 2", b"new 3", b"new 2"]
    new(_sample("k", b"1", 101))  # after the overlap: delivered, and the filter ends
    assert out[-1] == b"new 1" and not ov.seen


def test_follow_in_memory_switches_and_keeps_kept_partitions() -> None:
    bus = InMemoryBus()
    got: list[bytes] = []
    subs = DataSubscriptions(bus.transport(), lambda s: got.append(s.payload),
                             lambda s: got.append(b"cmd " + s.payload), lambda: None, P)
    assert subs.follow(range(P)) == (1, 0) and list(subs.by_partition) == [ALL]
    assert subs.follow([1, 2, 5]) == (3, 1)
    kept = subs.by_partition[2]
    assert subs.follow([2, 3]) == (1, 2) and subs.by_partition[2] is kept
    snd = bus.transport()
    name = next(f"s{i}" for i in range(100) if keys.partition_of(f"s{i}") == 3)
    snd.put(keys.sensor_key(name, "x"), b"a")
    snd.put(keys.command_key(name), b"b")
    assert got == [b"a", b"cmd b"]
    subs.follow(range(P))  # back to the wildcards: the new filter passes a new sample
    snd.put(keys.sensor_key(name, "x"), b"c")
    assert got[-1] == b"c"
    subs.close()


@pytest.mark.integration
def test_switching_over_zenoh_loses_nothing_and_delivers_nothing_twice() -> None:
    """While a sender puts numbered samples, the instance switches from the wildcard pair to
    per-partition pairs, then between partition sets again and again; every sample reaches
    the callback once, in order; one watcher thread however many partitions. (The way back
    to the wildcards loses what is sent in between: SwitchOverlap's docstring.)"""
    with listener_and_client() as (t1, t2):
        got: list[int] = []
        woke = threading.Event()
        threads = drain_watchers()
        subs = DataSubscriptions(t1, lambda s: got.append(int(s.payload)),
                                 lambda s: got.append(-int(s.payload)), woke.set, P)
        name = next(f"s{i}" for i in range(100) if keys.partition_of(f"s{i}") == 3)
        subs.follow(range(P))
        n = 10_000
        stop = threading.Event()

        pub = t2.publisher(keys.sensor_key(name, "x"))  # waits rather than drop (put drops)

        def send() -> None:
            for i in range(1, n + 1):
                if stop.is_set():
                    return
                pub.put(str(i).encode())
                if i % 20 == 0:
                    time.sleep(0.0002)

        th = threading.Thread(target=send)
        th.start()
        sets = [[3], [1, 3, 5, 7], [3, 4], [0, 3]]
        i = 0
        try:
            while th.is_alive():
                subs.follow(sets[i % len(sets)])
                i += 1
                assert drain_watchers() == threads + 1
                subs.group.drain(64)
                time.sleep(0.0005)
        finally:
            stop.set()
            th.join()
        assert i > len(sets)  # it did switch, several times
        assert subs.overlap is not None  # from the wildcards, once
        for _ in range(1000):  # bounded: what is still on its way
            subs.group.drain(4096)
            if got and got[-1] == n:
                break
            time.sleep(0.005)
        subs.close()
        missing = sorted(set(range(1, n + 1)) - set(got))
        twice = sorted(x for x in set(got) if got.count(x) > 1)
        assert (missing, twice) == ([], [])
        assert got == list(range(1, n + 1))
