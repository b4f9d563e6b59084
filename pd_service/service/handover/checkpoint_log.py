"""The checkpoints of every session in one append-only file, ``<state_dir>/checkpoints.log``.

A checkpoint per session and second is small (a paper session's state is ~3 KB) and frequent:
at 1,000 sessions, one file per session meant 1,000 files rewritten per second (open, write,
truncate, close, exchange: ~6 system calls and ext4 metadata each, and a GIL hand-off back
to the writer thread after every call, which the worker pays for). Here a batch of states
is one ``write`` at the end of the file; the newest record of a session is its checkpoint.

Format: the 8 bytes ``PDCKLOG1``, then records::

    u32 len(data) | u32 crc32(name + data) | u16 len(name) | name (utf-8) | data
    (little-endian; len(data) == 0: the session's checkpoint was removed)

Reading stops at the first record that is cut short or fails its CRC (a crash while
appending, or damage): the records before it hold, the rest is dropped. A file that is not
a regular file or does not start with the magic is renamed ``*.bad``; no checkpoint is read
from it. Either is logged and kept in :attr:`CheckpointLog.damaged`, which the daemon counts
(``checkpoint_log_damaged``) and reports to each restored session left without a checkpoint
(an ErrorReport, ``restore_refused_damaged``).

Compaction: before the first append after opening, after an append that failed (it may
have left a record cut short), and whenever the file grows beyond ``COMPACT_FACTOR`` times
the live states plus ``COMPACT_SLACK_BYTES`` (or half of ``MAX_LOG_BYTES``), the live
states are written to ``.checkpoints.log.tmp`` and renamed over the log (atomic; not
fsynced, like every checkpoint: a crash of the daemon keeps them, a power loss may not).
Checkpoint files of
earlier versions (``<session>.ckpt``, one per session) are read at opening for the sessions
the log does not hold, and deleted once a compaction has carried them into the log.
"""

from __future__ import annotations

import logging
import os
import stat
import struct
import threading
import zlib
from collections.abc import Iterable
from pathlib import Path

from pd_service.logs import LOGGER_NAME, event

log = logging.getLogger(LOGGER_NAME)

LOG_NAME = "checkpoints.log"
MAGIC = b"PDCKLOG1"
#: Checkpoint files of earlier versions: ``<session>.ckpt``, read at opening.
LEGACY_SUFFIX = ".ckpt"
#: Compact when the file exceeds this many times the live states' bytes, plus the slack.
COMPACT_FACTOR = 4
COMPACT_SLACK_BYTES = 1 << 20
#: Largest log read at opening (a larger one is refused as damaged: renamed ``*.bad``).
MAX_LOG_BYTES = 1 << 30

_HEAD = struct.Struct("<IIH")

#: Largest file of the state dir read (a spec or a checkpoint is far smaller), but the log.
MAX_FILE_BYTES = 1 << 20


def read_regular(path: Path, limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of ``path`` if it is a regular file (not a symlink, FIFO, device...) of at
    most ``limit`` bytes; OSError naming why otherwise. Never blocks: opened O_NONBLOCK and
    O_NOFOLLOW, checked with fstat before reading."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(f"not a regular file (mode {stat.filemode(st.st_mode)})")
        if st.st_size > limit:
            raise OSError(f"{st.st_size} bytes, more than {limit}")
        chunks, total = [], 0
        while total <= limit:
            b = os.read(fd, 65536)
            if not b:
                break
            chunks.append(b)
            total += len(b)
        if total > limit:
            raise OSError(f"more than {limit} bytes")
        return b"".join(chunks)
    finally:
        os.close(fd)


def write_all(fd: int, data: bytes) -> None:
    """Write every byte of ``data`` to ``fd`` (``os.write`` may write fewer)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def record(name: str, data: bytes) -> bytes:
    """One record: a session's checkpoint ``data``, or its removal (``data`` empty)."""
    nb = name.encode()
    return _HEAD.pack(len(data), zlib.crc32(data, zlib.crc32(nb)), len(nb)) + nb + data


def parse(buf: bytes, off: int = 0) -> tuple[dict[str, bytes], int]:
    """The newest checkpoint per session in the records of ``buf`` from ``off`` on, and the
    offset where reading stopped (``len(buf)`` unless a record is cut short or damaged)."""
    live: dict[str, bytes] = {}
    end = len(buf)
    while off < end:
        if off + _HEAD.size > end:
            break
        n_data, crc, n_name = _HEAD.unpack_from(buf, off)
        start = off + _HEAD.size
        stop = start + n_name + n_data
        if stop > end:
            break
        nb, data = buf[start:start + n_name], buf[start + n_name:stop]
        if zlib.crc32(data, zlib.crc32(nb)) != crc:
            break
        try:
            name = nb.decode()
        except UnicodeDecodeError:
            break
        if data:
            live[name] = data
        else:
            live.pop(name, None)
        off = stop
    return live, off


class CheckpointLog:
    """The log of one state directory. Thread-safe (one lock); :meth:`append` raises
    OSError when the disk refuses (the caller counts it), the next call tries again."""

    def __init__(self, directory: Path) -> None:
        self.dir = directory
        self.path = directory / LOG_NAME
        self._lock = threading.Lock()
        self._live: dict[str, bytes] | None = None  # read at first use
        self._live_bytes = 0
        self._legacy: list[Path] = []  # earlier versions' files, until compacted into the log
        self._fd: int | None = None
        self._size = 0
        #: What was wrong with the log when it was read (None: nothing), one line.
        self.damaged: str | None = None

    # --- reading --------------------------------------------------------------------------

    def get(self, session: str) -> bytes | None:
        """The newest checkpoint of ``session``, or None."""
        with self._lock:
            return self._states().get(session)

    def sessions(self) -> list[str]:
        with self._lock:
            return sorted(self._states())

    def damage(self) -> str | None:
        """:attr:`damaged`, the log read first if it was not yet."""
        with self._lock:
            self._states()
            return self.damaged

    def _states(self) -> dict[str, bytes]:
        if self._live is None:
            self._live = self._read()
            self._live_bytes = sum(len(d) for d in self._live.values())
        return self._live

    def _read(self) -> dict[str, bytes]:
        live: dict[str, bytes] = {}
        try:
            buf = read_regular(self.path, MAX_LOG_BYTES)
        except FileNotFoundError:
            buf = None
        except OSError as exc:
            self._set_aside(str(exc))
            buf = None
        if buf is not None:
            if not buf.startswith(MAGIC):
                self._set_aside("not a checkpoint log (no PDCKLOG1 magic)")
            else:
                live, stop = parse(buf, len(MAGIC))
                if stop < len(buf):
                    self.damaged = (f"{self.path.name}: the record at byte {stop} is cut short "
                                    f"or fails its CRC; the {len(buf) - stop} bytes from it "
                                    "on were dropped")
                    event(log, "checkpoint_log_damaged", logging.WARNING, file=str(self.path),
                          offset=stop, dropped_bytes=len(buf) - stop, sessions=len(live))
        for p in sorted(self.dir.glob(f"*{LEGACY_SUFFIX}")):
            name = p.name[: -len(LEGACY_SUFFIX)]
            try:
                data = read_regular(p)
            except OSError as exc:  # a FIFO, a symlink, unreadable: left alone, never read
                event(log, "checkpoint_unreadable", logging.WARNING, file=str(p),
                      reason=str(exc))
                continue
            if name not in live and data:
                live[name] = data
            self._legacy.append(p)
        return live

    def _set_aside(self, reason: str) -> None:
        self.damaged = f"{self.path.name}: {reason}; set aside as {self.path.name}.bad"
        event(log, "checkpoint_log_unreadable", logging.WARNING, file=str(self.path),
              reason=reason)
        try:
            self.path.rename(self.path.with_name(self.path.name + ".bad"))
        except OSError:
            pass

    # --- writing --------------------------------------------------------------------------

    def append(self, items: Iterable[tuple[str, bytes | None]]) -> None:
        """Write checkpoints (``(session, data)``) and removals (``(session, None)``), in
        order, with one write at the end of the log; compacts it when due."""
        with self._lock:
            live = self._states()
            if self._fd is None:
                self._compact()
            todo = list(items)
            buf = b"".join([record(name, data or b"") for name, data in todo])
            assert self._fd is not None
            try:
                write_all(self._fd, buf)
            except OSError:
                # part of the batch may be on disk, cut short: records appended after it
                # would not be read back, so the next append rewrites the log first
                self._close()
                raise
            self._size += len(buf)
            for name, data in todo:  # what the log now holds
                old = live.pop(name, None)
                if old is not None:
                    self._live_bytes -= len(old)
                if data:
                    live[name] = data
                    self._live_bytes += len(data)
            if self._size > min(COMPACT_FACTOR * self._live_bytes + COMPACT_SLACK_BYTES,
                                MAX_LOG_BYTES // 2):
                self._compact()

    def _compact(self) -> None:
        """Write the live states to a new log and rename it over the old one; open it for
        appending. Earlier versions' per-session files are deleted once carried over."""
        live = self._states()
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        body = b"".join([MAGIC] + [record(n, d) for n, d in live.items()])
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
        try:
            write_all(fd, body)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        self._close()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW)
        self._size = len(body)
        for p in self._legacy:
            try:
                p.unlink()
            except OSError:
                pass
        self._legacy = []

    def close(self) -> None:
        with self._lock:
            self._close()

    def _close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
