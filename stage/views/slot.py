"""One view with its own queues and thread: how a slow or broken view is kept away from the show.

The engine thread only appends to the slot's queues under a short lock and
returns. Frames beyond ``View.max_pending_frames`` push the oldest frame out
(counted); events are kept (up to ``MAX_PENDING_EVENTS``); status and scene
keep only the latest. The slot's thread delivers frames and events in the
order they were offered, then calls ``tick``, and sleeps until there is more
or the view's next deadline.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any, Sequence

from ..clock import Clock
from ..frames import FusedFrame
from ..events import Event
from .base import Scene, Status, View, ViewContext, overrides

log = logging.getLogger("stage.views")

#: Event batches a view may have waiting before the oldest batch is dropped (counted).
MAX_PENDING_EVENTS = 10_000


class Slot:
    """A view, its queues, its counters and (threaded) its thread."""

    def __init__(self, view: View, name: str, origin: str, clock: Clock) -> None:
        self.view, self.name, self.origin, self.clock = view, name, origin, clock
        self.cond = threading.Condition()
        self.wants_frames = overrides(view, "on_frame") and bool(getattr(view, "wants_frames",
                                                                         True))
        self.wants_events = overrides(view, "on_events")
        self.wants_status = overrides(view, "on_status")
        self.wants_scene = overrides(view, "on_scene")
        self.max_frames = max(1, int(getattr(view, "max_pending_frames", 4)))
        self._frames: deque[tuple[int, FusedFrame]] = deque()
        self._events: deque[tuple[int, list[Event]]] = deque()
        self._status: Status | None = None
        self._scene: Scene | None = None
        self._seq = 0
        self._stopping = False
        self.state = "loaded"       # loaded, running, failed, stopped
        self.error: str | None = None
        self.frames_in = self.frames_dropped = self.events_in = self.events_dropped = 0
        self._drops_warned = 0
        self.deadline: float | None = None
        self.thread: threading.Thread | None = None
        self.started = threading.Event()

    # ------------------------------------------------------------ producers (any thread)
    @property
    def alive(self) -> bool:
        return self.state in ("loaded", "running")

    def offer_frame(self, frame: FusedFrame) -> None:
        with self.cond:
            if not self.alive or self._stopping:
                return
            self._seq += 1
            self._frames.append((self._seq, frame))
            self.frames_in += 1
            if len(self._frames) > self.max_frames:
                self._frames.popleft()
                self.frames_dropped += 1
            self.cond.notify()

    def offer_events(self, events: list[Event]) -> None:
        with self.cond:
            if not self.alive or self._stopping:
                return
            self._seq += 1
            self._events.append((self._seq, events))
            self.events_in += len(events)
            while len(self._events) > MAX_PENDING_EVENTS:
                self.events_dropped += len(self._events.popleft()[1])
            self.cond.notify()

    def offer_status(self, status: Status) -> None:
        with self.cond:
            if self.alive and not self._stopping:
                self._status = status
                self.cond.notify()

    def offer_scene(self, scene: Scene) -> None:
        with self.cond:
            if self.alive and not self._stopping:
                self._scene = scene
                self.cond.notify()

    def request_stop(self) -> None:
        with self.cond:
            self._stopping = True
            self.cond.notify()

    # ------------------------------------------------------------ the view's side
    def _take(self) -> tuple[Scene | None, Status | None, list[tuple[int, Any]], bool]:
        """Everything waiting, in offer order (caller holds the lock)."""
        scene, status = self._scene, self._status
        self._scene = self._status = None
        items: list[tuple[int, Any]] = [*self._frames, *self._events]
        self._frames.clear()
        self._events.clear()
        if len(items) > 1:
            items.sort(key=lambda item: item[0])
        return scene, status, items, self._stopping

    def _has_work(self) -> bool:
        return bool(self._frames or self._events or self._status or self._scene or self._stopping)

    def call(self, method: str, *args: Any) -> Any:
        """Call a view method; a raise disables the view (named in a warning)."""
        try:
            return getattr(self.view, method)(*args)
        except Exception as exc:
            self.fail(method, exc)
            raise _Disabled from None

    def fail(self, method: str, exc: BaseException) -> None:
        first = self.state != "failed"
        self.state = "failed"
        self.error = f"{method}: {type(exc).__name__}: {exc}".splitlines()[0]
        if first:
            log.warning("view '%s' (%s) raised in %s: %s: %s; it is disabled, the show goes on",
                        self.name, self.origin, method, type(exc).__name__, exc)
            log.debug("traceback of view '%s'", self.name, exc_info=exc)
            with self.cond:
                self._frames.clear()
                self._events.clear()
            if method != "stop":
                try:  # let it release ports and sockets; its own failure here is only logged
                    self.view.stop()
                except Exception:
                    log.debug("view '%s' also raised in stop", self.name, exc_info=True)

    def start_view(self, ctx: ViewContext) -> bool:
        try:
            self.call("start", ctx)
            self.state = "running"
            self.deadline = self.call("tick", self.clock.now())
            return True
        except _Disabled:
            return False
        finally:
            self.started.set()

    def deliver(self) -> bool:
        """Deliver what waits and tick if due; False once the view is finished."""
        with self.cond:
            scene, status, items, stopping = self._take()
        try:
            self._deliver(scene, status, items)
            now = self.clock.now()
            if items or scene or status or (self.deadline is not None and now >= self.deadline):
                self.deadline = self.call("tick", now)
        except _Disabled:
            return False
        self._warn_drops()
        if stopping:
            self.finish()
            return False
        return True

    def _deliver(self, scene: Scene | None, status: Status | None,
                 items: list[tuple[int, Any]]) -> None:
        if scene is not None:
            self.call("on_scene", scene)
        if status is not None:
            self.call("on_status", status)
        batch: list[Event] = []
        for _, item in items:
            if isinstance(item, list):
                batch.extend(item)
                continue
            if batch:
                self.call("on_events", batch)
                batch = []
            self.call("on_frame", item)
        if batch:
            self.call("on_events", batch)

    def finish(self) -> None:
        if self.state == "running":
            try:
                self.call("stop")
                self.state = "stopped"
            except _Disabled:
                pass

    def _warn_drops(self) -> None:
        dropped = self.frames_dropped + self.events_dropped
        if dropped > self._drops_warned:
            if self._drops_warned == 0:
                log.warning("view '%s' is behind: its oldest frames are dropped (counted: "
                            "`stage plugins` and the monitor show how many)", self.name)
            self._drops_warned = dropped

    def run(self, ctx: ViewContext) -> None:
        """The slot's thread: start, deliver and tick until stopped, then stop the view."""
        if not self.start_view(ctx):
            return
        while True:
            with self.cond:
                while not self._has_work():
                    if self.deadline is None:
                        self.cond.wait()
                        continue
                    remaining = self.deadline - self.clock.now()
                    if remaining <= 0:
                        break
                    self.cond.wait(remaining)
            if not self.deliver():
                return

    def stats(self, own_stats: bool = True) -> dict[str, Any]:
        own: dict[str, Any] = {}
        if own_stats:
            try:
                own = dict(self.view.stats())
            except Exception as exc:  # stats of a broken view must not break the monitor
                own = {"error": f"{type(exc).__name__}: {exc}"}
        with self.cond:
            pending = len(self._frames)
        return {"origin": self.origin, "state": self.state, "error": self.error,
                "frames": self.frames_in, "frames_dropped": self.frames_dropped,
                "frames_pending": pending, "events": self.events_in,
                "events_dropped": self.events_dropped, "view": own}


class _Disabled(Exception):
    """A view raised; it has been disabled (internal control flow)."""


def wait_started(slots: Sequence[Slot], timeout_s: float) -> list[Slot]:
    """Wait for slots to finish starting; the ones still starting after the timeout."""
    deadline = time.monotonic() + timeout_s
    late = []
    for slot in slots:
        if not slot.started.wait(max(0.0, deadline - time.monotonic())):
            late.append(slot)
    return late
