"""The UDP edge of the engine: a receiver thread that decodes and hands items on.

The receiver never touches engine state: it reads datagrams, rate-limits per
source, decodes them (``protocol.decode_datagram``), counts drops and hands
each decoded message to a sink (the engine's ``submit``) as an ``Inbound``.
"""

from __future__ import annotations

import logging
import socket
import threading
from typing import Callable

from ..clock import Clock
from ..errors import TransportError
from ..stats import DropCounter
from .protocol import Inbound, decode_datagram

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
    """A bound UDP socket with a large receive buffer; TransportError with one line if not."""
    if not 0 <= port <= 65535:
        raise TransportError(f"cannot listen for OSC on udp {host}:{port}: a UDP port is 0-65535")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        why = exc.strerror or str(exc)
        raise TransportError(f"cannot listen for OSC on udp {host}:{port}: {why}") from None
    return sock


class Receiver:
    """Reads ``sock`` on its own thread and hands every decoded message to ``submit``."""

    def __init__(self, sock: socket.socket, submit: Callable[[Inbound], bool], drops: DropCounter,
                 clock: Clock, max_messages_per_s: float) -> None:
        self.sock, self.submit, self.drops, self.clock = sock, submit, drops, clock
        self.rate = max_messages_per_s
        self._buckets: dict[tuple[str, int], TokenBucket] = {}
        self._client_of: dict[tuple[str, int], str] = {}
        #: every datagram read, before any check: (arrival, source, data) -> None (recording)
        self.taps: list[Callable[[float, tuple[str, int], bytes], None]] = []

    def run(self, stop: threading.Event) -> None:
        sock, clock = self.sock, self.clock
        sock.settimeout(0.2)
        while not stop.is_set():
            try:
                data, source = sock.recvfrom(65536)
            except socket.timeout:
                continue
            except OSError as exc:
                if stop.is_set():
                    return
                # ICMP port-unreachable from a vanished view surfaces here on some systems
                log.debug("recvfrom: %s", exc)
                continue
            arrival = clock.now()
            for tap in self.taps:
                tap(arrival, source, data)
            self.handle(data, source, arrival)

    def handle(self, data: bytes, source: tuple[str, int], arrival: float) -> None:
        bucket = self._buckets.get(source)
        if bucket is None:
            if len(self._buckets) > 4096:  # spoofed source ports must not grow memory
                self._buckets.clear()
                self._client_of.clear()
            bucket = self._buckets[source] = TokenBucket(self.rate, arrival)
        if not bucket.take(arrival):
            self.drops.add(self._client_of.get(source, f"{source[0]}:{source[1]}"), "flood")
            return
        decoded = decode_datagram(data, f"{source[0]}:{source[1]}")
        for client, reason in decoded.drops:
            self.drops.add(client, reason)
        for message, timetag in decoded.messages:
            client = getattr(message, "client", None)
            if client is not None:
                self._client_of[source] = client
            self.submit(Inbound(message, arrival, source, timetag))
