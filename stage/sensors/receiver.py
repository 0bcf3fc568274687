"""UDP edges of the engine: a receiver thread that decodes and enqueues, and
the socket the engine sends Server-to-View datagrams from.

The receiver never touches engine state: it only decodes, rate-limits per
source, counts drops and enqueues ``Inbound`` items.
"""

from __future__ import annotations

import logging
import socket
import threading

from ..clock import Clock, MonotonicClock
from ..engine.engine import Engine
from .protocol import Inbound
from ..errors import TransportError
from .protocol import decode_datagram
from ..rig import Rig

log = logging.getLogger("stage.server")


class TokenBucket:
    """``rate`` datagrams per second with a burst of half a second's worth."""

    __slots__ = ("rate", "capacity", "tokens", "t")

    def __init__(self, rate: float, now: float) -> None:
        self.rate, self.capacity = rate, max(rate * 0.5, 1.0)
        self.tokens, self.t = self.capacity, now

    def take(self, now: float) -> bool:
        self.tokens = min(self.capacity, self.tokens + (now - self.t) * self.rate)
        self.t = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class UdpTransport:
    """Sends from the server's own socket, so views see replies from its port."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        self.sock.sendto(data, address)


def open_udp(host: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise TransportError(f"cannot listen for OSC on udp {host}:{port}: {exc.strerror}") from None
    return sock


class Server:
    """``stage serve``: the engine fed by a UDP socket, two threads."""

    def __init__(self, rig: Rig | None = None, host: str | None = None, port: int | None = None,
                 clock: Clock | None = None) -> None:
        self.rig = rig or Rig()
        self.clock = clock or MonotonicClock()
        self.sock = open_udp(host or self.rig.host, self.rig.port if port is None else port)
        self.engine = Engine(self.rig, self.clock, UdpTransport(self.sock))
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._buckets: dict[tuple[str, int], TokenBucket] = {}
        self._client_of: dict[tuple[str, int], str] = {}

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()[:2]

    def start(self) -> "Server":
        self._threads = [threading.Thread(target=self._receive, name="stage-receiver", daemon=True),
                         threading.Thread(target=self.engine.run, args=(self._stop,),
                                          name="stage-engine", daemon=True)]
        for thread in self._threads:
            thread.start()
        log.info("listening for sensors and views on udp %s:%d", *self.address)
        return self

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self.sock.close()

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _receive(self) -> None:
        sock, engine, clock = self.sock, self.engine, self.clock
        rate = self.rig.clients.max_messages_per_s
        sock.settimeout(0.2)
        while not self._stop.is_set():
            try:
                data, source = sock.recvfrom(65536)
            except socket.timeout:
                continue
            except OSError as exc:
                if self._stop.is_set():
                    return
                # ICMP port-unreachable from a vanished view surfaces here on some systems
                log.debug("recvfrom: %s", exc)
                continue
            arrival = clock.now()
            bucket = self._buckets.get(source)
            if bucket is None:
                if len(self._buckets) > 4096:  # spoofed source ports must not grow memory
                    self._buckets.clear()
                    self._client_of.clear()
                bucket = self._buckets[source] = TokenBucket(rate, arrival)
            if not bucket.take(arrival):
                engine.drops.add(self._client_of.get(source, f"{source[0]}:{source[1]}"), "flood")
                continue
            decoded = decode_datagram(data, f"{source[0]}:{source[1]}")
            for client, reason in decoded.drops:
                engine.drops.add(client, reason)
            for message, timetag in decoded.messages:
                client = getattr(message, "client", None)
                if client is not None:
                    self._client_of[source] = client
                engine.submit(Inbound(message, arrival, source, timetag))
