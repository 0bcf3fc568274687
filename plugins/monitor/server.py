"""The monitor's web server: the page, and its live data as server-sent events.

Standard library only (``http.server``); nothing is fetched from the internet.
The view thread publishes JSON into a ``Broadcaster``; each browser connection
has its own server thread that waits for something newer than what it has
sent. State kinds keep only their latest value (a slow browser skips frames,
it never falls behind); event lists are kept as a short log.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import deque
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from stage.errors import TransportError

log = logging.getLogger("stage.views.monitor")

_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
          "/index.html": ("index.html", "text/html; charset=utf-8"),
          "/monitor.js": ("monitor.js", "text/javascript; charset=utf-8"),
          "/monitor.css": ("monitor.css", "text/css; charset=utf-8")}
HEARTBEAT_S = 10.0
LOCAL_NAMES = {"127.0.0.1", "localhost", "::1", "[::1]"}
#: connections served at once (one thread each); beyond, new ones are closed at once
MAX_CONNECTIONS = 64
#: live pages (event streams) at once; beyond, 503
MAX_STREAMS = 16
#: a connection silent this long (no request, or not reading its stream) is closed
IDLE_TIMEOUT_S = 15.0


class Broadcaster:
    """Latest JSON per state kind, plus a log of appended items; thread-safe."""

    def __init__(self, log_size: int = 200) -> None:
        self.cond = threading.Condition()
        self.version = 0
        self.latest: dict[str, tuple[int, str]] = {}
        self.log: deque[tuple[int, str, str]] = deque(maxlen=log_size)
        self.closed = False
        self.clients = 0

    def set(self, kind: str, payload: Any) -> None:
        data = json.dumps(payload, separators=(",", ":"))
        with self.cond:
            self.version += 1
            self.latest[kind] = (self.version, data)
            self.cond.notify_all()

    def append(self, kind: str, payload: Any) -> None:
        data = json.dumps(payload, separators=(",", ":"))
        with self.cond:
            self.version += 1
            self.log.append((self.version, kind, data))
            self.cond.notify_all()

    def since(self, seen: int, timeout: float) -> tuple[int, list[tuple[str, str]]]:
        """(new version, [(kind, json)]) newer than ``seen``; waits up to ``timeout``."""
        with self.cond:
            if self.version <= seen and not self.closed:
                self.cond.wait(timeout)
            items = [(v, k, d) for k, (v, d) in self.latest.items() if v > seen]
            items += [(v, k, d) for v, k, d in self.log if v > seen]
            items.sort(key=lambda item: item[0])
            return self.version, [(k, d) for _, k, d in items]

    def snapshot(self) -> dict[str, Any]:
        with self.cond:
            out: dict[str, Any] = {k: json.loads(d) for k, (_, d) in self.latest.items()}
            out["log"] = [json.loads(d) for _, _, d in self.log]
        return out

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


class _Handler(BaseHTTPRequestHandler):
    server: "MonitorServer"
    protocol_version = "HTTP/1.1"
    timeout = IDLE_TIMEOUT_S  # socket timeout: idle connections do not keep a thread for ever

    def log_message(self, fmt: str, *args: Any) -> None:  # requests are not worth a log line
        log.debug("http %s: " + fmt, self.address_string(), *args)

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        if not self._host_allowed():
            self.send_error(HTTPStatus.FORBIDDEN, "the monitor answers to localhost only")
            return
        path = self.path.split("?", 1)[0]
        if path == "/events":
            self._events()
        elif path == "/state.json":
            self._send(json.dumps(self.server.broadcaster.snapshot()).encode(), "application/json")
        elif path in _FILES:
            name, ctype = _FILES[path]
            self._send(resources.files(__package__).joinpath(name).read_bytes(), ctype)
        else:
            self.send_error(HTTPStatus.NOT_FOUND)

    def _host_allowed(self) -> bool:
        """Refuse other Host names when bound to loopback (no DNS-rebinding reads)."""
        if not self.server.loopback:
            return True
        host = (self.headers.get("Host") or "").strip()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        return name in LOCAL_NAMES

    def _send(self, body: bytes, ctype: str) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        b = self.server.broadcaster
        if not self.server.streams.acquire(blocking=False):
            self.send_error(HTTPStatus.SERVICE_UNAVAILABLE,
                            f"{MAX_STREAMS} monitor pages are open already")
            return
        try:
            self._stream(b)
        finally:
            self.server.streams.release()

    def _stream(self, b: "Broadcaster") -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        with b.cond:
            b.clients += 1
        seen = 0
        try:
            self.wfile.write(b"retry: 1000\n\n")
            while not b.closed and not self.server.stopping:
                version, items = b.since(seen, HEARTBEAT_S)
                if items:
                    chunk = "".join(f"event: {k}\ndata: {d}\n\n" for k, d in items)
                    self.wfile.write(chunk.encode())
                else:
                    self.wfile.write(b": keep-alive\n\n")
                self.wfile.flush()
                seen = version
        except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError):
            pass  # the browser went away
        finally:
            with b.cond:
                b.clients -= 1


class MonitorServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, host: str, port: int, broadcaster: Broadcaster) -> None:
        try:
            super().__init__((host, port), _Handler)
        except OSError as exc:
            raise TransportError(f"cannot serve the monitor on http://{host}:{port}/: "
                                 f"{exc.strerror}") from None
        self.broadcaster = broadcaster
        self.loopback = host in LOCAL_NAMES or host.startswith("127.")
        self.stopping = False
        self.connections = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.streams = threading.BoundedSemaphore(MAX_STREAMS)
        self.refused = 0
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="stage-monitor-http", daemon=True)

    def process_request(self, request, client_address) -> None:  # noqa: ANN001 (socketserver's)
        """One thread per connection, at most MAX_CONNECTIONS: a thousand idle sockets must
        not become a thousand threads."""
        if not self.connections.acquire(blocking=False):
            self.refused += 1
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except Exception:
            self.connections.release()
            raise

    def process_request_thread(self, request, client_address) -> None:  # noqa: ANN001
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.connections.release()

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{port}/"

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self.stopping = True
        self.broadcaster.close()
        self.shutdown()
        self.server_close()
        self._thread.join(2.0)
