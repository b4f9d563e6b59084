"""The thread that appends the sessions' checkpoints to the checkpoint log
(:mod:`.checkpoint_log`, through :class:`~pd_service.service.spec_store.SpecStore`), so that
the worker never waits for the disk."""

from __future__ import annotations

import threading
import time
from collections import deque

from pd_service.logs import name_os_thread

from ..spec_store import SpecStore


class CheckpointWriter:
    """Writes checkpoints on a thread of its own, so the worker never waits for the disk.

    The worker hands over encoded states with :meth:`submit` (a dict insert; a newer state of
    the same session replaces one not yet written) and removals with :meth:`remove`; the
    thread takes what is pending in one batch, appends it to the checkpoint log with one write
    (:meth:`SpecStore.save_states`), then rests ``BATCH_WAIT_S`` so that the next batch
    gathers the states of many rounds (one write and two GIL hand-offs per batch, not ~6
    system calls per state: the worker paid for each hand-off). Outcomes ``(session, bytes,
    error or None)`` wait in :attr:`done` for the worker to count them. :meth:`close` writes
    what is pending, then stops the thread.
    """

    #: Rest (s) after a batch: checkpoints reach the log at most this much later.
    BATCH_WAIT_S = 0.02

    def __init__(self, store: SpecStore) -> None:
        self.store = store
        self.done: deque[tuple[str, int, OSError | None]] = deque()
        self._cond = threading.Condition()
        self._pending: dict[str, bytes | None] = {}  # None: remove the session's checkpoint
        self._writing = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="pd-service-ckpt", daemon=True)
        self._thread.start()

    def submit(self, session: str, data: bytes) -> None:
        with self._cond:
            self._pending[session] = data
            self._cond.notify()

    def remove(self, session: str) -> None:
        """Drop a pending write of ``session`` and remove its checkpoint (written after any
        state of it already taken: the log keeps their order)."""
        with self._cond:
            self._pending[session] = None
            self._cond.notify()

    def flush(self) -> None:
        """Return once every state submitted so far is written."""
        with self._cond:
            while self._pending or self._writing:
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
                batch, self._pending = self._pending, {}
                self._writing = True
            try:
                store.save_states(list(batch.items()))
                err: OSError | None = None
            except OSError as exc:
                err = exc
            for session, data in batch.items():
                if data is not None:
                    self.done.append((session, len(data), err))
            with self._cond:
                self._writing = False
                self._cond.notify_all()
                closed = self._closed
            if not closed:
                time.sleep(self.BATCH_WAIT_S)
