"""The view host: runs views beside the engine without ever making it wait.

``ViewHost`` is what ``stage play`` and ``stage monitor`` use. It registers
one engine listener (fused frames), is the piece runtime's ``EventSink``
(``emit``), collects engine status a few times a second, and fans all of it
out to the views, each through its own ``Slot`` (queue + thread).

On the engine thread the host only copies references into the slots' queues;
no I/O, no view code. Status is collected on the engine thread too (it reads
live engine state), at most every ``status_interval_s``: from the frame
listener when frames flow, and through ``Engine.call_soon`` when the stage is
empty, so a sensor going silent still reaches the monitor.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Iterable, Sequence, TYPE_CHECKING

from ..clock import Clock, MonotonicClock
from ..frames import FusedFrame
from ..errors import ConfigError
from ..events import Event, OutputDecl
from .base import Scene, Status, View, ViewContext
from .loader import PluginInfo, discover_views, make_view
from .slot import Slot, wait_started
from .status import StatusCollector

if TYPE_CHECKING:  # the engine is duck-typed here: views import no engine code
    from ..engine import Engine

log = logging.getLogger("stage.views")

#: Default HTTP port of the live monitor (the OSC port 7770 + 10).
MONITOR_PORT = 7780
#: How long start() waits for each view to open its ports before going on without it.
START_TIMEOUT_S = 5.0


class ViewHost:
    """Views fed by one engine. Thread-safe where documented; idempotent start/stop.

    ``threaded=False`` runs every view on the caller's thread in ``pump()``:
    deterministic tests with a ``ManualClock``.
    """

    def __init__(self, views: Iterable[View] = (), *, clock: Clock | None = None,
                 threaded: bool = True, status_interval_s: float = 0.5) -> None:
        self._clock = clock
        self.threaded = threaded
        self.status_interval_s = status_interval_s
        self.slots: list[Slot] = []
        self.failed_plugins: list[PluginInfo] = []
        self.engine: Engine | None = None
        self._collector = StatusCollector()
        #: the show's latest health (set by the app's health monitor), sent with the status
        self.health: dict[str, Any] = {}
        self._last_status = float("-inf")
        self._status_pending = False
        self._scene = Scene()
        self._state = "new"
        self._lock = threading.Lock()
        self._timer_stop = threading.Event()
        self._timer: threading.Thread | None = None
        for view in views:
            self.add(view)

    # ------------------------------------------------------------ building
    @property
    def clock(self) -> Clock:
        if self._clock is None:
            self._clock = self.engine.clock if self.engine is not None else MonotonicClock()
        return self._clock

    def add(self, view: View, name: str | None = None, origin: str = "") -> View:
        """Add a view before ``start()``; its name must be unique (a suffix is added if not)."""
        if self._state != "new":
            raise RuntimeError("add views before start()")
        base = name or view.name or type(view).__name__.lower()
        taken = {slot.name for slot in self.slots}
        final, k = base, 2
        while final in taken:
            final, k = f"{base}-{k}", k + 1
        view.name = final
        # the slot needs a clock now; the proxy follows attach() (the engine's clock)
        self.slots.append(Slot(view, final, origin or type(view).__module__, _ClockProxy(self)))
        return view

    def add_plugin(self, info: PluginInfo | None, name: str, **options: Any) -> View | None:
        """Build and add the view ``name`` from its plugin; a broken plugin is warned about.

        A ``ConfigError`` from the view's constructor (bad user options) is raised:
        the show must not start with a port or target the user mistyped.
        """
        if info is None:
            log.warning("no view plugin named '%s' is installed (see `stage plugins`); "
                        "the show goes on without it", name)
            return None
        if not info.loaded:
            self._warn_plugin(info)
            return None
        try:
            view = make_view(info, **options)
        except ConfigError:
            raise
        except Exception as exc:
            log.warning("view plugin '%s' (%s, from %s) could not be created: %s: %s; "
                        "the show goes on without it", name, info.value, info.distribution,
                        type(exc).__name__, exc)
            info.error = f"{type(exc).__name__}: {exc}"
            self.failed_plugins.append(info)
            return None
        return self.add(view, name, f"{info.distribution or '?'}: {info.value}")

    def _warn_plugin(self, info: PluginInfo) -> None:
        if info not in self.failed_plugins:
            self.failed_plugins.append(info)
            log.warning("view plugin '%s' (%s, from %s) failed to load: %s; it is disabled, "
                        "the show goes on", info.name, info.value, info.distribution or "?",
                        info.error)

    @classmethod
    def for_play(cls, outputs: Sequence[OutputDecl], *, midi_port: str | None = None,
                 midi_file: str | None = None, osc: Sequence[tuple[str, int]] = (),
                 monitor: bool | int = False, clock: Clock | None = None,
                 plugins: bool = True, relay: Sequence[tuple[str, int]] = (),
                 midi_clock_bpm: float | None = None, osc_bundles: bool = False,
                 monitor_host: str = "127.0.0.1",
                 plugin_options: dict[str, dict[str, Any]] | None = None,
                 threaded: bool = True, audio: str | None = None, synth: bool = False,
                 soundfont: str | None = None) -> "ViewHost":
        """The views of a show, built from the piece's outputs and the command line.

        outputs: the piece's declared outputs (kind "midi" or "osc").
        midi_port: ``--midi PORT`` (an existing port, else a new virtual port of that name);
        midi_file: ``--midi-file OUT.mid``; osc: ``--osc HOST:PORT`` targets;
        monitor: True for the live monitor on port 7780, an int for that port (0: any);
        plugins: also run every installed view that starts by itself (``autostart``);
        relay: other stage servers to send our fused bodies to (Client-to-Server API);
        midi_clock_bpm: send MIDI clock at this tempo; osc_bundles: OSC in timetagged bundles;
        plugin_options: keyword options per view name; audio: render the MIDI to this WAV
        file through FluidSynth; synth: play it live through FluidSynth on JACK; soundfont:
        theirs (default: a General MIDI one where the system installs it).
        """
        host = cls(clock=clock, threaded=threaded)
        found = discover_views()
        options = dict(plugin_options or {})
        for output in outputs:
            if output.kind not in ("midi", "osc"):
                log.warning("output '%s' has kind '%s': only 'midi' and 'osc' are played; "
                            "its events are ignored", output.name, output.kind)
        midi = [o for o in outputs if o.kind == "midi"]
        if midi or midi_port or midi_file or audio or synth:
            extra = {k: v for k, v in (("audio", audio), ("synth", synth),
                                       ("soundfont", soundfont)) if v}
            host.add_plugin(found.get("midi"), "midi", outputs=midi, port=midi_port,
                            file=midi_file, clock_bpm=midi_clock_bpm, **extra,
                            **options.pop("midi", {}))
        osc_outputs = [o for o in outputs if o.kind == "osc"]
        if osc_outputs or osc:
            host.add_plugin(found.get("osc"), "osc", outputs=osc_outputs, targets=list(osc),
                            bundles=osc_bundles, **options.pop("osc", {}))
        if monitor is not False and monitor is not None:
            port = MONITOR_PORT if monitor is True else int(monitor)
            host.add_plugin(found.get("monitor"), "monitor", port=port, host=monitor_host,
                            **options.pop("monitor", {}))
        for target in relay:
            host.add_plugin(found.get("relay"), "relay", target=tuple(target),
                            **options.get("relay", {}))
        options.pop("relay", None)
        if plugins:
            for name, info in found.items():
                if name in ("midi", "osc", "monitor", "relay"):
                    continue
                if not info.loaded:
                    host._warn_plugin(info)
                elif getattr(info.obj, "autostart", True):
                    host.add_plugin(info, name, **options.pop(name, {}))
        for name in options:
            log.warning("options given for view '%s', which is not running", name)
        return host

    # ------------------------------------------------------------ engine side
    def attach(self, engine: Engine) -> "ViewHost":
        """Listen to ``engine``'s fused frames and collect its status; call before start()."""
        self.engine = engine
        for slot in self.slots:
            ahead = float(getattr(slot.view, "forecast_s", 0.0) or 0.0)
            if ahead > 0 and slot.wants_frames:
                engine.people.want_forecast(ahead)
        engine.listeners.append(self._on_frame)
        return self

    def detach(self) -> None:
        if self.engine is not None and self._on_frame in self.engine.listeners:
            self.engine.listeners.remove(self._on_frame)

    def _on_frame(self, frame: FusedFrame) -> None:
        """Engine thread: enqueue only."""
        for slot in self.slots:
            if slot.wants_frames:
                ahead = getattr(slot.view, "forecast_s", 0.0)
                bodies = frame.forecasts.get(ahead) if ahead else None
                slot.offer_frame(frame if bodies is None else FusedFrame(
                    frame.t, bodies, frame.updated, frame.new, frame.lost, frame.forecasts))
        if frame.t - self._last_status >= self.status_interval_s:
            self.collect_status()

    def collect_status(self) -> Status | None:
        """Engine thread only: read the engine's state and hand it to the views."""
        self._status_pending = False
        if self.engine is None:
            return None
        now = self.engine.clock.now()
        self._last_status = now
        status = self._collector.collect(self.engine, self.stats(own=False), self.health)
        for slot in self.slots:
            if slot.wants_status:
                slot.offer_status(status)
        return status

    def _status_timer(self) -> None:
        """Asks the engine thread for status when no frame did for a while (empty stage)."""
        engine = self.engine
        while not self._timer_stop.wait(self.status_interval_s):
            if engine is None or self._status_pending:
                continue
            if engine.clock.now() - self._last_status >= self.status_interval_s:
                self._status_pending = True
                try:
                    engine.call_soon(lambda _engine: self.collect_status())
                except Exception:  # engine queue full: it is busy with frames, which collect
                    self._status_pending = False

    def emit(self, events: list[Event]) -> None:
        """``EventSink``: take piece events on the engine thread; never blocks."""
        if not events:
            return
        batch = list(events)
        for slot in self.slots:
            if slot.wants_events:
                slot.offer_events(batch)

    def set_scene(self, zones: list[dict], sections: list[str]) -> None:
        """The piece's zones (stage metres) and section names, for monitors."""
        self._scene = Scene(tuple(dict(z) for z in zones), tuple(str(s) for s in sections))
        for slot in self.slots:
            if slot.wants_scene:
                slot.offer_scene(self._scene)

    # ------------------------------------------------------------ life cycle
    def start(self) -> "ViewHost":
        """Start every view (each opens its ports on its own thread); returns when they have.

        A view that fails to start is named in a warning and disabled.
        """
        with self._lock:
            if self._state != "new":
                return self
            self._state = "running"
        clock = self.clock
        wall = time.time() - clock.now()
        for slot in self.slots:
            ctx = ViewContext(slot.name, clock, logging.getLogger(f"stage.views.{slot.name}"),
                              wall, self.stats)
            if self._scene.zones or self._scene.sections:
                slot.offer_scene(self._scene)
            if self.threaded:
                slot.thread = threading.Thread(target=slot.run, args=(ctx,),
                                               name=f"stage-view-{slot.name}", daemon=True)
                slot.thread.start()
            else:
                slot.start_view(ctx)
        if self.threaded:
            for slot in wait_started(self.slots, START_TIMEOUT_S):
                log.warning("view '%s' is still starting after %.0f s; the show starts without "
                            "waiting for it", slot.name, START_TIMEOUT_S)
            if self.engine is not None:
                self._timer = threading.Thread(target=self._status_timer,
                                               name="stage-view-status", daemon=True)
                self._timer.start()
        return self

    def pump(self) -> None:
        """Unthreaded hosts: deliver what waits and run due ticks, on this thread."""
        if self.threaded:
            raise RuntimeError("pump() is for ViewHost(threaded=False)")
        for slot in self.slots:
            if slot.alive and slot.state == "running":
                slot.deliver()

    def next_deadline(self) -> float | None:
        """Unthreaded hosts: the earliest time a view asked to be ticked."""
        times = [s.deadline for s in self.slots if s.state == "running" and s.deadline is not None]
        return min(times) if times else None

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop every view: queued events are delivered first, then ``View.stop`` (notes off,
        files closed). Idempotent; safe to call from any thread but the engine's."""
        with self._lock:
            if self._state == "stopped":
                return
            started = self._state == "running"
            self._state = "stopped"
        self._timer_stop.set()
        self.detach()
        if not started:
            return
        for slot in self.slots:
            slot.request_stop()
        if not self.threaded:
            for slot in self.slots:
                if slot.state == "running":
                    slot.deliver()
            return
        deadline = time.monotonic() + timeout_s
        for slot in self.slots:
            if slot.thread is not None:
                slot.thread.join(max(0.1, deadline - time.monotonic()))
                if slot.thread.is_alive():
                    log.warning("view '%s' did not stop within %.0f s; left behind",
                                slot.name, timeout_s)
        if self._timer is not None:
            self._timer.join(1.0)

    def __enter__(self) -> "ViewHost":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------ reading
    @property
    def views(self) -> list[View]:
        return [slot.view for slot in self.slots]

    def view(self, name: str) -> View | None:
        for slot in self.slots:
            if slot.name == name:
                return slot.view
        return None

    def stats(self, own: bool = True) -> dict[str, dict[str, Any]]:
        """Per view: origin, state, error, frames in/dropped/pending, events, and (``own``)
        the view's own counters (``View.stats()``, which runs view code: not on the engine thread)."""
        return {slot.name: slot.stats(own) for slot in self.slots}

    @property
    def monitor_url(self) -> str | None:
        """The live monitor's address once started (None without a monitor)."""
        for slot in self.slots:
            url = getattr(slot.view, "url", None)
            if url:
                return url
        return None

    def summary(self) -> list[str]:
        """One line per view: where its output goes (for `stage play` to print at start)."""
        lines = []
        for slot in self.slots:
            where = slot.stats()["view"].get("summary", "")
            state = f" [failed: {slot.error}]" if slot.state == "failed" else ""
            lines.append(f"{slot.name}: {where}{state}".rstrip(": "))
        return lines


class _ClockProxy:
    """The host's clock, resolved when used (the engine may be attached after add())."""

    def __init__(self, host: ViewHost) -> None:
        self._host = host

    def now(self) -> float:
        return self._host.clock.now()
