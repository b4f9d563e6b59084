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

Serving many pages: each event is encoded once and written to every page in batches by one
thread (:mod:`.web_fanout`); at most ``--max-clients`` pages (default 256) are connected, the
next is answered ``503`` with the reason; a page too slow to read is closed (it reconnects).
A request whose ``Host`` is a name other than localhost, the ``--host`` name, this machine's
name or an ``--allow-host`` name is answered ``403`` (DNS rebinding: a web page elsewhere
must not read ``/events`` through a name it controls); IP addresses are served.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import socket
import sys
import threading
import time
from collections.abc import Sequence
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from pd_service.transport import Transport

from . import common
from .web_fanout import MAX_CLIENTS, Fanout, frame
from .web_feed import LiveFeed

TOOL = "pd-web"
STATIC = {"/": ("index.html", "text/html; charset=utf-8"),
          "/index.html": ("index.html", "text/html; charset=utf-8"),
          "/app.js": ("app.js", "text/javascript; charset=utf-8"),
          "/style.css": ("style.css", "text/css; charset=utf-8")}
#: Connections the kernel queues before pd-web accepts them (the standard library's 5 drops
#: the SYNs of a burst's 7th and later connections: each waits 1 s for its retry).
LISTEN_BACKLOG = 128


def static_files() -> dict[str, bytes]:
    """The page's files, read from the package (``pd_client/tools/web/``)."""
    root = resources.files("pd_client.tools").joinpath("web")
    return {name: root.joinpath(name).read_bytes() for name, _ in set(STATIC.values())}


def page_weight() -> int:
    """Bytes of HTML + JS + CSS the page loads."""
    return sum(len(b) for b in static_files().values())


def host_name(header: str) -> str:
    """The host of a ``Host`` header, lower case, without port, brackets or a final dot."""
    h = header.strip().lower()
    if h.startswith("["):
        return h[1:h.find("]")] if "]" in h else h
    if h.count(":") == 1:
        h = h.split(":", 1)[0]
    return h.rstrip(".")


def host_allowed(header: str | None, names: frozenset[str]) -> bool:
    """Whether a request's ``Host`` header may be served (the DNS-rebinding guard).

    An IP address is what the browser connected to, so the page's origin is this server;
    a name must be one of ``names`` (localhost, the bound name, this machine's name,
    ``--allow-host``): a rebinding page's origin is the attacker's name, refused here. A
    request without ``Host`` (HTTP/1.0; browsers always send one) is served."""
    if header is None:
        return True
    name = host_name(header)
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        return name in names


class _HTTPServer(ThreadingHTTPServer):
    """A thread per request; an ``/events`` socket is handed over to the fan-out, not closed."""

    daemon_threads = True
    request_queue_size = LISTEN_BACKLOG

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler]) -> None:
        self.handed: set[socket.socket] = set()
        self.handed_lock = threading.Lock()
        super().__init__(address, handler)

    def shutdown_request(self, request: Any) -> None:
        with self.handed_lock:
            if request in self.handed:
                self.handed.discard(request)
                return
        super().shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        if isinstance(exc, ConnectionError):  # the client left: one line, not a traceback
            print(f"{TOOL}: {client_address[0]}:{client_address[1]} left before its reply "
                  f"was written ({type(exc).__name__})", file=sys.stderr, flush=True)
        else:
            super().handle_error(request, client_address)


class WebServer:
    """The HTTP server (a thread per request), the fan-out thread and the feed's
    status/tick thread. ``max_clients`` pages at a time (503 beyond); ``allow_hosts``:
    names besides localhost, the bound name and this machine's name that ``Host`` may be."""

    def __init__(self, transport: Transport, host: str = "127.0.0.1", port: int = 8080, *,
                 stale_s: float = 1.0, tick_s: float = 0.5, max_clients: int = MAX_CLIENTS,
                 allow_hosts: Sequence[str] = ()) -> None:
        self.fanout = Fanout(max_clients=max_clients)
        self.feed = LiveFeed(transport, self.fanout.publish, stale_s=stale_s)
        self.files = static_files()
        self.tick_s = tick_s
        self.names = frozenset({"localhost", host_name(host), host_name(socket.gethostname()),
                                *(host_name(h) for h in allow_hosts)})
        self.hosts_refused = 0
        self._stop = threading.Event()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: object) -> None:
                pass  # one line per request would flood the terminal

            def do_GET(self) -> None:
                if not host_allowed(self.headers.get("Host"), server.names):
                    server.hosts_refused += 1
                    self._send(f"{TOOL}: Host {self.headers.get('Host')!r} is not served (a guard "
                               "against DNS rebinding): use this machine's address or start "
                               "pd-web with --allow-host NAME\n", HTTPStatus.FORBIDDEN)
                    return
                path = self.path.split("?", 1)[0]
                if path == "/events":
                    server._serve_events(self)
                elif path == "/state.json":
                    self._send(json.dumps(server.state()).encode(), ctype="application/json")
                elif path in STATIC:
                    name, ctype = STATIC[path]
                    self._send(server.files[name], ctype=ctype)
                else:
                    self._send(f"{TOOL}: nothing at {path}\n", HTTPStatus.NOT_FOUND)

            def _send(self, body: bytes | str, status: HTTPStatus = HTTPStatus.OK,
                      ctype: str = "text/plain; charset=utf-8") -> None:
                data = body.encode() if isinstance(body, str) else body
                self.send_response(status)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(data)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(data)

        self.httpd = _HTTPServer((host, port), Handler)
        self._threads = [threading.Thread(target=self.httpd.serve_forever, name="pd-web-http",
                                          daemon=True),
                         threading.Thread(target=self._status_loop, name="pd-web-status",
                                          daemon=True)]

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host!s}:{port}/"

    def start(self) -> WebServer:
        self.fanout.start()
        for t in self._threads:
            t.start()
        return self

    def state(self) -> dict[str, object]:
        with self.feed.lock:
            sessions = {s: v.predictions for s, v in self.feed.views.items()}
        f = self.fanout
        return {"published": f.published, "batches": f.batches, "listeners": f.listeners,
                "max_clients": f.max_clients, "refused": f.refused, "cut": f.cut,
                "hosts_refused": self.hosts_refused, "sessions": sessions,
                "reported": self.feed.reported, "invalid": self.feed.invalid}

    def _status_loop(self) -> None:
        last_poll = 0.0
        while not self._stop.wait(self.tick_s):
            if time.monotonic() - last_poll >= 1.0:
                last_poll = time.monotonic()
                self.feed.poll_status()
            self.fanout.publish(self.feed.tick())

    def _serve_events(self, h: BaseHTTPRequestHandler) -> None:
        """Headers here; the snapshot and every later event from the fan-out thread."""
        h.close_connection = True
        if not self.fanout.reserve():
            text = (f"{TOOL}: {self.fanout.max_clients} pages are connected, its cap: close "
                    "one, or start pd-web with a larger --max-clients\n").encode()
            h.send_response(HTTPStatus.SERVICE_UNAVAILABLE)
            h.send_header("Content-Type", "text/plain; charset=utf-8")
            h.send_header("Content-Length", str(len(text)))
            h.send_header("Retry-After", "10")
            h.end_headers()
            h.wfile.write(text)
            return
        try:
            h.send_response(HTTPStatus.OK)
            h.send_header("Content-Type", "text/event-stream")
            h.send_header("Cache-Control", "no-store")
            h.send_header("Connection", "close")
            h.end_headers()
        except BaseException:
            self.fanout.release()
            raise
        tick = self.feed.tick()
        sock = h.connection
        with self.httpd.handed_lock:
            self.httpd.handed.add(sock)
        with self.feed.lock:  # no event lost or repeated between the snapshot and the fan-out
            first = b"".join(frame(e) for e in (b'{"type":"hello"}', tick, *self.feed.snapshot()))
            self.fanout.attach(sock, first)

    def close(self) -> None:
        self._stop.set()
        if self._threads[0].is_alive():  # shutdown() waits for a serve_forever that ran
            self.httpd.shutdown()
        self.httpd.server_close()
        self.feed.close()
        self.fanout.close()


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
    ap.add_argument("--max-clients", type=int, default=MAX_CLIENTS,
                    help=f"pages connected at a time; the next gets HTTP 503 (default {MAX_CLIENTS})")
    ap.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                    help="a name the page may be reached by besides localhost, the --host name and "
                         "this machine's name (repeatable; IP addresses are always served)")


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    if not 0 <= args.port <= 65535:
        ap.error("--port must be 0..65535")
    if args.max_clients < 1:
        ap.error("--max-clients must be >= 1")
    return common.run_on_transport(TOOL, args, lambda t: _serve(t, args, stop), stop=stop)


def _serve(transport: Transport, args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        server = WebServer(transport, args.host, args.port, stale_s=args.stale,
                           max_clients=args.max_clients, allow_hosts=args.allow_host)
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
