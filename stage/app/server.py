"""The live server: the engine fed by a UDP socket, on two threads.

``Server`` is what ``stage serve`` runs and what every live show is built on:
a bound socket, a receiver thread (``stage.sensors.receiver``) that only
decodes and enqueues, and the engine thread (``Engine.run``) that owns all
live state and sends Server-to-View datagrams from the same socket.
"""

from __future__ import annotations

import logging
import threading

from ..clock import Clock, MonotonicClock
from ..engine import Engine
from ..rig import Rig
from ..sensors.receiver import Receiver, UdpTransport, open_udp

log = logging.getLogger("stage.server")


class Server:
    """The engine behind a UDP socket (see the module docstring). A context manager."""

    def __init__(self, rig: Rig | None = None, host: str | None = None, port: int | None = None,
                 clock: Clock | None = None) -> None:
        self.rig = rig or Rig()
        self.clock = clock or MonotonicClock()
        self.sock = open_udp(host or self.rig.host, self.rig.port if port is None else port)
        self.engine = Engine(self.rig, self.clock, UdpTransport(self.sock))
        self.receiver = Receiver(self.sock, self.engine.submit, self.engine.drops, self.clock,
                                 self.rig.clients.max_messages_per_s, self.rig.allow_sensors,
                                 self.rig.clients.max_messages_per_s_per_host,
                                 self.rig.limits.max_sources, self.engine.submit_batch)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()[:2]

    def start(self) -> "Server":
        self._threads = [threading.Thread(target=self.receiver.run, args=(self._stop,),
                                          name="stage-receiver", daemon=True),
                         threading.Thread(target=self.engine.run, args=(self._stop,),
                                          name="stage-engine", daemon=True)]
        for thread in self._threads:
            thread.start()
        log.info("listening for sensors and views on udp %s:%d", *self.address)
        return self

    def stop(self) -> None:
        """Stop both threads and close the socket (idempotent)."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self.sock.close()

    def close(self) -> None:
        """Release the socket of a server that was never started."""
        self.sock.close()

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
