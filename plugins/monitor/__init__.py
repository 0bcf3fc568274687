"""The live monitor: a web page on localhost showing the stage as the engine sees it.

From above and from the front: every fused body, the piece's zones (lit when
occupied), the sensors at their calibrated positions (red, with the reason,
when one lost tracking, is not calibrated or its calibration fitness fell),
frame rates, the current section, the last events and the drop counters.
Served by the standard library; updates by server-sent events; no internet.

``stage monitor`` runs it beside a server; ``stage play --monitor`` beside a
piece (``ViewHost.for_play(monitor=True)``).
"""

from __future__ import annotations

from collections import deque
from typing import Any, Sequence

from stage.frames import FusedFrame
from stage.events import (ControlChange, Event, MappingValue, OscOut, SectionChange, ZoneState,
                          to_json)
from stage.views import Scene, Status, View, ViewContext

from .server import Broadcaster, MonitorServer
from .state import event_text, frame_json, scene_json, status_json

#: The page is sent at most this many frames a second (the screen cannot show more).
MAX_FPS = 30.0


class MonitorView(View):
    """Live web monitor: stage from above and the front, bodies, zones, sensors, events."""

    description = "live web monitor on localhost: bodies, zones, sensors, events, drops"
    autostart = False
    # only the newest frame matters to a picture, but a drop here should mean trouble,
    # not a hiccup: a few frames of slack
    max_pending_frames = 8

    def __init__(self, port: int = 7780, host: str = "127.0.0.1", max_fps: float = MAX_FPS,
                 events_kept: int = 50) -> None:
        self.port, self.host = int(port), host
        self.period = 1.0 / max_fps
        self.broadcaster = Broadcaster()
        self.server: MonitorServer | None = None
        self.url: str | None = None
        self._pending: FusedFrame | None = None
        self._next_publish = float("-inf")
        self._arrivals: deque[float] = deque(maxlen=64)
        self._section: dict[str, Any] = {"section": None, "index": None}
        self._zones: dict[str, list[int]] = {}
        self._mappings: dict[str, float] = {}
        self._outputs: dict[str, str] = {}      # continuous outputs: latest value per address
        self._seq = 0
        self._t0 = 0.0
        self._events_kept = events_kept
        self.frames_published = 0
        self.summary = ""

    def start(self, ctx: ViewContext) -> None:
        self._t0 = ctx.now()      # event times are shown from here (the engine clock's zero is arbitrary)
        self.server = MonitorServer(self.host, self.port, self.broadcaster)
        self.server.start()
        self.url = self.server.url
        self.summary = self.url
        self.broadcaster.set("scene", scene_json((), ()))
        self._publish_piece()
        ctx.log.info("monitor on %s", self.url)

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None

    # ------------------------------------------------------------ inputs
    def on_scene(self, scene: Scene) -> None:
        self.broadcaster.set("scene", scene_json(scene.zones, scene.sections))

    def on_status(self, status: Status) -> None:
        self.broadcaster.set("status", status_json(status))

    def on_events(self, events: Sequence[Event]) -> None:
        items = []
        piece_changed = False
        for event in events:
            if isinstance(event, ZoneState):
                if event.occupied:
                    self._zones[event.zone] = [int(p) for p in event.persons]
                else:
                    self._zones.pop(event.zone, None)
                piece_changed = True
            elif isinstance(event, SectionChange):
                self._section = {"section": event.section, "index": event.index}
                piece_changed = True
            elif isinstance(event, MappingValue):
                self._mappings[event.mapping] = round(float(event.value), 4)
                piece_changed = True
                continue  # continuous values go to the table, not the event list
            elif isinstance(event, (OscOut, ControlChange)) and len(self._outputs) < 64:
                # usually a mapping sent every frame: a table of latest values, not a flood
                if isinstance(event, OscOut):
                    key = f"{event.output} {event.address}"
                    value = " ".join(f"{a:.3f}" if isinstance(a, float) else str(a)
                                     for a in event.args)
                else:
                    key = f"{event.output} ch {event.channel + 1} cc {event.control}"
                    value = str(event.value)
                self._outputs[key] = value
                piece_changed = True
                continue
            elif isinstance(event, (OscOut, ControlChange)):
                continue
            self._seq += 1
            items.append({"seq": self._seq, "t": round(event.t - self._t0, 2),
                          "type": type(event).__name__, "text": event_text(event),
                          "event": _plain(to_json(event))})
        if items:
            self.broadcaster.append("events", items[-self._events_kept:])
        if piece_changed:
            self._publish_piece()

    def _publish_piece(self) -> None:
        self.broadcaster.set("piece", {**self._section, "zones": self._zones,
                                       "mappings": self._mappings, "outputs": self._outputs})

    def on_frame(self, frame: FusedFrame) -> None:
        self._pending = frame
        self._arrivals.append(frame.t)

    def tick(self, now: float) -> float | None:
        if self._pending is None:
            return None
        if now < self._next_publish:
            return self._next_publish
        frame, self._pending = self._pending, None
        self.broadcaster.set("frame", frame_json(frame, self._fps()))
        self.frames_published += 1
        self._next_publish = now + self.period
        return None

    def _fps(self) -> float:
        if len(self._arrivals) < 2:
            return 0.0
        span = self._arrivals[-1] - self._arrivals[0]
        return (len(self._arrivals) - 1) / span if span > 0 else 0.0

    def stats(self) -> dict[str, Any]:
        return {"url": self.url, "browsers": self.broadcaster.clients,
                "frames_published": self.frames_published, "summary": self.summary}


def _plain(value: Any) -> Any:
    """JSON-safe copy (NaN and infinities become None)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
