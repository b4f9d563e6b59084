"""pd-web's fan-out: every event framed once, written to every connected page by one thread.

The feed calls :meth:`Fanout.publish` with an event's JSON (bytes) from a transport callback;
it is framed once as a Server-Sent Event (``data: <json>\\n\\n``) and queued. One thread
(``pd-web-fanout``) wakes at most every ``flush_s`` seconds, joins what was queued into one
batch (one ``bytes`` object shared by every page) and writes it to each page's socket without
blocking (``selectors``: a page that does not read keeps its bytes in its own buffer, the
others are written on). A page whose unsent bytes pass ``buffer_limit`` is too slow: it is
closed and counted (``cut``), its browser reconnects and gets the snapshot again; an event is
never dropped from the middle of a page's stream.

At most ``max_clients`` pages are connected at a time: :meth:`reserve` refuses the next one
(the HTTP layer answers 503) and counts it (``refused``).
"""

from __future__ import annotations

import selectors
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field

#: Pages connected at a time (``pd-web --max-clients``).
MAX_CLIENTS = 256
#: Longest wait of an event before it is written (s): events of this window go in one batch.
FLUSH_S = 0.02
#: Unsent bytes of one page before it counts as too slow and is closed.
BUFFER_LIMIT = 8 << 20


def frame(data: bytes) -> bytes:
    """One Server-Sent Event carrying ``data`` (a JSON text without newlines)."""
    return b"data: " + data + b"\n\n"


@dataclass
class _Page:
    sock: socket.socket
    out: deque[memoryview] = field(default_factory=deque)
    unsent: int = 0  # bytes in out

    def queue(self, data: bytes) -> None:
        if data:
            self.out.append(memoryview(data))
            self.unsent += len(data)


class Fanout:
    """Event bytes -> every connected page (see the module's docstring)."""

    def __init__(self, *, max_clients: int = MAX_CLIENTS, flush_s: float = FLUSH_S,
                 buffer_limit: int = BUFFER_LIMIT) -> None:
        if max_clients < 1:
            raise ValueError("max_clients must be >= 1")
        self.max_clients = max_clients
        self.flush_s = flush_s
        self.buffer_limit = buffer_limit
        self._lock = threading.Lock()
        self._pending: list[bytes] = []            # framed events not yet in a batch
        self._joining: list[tuple[socket.socket, bytes, int]] = []  # (sock, first bytes, index)
        self._reserved = 0                          # pages connected or being attached
        self.published = 0
        self.batches = 0
        self.cut = 0                                # pages closed as too slow
        self.refused = 0                            # pages refused at the cap
        self._pages: dict[int, _Page] = {}          # by fd; fan-out thread only
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        for s in (self._wake_r, self._wake_w):
            s.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pd-web-fanout", daemon=True)

    # --- any thread ------------------------------------------------------------------------

    def start(self) -> Fanout:
        self._thread.start()
        return self

    def publish(self, data: bytes) -> None:
        """Queue one event (its JSON bytes) for every page. Never blocks on a page."""
        framed = frame(data)
        with self._lock:
            self.published += 1
            self._pending.append(framed)
            first = len(self._pending) == 1
        if first:
            self._wake()

    def reserve(self) -> bool:
        """Take a page's place; False (counted in ``refused``) when ``max_clients`` are taken."""
        with self._lock:
            if self._reserved >= self.max_clients:
                self.refused += 1
                return False
            self._reserved += 1
            return True

    def release(self) -> None:
        """Give back a place taken by :meth:`reserve` that was not attached."""
        with self._lock:
            self._reserved -= 1

    def attach(self, sock: socket.socket, first: bytes) -> None:
        """Hand a reserved page's socket (HTTP headers already sent) to the fan-out thread;
        ``first`` (its snapshot) goes before every event published after this call. Call it
        under the lock that serializes :meth:`publish` with the snapshot, so that no event is
        lost or repeated between them."""
        with self._lock:
            self._joining.append((sock, first, len(self._pending)))
        self._wake()

    @property
    def listeners(self) -> int:
        with self._lock:
            return self._reserved

    def close(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread.is_alive():
            self._thread.join(5.0)
        for page in list(self._pages.values()):
            self._drop(page)
        with self._lock:
            for sock, _, _ in self._joining:
                sock.close()
            self._joining.clear()
        self._sel.close()
        self._wake_r.close()
        self._wake_w.close()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already awake (buffer full) or closing

    # --- the fan-out thread ----------------------------------------------------------------

    def _run(self) -> None:
        last = 0.0
        while not self._stop.is_set():
            with self._lock:
                waiting = bool(self._pending or self._joining)
            timeout = max(0.0, last + self.flush_s - time.monotonic()) if waiting else None
            for key, mask in self._sel.select(timeout):
                if key.fileobj is self._wake_r:
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except BlockingIOError:
                        pass
                    continue
                page = self._pages.get(key.fd)
                if page is None:
                    continue
                if mask & selectors.EVENT_READ and not self._readable(page):
                    continue
                if mask & selectors.EVENT_WRITE:
                    self._write(page)
            if time.monotonic() - last >= self.flush_s:
                last = time.monotonic()
                self._flush()

    def _flush(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
            joining, self._joining = self._joining, []
        if pending:
            self.batches += 1
            batch = b"".join(pending)  # one object, shared by every page
            for page in list(self._pages.values()):
                page.queue(batch)
                self._write(page)
        for sock, first, index in joining:
            try:
                sock.setblocking(False)
                self._sel.register(sock, selectors.EVENT_READ)
            except (OSError, ValueError):
                sock.close()
                self.release()
                continue
            page = self._pages[sock.fileno()] = _Page(sock)
            page.queue(first)
            page.queue(b"".join(pending[index:]))
            self._write(page)

    def _readable(self, page: _Page) -> bool:
        """A page sends nothing after its request: EOF or an error means it left."""
        try:
            if page.sock.recv(4096):
                return True
        except BlockingIOError:
            return True
        except OSError:
            pass
        self._drop(page)
        return False

    def _write(self, page: _Page) -> None:
        try:
            while page.out:
                n = page.sock.send(page.out[0])
                page.unsent -= n
                if n == len(page.out[0]):
                    page.out.popleft()
                else:
                    page.out[0] = page.out[0][n:]
        except BlockingIOError:
            pass
        except OSError:
            self._drop(page)
            return
        if page.unsent > self.buffer_limit:
            self.cut += 1
            self._drop(page)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if page.out else 0)
        if self._sel.get_key(page.sock).events != events:
            self._sel.modify(page.sock, events)

    def _drop(self, page: _Page) -> None:
        if self._pages.pop(page.sock.fileno(), None) is None:
            return
        try:
            self._sel.unregister(page.sock)
        except (KeyError, ValueError):
            pass
        try:
            page.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        page.sock.close()
        page.out.clear()
        self.release()
