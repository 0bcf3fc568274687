"""The view plugin interface: what a view receives and when.

A view turns the show into something else: notes, OSC, pictures, a relay to
another room. It gets three streams, each on the view's own thread (never the
engine thread), one call at a time, so a view needs no locks of its own:

- fused frames (``on_frame``): every person on stage, stage space, metres;
- piece events (``on_events``): notes, controls, sections, triggers, zones
  (``stage.events``), in the order the piece emitted them;
- engine status (``on_status``): sensors with their position, frame rate and
  calibration health, drop counters, latency; a few times a second.

``tick`` lets a view act at precise times (a note-off, a MIDI clock pulse)
instead of on the next frame. A view that raises is named in a warning and
disabled; the show goes on. A slow view only delays itself: its frames wait in
its own bounded queue and the oldest are dropped (and counted) when it falls
behind. Events are never dropped unless a view is thousands behind.

Plugins register a factory (usually the View subclass itself) in the
entry-point group ``stage.views.v1``; see docs/views.md.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Sequence

from ..clock import Clock, MonotonicClock
from ..frames import FusedFrame
from ..events import Event

#: The entry-point group views register in. The suffix is the API version:
#: a change that breaks plugins gets a new group, so old plugins are not loaded
#: into a host they do not understand.
GROUP = "stage.views.v1"
API_VERSION = 1


@dataclass(frozen=True, slots=True)
class SensorStatus:
    """One sensor as an installer needs to see it.

    ``ok`` is False when the sensor lost tracking (silent), is not calibrated,
    or its calibration fitness fell; ``reason`` then says which, in words.
    """

    id: str
    position: tuple[float, float, float] | None  # stage space, metres; None: not calibrated
    fps: float              # skeleton frames per second received since the previous status
    active: bool            # False: silent longer than the rig's clients.timeout_s
    calibrated: bool        # its frames are transformed into stage space and fused
    fitness: float | None   # calibration fitness (0, 1], 1 = perfect; None: unknown
    state: str              # calibration state as the calibration engine wrote it ("" if none)
    ok: bool
    reason: str             # "" when ok
    drops: int = 0          # messages from this sensor dropped so far (all reasons)


@dataclass(frozen=True, slots=True)
class Status:
    """The engine's state a few times a second (collected on the engine thread).

    ``engine`` is ``Engine.stats()`` exactly as ``/stage/stats`` reports it
    (docs/osc-api.md); ``sensors`` is the installer's digest of it; ``views``
    is ``ViewHost.stats()`` (each view's state and queue drops);
    ``registered_views`` are the OSC views the engine streams to (rig,
    ``--view``, ``/registerView``).
    """

    t: float
    engine: dict[str, Any]
    sensors: dict[str, SensorStatus]
    views: dict[str, dict[str, Any]] = field(default_factory=dict)
    registered_views: tuple[tuple[str, int], ...] = ()
    #: the show's health (``stage.app.health``: sensors, views, synths, engine), when a
    #: live show checks it; {} otherwise
    health: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Scene:
    """What the piece declares about the stage, for monitors.

    ``zones``: dicts like ``{"name": "centre", "shape": "cylinder", ...}`` with
    the shape's parameters in stage metres; ``sections``: names in order.
    """

    zones: tuple[dict[str, Any], ...] = ()
    sections: tuple[str, ...] = ()


@dataclass(slots=True)
class ViewContext:
    """What the host gives a view when it starts."""

    name: str                 # the view's name in logs and `stage plugins` (entry-point name)
    clock: Clock              # the engine's clock: event and frame times are on it
    log: logging.Logger       # "stage.views.<name>"
    wall_minus_clock: float   # add to an engine time to get Unix time (OSC timetags)
    #: every view's counters (``ViewHost.stats()``); call from the view's own thread
    host_stats: Callable[[], dict[str, dict[str, Any]]] = lambda: {}

    def now(self) -> float:
        return self.clock.now()


def default_context(name: str, clock: Clock | None = None) -> ViewContext:
    """A context for running a view by hand (tests, scripts)."""
    clock = clock or MonotonicClock()
    return ViewContext(name, clock, logging.getLogger(f"stage.views.{name}"),
                       time.time() - clock.now())


class View:
    """Base class of every view. Override what you need; every method is optional.

    All methods run on the view's own thread, one at a time, in this order:
    ``start`` once, then any number of ``on_scene``/``on_events``/``on_status``/
    ``on_frame`` calls each followed by ``tick``, then ``stop`` once. A view
    receives only the streams whose method it overrides (a view without
    ``on_frame`` costs the engine nothing per frame).

    Construction must be cheap and must not open devices: ``stage plugins``
    constructs nothing, the host constructs a view and then calls ``start``.
    Options come as keyword arguments (``ViewHost.for_play(plugin_options=...)``).
    """

    #: One line for `stage plugins`.
    description: ClassVar[str] = ""
    #: True: the host runs this view in every show once it is installed.
    #: Views that need to be told where to send (ports, files) say False and are
    #: created by the host from the command line instead.
    autostart: ClassVar[bool] = True
    #: Fused frames that may wait for this view; beyond that the oldest are dropped.
    max_pending_frames: ClassVar[int] = 4
    #: > 0: ``on_frame`` gets every body predicted this many seconds past its capture time
    #: (``Body.horizon``, ``Body.sd``; docs/anticipation.md) instead of as measured. Set it
    #: before the host is attached to the engine (a class attribute or in ``__init__``).
    forecast_s: float = 0.0
    #: False: the host never calls ``on_frame``, though the class defines it (a view that
    #: knows in ``__init__`` it has nowhere to send bodies: no frame is queued for it and
    #: its thread is not woken for one). Read when the host is built.
    wants_frames: bool = True

    name: str = ""   # set by the host before start()

    def start(self, ctx: ViewContext) -> None:
        """Open what the view needs (ports, sockets, files). Raise to refuse to run."""

    def on_scene(self, scene: Scene) -> None:
        """The piece's zones and sections (at start and when a piece is loaded)."""

    def on_events(self, events: Sequence[Event]) -> None:
        """Piece events, in emission order. ``event.t`` may be in the future (schedule it)."""

    def on_status(self, status: Status) -> None:
        """Engine status, at most a few times a second."""

    def on_frame(self, frame: FusedFrame) -> None:
        """One fused frame: ``frame.bodies`` {id: Body}, joints (25, 3) metres, stage space.

        The arrays are copies made for the views; do not modify them (all views share them).
        """

    def tick(self, now: float) -> float | None:
        """Called after each delivery and when the time you last returned has come.

        ``now``: engine clock, seconds. Return the next engine time at which you
        want to be called (a note-off, a clock pulse), or None.
        """
        return None

    def stop(self) -> None:
        """Release everything; silence what sounds. Called once, also after a failure."""

    def stats(self) -> dict[str, Any]:
        """Counters for `stage plugins`, the monitor and logs (read from the host thread)."""
        return {}


def overrides(view: View, method: str) -> bool:
    """Whether ``view``'s class overrides ``View.<method>``: the host delivers only those streams."""
    return getattr(type(view), method, None) is not getattr(View, method)
