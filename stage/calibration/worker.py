"""A worker thread beside the engine, changing engine state only through call_soon.

``EngineWorker`` owns the threading of the live calibrator: a thread that
wakes on demand (or every half second) and runs ``_poll``; engine changes
decided off the engine thread are queued (``_act``) and handed to
``engine.call_soon`` once the caller's locks are released (``_send``), since
call_soon may wait on a full engine queue while the engine thread waits for
those locks. With ``threaded=False`` nothing runs in the background: the
subclass polls inline on the engine thread (tests, offline replays).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from typing import Callable

from ..engine.engine import Engine
from ..errors import StageError

log = logging.getLogger("stage.calibration")

#: the longest a yielding worker waits for the engine thread to be idle, s
YIELD_MAX_S = 0.05


class EngineWorker:
    name = "stage-worker"

    def __init__(self, engine: Engine, threaded: bool) -> None:
        self.engine, self.threaded = engine, threaded
        self._worker: threading.Thread | None = None
        self._engine_thread: threading.Thread | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._outbox: deque[Callable[[Engine], None]] = deque()
        self._flush_asked = 0
        self._flush_done = 0
        self._poll_done = threading.Condition()

    def _poll(self) -> None:  # the subclass's periodic work
        raise NotImplementedError

    def _crashed(self, where: str, exc: BaseException) -> None:  # the subclass restarts itself
        log.error("calibration %s failed", where, exc_info=exc)

    def _start_worker(self) -> None:
        if self.threaded:
            self._worker = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._worker.start()

    def _stop_worker(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._worker is not None:
            self._worker.join(timeout=10.0)

    def flush(self, timeout: float = 5.0) -> None:
        """Run one poll now and wait for it (threaded mode: on the worker)."""
        if not self.threaded:
            self._poll()
            return
        with self._poll_done:
            self._flush_asked += 1
            target = self._flush_asked
            self._wake.set()
            if not self._poll_done.wait_for(lambda: self._flush_done >= target, timeout):
                raise StageError("the calibration worker did not answer")

    def _act(self, fn: Callable[[Engine], None]) -> None:
        """Change engine state: at once on the engine thread, else queued for call_soon."""
        if not self.threaded or threading.current_thread() is self._engine_thread:
            fn(self.engine)
        else:
            self._outbox.append(fn)

    def _send(self) -> None:
        while self._outbox:
            fn = self._outbox.popleft()
            try:
                self.engine.call_soon(fn)
            except queue.Full:
                log.error("engine queue full: a calibration change was lost; it will be "
                          "decided again")

    def _yield(self, wait: bool = True) -> None:
        """Worker, between chunks of work: wait (at most ``YIELD_MAX_S``) while the engine
        thread has datagrams queued or in hand, then let it have the GIL.

        Measured (bench_engine.py --trace, aligned 6 x 6): while a poll ran, each engine
        batch waited p50 0.5-1.0 / p90 2.9-4.8 ms for the GIL, 0.06 / 0.6-1.9 ms otherwise,
        because a thread that gives up the GIL for a send gets it back only after the
        worker's next switch interval (5 ms). Parked here, the worker does not take it.
        The bound keeps the calibrator going when the engine is never idle; ``wait=False``
        only lets the engine have the GIL (a worker that must catch up)."""
        if self.threaded:
            if wait:
                self.engine.idle.wait(YIELD_MAX_S)
            time.sleep(0)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=0.5)
            self._wake.clear()
            if self._stop.is_set():
                break
            with self._poll_done:
                asked = self._flush_asked
            try:
                self._poll()
            except Exception as exc:  # the show goes on; the worker starts afresh
                self._crashed("poll", exc)
            self._send()
            with self._poll_done:
                self._flush_done = asked
                self._poll_done.notify_all()
