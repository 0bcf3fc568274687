"""Event sinks of the piece runtime besides the views: recording and fan-out."""

from __future__ import annotations

import logging
from collections import deque

from ..events import Event, EventSink

log = logging.getLogger("stage.piece")


class RecordingSink:
    """An EventSink that keeps the events (tests, offline rendering, summaries).

    ``limit``: keep only the newest ``limit`` events (a show that runs for weeks
    must not grow without bound); None keeps everything.
    """

    def __init__(self, limit: int | None = None) -> None:
        self.events: list[Event] | deque = [] if limit is None else deque(maxlen=limit)

    def emit(self, events: list[Event]) -> None:
        self.events.extend(events)

    def of(self, kind: type) -> list:
        return [e for e in self.events if isinstance(e, kind)]


class FanoutSink:
    """Hands every batch to several sinks; one failing sink does not silence the others."""

    def __init__(self, *sinks: EventSink) -> None:
        self.sinks = [s for s in sinks if s is not None]

    def emit(self, events: list[Event]) -> None:
        for sink in self.sinks:
            try:
                sink.emit(events)
            except Exception:
                log.exception("event sink %r failed", sink)
