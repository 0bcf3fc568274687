"""The UDP edge of the engine: a receiver thread that decodes and hands items on.

The receiver never touches engine state: it reads datagrams, drops those
from addresses the rig does not allow (``allow: sensors``), rate-limits per
source and per host, decodes them (``protocol.decode_datagram``), counts
drops and hands each decoded message to a sink (the engine's ``submit``)
as an ``Inbound``. Its tables are bounded (least recently used entries go),
so no number of spoofed source ports can grow its memory.

Two things only the kernel knows are brought to light here (Linux):

- datagrams the kernel dropped because the socket's receive queue was full
  (``SO_RXQ_OVFL``: a running count on each datagram read), counted as
  ``kernel_overflow`` under the key ``(kernel)``;
- views whose port is closed (``IP_RECVERR``: the ICMP error comes back on
  the socket's error queue with the address it was sent to), handed to the
  engine as ``ViewUnreachable`` so it can drop a dead view.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import sys
import threading
from collections import OrderedDict
from typing import Callable

from ..clock import Clock
from ..errors import TransportError
from ..network import Networks
from ..stats import OTHER, DropCounter
from .protocol import Inbound, ViewUnreachable, decode_datagram

log = logging.getLogger("stage.server")

#: Linux socket options (not all Python builds name them)
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
IP_RECVERR = getattr(socket, "IP_RECVERR", 11)
_LINUX = sys.platform.startswith("linux")
#: where kernel drops are counted
KERNEL = "(kernel)"


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
        try:
            self.sock.sendto(data, address)
        except ConnectionRefusedError:
            # with IP_RECVERR the socket reports an earlier datagram's ICMP error on the
            # next send, whatever its destination: this datagram was not sent; send it
            # (the receiver reads the error queue and names the view that refused)
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
    """Reads ``sock`` on its own thread and hands every decoded message to ``submit``.

    allow: the addresses datagrams are read from (None: everyone, as in-process).
    submit_batch: when given, each datagram's messages are handed over in one call (one
    queue entry: ``Engine.submit_batch``) instead of one ``submit`` each.
    """

    def __init__(self, sock: socket.socket, submit: Callable[[Inbound], bool], drops: DropCounter,
                 clock: Clock, max_messages_per_s: float, allow: Networks | None = None,
                 max_per_host_s: float | None = None, max_sources: int = 4096,
                 submit_batch: Callable[[list[Inbound]], bool] | None = None) -> None:
        self.sock, self.submit, self.drops, self.clock = sock, submit, drops, clock
        self.submit_batch = submit_batch
        self.rate = max_messages_per_s
        self.host_rate = max_per_host_s if max_per_host_s is not None else 8 * max_messages_per_s
        self.allow = allow
        self.max_sources = max_sources
        # source -> [bucket, client id seen from it]; host -> bucket. Least recently used first.
        self._sources: OrderedDict[tuple[str, int], list] = OrderedDict()
        self._hosts: OrderedDict[str, TokenBucket] = OrderedDict()
        #: every datagram read, before any check: (arrival, source, data) -> None (recording)
        self.taps: list[Callable[[float, tuple[str, int], bytes], None]] = []
        self.kernel_drops = 0           # receive-queue overflows the kernel reported
        self.unreachable = 0            # ICMP errors read from the error queue
        self._ovfl_seen = 0
        self._ovfl = self._errqueue = False
        if _LINUX:
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
                self._ovfl = True
            except OSError:
                pass
            try:
                sock.setsockopt(socket.SOL_IP, IP_RECVERR, 1)
                self._errqueue = True
            except OSError:
                pass

    def run(self, stop: threading.Event) -> None:
        if self._errqueue and hasattr(select, "poll"):
            self._run_poll(stop)
        else:
            self._run_plain(stop)

    def _run_plain(self, stop: threading.Event) -> None:
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
            self._got(data, source, clock.now())

    def _run_poll(self, stop: threading.Event) -> None:
        """Linux: poll for data and for errors (a bare timed recv would spin on POLLERR)."""
        sock, clock = self.sock, self.clock
        sock.setblocking(False)
        poller = select.poll()
        poller.register(sock, select.POLLIN | select.POLLERR)
        space = socket.CMSG_SPACE(4) if self._ovfl else 0
        while not stop.is_set():
            try:
                events = poller.poll(200)
            except OSError:
                if stop.is_set():
                    return
                continue
            if not events:
                continue
            if events[0][1] & select.POLLERR:
                self._read_errors()
            for _ in range(256):  # a burst at a time, then check errors and stop again
                try:
                    if space:
                        data, anc, _flags, source = sock.recvmsg(65536, space)
                        if anc:
                            self._overflow(anc)
                    else:
                        data, source = sock.recvfrom(65536)
                except (BlockingIOError, InterruptedError):
                    break
                except ConnectionRefusedError:
                    self._read_errors()
                    continue
                except OSError as exc:
                    if stop.is_set():
                        return
                    log.debug("recvmsg: %s", exc)
                    break
                self._got(data, source, clock.now())

    def _overflow(self, anc: list) -> None:
        for level, kind, value in anc:
            if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                total = struct.unpack("=I", value[:4])[0]
                new = (total - self._ovfl_seen) & 0xFFFFFFFF
                self._ovfl_seen = total
                if new:
                    self.kernel_drops += new
                    self.drops.add(KERNEL, "kernel_overflow", new)

    def _read_errors(self) -> None:
        """Drain the socket's error queue: each entry names a destination that refused."""
        for _ in range(1024):
            try:
                _data, _anc, _flags, address = self.sock.recvmsg(
                    1, 512, socket.MSG_ERRQUEUE | getattr(socket, "MSG_DONTWAIT", 0))
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if isinstance(address, tuple) and len(address) >= 2:
                self.unreachable += 1
                self.submit(Inbound(ViewUnreachable(address[0], address[1]), self.clock.now(),
                                    ("engine", 0)))

    def _got(self, data: bytes, source: tuple[str, int], arrival: float) -> None:
        for tap in self.taps:
            tap(arrival, source, data)
        self.handle(data, source, arrival)

    def handle(self, data: bytes, source: tuple[str, int], arrival: float) -> None:
        if self.allow is not None and not self.allow.allows(source[0]):
            self.drops.add(OTHER, "not_allowed")  # one key: a stranger gets no line of its own
            return
        entry = self._sources.get(source)
        if entry is None:
            if len(self._sources) >= self.max_sources:  # LRU: spoofed ports cannot grow memory
                self._sources.popitem(last=False)
            entry = self._sources[source] = [TokenBucket(self.rate, arrival), None]
        else:
            self._sources.move_to_end(source)
        host = self._hosts.get(source[0])
        if host is None:
            if len(self._hosts) >= self.max_sources:
                self._hosts.popitem(last=False)
            host = self._hosts[source[0]] = TokenBucket(self.host_rate, arrival)
        else:
            self._hosts.move_to_end(source[0])
        # both budgets: evicting a source's bucket (many ports) still leaves its host's
        if not entry[0].take(arrival) or not host.take(arrival):
            self.drops.add(entry[1] or f"{source[0]}:{source[1]}", "flood")
            return
        decoded = decode_datagram(data, f"{source[0]}:{source[1]}")
        for client, reason in decoded.drops:
            self.drops.add(client, reason)
        items = []
        for message, timetag in decoded.messages:
            client = getattr(message, "client", None)
            if client is not None:
                entry[1] = client
            items.append(Inbound(message, arrival, source, timetag))
        if self.submit_batch is not None:
            self.submit_batch(items)
        else:
            for item in items:
                self.submit(item)

    @property
    def sources(self) -> int:
        """Rate-limit entries held (per source and per host)."""
        return len(self._sources) + len(self._hosts)
