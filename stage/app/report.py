"""What happened in a performance, from its events: sections, phrases, notes, levels.

``Performance.load(events.jsonl)`` (or ``from_events``) reads the events a
show wrote (``stage play --events``) and puts them together: the sections
with their times, every phrase with the trigger that fired it, every note
with how long it really sounded (``NoteCut`` events; the sustain pedal of an
ending), the zone occupancy. ``summary()`` says it in lines; with the show's
WAV file (``stage play --audio``), ``audio_report`` measures the level of each
section and finds silence where notes sound and sound where none do.
``stage report`` prints both and draws the score (``stage.app.score``).
"""

from __future__ import annotations

import json
import math
import os
import wave
from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from ..errors import ConfigError
from ..events import (AllNotesOff, ControlChange, Event, Note, NoteCut, PhrasePlayed, PhraseSkipped,
                      SectionChange, TriggerFired, ZoneState, to_json)

#: an audio window quieter than this (dBFS, RMS) is silence
SILENCE_DB = -60.0
#: after a note ends, the instrument's release and the hall may ring this long (s)
TAIL_S = 2.5
#: stretches shorter than this are not reported (s)
MIN_STRETCH_S = 0.5
WINDOW_S = 0.05


@dataclass
class NoteRec:
    t: float              # onset, seconds from the piece's start
    duration: float       # as scheduled
    sounded: float        # until its note-off (or the cut)
    held: float           # until it really stopped (a sustain pedal holds it on)
    note: int
    channel: int
    output: str
    play: int
    cut: str = ""         # why it was cut ("" if it sounded whole)


@dataclass
class Section:
    name: str
    index: int
    start: float
    end: float
    cause: str


@dataclass
class Performance:
    origin: float                                  # engine time of the piece's start
    end: float                                     # seconds from the start
    sections: list[Section] = field(default_factory=list)
    phrases: dict[int, dict] = field(default_factory=dict)
    skipped: list[dict] = field(default_factory=list)
    notes: list[NoteRec] = field(default_factory=list)
    triggers: list[dict] = field(default_factory=list)
    zones: dict[str, list[tuple[float, float]]] = field(default_factory=dict)

    # ------------------------------------------------------------ reading
    @classmethod
    def load(cls, path: str | os.PathLike) -> "Performance":
        """Read a ``--events`` file; ConfigError (one line) when it is not one."""
        events = []
        try:
            with open(path, encoding="utf-8") as f:
                for k, line in enumerate(f, 1):
                    if not line.strip():
                        continue
                    try:
                        event = json.loads(line)
                    except json.JSONDecodeError:
                        raise ConfigError(f"line {k} is not JSON: expected one event per line "
                                          "(stage play --events)", path=str(path),
                                          line=k) from None
                    if not isinstance(event, dict) or "type" not in event or "t" not in event:
                        raise ConfigError(f"line {k} is not an event (no 'type' and 't')",
                                          path=str(path), line=k)
                    events.append(event)
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
        if not any(e["type"] == "SectionChange" for e in events):
            raise ConfigError(f"{path}: no section starts in it: not the events of a piece")
        return cls.from_events(events)

    @classmethod
    def from_events(cls, events: Iterable[Any]) -> "Performance":
        """From event objects or their ``to_json`` dicts, in the order they were emitted."""
        evs = [e if isinstance(e, dict) else to_json(e) for e in events]
        starts = [e for e in evs if e["type"] == "SectionChange"]
        origin = starts[0]["t"] if starts else (evs[0]["t"] if evs else 0.0)
        rel = lambda t: float(t) - origin  # noqa: E731
        end = max((rel(e["t"]) for e in evs), default=0.0)
        perf = cls(origin, end)
        for k, e in enumerate(starts):
            nxt = rel(starts[k + 1]["t"]) if k + 1 < len(starts) else None
            perf.sections.append(Section(e["section"], e["index"], rel(e["t"]),
                                         nxt if nxt is not None else end, e.get("cause", "")))
        cuts: dict[tuple, dict] = {}
        pedal: dict[tuple[str, int], list[list[float]]] = {}
        open_zones: dict[str, float] = {}
        for e in evs:
            kind = e["type"]
            if kind == "PhrasePlayed":
                perf.phrases[e["id"]] = {**e, "t": rel(e["t"]), "end": rel(e["end"]),
                                         "decided": rel(e["decided"])}
            elif kind == "PhraseSkipped":
                perf.skipped.append({**e, "t": rel(e["t"])})
            elif kind == "TriggerFired":
                perf.triggers.append({**e, "t": rel(e["t"])})
            elif kind == "NoteCut":
                cuts[(e["output"], e["channel"], e["note"], round(e["onset"], 6))] = e
            elif kind == "ControlChange" and e["control"] == 64:
                spans = pedal.setdefault((e["output"], e["channel"]), [])
                if e["value"] >= 64 and (not spans or spans[-1][1] < math.inf):
                    spans.append([rel(e["t"]), math.inf])
                elif e["value"] < 64 and spans and spans[-1][1] == math.inf:
                    spans[-1][1] = rel(e["t"])
            elif kind == "ZoneState":
                if e["occupied"] and e["zone"] not in open_zones:
                    open_zones[e["zone"]] = rel(e["t"])
                elif not e["occupied"] and e["zone"] in open_zones:
                    perf.zones.setdefault(e["zone"], []).append(
                        (open_zones.pop(e["zone"]), rel(e["t"])))
        for zone, since in open_zones.items():
            perf.zones.setdefault(zone, []).append((since, end))
        for e in evs:
            if e["type"] != "Note":
                continue
            cut = cuts.get((e["output"], e["channel"], e["note"], round(e["t"], 6)))
            sounded = cut["sounded"] if cut else e["duration"]
            t, off = rel(e["t"]), rel(e["t"]) + sounded
            held = off
            for a, b in pedal.get((e["output"], e["channel"]), ()):
                if sounded > 0 and a <= off < b:
                    held = min(b, end)
            perf.notes.append(NoteRec(t, e["duration"], sounded, held - t, e["note"],
                                      e["channel"], e["output"], e.get("play", 0),
                                      cut["why"] if cut else ""))
        return perf

    # ------------------------------------------------------------ facts
    def sounding(self) -> list[tuple[float, float]]:
        """Where notes sound (onset to note-off or cut), merged, seconds."""
        return _merge([(n.t, n.t + n.sounded) for n in self.notes if n.sounded > 0])

    def ringing(self, tail: float = 0.0) -> list[tuple[float, float]]:
        """Where sound may go on: notes, the ending's pedal holding them as they fade, and
        ``tail`` seconds of release after that, merged."""
        return _merge([(n.t, n.t + max(n.held, n.sounded) + tail) for n in self.notes
                       if n.sounded > 0])

    def counts(self) -> dict[str, int]:
        return {"notes": sum(1 for n in self.notes if n.sounded > 0),
                "cancelled": sum(1 for n in self.notes if n.sounded <= 0),
                "shortened": sum(1 for n in self.notes if 0 < n.sounded < n.duration - 1e-9),
                "phrases": len(self.phrases), "skipped": len(self.skipped),
                "fired": len(self.triggers)}

    def section_at(self, t: float) -> Section | None:
        for s in self.sections:
            if s.start <= t < s.end or (s is self.sections[-1] and t >= s.start):
                return s
        return None

    def summary(self) -> list[str]:
        c = self.counts()
        out = [f"{self.end:.1f} s, {len(self.sections)} section(s), {c['fired']} triggers fired, "
               f"{c['phrases']} phrases played ({c['skipped']} not), {c['notes']} notes sounded "
               f"({c['cancelled']} cancelled, {c['shortened']} cut short)"]
        for s in self.sections:
            names = [p["phrase"] for p in self.phrases.values() if p["section"] == s.name]
            out.append(f"  {s.start:6.1f}-{s.end:6.1f} s  {s.name}: {len(names)} phrase(s)"
                       + (f" ({', '.join(names)})" if names else ""))
        for sk in self.skipped:
            out.append(f"  {sk['t']:6.1f} s  not played: {sk['phrase']} ({sk['trigger']}): "
                       f"{sk['why']}")
        for n in self.notes:
            if n.cut:
                what = "cancelled" if n.sounded <= 0 else f"cut after {n.sounded:.2f} s of " \
                                                           f"{n.duration:.2f} s"
                out.append(f"  {n.t:6.1f} s  note {n.note} {what}: {n.cut}")
        return out


class ScoreSink:
    """An EventSink keeping only what a score and a report need (a live show's other
    events -- mappings, OSC -- would fill memory for nothing)."""

    KINDS = (Note, NoteCut, PhrasePlayed, PhraseSkipped, SectionChange, TriggerFired, ZoneState,
             AllNotesOff)

    def __init__(self) -> None:
        self.events: list[Event] = []

    def emit(self, events: list[Event]) -> None:
        self.events.extend(e for e in events if isinstance(e, self.KINDS) or (
            isinstance(e, ControlChange) and e.control == 64))


def _merge(spans: list[tuple[float, float]], gap: float = 0.0) -> list[tuple[float, float]]:
    out: list[list[float]] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1] + gap:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


# ------------------------------------------------------------------ audio
def read_wav(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """(samples (n, channels) float in [-1, 1], rate) of a 16-bit PCM WAV file."""
    try:
        with wave.open(str(path)) as w:
            if w.getsampwidth() != 2:
                raise ConfigError(f"{path}: only 16-bit WAV files are read")
            data = np.frombuffer(w.readframes(w.getnframes()), "<i2")
            return data.reshape(-1, w.getnchannels()).astype(np.float64) / 32768.0, \
                w.getframerate()
    except (OSError, EOFError, wave.Error) as exc:
        raise ConfigError(f"{path}: not a WAV file ({exc})") from None


def db(x: float) -> float:
    return 20.0 * math.log10(max(x, 1e-10))


def audio_report(perf: Performance, wav: str | os.PathLike) -> dict[str, Any]:
    """Levels per section and where sound and notes disagree, for a show's WAV file.

    The WAV's first sample is the show's start (``stage play --audio``). Returns
    {"seconds", "sections": [{name, start, end, rms_db, peak_db}], "silent": [(a, b)],
    "silent_while_notes": [(a, b)], "sound_without_notes": [(a, b)]} (seconds).
    """
    audio, rate = read_wav(wav)
    n = int(WINDOW_S * rate)
    frames = len(audio) // n
    blocks = audio[: frames * n].reshape(frames, n, -1)
    rms = np.sqrt((blocks ** 2).mean(axis=(1, 2)))
    quiet = 20.0 * np.log10(np.maximum(rms, 1e-10)) < SILENCE_DB
    out: dict[str, Any] = {"seconds": len(audio) / rate, "sections": []}
    for s in perf.sections:
        a, b = int(s.start * rate), int(min(s.end, len(audio) / rate) * rate)
        part = audio[a:b]
        out["sections"].append({"name": s.name, "start": s.start, "end": s.end,
                                "rms_db": db(float(np.sqrt((part ** 2).mean()))) if len(part)
                                else -200.0,
                                "peak_db": db(float(np.abs(part).max())) if len(part)
                                else -200.0})
    silent = _runs(quiet, True)
    loud = _runs(quiet, False)
    sounding = perf.sounding()
    ringing = perf.ringing(TAIL_S)
    out["silent"] = [r for r in silent if r[1] - r[0] >= MIN_STRETCH_S]
    out["silent_while_notes"] = [r for r in _intersect(silent, sounding)
                                 if r[1] - r[0] >= MIN_STRETCH_S]
    out["sound_without_notes"] = [r for r in _subtract(loud, ringing)
                                  if r[1] - r[0] >= WINDOW_S * 2]
    return out


def _runs(mask: np.ndarray, value: bool) -> list[tuple[float, float]]:
    """Stretches (seconds) where ``mask`` equals ``value``."""
    out, start = [], None
    for k, m in enumerate(mask):
        if m == value and start is None:
            start = k
        elif m != value and start is not None:
            out.append((start * WINDOW_S, k * WINDOW_S))
            start = None
    if start is not None:
        out.append((start * WINDOW_S, len(mask) * WINDOW_S))
    return out


def _intersect(a: list[tuple[float, float]], b: list[tuple[float, float]]):
    out = []
    for x0, x1 in a:
        for y0, y1 in b:
            lo, hi = max(x0, y0), min(x1, y1)
            if hi > lo:
                out.append((lo, hi))
    return out


def _subtract(a: list[tuple[float, float]], b: list[tuple[float, float]]):
    out = []
    for x0, x1 in a:
        pieces = [(x0, x1)]
        for y0, y1 in b:
            pieces = [p for q0, q1 in pieces for p in ((q0, min(q1, y0)), (max(q0, y1), q1))
                      if p[1] > p[0]]
        out.extend(pieces)
    return out


def audio_lines(report: dict[str, Any]) -> list[str]:
    """``audio_report`` in words."""
    spans = lambda rs: ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in rs) or "none"  # noqa: E731
    out = [f"audio: {report['seconds']:.1f} s"]
    for s in report["sections"]:
        out.append(f"  {s['start']:6.1f}-{s['end']:6.1f} s  {s['name']}: RMS "
                   f"{s['rms_db']:.1f} dBFS, peak {s['peak_db']:.1f} dBFS")
    out.append(f"  silent (below {SILENCE_DB:g} dBFS for {MIN_STRETCH_S:g} s or more): "
               f"{spans(report['silent'])}")
    out.append(f"  silent while notes sound: {spans(report['silent_while_notes'])}")
    out.append(f"  sound while no note sounds (beyond a {TAIL_S:g} s release): "
               f"{spans(report['sound_without_notes'])}")
    return out


# ------------------------------------------------------------------ the grid
def grid_check(perf: Performance, piece: Any) -> list[tuple[dict, str, bool]]:
    """(phrase, its quantize, on the grid?) for every phrase played, against ``piece``.

    The grid is the runtime's: the piece's tempo and meter from the start; a section
    at another tempo starts its own grid where it begins.
    """
    from ..piece.music import meter_beats
    from ..piece.voices import Grid
    bar = float(meter_beats(piece.meter)) if piece.meter else 4.0
    grids: dict[str, Grid] = {}
    grid = Grid(0.0, piece.tempo, bar)
    for s in perf.sections:
        tempo = piece.section(s.name).tempo or piece.tempo
        if tempo != grid.tempo:
            grid = Grid(s.start, tempo, bar)
        grids[s.name] = grid
    out = []
    for p in perf.phrases.values():
        section = piece.section(p["section"])
        trig = next((t for t in [*section.triggers, *piece.triggers] if t.name == p["trigger"]),
                    None)
        unit = (trig.quantize if trig is not None else None) or section.quantize or \
            piece.quantize
        out.append((p, unit, grids[p["section"]].on(p["t"], unit)))
    return out


def grid_lines(perf: Performance, piece: Any) -> list[str]:
    checked = grid_check(perf, piece)
    quantised = [c for c in checked if c[1] not in (None, "none")]
    off = [c for c in quantised if not c[2]]
    units = sorted({c[1] for c in quantised})
    out = [f"grid: {len(quantised) - len(off)} of {len(quantised)} quantised phrase starts on "
           f"the grid ({', '.join(units) or 'nothing quantised'}, {piece.tempo:g} bpm"
           + (f", {piece.meter}" if piece.meter else "") + ")"]
    for p, unit, _ in off:
        out.append(f"  off the {unit}: {p['phrase']} at {p['t']:.3f} s ({p['trigger']})")
    return out
