"""Session specs on disk: one ``<session>.msgpack`` file per session (the wire encoding).

Writes are atomic and durable: write ``.<session>.msgpack.tmp``, fsync it, rename it over the
old file (exchange the two where Linux allows: the old content stays in the ``.tmp`` file,
reused by the next write), fsync the directory. A crash leaves either the old or the new
spec, never half of one. Only regular files of at most ``MAX_FILE_BYTES`` are read at
startup (never a symlink, a FIFO or a device: startup never blocks); anything else, and
unreadable files, are renamed ``*.bad`` and reported, never fatal.
"""

from __future__ import annotations

import ctypes
import logging
import os
import stat
import threading
from collections import deque
from pathlib import Path
from typing import Any

from pd_service.logs import LOGGER_NAME, event, name_os_thread
from pd_service.wire import SessionSpec, WireError, decode, encode
from pd_service.wire.keys import KeyError_, check_name

log = logging.getLogger(LOGGER_NAME)

SUFFIX = ".msgpack"
#: Checkpoint files: ``<session>.ckpt`` (an encoded SessionState).
STATE_SUFFIX = ".ckpt"
#: Largest state file read (a spec or a checkpoint is far smaller); larger ones are refused.
MAX_FILE_BYTES = 1 << 20


_RENAME_EXCHANGE = 2
_renameat2: Any = None


def _exchange(tmp: Path, final: Path) -> bool:
    """Swap ``tmp`` and ``final`` atomically (Linux ``renameat2(RENAME_EXCHANGE)``): the old
    content stays in ``tmp``, whose inode the next write truncates and reuses, so rewriting
    a checkpoint creates and deletes no inode (on ext4 a new inode per write cost ~0.5 ms of
    kernel time). False where unsupported (no such file yet, other OS or file system): the
    caller renames instead."""
    global _renameat2
    if _renameat2 is None:
        try:
            fn = ctypes.CDLL(None, use_errno=True).renameat2
            fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                           ctypes.c_uint]
            _renameat2 = fn
        except (OSError, AttributeError):
            _renameat2 = False
    if not _renameat2:
        return False
    at_fdcwd = -100  # fails (ENOENT) when there is no final file yet
    return _renameat2(at_fdcwd, os.fsencode(tmp), at_fdcwd, os.fsencode(final),
                      _RENAME_EXCHANGE) == 0


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


class SpecStore:
    """Persisted specs in ``directory`` (created if missing, mode 0700)."""

    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)

    def path(self, session: str) -> Path:
        return self.dir / f"{check_name(session, 'session')}{SUFFIX}"

    def save(self, spec: SessionSpec) -> None:
        """Persist ``spec`` atomically (tmp + fsync + rename + fsync dir)."""
        self._write(self.path(spec.session), encode(spec))

    def state_path(self, session: str) -> Path:
        return self.dir / f"{check_name(session, 'session')}{STATE_SUFFIX}"

    def save_state(self, session: str, data: bytes) -> None:
        """Write a session's checkpoint (encoded SessionState) atomically, without fsync: it
        survives a crash of the daemon (kill -9: the kernel holds the data), not
        necessarily a power loss, after which a checkpoint may be older or unreadable
        (then refused as corrupt at restart: the session starts from its prior). Checkpoints
        with an fsync each cost ~15-25 µs per session-step at 200 sessions (bench/service.py,
        single runs): ~10 % of the daemon's CPU."""
        self._write(self.state_path(session), data, sync=False)

    def load_state(self, session: str) -> bytes | None:
        """The session's checkpoint bytes, or None if there is none (or it is unreadable)."""
        try:
            return read_regular(self.state_path(session))
        except OSError:
            return None

    def remove_state(self, session: str) -> None:
        self._remove(self.state_path(session))

    def _write(self, final: Path, data: bytes, sync: bool = True) -> None:
        """Write ``data`` to a temp file and exchange it with ``final`` (atomic: a reader
        sees the old or the new file). ``sync``: fsync the file and the directory, so the
        write also survives a power loss, not only a crash of the process."""
        tmp = final.with_name(f".{final.name}.tmp")
        # no O_TRUNC: the temp file (the previous exchange's old content) is overwritten in
        # place and cut to the new length. Truncating to zero and renaming over a file makes
        # ext4 start the data's writeback at once (its auto_da_alloc heuristic): measured
        # ~230 µs of kernel time per checkpoint against ~25 µs this way (docs/service.md)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        try:
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            os.ftruncate(fd, len(data))
            if sync:
                os.fsync(fd)
        finally:
            os.close(fd)
        if not _exchange(tmp, final):
            os.replace(tmp, final)
        if sync:
            self._sync_dir()

    def remove(self, session: str) -> None:
        self._remove(self.path(session))

    def _remove(self, path: Path) -> None:
        """Delete a spec or state file and its exchanged previous version (``.<name>.tmp``)."""
        try:
            path.with_name(f".{path.name}.tmp").unlink()
        except FileNotFoundError:
            pass
        try:
            path.unlink()
        except FileNotFoundError:
            return
        self._sync_dir()

    def set_aside(self, session: str, reason: str) -> None:
        """Rename a persisted spec that will not be run to ``<file>.refused`` (kept for the
        operator, never read again) and log why."""
        p = self.path(session)
        try:
            p.rename(p.with_name(p.name + ".refused"))
        except OSError:
            pass
        event(log, "spec_set_aside", logging.WARNING, file=str(p), reason=reason)

    def load_all(self) -> tuple[dict[str, SessionSpec], list[str]]:
        """Every readable spec by session, and the names of the files that were not readable
        (renamed to ``*.bad``)."""
        specs: dict[str, SessionSpec] = {}
        bad: list[str] = []
        for p in sorted(self.dir.glob(f"*{SUFFIX}")):
            try:
                if p.is_symlink() or not p.is_file():  # lstat / stat: no open, no block
                    raise OSError("not a regular file")
                session = check_name(p.name[: -len(SUFFIX)], "session")
                spec = decode(read_regular(p), SessionSpec)
                if spec.session != session:
                    raise WireError(f"file holds session {spec.session!r}")
                specs[session] = spec
            except (OSError, WireError, KeyError_) as exc:
                bad.append(p.name)
                event(log, "spec_unreadable", logging.WARNING, file=str(p), reason=str(exc))
                try:
                    p.rename(p.with_name(p.name + ".bad"))
                except OSError:
                    pass
        return specs, bad

    def _sync_dir(self) -> None:
        try:
            fd = os.open(self.dir, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)


class StateWriter:
    """Writes checkpoints on a thread of its own, so the worker never waits for the disk.

    The worker hands over encoded states with :meth:`submit` (a dict insert; a newer state of
    the same session replaces one not yet written); the thread writes them with
    :meth:`SpecStore.save_state` (tmp + exchange, no fsync). Outcomes ``(session, bytes,
    error or None)`` wait in :attr:`done` for the worker to count them. :meth:`remove`
    deletes a checkpoint after any pending or running write of it; :meth:`close` writes what
    is pending, then stops the thread.
    """

    def __init__(self, store: SpecStore) -> None:
        self.store = store
        self.done: deque[tuple[str, int, OSError | None]] = deque()
        self._cond = threading.Condition()
        self._pending: dict[str, bytes] = {}
        self._writing: str | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="pd-service-ckpt", daemon=True)
        self._thread.start()

    def submit(self, session: str, data: bytes) -> None:
        with self._cond:
            self._pending[session] = data
            self._cond.notify()

    def remove(self, session: str) -> None:
        """Drop a pending write of ``session`` and delete its checkpoint file."""
        with self._cond:
            self._pending.pop(session, None)
            while self._writing == session:
                self._cond.wait()
            self.store.remove_state(session)

    def flush(self) -> None:
        """Return once every state submitted so far is written."""
        with self._cond:
            while self._pending or self._writing is not None:
                self._cond.wait()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout=30.0)

    def _run(self) -> None:
        name_os_thread("pd-ckpt")
        store = self.store
        while True:
            with self._cond:
                while not self._pending and not self._closed:
                    self._cond.wait()
                if not self._pending:
                    return
            while True:
                with self._cond:
                    if not self._pending:
                        self._writing = None
                        self._cond.notify_all()
                        break
                    session = next(iter(self._pending))
                    data = self._pending.pop(session)
                    self._writing = session
                try:
                    store.save_state(session, data)
                    err: OSError | None = None
                except OSError as exc:
                    err = exc
                self.done.append((session, len(data), err))
                with self._cond:
                    self._writing = None
                    self._cond.notify_all()
