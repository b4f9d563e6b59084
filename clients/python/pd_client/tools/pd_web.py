"""``pd-web``: a live view of every session in the browser, served from the display side.

    pd-web                                     # http://127.0.0.1:8080/ , Ctrl-C to stop
    pd-web --port 8090 --host 0.0.0.0          # other interfaces: anyone who reaches it sees it
    pd-web --linger 10 --duration 60           # stop after 60 s, serving the last state 10 s more

This process subscribes to the daemon's predictions, the measurements it receives, the
operator's commands and a simulator's truth (the Zenoh group below; TOOL role) and pushes one
compact JSON event per prediction to the page with Server-Sent Events (``/events``). The page
(``/``: index.html, app.js, style.css, shipped in the package: no CDN, works air-gapped)
draws per session a plan view (predicted position x(now+lead) with its 2-sigma ellipse, the
newest measured position with its age, the truth, a short trail of each, the command), time
series (prediction error, predicted variance, measured delay per sensor, latency), the
counters and a warning when predictions stop or a sensor goes silent. A page that connects
late or reloads gets the last events of each session (the final state after a run).
``/state.json``: events published, listeners and sessions (for scripts and tests).
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from collections.abc import Sequence
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

from pd_service.transport import Transport

from . import common
from .web_feed import LiveFeed

TOOL = "pd-web"
STATIC = {"/": ("index.html", "text/html; charset=utf-8"),
          "/index.html": ("index.html", "text/html; charset=utf-8"),
          "/app.js": ("app.js", "text/javascript; charset=utf-8"),
          "/style.css": ("style.css", "text/css; charset=utf-8")}
#: Events queued for one page before it counts as too slow and loses the oldest.
QUEUE_LIMIT = 4096


def static_files() -> dict[str, bytes]:
    """The page's files, read from the package (``pd_client/tools/web/``)."""
    root = resources.files("pd_client.tools").joinpath("web")
    return {name: root.joinpath(name).read_bytes() for name, _ in set(STATIC.values())}


def page_weight() -> int:
    """Bytes of HTML + JS + CSS the page loads."""
    return sum(len(b) for b in static_files().values())


class Hub:
    """Fan-out of event texts to the connected pages (one bounded queue each)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queues: set[queue.Queue[str]] = set()
        self.published = 0
        self.dropped = 0

    def publish(self, text: str) -> None:
        with self._lock:
            self.published += 1
            for q in self._queues:
                try:
                    q.put_nowait(text)
                except queue.Full:
                    self.dropped += 1

    def add(self, backlog: Sequence[str]) -> queue.Queue[str]:
        q: queue.Queue[str] = queue.Queue(QUEUE_LIMIT)
        for t in backlog[-QUEUE_LIMIT:]:
            q.put_nowait(t)
        with self._lock:
            self._queues.add(q)
        return q

    def remove(self, q: queue.Queue[str]) -> None:
        with self._lock:
            self._queues.discard(q)

    @property
    def listeners(self) -> int:
        with self._lock:
            return len(self._queues)


class WebServer:
    """The HTTP server (a thread per request) and the feed's status/tick thread."""

    def __init__(self, transport: Transport, host: str = "127.0.0.1", port: int = 8080, *,
                 stale_s: float = 1.0, tick_s: float = 0.5) -> None:
        self.hub = Hub()
        self.feed = LiveFeed(transport, self.hub.publish, stale_s=stale_s)
        self.files = static_files()
        self.tick_s = tick_s
        self._stop = threading.Event()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: object) -> None:
                pass  # one line per request would flood the terminal

            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                if path == "/events":
                    server._serve_events(self)
                elif path == "/state.json":
                    self._send(json.dumps(server.state()).encode(), "application/json")
                elif path in STATIC:
                    name, ctype = STATIC[path]
                    self._send(server.files[name], ctype)
                else:
                    self.send_error(HTTPStatus.NOT_FOUND)

            def _send(self, body: bytes, ctype: str) -> None:
                self.send_response(HTTPStatus.OK)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

        self.httpd = ThreadingHTTPServer((host, port), Handler)
        self.httpd.daemon_threads = True
        self._threads = [threading.Thread(target=self.httpd.serve_forever, name="pd-web-http",
                                          daemon=True),
                         threading.Thread(target=self._status_loop, name="pd-web-status",
                                          daemon=True)]

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host!s}:{port}/"

    def start(self) -> WebServer:
        for t in self._threads:
            t.start()
        return self

    def state(self) -> dict[str, object]:
        with self.feed.lock:
            sessions = {s: v.predictions for s, v in self.feed.views.items()}
        return {"published": self.hub.published, "dropped": self.hub.dropped,
                "listeners": self.hub.listeners, "sessions": sessions,
                "reported": self.feed.reported, "invalid": self.feed.invalid}

    def _status_loop(self) -> None:
        last_poll = 0.0
        while not self._stop.wait(self.tick_s):
            if time.monotonic() - last_poll >= 1.0:
                last_poll = time.monotonic()
                self.feed.poll_status()
            self.hub.publish(self.feed.tick())

    def _serve_events(self, h: BaseHTTPRequestHandler) -> None:
        h.send_response(HTTPStatus.OK)
        h.send_header("Content-Type", "text/event-stream")
        h.send_header("Cache-Control", "no-store")
        h.send_header("Connection", "close")
        h.end_headers()
        tick = self.feed.tick()
        with self.feed.lock:  # no event lost or repeated between the snapshot and the queue
            q = self.hub.add([json.dumps({"type": "hello"}), tick, *self.feed.snapshot()])
        try:
            while not self._stop.is_set():
                try:
                    first = q.get(timeout=1.0)
                except queue.Empty:
                    h.wfile.write(b": ping\n\n")
                    h.wfile.flush()
                    continue
                batch = [first]
                while len(batch) < 256:
                    try:
                        batch.append(q.get_nowait())
                    except queue.Empty:
                        break
                h.wfile.write("".join(f"data: {t}\n\n" for t in batch).encode())
                h.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass
        finally:
            self.hub.remove(q)
            h.close_connection = True

    def close(self) -> None:
        self._stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.feed.close()


# --- command line ----------------------------------------------------------------------------

def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--host", default="127.0.0.1",
                    help="interface to serve on (default 127.0.0.1: this machine only)")
    ap.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080; 0: any free port)")
    ap.add_argument("--stale", type=float, default=1.0,
                    help="seconds without predictions / samples before the page warns (default 1)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")
    ap.add_argument("--linger", type=float, default=0.0,
                    help="on SIGINT/SIGTERM or --duration, keep serving the last state this many "
                         "seconds more (default 0)")


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    if not 0 <= args.port <= 65535:
        ap.error("--port must be 0..65535")
    return common.run_on_transport(TOOL, args, lambda t: _serve(t, args, stop), stop=stop)


def _serve(transport: Transport, args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        server = WebServer(transport, args.host, args.port, stale_s=args.stale)
    except OSError as exc:
        return common.fail(TOOL, f"cannot serve on {args.host}:{args.port}: {exc}")
    server.start()
    print(f"{TOOL}: live view at {server.url} (page {page_weight()} bytes)", flush=True)
    try:
        stop.wait(args.duration)
        if args.linger > 0:
            stop.clear()
            common.progress(TOOL, f"serving the last state for {args.linger:g} s more")
            stop.wait(args.linger)
    finally:
        server.close()
    return 0


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
