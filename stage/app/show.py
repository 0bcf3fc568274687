"""The application layer: one way to assemble and run a show, for every command.

A show is: a source of sensor datagrams (real sensors on a UDP port, the
simulator, a recording, or another installed source), the engine (behind a
UDP server live, in-process on a manual clock offline), the live calibrator
(self-healing, on unless asked not to), optionally a piece, the views (the
piece's outputs, the live monitor, relays, installed plugins, Server-to-View
OSC targets), a console status line, a fused-frame log, and the stop
handling (Ctrl-C, SIGTERM, a duration, the end of the source or the piece).

``stage serve``, ``demo``, ``monitor``, ``play``, ``calibrate --live`` and
``replay --offline`` only turn their arguments into ``ShowOptions``; the
defaults live here, once. Offline runs of the same material with the same
options give the same fused output bit for bit whichever command runs them.

    show = Show(ShowOptions(piece="pieces/liminal.yaml", sim=""))
    result = show.run()          # start(), wait(), stop()
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, TextIO

from ..calibration import LiveCalibrator, LiveSettings, attach_live
from ..clock import Clock, ManualClock, MonotonicClock
from ..engine import Engine
from ..errors import ConfigError
from ..frames import fused_json
from ..piece.loader import load_piece
from ..piece.model import Piece
from ..piece.narrator import EventsFile, Narrator
from ..piece.runtime import FanoutSink, PieceRuntime, RecordingSink
from ..rig import Rig, load_rig
from ..sensors.source import Source, load_source
from ..views import ViewHost
from . import offline as offline_mod
from .options import ShowOptions
from .report import Performance, ScoreSink
from .health import HealthMonitor
from .heap import freeze_start_up, thaw
from .server import Server
from .status_line import StatusLine

log = logging.getLogger("stage.app")

#: how often the piece runtime sees time pass (zones, timed triggers, transitions)
PIECE_TICK_S = 0.05
#: when a source ends by itself, sounding phrases may finish, up to this long
RING_OUT_S = 5.0
#: events kept in memory during a live show (for the summary; a show may run for weeks)
KEEP_EVENTS = 10000
#: --sim given without a scenario: the piece's rehearsal scenario, else the simulator's default
PIECE_SCENARIO = ""


@dataclass
class ShowResult:
    stats: dict                          # the engine's stats at the end
    seconds: float                       # show time, engine clock
    interrupted: bool = False            # stopped by the stop event (Ctrl-C, SIGTERM, caller)
    piece: Piece | None = None
    runtime: PieceRuntime | None = None
    recorded: RecordingSink | None = None
    views: list[str] = field(default_factory=list)
    datagrams_fed: int = 0               # offline: datagrams handed to the engine


class TickingClock(ManualClock):
    """A manual clock that calls ``hook(t)`` whenever it moves (offline runs).

    The offline driver advances the clock datagram by datagram; the hook lets
    the piece runtime see time pass on an empty stage and lets unthreaded
    views send what is due, on the same thread, in time order.
    """

    def __init__(self, start: float = 0.0) -> None:
        super().__init__(start)
        self.hook: Callable[[float], None] | None = None

    def set(self, t: float) -> None:
        super().set(t)
        if self.hook is not None:
            self.hook(self.now())


def summary(stats: dict) -> str:
    """One line about a run: frames in, fused, out, dropped, latency."""
    c = stats["counts"]
    lat = stats["latency_ms"]
    text = (f"{c['frames']} sensor frames in, {c['fused_frames']} fused, "
            f"{c['datagrams_out']} datagrams out, {stats['drops_total']} dropped")
    if lat.get("n"):
        text += f", latency p50 {lat['p50']:.2f} ms p99 {lat['p99']:.2f} ms"
    return text


def reachable(address: tuple[str, int]) -> tuple[str, int]:
    """Where a local source should send to reach a server bound to ``address``."""
    host, port = address
    return ("127.0.0.1" if host in ("0.0.0.0", "") else host), port


class Show:
    """One show (see the module docstring). ``run()``, or ``start()``/``wait()``/``stop()``."""

    def __init__(self, opts: ShowOptions, out: TextIO | None = None,
                 stop_event: threading.Event | None = None) -> None:
        self.opts = opts
        self.out = out or sys.stdout
        self.stop_event = stop_event or threading.Event()
        given = [name for name, on in (("--sim", opts.sim is not None),
                                       ("--replay", opts.replay is not None),
                                       ("--source", opts.source is not None)) if on]
        if len(given) > 1:
            raise ConfigError(f"give one source, not {' and '.join(given)}")
        self.piece: Piece | None = load_piece(opts.piece) if opts.piece else None
        self.seed = opts.seed if opts.seed is not None else (
            self.piece.seed if self.piece is not None and self.piece.seed is not None
            else int(time.time()) % 100000 if self.piece is not None else 1)
        if opts.offline:
            if not given:
                raise ConfigError("--offline needs a source to run ahead of time: --sim or --replay")
            if opts.midi is not None:
                raise ConfigError("--offline runs ahead of time: MIDI goes to a file "
                                  "(--midi-file), not to a port")
            if opts.synth:
                raise ConfigError("--offline runs ahead of time: --synth plays in real time; "
                                  "render with --audio OUT.wav instead")
            if self.piece is not None and opts.midi_file is None and opts.audio is None and any(
                    o.kind == "midi" for o in self.piece.outputs.values()):
                # ahead of time the MIDI can only be a file: name it after the piece, here
                opts.midi_file = os.path.splitext(os.path.basename(opts.piece))[0] + "-offline.mid"
        if not opts.speed > 0:
            raise ConfigError("--speed must be greater than 0")
        self.source: Source | None = self._make_source()
        if opts.offline and self.source is not None and not self.source.offline:
            raise ConfigError(f"the {self.source.name} source cannot run offline")
        self.rig = self._make_rig()
        for view in opts.views:
            if view not in self.rig.views:
                self.rig.views.append(view)
        if opts.view_forecast_s is not None:
            limit = self.rig.forecast.max_s
            if not 0 <= opts.view_forecast_s <= limit:
                raise ConfigError(f"--view-forecast {opts.view_forecast_s:g}: must be between 0 "
                                  f"and the rig's forecast: max_s ({limit:g} s)")
            self.rig.forecast = dataclasses.replace(self.rig.forecast,
                                                    views_s=float(opts.view_forecast_s))
        self.recorded = RecordingSink(None if opts.offline else KEEP_EVENTS) if self.piece else None
        self.score: ScoreSink | None = None
        if opts.score:
            if self.piece is None:
                raise ConfigError("--score draws a piece's performance: give a piece")
            from .score import check_score_path
            check_score_path(opts.score)
            self.score = ScoreSink()
        self.events_file: EventsFile | None = None
        self.fused_file: TextIO | None = None
        self.engine: Engine | None = None
        self.server: Server | None = None
        self.calibrator: LiveCalibrator | None = None
        self.host: ViewHost | None = None
        self.runtime: PieceRuntime | None = None
        self.narrator: Narrator | None = None
        self.status: StatusLine | None = None
        self.health: HealthMonitor | None = None
        self.clock: Clock | None = None
        self._closers: list[Callable[[], None]] = []
        self._threads: list[threading.Thread] = []
        self._frozen = 0     # objects frozen at start-up (stage.app.heap), 0: none
        self._started_at = 0.0
        self._state = "new"
        self._fed = 0

    # ------------------------------------------------------------ assembly
    def _make_source(self) -> Source | None:
        o = self.opts
        if o.sim is not None:
            scenario = o.sim or (self.piece.rehearsal if self.piece is not None else None)
            options = {"scenario": scenario or None, "seed": self.seed, "speed": o.speed,
                       "duration": o.duration, **o.source_options}
            return load_source("sim", **options)
        if o.replay is not None:
            if not os.path.exists(o.replay):
                raise ConfigError(f"--replay {o.replay}: no such file")
            return load_source("replay", path=o.replay, speed=o.speed, loop=o.loop,
                               **o.source_options)
        if o.source is not None:
            return load_source(o.source, **o.source_options)
        return None

    def _make_rig(self) -> Rig:
        """The given rig, else the rig file, else the source's own (a simulator's exact one,
        a recording's), else an empty rig."""
        o = self.opts
        if o.rig_data is not None:
            return o.rig_data
        if o.rig:
            if not os.path.exists(o.rig) and o.create_rig:
                return Rig(path=o.rig)
            return load_rig(o.rig)
        rig = self.source.rig() if self.source is not None else None
        return rig if rig is not None else Rig()

    def _open_files(self) -> None:
        o = self.opts
        if o.events and self.piece is not None:
            try:
                self.events_file = EventsFile(o.events)
            except OSError as exc:
                raise ConfigError(f"--events {o.events}: cannot write: {exc.strerror}") from None
        if o.fused:
            try:
                self.fused_file = open(o.fused, "w", encoding="utf-8")
            except OSError as exc:
                raise ConfigError(f"--fused {o.fused}: cannot write: {exc.strerror}") from None

    def _attach(self, engine: Engine, threaded: bool) -> None:
        """Calibrator, views, piece, status line and fused log on ``engine``."""
        o = self.opts
        settings = o.calibration or LiveSettings()
        if not o.self_healing:
            settings = replace(settings, heal=False, auto_calibrate=False)
        if o.offline:  # deterministic: on the engine thread, nothing written to the rig file
            settings = replace(settings, save=False)
        self.calibrator = attach_live(engine, None if o.offline else o.rig, settings,
                                      threaded=threaded)
        if self.fused_file is not None:
            out = self.fused_file
            engine.listeners.append(lambda frame: out.write(json.dumps(fused_json(frame)) + "\n"))
        self.host = self._view_host(threaded)
        if self.host is not None:
            self.host.attach(engine)
        if self.piece is not None:
            self.narrator = Narrator(self.out, origin=self._started_at, direct=not threaded)
            sink = FanoutSink(self.host, self.events_file, self.recorded, self.score)
            self.runtime = PieceRuntime(self.piece, sink, seed=self.seed, narrator=self.narrator)
            # (lazily: the runtime reads them on the engine thread, while the engine calls
            # it, and only where a section's trigger anticipates or the piece forecasts)
            for horizon in sorted(self.piece.horizons()):   # forecast_s, anticipate
                engine.people.want_forecast(horizon, lazy=True)
            engine.listeners.append(self.runtime)
        if o.status_line:
            self.status = StatusLine(engine, out=self.out)
            engine.listeners.append(self.status)

    def _view_host(self, threaded: bool) -> ViewHost | None:
        o = self.opts
        outputs = list(self.piece.outputs.values()) if self.piece is not None else []
        host = ViewHost.for_play(outputs, midi_port=o.midi, midi_file=o.midi_file,
                                 osc=list(o.osc), monitor=o.monitor, clock=self.clock,
                                 plugins=o.plugins, relay=list(o.relay),
                                 monitor_host=o.monitor_bind, threaded=threaded,
                                 audio=o.audio, synth=o.synth, soundfont=o.soundfont)
        if not host.slots:
            return None
        if self.piece is not None:
            zones, sections = self.piece.scene()
            host.set_scene(zones, sections)
        return host

    # ------------------------------------------------------------ life cycle
    def start(self) -> "Show":
        """Build and start everything (live), or build it (offline; ``wait`` runs it)."""
        if self._state != "new":
            return self
        self._state = "started"
        self._open_files()
        try:
            if self.opts.offline:
                self._build_offline()
            else:
                self._start_live()
                if self.opts.freeze_heap:
                    self._frozen = freeze_start_up()
                    log.debug("%d start-up objects set aside from garbage collection",
                              self._frozen)
        except BaseException:
            self._abandon()
            raise
        return self

    def _build_offline(self) -> None:
        clock = TickingClock(0.0)
        self.clock = clock
        self._started_at = 0.0
        self.engine = Engine(self.rig, clock)
        self.engine.rig_store.threaded = False
        self._attach(self.engine, threaded=False)
        if self.host is not None:
            self.host.start()
        next_tick = [clock.now()]
        runtime, host = self.runtime, self.host

        def hook(t: float) -> None:
            # the piece sees time pass every PIECE_TICK_S, and the moment its ending is over
            if runtime is not None and (t >= next_tick[0] or (
                    runtime.ending and not runtime.ended and t >= runtime.ends_at)):
                next_tick[0] = t + PIECE_TICK_S
                runtime.tick(t)
            if host is not None:
                host.pump()
        clock.hook = hook

    def _start_live(self) -> None:
        o = self.opts
        clock = MonotonicClock()
        self.clock = clock
        local = self.source is not None and not o.listen
        host = o.host or (None if not local else "127.0.0.1")
        port = o.port if o.port is not None else (0 if local else None)
        self.server = server = Server(self.rig, host=host, port=port, clock=clock)
        self._started_at = clock.now()
        engine = self.engine = server.engine
        self._attach(engine, threaded=True)
        if self.host is not None:
            self.host.start()
        runtime = self.runtime
        if runtime is not None:
            engine.call_soon(lambda e: runtime.start(e.clock.now()))
        server.start()
        if o.health:
            alerts = self.rig.alerts
            changes = {k: v for k, v in (("after_s", o.alert_after_s),
                                         ("command", o.alert_command), ("osc", o.alert_osc))
                       if v is not None}
            if changes:
                alerts = dataclasses.replace(alerts, **changes)
            self.health = HealthMonitor(engine, self.host, self.calibrator, alerts,
                                        self.status).start()
        if runtime is not None:
            self._threads.append(_every(PIECE_TICK_S, self.stop_event, lambda: _soon(
                engine, lambda e: runtime.tick(e.clock.now()))))
        if self.source is not None:
            self.source.start(reachable(server.address))

    def wait(self) -> bool:
        """Run (offline) or wait (live) until the show ends; True when stopped by the event."""
        if self._state == "new":
            self.start()
        if self.opts.offline:
            return self._run_offline()
        return self._wait_live()

    def _run_offline(self) -> bool:
        assert self.engine is not None and isinstance(self.clock, TickingClock)
        o, clock, engine = self.opts, self.clock, self.engine
        if self.runtime is not None:
            self.runtime.start(clock.now())
        source = self.source
        assert source is not None
        length = o.duration if o.duration is not None else source.duration
        end = None if length is None else source.start_time + length
        runtime = self.runtime
        stop = (lambda: runtime.ended) if runtime is not None else None
        self._fed = offline_mod.feed(engine, clock, source.items(), end=end, stop=stop)
        if runtime is not None and not runtime.ended:
            deadline = None if o.duration is None else self._started_at + o.duration
            end = self.ring_until(clock.now())
            if deadline is not None:
                end = min(end, deadline)
            while clock.now() < end and not runtime.ended and not self.stop_event.is_set():
                clock.advance(min(PIECE_TICK_S, end - clock.now()))
        return self.stop_event.is_set()

    def ring_until(self, now: float) -> float:
        """When the source has ended: until the piece's ending is over, else up to
        ``RING_OUT_S`` for the last notes to end."""
        runtime = self.runtime
        if runtime is None or runtime.ended:
            return now
        if runtime.ending:
            return runtime.ends_at
        return min(now + RING_OUT_S, runtime.last_note_end)

    def _wait_live(self) -> bool:
        o, clock = self.opts, self.clock
        assert clock is not None
        deadline = None if o.duration is None else self._started_at + o.duration
        ring_until = None
        while not self.stop_event.is_set():
            if self.narrator is not None:
                self.narrator.print_pending()
            now = clock.now()
            if deadline is not None and now >= deadline:
                return False
            source_done = (self.source is not None and self.source.done.is_set()
                           and o.end_with_source)
            if self.runtime is not None and self.runtime.ended:
                return False               # the piece is over: its ending has rung out
            if source_done and deadline is None:
                if self.runtime is None:
                    return False
                if ring_until is None:
                    self.narrator.print_pending()  # type: ignore[union-attr]
                    self.narrator.say("stage play: the source has ended; letting the "  # type: ignore[union-attr]
                                      "piece finish")
                    ring_until = self.ring_until(now)
                if now >= ring_until:
                    return False
            self.stop_event.wait(0.1)
        return True

    def stop(self, interrupted: bool = False) -> ShowResult:
        """Stop everything in order: sources and helpers, the engine, then piece and views."""
        if self._state == "stopped":
            raise RuntimeError("the show is already stopped")
        self._state = "stopped"
        self.stop_event.set()
        if self.source is not None:
            self.source.stop()
        for closer in self._closers:
            closer()
        if self.health is not None:
            self.health.stop()
        if self.calibrator is not None:
            self.calibrator.stop()
        for thread in self._threads:
            thread.join(timeout=2.0)
        if self.server is not None:
            self.server.stop()
        if self.engine is not None:
            self.engine.rig_store.flush()
        now = self.clock.now() if self.clock is not None else 0.0
        if self.runtime is not None:
            self.runtime.stop(now)
        if self.host is not None:
            self.host.stop()
        if self.narrator is not None:
            self.narrator.print_pending()
        self._close_files()
        if self._frozen:
            thaw()
            self._frozen = 0
        if self.score is not None and self.score.events:
            from .score import draw_score
            try:
                path = draw_score(Performance.from_events(self.score.events), self.opts.score,
                                  self.piece.title if self.piece is not None else "")
                log.info("score: %s", path)
            except Exception:     # the show is over; a drawing must not turn it into a crash
                log.exception("could not draw the score %s", self.opts.score)
        stats = self.engine.stats() if self.engine is not None else {}
        return ShowResult(stats, now - self._started_at, interrupted, self.piece, self.runtime,
                          self.recorded, self.host.summary() if self.host is not None else [],
                          self._fed)

    def run(self) -> ShowResult:
        """start(), wait(), stop(): the whole show."""
        try:
            self.start()
            interrupted = self.wait()
        except BaseException:
            if self._state == "started":
                self.stop()
            raise
        return self.stop(interrupted)

    def add_closer(self, fn: Callable[[], None]) -> None:
        """Call ``fn`` when the show stops (before the engine stops)."""
        self._closers.append(fn)

    def _close_files(self) -> None:
        if self.events_file is not None:
            self.events_file.close()
        if self.fused_file is not None:
            self.fused_file.close()

    def _abandon(self) -> None:
        """Setting up failed before the show began: close what was opened."""
        self._state = "stopped"
        self.stop_event.set()
        if self.source is not None:
            self.source.stop()
        if self.health is not None:
            self.health.stop()
        if self.calibrator is not None:
            self.calibrator.stop()
        if self.server is not None:
            self.server.stop()
        if self.host is not None:
            self.host.stop()
        self._close_files()

    # ------------------------------------------------------------ reading
    @property
    def address(self) -> tuple[str, int] | None:
        """The live server's UDP address (None offline)."""
        return self.server.address if self.server is not None else None

    def describe_source(self) -> str:
        if self.source is None:
            where = self.address
            return f"sensors on udp {where[0]}:{where[1]}" if where else "no source"
        text = self.source.describe()
        if self.opts.offline:
            return f"{text} (offline)"
        where = self.address
        return f"{text} -> udp {where[0]}:{where[1]}" if where else text


def _soon(engine: Engine, fn: Callable[[Engine], None]) -> None:
    try:
        engine.call_soon(fn)
    except Exception:  # queue full for a second: the engine is flooded; skip this tick
        log.debug("engine queue full; a tick was skipped")


def _every(period: float, stop: threading.Event, fn: Callable[[], None]) -> threading.Thread:
    def run() -> None:
        while not stop.wait(period):
            fn()
    thread = threading.Thread(target=run, name="stage-piece-tick", daemon=True)
    thread.start()
    return thread


__all__ = ["Show", "ShowOptions", "ShowResult", "TickingClock", "summary", "reachable",
           "PIECE_SCENARIO", "RING_OUT_S", "KEEP_EVENTS"]
