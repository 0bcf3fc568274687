"""Running an engine ahead of time: datagrams fed in on a manual clock, no sleeping.

Every datagram is handed to the engine at its arrival time on the clock and
the engine ticks on a fixed grid (``TICK_S``, as often as its thread does in
real time), so nothing depends on the machine's speed: the same material
(a recording, or a simulator scenario and seed) and the same settings give
the same fused output bit for bit, whichever command runs it.
"""

from __future__ import annotations

import logging
import os
from typing import Any, Callable, Iterable

from ..clock import ManualClock
from ..engine import Engine
from ..engine.engine import TICK_S
from ..rig import Rig
from ..sensors.replay import ReplaySource

log = logging.getLogger("stage.app")

#: (arrival, sender, datagram) or (arrival, sender, datagram, capture), seconds; or the
#: simulator's ``Datagram``
FeedItem = Any


def feed(engine: Engine, clock: ManualClock, items: Iterable[FeedItem], *,
         end: float | None = None, until: float | None = None, tick_s: float = TICK_S,
         recorder=None, stop: Callable[[], bool] | None = None) -> int:
    """Feed datagrams, in arrival order, into ``engine`` on ``clock``; returns how many.

    Arrival times are used as they are when the clock has not passed the
    first one; otherwise the material is shifted to start at the clock's
    reading. The engine ticks every ``tick_s`` on a grid starting at the
    clock's reading now. ``end``: the material's end, in the items' own time
    (nothing later is fed; the engine ticks up to it); ``until``: keep ticking
    up to this clock time after the last datagram. With a ``recorder``
    (``RecordingWriter``) every datagram is recorded on the way at its
    (shifted) times, so replaying the recording reproduces this run exactly.
    ``stop``: checked as the clock moves; once it says True nothing more is fed
    (a piece that has ended ends its offline show).
    """
    next_tick = clock.now() + tick_s
    shift: float | None = None
    n = 0
    for item in items:
        if hasattr(item, "arrival"):  # the simulator's Datagram
            item = (item.arrival, item.source, item.data, item.capture)
        arrival, source, data = item[0], item[1], item[2]
        if end is not None and arrival > end:
            break
        if shift is None:
            shift = max(0.0, clock.now() - arrival)
        arrival += shift
        while next_tick <= arrival:
            clock.set(max(clock.now(), next_tick))
            engine.tick(clock.now())
            next_tick += tick_s
            if stop is not None and stop():
                return n
        clock.set(max(clock.now(), arrival))
        if recorder is not None:
            recorder.write(arrival, source, data, item[3] + shift if len(item) > 3 else None)
        engine.handle_datagram(data, source, clock.now())
        n += 1
    if end is not None:
        ends = end + (shift or 0.0)
        until = ends if until is None else max(until, ends)
    while until is not None and next_tick <= until:
        if stop is not None and stop():
            return n
        clock.set(max(clock.now(), next_tick))
        engine.tick(clock.now())
        next_tick += tick_s
    return n


def replay_offline(path: str | os.PathLike, engine: Engine, clock: ManualClock, *,
                   until: float | None = None, tick_s: float = TICK_S) -> int:
    """Feed every record of a recording into ``engine`` (see ``feed``); returns the records fed.

    A recording cut by a crash replays up to its last whole record.
    """
    return feed(engine, clock, ReplaySource(path).items(), until=until, tick_s=tick_s)


def offline_engine(path: str | os.PathLike, rig: Rig | None = None, start: float = 0.0,
                   ) -> tuple[Engine, ManualClock]:
    """An in-process engine for replaying ``path``: the given rig, else the recording's own."""
    if rig is None:
        rig = ReplaySource(path).rig() or Rig()
    clock = ManualClock(start)
    return Engine(rig, clock), clock
