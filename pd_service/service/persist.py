"""Session specs on disk: one ``<session>.msgpack`` file per session (the wire encoding).

Writes are atomic and durable: write ``.<session>.msgpack.tmp``, fsync it, rename it over the
old file, fsync the directory. A crash leaves either the old or the new spec, never half of
one. Unreadable files found at startup are renamed ``*.bad`` and reported, never fatal.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from pd_service.logs import LOGGER_NAME, event
from pd_service.wire import SessionSpec, WireError, decode, encode
from pd_service.wire.keys import KeyError_, check_name

log = logging.getLogger(LOGGER_NAME)

SUFFIX = ".msgpack"
#: Checkpoint files: ``<session>.ckpt`` (an encoded SessionState).
STATE_SUFFIX = ".ckpt"


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
        """Write a session's checkpoint (encoded SessionState) atomically, like a spec."""
        self._write(self.state_path(session), data)

    def load_state(self, session: str) -> bytes | None:
        """The session's checkpoint bytes, or None if there is none (or it is unreadable)."""
        try:
            return self.state_path(session).read_bytes()
        except OSError:
            return None

    def remove_state(self, session: str) -> None:
        try:
            self.state_path(session).unlink()
        except FileNotFoundError:
            return
        self._sync_dir()

    def _write(self, final: Path, data: bytes) -> None:
        tmp = final.with_name(f".{final.name}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, final)
        self._sync_dir()

    def remove(self, session: str) -> None:
        try:
            self.path(session).unlink()
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
                session = check_name(p.name[: -len(SUFFIX)], "session")
                spec = decode(p.read_bytes(), SessionSpec)
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
