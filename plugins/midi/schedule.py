"""Piece events in, timed MIDI bytes out: the MIDI view's pure core.

No clock, no ports: the caller says what time it is (``due(now)``) and sends
what comes out. Every note carries its own duration, so its note-off is
scheduled when the note is added, at ``t + duration`` exactly, not on some
later frame.

Rules:
- at equal times, note-offs go before note-ons (a note repeated back to back
  is re-struck, not cut);
- a note struck again while it still sounds (same output, channel, key) gets
  a note-off first; the earlier note's own note-off is then void;
- ``AllNotesOff`` silences every matching sounding note at its time, cancels
  the matching notes that were scheduled before it and have not started, and
  adds a controller 123 (all notes off) per channel used, for synths that
  hold notes we did not start;
- a ``NoteCut`` whose ``why`` is ``contradicted`` (a trigger fired on a predicted
  crossing the measurements did not make, docs/anticipation.md) ends that note
  at its time, or cancels it if it has not begun; other NoteCuts are the
  piece's account of what the rules above already do, and change nothing.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import NamedTuple

from stage.events import AllNotesOff, ControlChange, Event, Note, NoteCut, ProgramChange

NOTE_ON, NOTE_OFF, CONTROL, PROGRAM = 0x90, 0x80, 0xB0, 0xC0
ALL_NOTES_OFF_CC = 123


class Out(NamedTuple):
    """One MIDI message due: ``t`` engine clock (the time it was meant for), bytes to send."""

    t: float
    output: str
    data: bytes


@dataclass(eq=False, slots=True)
class _Note:
    id: int
    output: str
    channel: int
    key: int
    velocity: int
    seq: int
    state: str = "pending"   # pending, sounding, done, cancelled
    onset: float = 0.0       # its Note's time
    play: int = 0            # its Note's phrase id


@dataclass(order=True, slots=True)
class _Entry:
    t: float
    order: int                       # 0: note-off, 1: everything else (same-time offs first)
    seq: int
    kind: str = field(compare=False)
    payload: object = field(compare=False)


class MidiScheduler:
    """Schedules the MIDI of piece events; ``stats`` counts what happened."""

    def __init__(self, late_s: float = 0.005) -> None:
        self.late_s = late_s
        self._heap: list[_Entry] = []
        self._seq = 0
        self._pending: dict[int, _Note] = {}
        self._sounding: dict[tuple[str, int, int], _Note] = {}
        self._used: dict[str, set[int]] = {}   # output -> channels that got a note
        self.stats = {"notes": 0, "controls": 0, "programs": 0, "all_notes_off": 0,
                      "cancelled": 0, "retriggered": 0, "late": 0, "bad": 0}
        self.last_bad: str | None = None

    # ------------------------------------------------------------ input
    def add(self, event: Event, now: float, output: str | None = None) -> bool:
        """Schedule one event (``output`` overrides ``event.output``); False if it is invalid."""
        problem = _check(event)
        if problem:
            self.stats["bad"] += 1
            self.last_bad = f"{type(event).__name__}: {problem}"
            return False
        if event.t < now - self.late_s:
            self.stats["late"] += 1
        self._seq += 1
        seq = self._seq
        name = output if output is not None else getattr(event, "output", None)
        if isinstance(event, Note):
            note = _Note(seq, name, event.channel, event.note, event.velocity, seq,
                         onset=event.t, play=event.play)
            self._pending[note.id] = note
            heapq.heappush(self._heap, _Entry(event.t, 1, seq, "on", note))
            heapq.heappush(self._heap, _Entry(event.t + event.duration, 0, seq, "off", note))
        elif isinstance(event, ControlChange):
            heapq.heappush(self._heap, _Entry(event.t, 1, seq, "data", (
                name, bytes((CONTROL | event.channel, event.control, event.value)))))
        elif isinstance(event, ProgramChange):
            heapq.heappush(self._heap, _Entry(event.t, 1, seq, "data", (
                name, bytes((PROGRAM | event.channel, event.program)))))
        elif isinstance(event, NoteCut):
            if event.why != "contradicted":
                self._seq -= 1
                return True      # the account of a cut this schedule makes by itself
            heapq.heappush(self._heap, _Entry(event.t, 0, seq, "cut", (
                name, event.channel, event.note, event.onset, event.play)))
        elif isinstance(event, AllNotesOff):
            heapq.heappush(self._heap, _Entry(event.t, 0, seq, "alloff", (output or event.output,
                                                                          event.channel)))
        else:
            self._seq -= 1
            return False
        return True

    def next_time(self) -> float | None:
        return self._heap[0].t if self._heap else None

    # ------------------------------------------------------------ output
    def due(self, now: float) -> list[Out]:
        """Every message whose time has come, in time order."""
        out: list[Out] = []
        heap = self._heap
        while heap and heap[0].t <= now:
            entry = heapq.heappop(heap)
            if entry.kind == "on":
                self._note_on(entry.t, entry.payload, out)  # type: ignore[arg-type]
            elif entry.kind == "off":
                self._note_off(entry.t, entry.payload, out)  # type: ignore[arg-type]
            elif entry.kind == "cut":
                self._cut(entry.t, entry.payload, out)  # type: ignore[arg-type]
            elif entry.kind == "data":
                output, data = entry.payload  # type: ignore[misc]
                self.stats["controls" if data[0] & 0xF0 == CONTROL else "programs"] += 1
                out.append(Out(entry.t, output, data))
            else:
                output, channel = entry.payload  # type: ignore[misc]
                self.stats["all_notes_off"] += 1
                out.extend(self._silence(entry.t, output, channel, entry.seq))
        return out

    def silence(self, now: float, output: str | None = None,
                channel: int | None = None) -> list[Out]:
        """Everything matching off now and every matching pending note cancelled (stop)."""
        self._seq += 1
        return self._silence(now, output, channel, self._seq)

    @property
    def sounding(self) -> int:
        return len(self._sounding)

    @property
    def pending(self) -> int:
        return len(self._pending)

    def _note_on(self, t: float, note: _Note, out: list[Out]) -> None:
        if note.state != "pending":
            return
        del self._pending[note.id]
        key = (note.output, note.channel, note.key)
        previous = self._sounding.get(key)
        if previous is not None:  # struck again while sounding: end the old one first
            previous.state = "done"
            self.stats["retriggered"] += 1
            out.append(Out(t, note.output, bytes((NOTE_OFF | note.channel, note.key, 0))))
        note.state = "sounding"
        self._sounding[key] = note
        self._used.setdefault(note.output, set()).add(note.channel)
        self.stats["notes"] += 1
        out.append(Out(t, note.output, bytes((NOTE_ON | note.channel, note.key, note.velocity))))

    def _note_off(self, t: float, note: _Note, out: list[Out]) -> None:
        if note.state != "sounding":
            return
        note.state = "done"
        key = (note.output, note.channel, note.key)
        if self._sounding.get(key) is note:
            del self._sounding[key]
        out.append(Out(t, note.output, bytes((NOTE_OFF | note.channel, note.key, 0))))

    def _cut(self, t: float, which: tuple, out: list[Out]) -> None:
        """End (or cancel) the one note a NoteCut names: output, channel, key, onset, play."""
        output, channel, key, onset, play = which
        for nid, note in list(self._pending.items()):
            if (note.output, note.channel, note.key, note.play) == (output, channel, key, play) \
                    and abs(note.onset - onset) < 1e-9:
                note.state = "cancelled"
                del self._pending[nid]
                self.stats["cancelled"] += 1
                return
        note = self._sounding.get((output, channel, key))
        if note is not None and note.play == play and abs(note.onset - onset) < 1e-9:
            self._note_off(t, note, out)

    def _silence(self, t: float, output: str | None, channel: int | None,
                 seq: int) -> list[Out]:
        def matches(o: str, c: int) -> bool:
            return (output is None or o == output) and (channel is None or c == channel)

        out: list[Out] = []
        for key, note in list(self._sounding.items()):
            if matches(note.output, note.channel):
                self._note_off(t, note, out)
        for nid, note in list(self._pending.items()):
            if note.seq < seq and matches(note.output, note.channel):
                note.state = "cancelled"
                del self._pending[nid]
                self.stats["cancelled"] += 1
        for o, channels in self._used.items():
            for c in sorted(channels):
                if matches(o, c):
                    out.append(Out(t, o, bytes((CONTROL | c, ALL_NOTES_OFF_CC, 0))))
        return out


def _check(event: Event) -> str | None:
    """Why ``event`` cannot become MIDI, or None."""
    t = getattr(event, "t", None)
    if not isinstance(t, (int, float)) or not math.isfinite(t):
        return f"time {t!r} is not a finite number"
    fields = {Note: (("channel", 0, 15), ("note", 0, 127), ("velocity", 1, 127)),
              ControlChange: (("channel", 0, 15), ("control", 0, 127), ("value", 0, 127)),
              ProgramChange: (("channel", 0, 15), ("program", 0, 127))}.get(type(event), ())
    for name, lo, hi in fields:
        value = getattr(event, name)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            return f"{name} {value!r} is not a whole number {lo}-{hi}"
    if isinstance(event, Note):
        d = event.duration
        if not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0:
            return f"duration {d!r} is not a positive number of seconds"
    if isinstance(event, AllNotesOff) and event.channel is not None and (
            isinstance(event.channel, bool) or not isinstance(event.channel, int)
            or not 0 <= event.channel <= 15):
        return f"channel {event.channel!r} is not a whole number 0-15"
    return None
