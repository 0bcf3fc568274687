"""Ctrl-C and SIGTERM as a stop request, for every command that runs a show."""

from __future__ import annotations

import signal
import threading


class StopSignals:
    """Turns SIGINT and SIGTERM into an event, from before anything starts.

    Installed before a show starts, so a signal that arrives while it is
    starting still ends in a clean stop (every note off, files closed) rather
    than a KeyboardInterrupt. ``received`` names the signal that stopped the
    show, if one did: the command then exits with status 130 (interrupted).
    """

    def __init__(self, event: threading.Event | None = None) -> None:
        self.event = event or threading.Event()
        self.received: str | None = None
        self._previous: dict = {}

    def _handle(self, signum: int, _frame: object) -> None:
        self.received = signal.Signals(signum).name
        self.event.set()

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle)
                              for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def wait(self, duration: float | None) -> None:
        """Block until a signal or the end of ``duration`` seconds."""
        self.event.wait(duration)
