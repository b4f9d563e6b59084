"""Returning the C heap's free pages to the system (glibc's ``malloc_trim``).

Why: Zenoh's threads and the worker allocate messages through glibc's malloc, which gives
each thread an arena of its own (up to 8 per core). When the daemon falls behind, the
samples waiting in the drains' channels fill those arenas; once the backlog is taken, the
memory is free but glibc keeps it (it trims only the top of the main heap on its own). A
daemon overloaded a few times in an hour then shows its highest backlog as RSS for good:
in a soak, 173 MB of arenas held 70 MB in use (docs/service.md, "Long runs").
``malloc_trim(0)`` walks every arena and hands whole free pages back (``madvise``), which
costs milliseconds and is done off the worker, once a minute, by the daemon's main thread.

Not glibc (musl, macOS): nothing to call; :func:`return_free_heap` returns None.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Callable

#: How often the daemon returns free heap pages (s).
TRIM_INTERVAL_S = 60.0


def _load_trim() -> Callable[[int], int] | None:
    """glibc's ``int malloc_trim(size_t pad)``, or None where the C library has none."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


_TRIM = _load_trim()
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_bytes() -> int:
    """This process's resident set (bytes) from /proc/self/statm; 0 where unreadable."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return 0


def return_free_heap() -> tuple[int, int] | None:
    """Hand the C heap's free pages back to the system: ``(rss_before, rss_after)`` in bytes,
    or None without glibc's ``malloc_trim``. ctypes releases the GIL for the call, so the
    other Python threads go on; each arena's lock is held while that arena is walked."""
    if _TRIM is None:
        return None
    before = rss_bytes()
    _TRIM(0)
    return before, rss_bytes()
