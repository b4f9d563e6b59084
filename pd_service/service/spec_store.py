"""Session specs on disk: one ``<session>.msgpack`` file per session (the wire encoding);
the sessions' checkpoints in one log beside them (:mod:`.handover.checkpoint_log`), written
by a thread of their own (:class:`~.handover.checkpoint_writer.CheckpointWriter`).

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
from pathlib import Path
from typing import Any

from pd_service.logs import LOGGER_NAME, event
from pd_service.wire import SessionSpec, WireError, decode, encode
from pd_service.wire.keys import KeyError_, check_name

from .handover.checkpoint_log import CheckpointLog, read_regular, write_all

log = logging.getLogger(LOGGER_NAME)

SUFFIX = ".msgpack"


_RENAME_EXCHANGE = 2
_renameat2: Any = None


def _exchange(tmp: Path, final: Path) -> bool:
    """Swap ``tmp`` and ``final`` atomically (Linux ``renameat2(RENAME_EXCHANGE)``): the old
    content stays in ``tmp``, whose inode the next write truncates and reuses, so rewriting
    a spec creates and deletes no inode (each costs the kernel metadata work). False where
    unsupported (no such file yet, other OS or file system): the
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


class SpecStore:
    """Persisted specs in ``directory`` (created if missing, mode 0700)."""

    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        #: The checkpoints (read at first use).
        self.states = CheckpointLog(self.dir)

    def path(self, session: str) -> Path:
        return self.dir / f"{check_name(session, 'session')}{SUFFIX}"

    def save(self, spec: SessionSpec) -> None:
        """Persist ``spec`` atomically (tmp + fsync + rename + fsync dir)."""
        self._write(self.path(spec.session), encode(spec))

    def save_state(self, session: str, data: bytes) -> None:
        """Write a session's checkpoint (an encoded SessionState; :meth:`save_states`)."""
        self.states.append([(session, data)])

    def save_states(self, items: list[tuple[str, bytes | None]]) -> None:
        """Write checkpoints ``(session, data)`` and removals ``(session, None)``, in order,
        to the checkpoint log (one write; :mod:`.handover.checkpoint_log`), without fsync: they survive a
        crash of the daemon (kill -9: the kernel holds the data), not necessarily a power
        loss, after which a checkpoint may be older or the log's end damaged (the records
        before the damage are read). OSError if the disk refuses."""
        self.states.append(items)

    def load_state(self, session: str) -> bytes | None:
        """The session's checkpoint bytes, or None if there is none."""
        return self.states.get(session)

    def states_damaged(self) -> str | None:
        """What was wrong with the checkpoint log when it was read (None: nothing)."""
        return self.states.damage()

    def remove_state(self, session: str) -> None:
        self.states.append([(session, None)])

    def close(self) -> None:
        """Close the checkpoint log's file (reopened by the next write)."""
        self.states.close()

    def _write(self, final: Path, data: bytes) -> None:
        """Write ``data`` to a temp file, fsync it, exchange it with ``final`` (atomic: a
        reader sees the old or the new file) and fsync the directory: the write survives a
        power loss, not only a crash of the process."""
        tmp = final.with_name(f".{final.name}.tmp")
        # no O_TRUNC: overwritten in place and cut to the new length, since truncating and
        # renaming over a file makes ext4 start its writeback at once (auto_da_alloc)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        try:
            write_all(fd, data)
            os.ftruncate(fd, len(data))
            os.fsync(fd)
        finally:
            os.close(fd)
        if not _exchange(tmp, final):
            os.replace(tmp, final)
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
