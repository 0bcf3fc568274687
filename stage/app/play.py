"""`stage play`: a piece, a source of bodies, the views, and a clean stop.

Sources: real sensors (the engine listening on UDP, as `stage serve`), the
simulator (``--sim [SCENARIO]``, real OSC over loopback in real time), or a
recording (``--replay FILE``). ``offline=True`` runs the simulator or the
recording in-process on a manual clock, as fast as the machine goes (tests,
rendering a rehearsal to a MIDI file); the events are the same as in real
time for the same seed.

The piece runtime and the view host both listen to the engine; the runtime
hands its events to the views, to the ``--events`` file and (as readable
lines) to the console. On stop -- Ctrl-C, SIGTERM, the end of ``--duration``
or of the source -- pending notes are cancelled, every sounding note gets
its note-off and the outputs are flushed.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, TextIO

from ..clock import Clock, ManualClock, MonotonicClock
from ..engine.engine import Engine
from ..errors import ConfigError, StageError
from ..rig import Rig, load_rig
from ..piece.narrator import Console, EventsFile
from ..piece.loader import load_piece
from ..piece.model import Piece
from ..piece.runtime import FanoutSink, PieceRuntime, RecordingSink

log = logging.getLogger("stage.piece.play")

#: --sim given without a scenario: the piece's rehearsal scenario, else the simulator's default
PIECE_SCENARIO = ""
TICK_S = 0.05
#: when a scenario or recording ends by itself, sounding phrases may finish, up to this long
RING_OUT_S = 5.0
#: events kept in memory during a real-time show (for the summary; a show may run for weeks)
KEEP_EVENTS = 10000


@dataclass
class PlayOptions:
    piece: str
    sim: str | None = None          # None: no simulator; PIECE_SCENARIO: the piece's; else a name
    replay: str | None = None
    port: int | None = None
    host: str | None = None
    rig: str | None = None
    midi: str | None = None
    midi_file: str | None = None
    osc: list[tuple[str, int]] = field(default_factory=list)
    seed: int | None = None
    duration: float | None = None
    events: str | None = None
    monitor: bool | int = False
    offline: bool = False
    speed: float = 1.0


@dataclass
class PlayResult:
    piece: Piece
    runtime: PieceRuntime
    recorded: RecordingSink
    views: list[str]
    seconds: float


class TickingClock(ManualClock):
    """A manual clock that calls ``hook(t)`` whenever it moves (offline runs).

    The offline source advances the clock frame by frame; the hook lets the
    piece runtime see time pass on an empty stage and lets unthreaded views
    send what is due, on the same thread, in time order.
    """

    def __init__(self, start: float = 0.0) -> None:
        super().__init__(start)
        self.hook: Callable[[float], None] | None = None

    def set(self, t: float) -> None:
        super().set(t)
        if self.hook is not None:
            self.hook(self.now())


def resolve_scenario(piece: Piece, sim: str) -> str | None:
    """The scenario `--sim` means: its argument, else the piece's rehearsal, else None (default)."""
    if sim:
        return sim
    return piece.rehearsal


def _import_sources():
    try:
        from ..sensors import sim
    except ImportError as exc:
        raise StageError(f"the simulator is not available ({exc}); --sim needs stage.sim") from None
    return sim


def _replay_module():
    try:
        from ..sensors import replay
    except ImportError as exc:
        raise StageError(f"replay is not available ({exc}); --replay needs stage.replay") from None
    return replay


def _recording_rig(path: str) -> Rig:
    """The rig a recording carries (the simulator stores its exact one), else an empty one."""
    replay = _replay_module()
    from ..sensors.recording import read_recording
    try:
        meta = read_recording(path).meta
    except FileNotFoundError:
        raise ConfigError(f"--replay {path}: no such file") from None
    return replay.rig_from_meta(meta) or Rig()


def _view_host(piece: Piece, opts: PlayOptions, clock: Clock, threaded: bool):
    try:
        from ..views import ViewHost
    except ImportError as exc:
        log.warning("views are not available (%s): events go to the console and --events only",
                    exc)
        return None
    host = ViewHost.for_play(list(piece.outputs.values()), midi_port=opts.midi,
                             midi_file=opts.midi_file, osc=list(opts.osc), monitor=opts.monitor,
                             clock=clock, threaded=threaded)
    zones, sections = piece.scene()
    host.set_scene(zones, sections)
    return host


class Player:
    """One performance. ``run()`` blocks until the end and returns a PlayResult."""

    def __init__(self, opts: PlayOptions, out: TextIO | None = None,
                 stop_event: threading.Event | None = None) -> None:
        self.opts = opts
        self.out = out or sys.stdout
        self.stop_event = stop_event or threading.Event()
        self.piece = load_piece(opts.piece)
        if opts.sim is not None and opts.replay is not None:
            raise ConfigError("give --sim or --replay, not both")
        if opts.offline and opts.sim is None and opts.replay is None:
            raise ConfigError("--offline needs a source to run ahead of time: --sim or --replay")
        if opts.offline and opts.midi is not None:
            raise ConfigError("--offline runs ahead of time: MIDI goes to a file (--midi-file), "
                              "not to a port")
        if opts.offline and opts.midi_file is None and any(
                o.kind == "midi" for o in self.piece.outputs.values()):
            # ahead of time the MIDI can only be a file: name it after the piece, here
            opts.midi_file = os.path.splitext(os.path.basename(opts.piece))[0] + "-offline.mid"
        self.seed = opts.seed if opts.seed is not None else (
            self.piece.seed if self.piece.seed is not None else int(time.time()) % 100000)
        self.recorded = RecordingSink(None if opts.offline else KEEP_EVENTS)
        self.events_file: EventsFile | None = None
        if opts.events:
            try:
                self.events_file = EventsFile(opts.events)
            except OSError as exc:
                raise ConfigError(f"--events {opts.events}: cannot write: {exc.strerror}") from None

    # ------------------------------------------------------------ shared
    def _runtime(self, console: Console, host) -> PieceRuntime:
        sink = FanoutSink(host, self.events_file, self.recorded)
        return PieceRuntime(self.piece, sink, seed=self.seed, narrator=console)

    def _banner(self, console: Console, source: str, host) -> None:
        p = self.piece
        console.say(f"stage play: \"{p.title}\"" + (f" ({p.composer})" if p.composer else "")
                    + f" -- {len(p.sections)} sections, seed {self.seed}; source: {source}")
        if host is not None:
            for line in host.summary():
                console.say(f"  view {line}")
        if self.events_file is not None:
            console.say(f"  events -> {self.events_file.path}")

    def _finish(self, runtime: PieceRuntime, host, console: Console, t: float,
                started: float) -> PlayResult:
        runtime.stop(t)
        if host is not None:
            host.stop()
        if self.events_file is not None:
            self.events_file.close()
        console.print_pending()
        c = runtime.counts
        seen = list(dict.fromkeys(runtime.visited))
        console.say(f"stage play: stopped after {t - started:.1f} s; sections reached: "
                    f"{len(seen)}/{len(self.piece.sections)} ({', '.join(seen)}); "
                    f"{c['fired']} triggers fired, {c['notes']} notes" +
                    (f", {c['errors']} runtime errors (see log)" if c["errors"] else ""))
        if host is not None:
            for line in host.summary():
                console.say(f"  view {line}")
        return PlayResult(self.piece, runtime, self.recorded,
                          host.summary() if host is not None else [], t - started)

    # ------------------------------------------------------------ offline
    def _abandon(self) -> None:
        """Setting up failed before the show began: close what was opened."""
        if self.events_file is not None:
            self.events_file.close()

    def run_offline(self) -> PlayResult:
        """Simulator or recording in-process on a manual clock, no sleeping."""
        try:
            return self._run_offline()
        except BaseException:
            self._abandon()
            raise

    def _run_offline(self) -> PlayResult:
        opts = self.opts
        clock = TickingClock(0.0)
        console = Console(self.out, origin=0.0, direct=True)
        if opts.sim is not None:
            sim = _import_sources()
            scenario = sim.load_scenario(resolve_scenario(self.piece, opts.sim) or None)
            simulator = sim.Simulator(scenario, self.seed)
            rig = load_rig(opts.rig) if opts.rig else simulator.rig()
            duration = opts.duration or scenario.duration
            if not duration:
                raise ConfigError("--offline needs --duration (the scenario has no end)")
            source = f"simulator (offline, {duration:g} s)"
        else:
            rig = load_rig(opts.rig) if opts.rig else _recording_rig(opts.replay)
            source = f"replay of {opts.replay} (offline)"
        engine = Engine(rig, clock)
        # self-healing calibration, on the engine thread and without saving: deterministic
        from ..calibration import attach_live
        attach_live(engine, None, threaded=False, save=False)
        host = _view_host(self.piece, opts, clock, threaded=False)
        runtime = self._runtime(console, host)
        if host is not None:
            host.attach(engine)
        engine.listeners.append(runtime)
        if host is not None:
            host.start()
        self._banner(console, source, host)
        runtime.start(clock.now())
        next_tick = [clock.now()]

        def hook(t: float) -> None:
            if t >= next_tick[0]:
                next_tick[0] = t + TICK_S
                runtime.tick(t)
            if host is not None:
                host.pump()
        clock.hook = hook
        try:
            if opts.sim is not None:
                simulator.feed(engine, clock, duration)
            else:
                _replay_module().replay_offline(opts.replay, engine, clock)
            if opts.duration is None:  # the source ended by itself: let the last phrase end
                end = min(clock.now() + RING_OUT_S, runtime.last_note_end)
                while clock.now() < end:
                    clock.advance(min(TICK_S, end - clock.now()))
        finally:
            clock.hook = None
            result = self._finish(runtime, host, console, clock.now(), 0.0)
        return result

    # ------------------------------------------------------------ real time
    def run(self) -> PlayResult:
        if self.opts.offline:
            return self.run_offline()
        try:
            return self._run_realtime()
        except BaseException:
            self._abandon()
            raise

    def _run_realtime(self) -> PlayResult:
        from ..sensors.receiver import Server
        opts = self.opts
        simulator = None
        if opts.sim is not None:
            sim = _import_sources()
            scenario = sim.load_scenario(resolve_scenario(self.piece, opts.sim) or None)
            simulator = sim.Simulator(scenario, self.seed)
            rig = load_rig(opts.rig) if opts.rig else simulator.rig()
            host_addr = opts.host or "127.0.0.1"
        elif opts.replay is not None:
            rig = load_rig(opts.rig) if opts.rig else _recording_rig(opts.replay)
            host_addr = opts.host or "127.0.0.1"
        else:
            rig = load_rig(opts.rig) if opts.rig else Rig()
            host_addr = opts.host
        port = opts.port if opts.port is not None else (0 if (simulator or opts.replay) else None)
        clock = MonotonicClock()
        server = Server(rig, host=host_addr, port=port, clock=clock)
        engine = server.engine
        started = clock.now()
        console = Console(self.out, origin=started)
        try:
            host = _view_host(self.piece, opts, clock, threaded=True)
        except BaseException:
            server.sock.close()
            raise
        runtime = self._runtime(console, host)
        if host is not None:
            host.attach(engine)
        engine.listeners.append(runtime)
        where = f"{server.address[0]}:{server.address[1]}"
        source = (f"simulator -> udp {where}" if simulator else
                  f"replay of {opts.replay} -> udp {where}" if opts.replay else
                  f"sensors on udp {where}")
        threads: list[threading.Thread] = []
        safety: list[Any] = []
        try:
            if host is not None:
                host.start()
            self._banner(console, source, host)
            engine.call_soon(lambda e: runtime.start(e.clock.now()))
            server.start()
            threads.append(_every(TICK_S, self.stop_event, lambda: _soon(
                engine, lambda e: runtime.tick(e.clock.now()))))
            safety = self._safety(engine, runtime, console)
            from ..calibration import attach_live
            safety.append(attach_live(engine, opts.rig).stop)
            source_done = threading.Event()
            if simulator is not None:
                length = opts.duration or simulator.scenario.duration
                threads.append(_background(lambda: simulator.run_realtime(
                    target=server.address, duration=length, speed=opts.speed,
                    stop_event=self.stop_event), source_done))
            elif opts.replay is not None:
                source_obj = _replay_module().ReplaySource(opts.replay, target=server.address,
                                                           speed=opts.speed).start()
                safety.append(source_obj.stop)
                threads.append(_background(lambda: source_obj.wait(), source_done))
            deadline = None if opts.duration is None else started + opts.duration
            ring_until = None
            while not self.stop_event.is_set():
                console.print_pending()
                now = clock.now()
                if deadline is not None and now >= deadline:
                    break
                if (source_done.is_set() and deadline is None) or runtime.ended:
                    if ring_until is None:
                        console.print_pending()
                        console.say("stage play: the " + ("piece" if runtime.ended else "source")
                                    + " has ended; letting the last notes ring")
                        ring_until = min(now + RING_OUT_S, runtime.last_note_end)
                    if now >= ring_until:
                        break
                self.stop_event.wait(0.1)
        finally:
            self.stop_event.set()
            for closer in safety:
                closer()
            for thread in threads:
                thread.join(timeout=2.0)
            server.stop()
            result = self._finish(runtime, host, console, clock.now(), started)
        return result

    # ------------------------------------------------------------ safety
    def _safety(self, engine: Engine, runtime: PieceRuntime, console: Console) -> list:
        """The cellist's / operator's way to force a section: console keys and an OSC port."""
        closers = []
        s = self.piece.safety

        def force(target: str, cause: str) -> None:
            _soon(engine, lambda e: runtime.goto(target, e.clock.now(), cause))

        if s.keys and sys.stdin is not None and sys.stdin.isatty():
            console.say("  safety: type n + Enter for the next section, p + Enter for the "
                        "previous, or a section's number or name")
            names = [sec.name for sec in self.piece.sections]

            def keys() -> None:
                for line in sys.stdin:
                    word = line.strip()
                    if self.stop_event.is_set():
                        return
                    if word in ("n", "next"):
                        force("next", "operator")
                    elif word in ("p", "previous"):
                        force("previous", "operator")
                    elif word.isdigit() and 1 <= int(word) <= len(names):
                        force(names[int(word) - 1], "operator")
                    elif word in names:
                        force(word, "operator")
                    elif word:
                        console.say(f"  safety: '{word}'? n, p, 1-{len(names)} or a section name")
            threading.Thread(target=keys, name="stage-safety-keys", daemon=True).start()
        if s.osc_port is not None:
            closers.append(osc_safety(s.osc_port, [sec.name for sec in self.piece.sections],
                                      force, self.stop_event, console))
        return closers


def osc_safety(port: int, names: list[str], force: Callable[[str, str], None],
               stop: threading.Event, console: Console) -> Callable[[], None]:
    """Listen on UDP ``port`` for ``/stage/section next|previous|NAME|NUMBER``; returns a closer.

    NUMBER counts from 1 in the piece's order.
    """
    from pythonosc.osc_message import OscMessage
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(("0.0.0.0", port))
    except OSError as exc:  # the show goes on without it; the console keys may still work
        sock.close()
        log.warning("cannot listen for the safety on udp port %d (%s): no OSC safety this time",
                    port, exc.strerror)
        return lambda: None
    sock.settimeout(0.2)
    console.say(f"  safety: send /stage/section next|previous|NAME to udp port {port}")

    def run() -> None:
        while not stop.is_set():
            try:
                data, _ = sock.recvfrom(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            try:
                msg = OscMessage(data)
            except Exception:
                log.warning("safety port: a datagram that is not OSC was ignored")
                continue
            if msg.address == "/stage/section" and msg.params:
                arg = msg.params[0]
                if isinstance(arg, int) and 1 <= arg <= len(names):
                    arg = names[arg - 1]
                force(str(arg), "operator (OSC)")
            else:
                log.warning("safety port: ignored %s (expected /stage/section next|previous|NAME)",
                            msg.address)
    thread = threading.Thread(target=run, name="stage-safety-osc", daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        thread.join(timeout=1.0)
        sock.close()
    return close


def _soon(engine: Engine, fn) -> None:
    try:
        engine.call_soon(fn)
    except Exception:  # queue full for a second: the engine is flooded; skip this tick
        log.debug("engine queue full; a tick was skipped")


def _every(period: float, stop: threading.Event, fn) -> threading.Thread:
    def run() -> None:
        while not stop.wait(period):
            fn()
    thread = threading.Thread(target=run, name="stage-piece-tick", daemon=True)
    thread.start()
    return thread


def _background(fn, done: threading.Event) -> threading.Thread:
    """Run a source; ``done`` is set when it ends (scenario or recording over, or failed)."""
    def run() -> None:
        try:
            fn()
        except Exception:
            log.exception("the source failed")
        finally:
            done.set()
    thread = threading.Thread(target=run, name="stage-play-source", daemon=True)
    thread.start()
    return thread


def play(opts: PlayOptions, out: TextIO | None = None,
         stop_event: threading.Event | None = None) -> PlayResult:
    """Run one performance (see module docstring)."""
    return Player(opts, out, stop_event).run()


__all__ = ["PlayOptions", "PlayResult", "Player", "play", "TickingClock"]
