"""Returning free C heap pages (pd_service.service.heap) and the daemon's use of it."""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

import pytest

from pd_service.service import Settings
from pd_service.service.daemon import Daemon
from pd_service.service.heap import return_free_heap, rss_bytes
from pd_service.transport import InMemoryBus

glibc = pytest.mark.skipif(return_free_heap() is None, reason="needs glibc's malloc_trim")


def _fragment_a_thread_arena(mb: int) -> None:
    """In a thread of its own (so in a glibc arena of its own, as Zenoh's threads allocate):
    malloc ``mb`` MB in 1 KiB blocks, touch them, free all but the last (it pins the arena's
    top, so glibc's own trimming of the top returns nothing)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]

    def run() -> None:
        blocks = [libc.malloc(1024) for _ in range(mb * 1024)]
        for b in blocks:
            ctypes.memset(b, 1, 1024)
        for b in blocks[:-1]:
            libc.free(b)

    t = threading.Thread(target=run)
    t.start()
    t.join()


@glibc
def test_free_pages_of_a_thread_arena_go_back_to_the_system():
    _fragment_a_thread_arena(64)
    held = rss_bytes()
    got = return_free_heap()
    assert got is not None
    before, after = got
    assert before == pytest.approx(held, abs=8 << 20)
    assert before - after >= 48 << 20  # of the 64 MB freed, nearly all handed back


@glibc
def test_the_daemon_counts_what_it_returned(tmp_path):
    d = Daemon(Settings(instance="heap", state_dir=tmp_path / "state"),
               transport=InMemoryBus().transport())
    d.start()
    try:
        assert d.core is not None
        assert d.core.counters["heap_trims"] == 0  # present before the first trim
        _fragment_a_thread_arena(32)
        d.trim_heap()
        assert d.core.counters["heap_trims"] == 1
        assert d.core.counters["heap_returned_bytes"] >= 24 << 20
    finally:
        d.stop()
