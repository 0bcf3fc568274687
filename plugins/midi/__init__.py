"""The MIDI view: piece notes, controls and programs to MIDI ports or a Standard MIDI File.

Each output the piece declares (``kind: midi``) goes to its own port (the
piece's ``port``), else to the command line's ``--midi PORT``, else to a new
virtual port named after the output; ``--midi-file OUT.mid`` records every
output (and replaces the virtual ports). The channel is the event's: one
channel per output in the piece. When no MIDI system is available (no ALSA
sequencer, no JACK server) one warning says so and the notes go to a file.
Without a synthesizer: ``--audio OUT.wav`` renders every output through
FluidSynth into a WAV file, ``--synth`` plays them live through FluidSynth on
JACK (both replace the virtual ports; see ``synth.py``).

Timing: every note's note-off is scheduled when the note arrives, at
``t + duration`` on the engine clock; the view's thread sleeps until the
next due message (``View.tick``), so timing does not depend on frames.
``bench/bench_midi.py`` measures it through JACK.
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
from pathlib import Path
from typing import Any, Sequence

from stage.errors import ConfigError, StageError
from stage.events import (AllNotesOff, ControlChange, Event, Note, NoteCut, OutputDecl,
                          ProgramChange)
from stage.views import View, ViewContext

from .ports import PortSink, choose_api
from .schedule import MidiScheduler, Out
from .smf import SmfWriter
from .synth import LiveSynth, WavRenderer

_MIDI_EVENTS = (Note, ControlChange, ProgramChange, AllNotesOff, NoteCut)
CLOCK, START, STOP = b"\xf8", b"\xfa", b"\xfc"
#: how often the ports are checked (a JACK server killed, a synth quit) and reopened
CHECK_EVERY_S = 2.0


class MidiView(View):
    """MIDI out: ports (JACK, ALSA, CoreMIDI, Windows), virtual ports, Standard MIDI Files."""

    description = ("MIDI out: notes with precise note-offs to ports, virtual ports or a "
                   "Standard MIDI File")
    autostart = False          # needs outputs from a piece or --midi/--midi-file

    def __init__(self, outputs: Sequence[OutputDecl] = (), port: str | None = None,
                 file: str | os.PathLike | None = None, clock_bpm: float | None = None,
                 client: str = "stage", flush_every_s: float = 1.0,
                 fallback_dir: str | os.PathLike = ".", audio: str | os.PathLike | None = None,
                 synth: bool = False, soundfont: str | os.PathLike | None = None) -> None:
        """outputs: the piece's MIDI outputs; port: ``--midi``; file: ``--midi-file``;
        clock_bpm: send MIDI clock (24 per beat, start/stop) to the ports at this tempo;
        audio: ``--audio OUT.wav``; synth: ``--synth``; soundfont: ``--soundfont``."""
        self.outputs = [o for o in outputs if o.kind == "midi"] or [OutputDecl("midi", "midi")]
        self.port, self.client = port, client
        self.file = Path(file) if file is not None else None
        if self.file is not None and not self.file.parent.is_dir():
            raise ConfigError(f"--midi-file {self.file}: folder '{self.file.parent}' does not exist")
        if clock_bpm is not None and not 20 <= clock_bpm <= 400:
            raise ConfigError(f"MIDI clock tempo {clock_bpm} bpm is outside 20-400")
        self.clock_bpm = clock_bpm
        self.audio_path = Path(audio) if audio is not None else None
        self.soundfont = soundfont
        self.audio: WavRenderer | None = None
        self.synth: LiveSynth | None = None
        if self.audio_path is not None:      # a missing library or soundfont: said now
            self.audio = WavRenderer(self.audio_path, soundfont)
        if synth:
            self.synth = LiveSynth(soundfont)
        self.flush_every_s = flush_every_s
        self.fallback_dir = Path(fallback_dir)
        self.scheduler = MidiScheduler()
        self.routes: dict[str, list[Any]] = {}
        self.default = self.outputs[0].name
        self.ports: dict[str, PortSink] = {}
        self._closed: list[PortSink] = []
        self.smf: SmfWriter | None = None
        self._ctx: ViewContext | None = None
        self._next_flush = self._next_clock = self._next_check = float("inf")
        self._clock_k = 0
        self._clock_t0 = 0.0
        self._warned_outputs: set[str] = set()
        self._warned_bad = False
        self.summary = ""

    # ------------------------------------------------------------ life cycle
    def start(self, ctx: ViewContext) -> None:
        self._ctx = ctx
        now = ctx.now()
        wanted: dict[str, str] = {}      # output -> port name
        named: set[str] = set()          # names the user gave: an existing port may be meant
        synthesized = self.file is not None or self.audio_path is not None or self.synth
        for o in self.outputs:
            name = o.target or self.port or (None if synthesized else o.name)
            if name:
                wanted[o.name] = name
            if o.target or self.port:
                named.add(name)
        failed: list[str] = []
        api, why = choose_api() if wanted else (None, "")
        for output, name in wanted.items():
            if name not in self.ports and name not in failed:
                if api is None:
                    failed.append(name)
                    continue
                # one client per port (rtmidi's way); distinct names, so JACK does not rename
                # them and the summary shows the names to connect
                client = self.client if not self.ports else f"{self.client}-{len(self.ports) + 1}"
                try:
                    self.ports[name] = PortSink(name, api, client, existing=name in named)
                except StageError as exc:
                    ctx.log.warning("%s", exc)
                    failed.append(name)
        if failed and self.file is None:
            stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
            self.file = self.fallback_dir / f"stage-{stamp}.mid"
        if failed:
            ctx.log.warning("no MIDI port available for %s (%s): writing the MIDI to %s instead",
                            ", ".join(f"'{n}'" for n in failed), why or "could not open",
                            self.file)
        if self.file is not None:
            self.smf = SmfWriter(self.file, now, name=self.outputs[0].name)
            self._next_flush = now + self.flush_every_s
        if self.audio is not None:
            self.audio.begin(now)
        for o in self.outputs:
            sinks: list[Any] = []
            port = self.ports.get(wanted.get(o.name, ""))
            if port is not None:
                sinks.append(port)
            if self.smf is not None:
                sinks.append(self.smf)
            if self.synth is not None:
                sinks.append(self.synth)
            if self.audio is not None:
                sinks.append(self.audio)
            self.routes[o.name] = sinks
        if self.ports:
            self._next_check = now + CHECK_EVERY_S
        if self.clock_bpm and self.ports:
            self._clock_t0 = now
            self._next_clock = now
            for port in self.ports.values():
                port.send(START)
        parts = [f"'{o.name}' -> " + (", ".join(s.where if isinstance(s, (PortSink, LiveSynth))
                                                 else f"file {s.path}" for s in self.routes[o.name])
                                      or "nowhere")
                 for o in self.outputs]
        self.summary = "; ".join(parts)
        ctx.log.info("MIDI: %s", self.summary)

    def stop(self) -> None:
        now = self._ctx.now() if self._ctx else 0.0
        try:
            self._send(self.scheduler.due(now))
            silence = self.scheduler.silence(now)
            self._send(silence)
            for out in silence:     # (sent again by a JACK port as it closes)
                for sink in self.routes.get(out.output, ()):
                    if isinstance(sink, PortSink):
                        sink.again_at_close(out.data)
            if self.clock_bpm:
                for port in self.ports.values():
                    port.send(STOP)
        finally:
            for port in self.ports.values():
                state = port.state() if hasattr(port, "state") else {}
                if state.get("down_s"):
                    self._log().warning("MIDI port '%s' was disconnected for %.0f s in all "
                                        "(%d message(s) not sent, %d reconnection(s))", port.name,
                                        state["down_s"], state["dropped"], state["reconnects"])
                port.close()
            self._closed = list(self.ports.values())
            self.ports.clear()
            if self.smf is not None:
                self.smf.close()
            if self.synth is not None:
                self.synth.close()
            if self.audio is not None:
                self.audio.close()

    # ------------------------------------------------------------ events and time
    def on_events(self, events: Sequence[Event]) -> None:
        now = self._ctx.now() if self._ctx else 0.0
        for event in events:
            if not isinstance(event, _MIDI_EVENTS):
                continue
            output = event.output
            if output is not None and output not in self.routes:
                if output not in self._warned_outputs:
                    self._warned_outputs.add(output)
                    self._log().warning("MIDI events for output '%s', which the piece does not "
                                        "declare, go to '%s'", output, self.default)
                output = self.default
            if not self.scheduler.add(event, now, output) and not self._warned_bad:
                self._warned_bad = True
                self._log().warning("MIDI event dropped (counted): %s", self.scheduler.last_bad)

    def tick(self, now: float) -> float | None:
        if now >= self._next_check:
            self._next_check = now + CHECK_EVERY_S
            self._check_ports()
        self._send(self.scheduler.due(now))
        if now >= self._next_clock:
            period = 60.0 / (self.clock_bpm or 120.0) / 24.0
            while self._next_clock <= now:
                for port in self.ports.values():
                    port.send(CLOCK)
                self._clock_k += 1
                self._next_clock = self._clock_t0 + self._clock_k * period
        if self.smf is not None and now >= self._next_flush:
            self.smf.flush()
            self._next_flush = now + self.flush_every_s
        times = [t for t in (self.scheduler.next_time(), self._next_clock, self._next_flush,
                             self._next_check)
                 if t is not None and t != float("inf")]
        return min(times) if times else None

    def _check_ports(self) -> None:
        """A port whose server or synth went away is reopened when it is back (health)."""
        for port in self.ports.values():
            check = getattr(port, "check", None)
            change = check() if check is not None else None
            if change:
                lost = not getattr(port, "connected", True)
                (self._log().warning if lost else self._log().info)("%s", change)

    def _send(self, outs: list[Out]) -> None:
        for out in outs:
            for sink in self.routes.get(out.output, ()):
                if isinstance(sink, (PortSink, LiveSynth)):
                    sink.send(out.data)
                else:
                    sink.write(out.t, out.data)

    def _log(self) -> logging.Logger:
        return self._ctx.log if self._ctx else logging.getLogger("stage.views.midi")

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.scheduler.stats)
        out["sounding"] = self.scheduler.sounding
        out["pending"] = self.scheduler.pending
        ports = list(self.ports.values()) + self._closed
        out["sent"] = sum(p.sent for p in ports)
        out["send_errors"] = sum(p.errors for p in ports)
        out["ports"] = {p.name: p.state() for p in self.ports.values() if hasattr(p, "state")}
        if self.smf is not None:
            out["file"] = str(self.smf.path)
            out["file_events"] = self.smf.events
        if self.audio is not None:
            out["audio"] = str(self.audio.path)
            out["audio_seconds"] = round(self.audio.seconds, 3)
        out["summary"] = self.summary
        return out
