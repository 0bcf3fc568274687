"""Musical time and voices: the beat grid, and what sounds and waits on each output.

``Grid``: a tempo and a meter give beats and bars counted from an origin (the
piece's start, or the start of a section at another tempo). A quantised phrase
starts on the first beat or bar line at or after the moment its trigger fired.

``Voices``: every phrase and note action a piece plays goes through
``Voices.play``, which applies its output's voice policy when something still
sounds or waits there:

* ``queue`` (the default): it starts when what sounds and waits has ended,
  on the grid; a trigger whose earlier phrase still waits is not heard again
  (a hesitating hand does not pile phrases up);
* ``layer``: it sounds at once, with the others;
* ``replace``: it cuts the others where it starts (an ``AllNotesOff``);
* ``ignore``: it is not played.

Voices keep the notes they scheduled, so the runtime can say what really
sounded. The MIDI view applies the same rules to the same events
(``stage_plugins.midi.schedule``): an ``AllNotesOff`` cancels the notes it
finds not yet begun and ends the sounding ones; a key struck again while it
sounds ends the earlier note first. Each such note is reported once, as a
``NoteCut`` event.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

from ..events import AllNotesOff, ControlChange, Event, Note, NoteCut, PhrasePlayed, PhraseSkipped

#: times closer than this are the same moment (sums of float beat lengths)
EPS = 1e-6
#: CC numbers of the ending
SUSTAIN, EXPRESSION = 64, 11
#: the ending's expression fade is sent in steps this far apart (seconds)
FADE_STEP_S = 0.05
#: how long scheduled notes are kept after they end (for the honest count of cuts)
KEEP_S = 1.0


class Grid:
    """Beats and bars from ``origin`` (engine seconds) at ``tempo`` quarter notes a minute."""

    def __init__(self, origin: float, tempo: float, beats_per_bar: float = 4.0) -> None:
        self.origin, self.tempo, self.beats_per_bar = origin, tempo, beats_per_bar

    @property
    def beat(self) -> float:
        return 60.0 / self.tempo

    def step(self, unit: str | None) -> float:
        return self.beat * (self.beats_per_bar if unit == "bar" else 1.0)

    def next(self, t: float, unit: str | None) -> float:
        """The first beat/bar line at or after ``t`` (``t`` itself for none)."""
        if unit in (None, "none"):
            return t
        step = self.step(unit)
        k = math.ceil((t - self.origin) / step - EPS)
        return self.origin + k * step

    def on(self, t: float, unit: str | None, tolerance: float = 1e-3) -> bool:
        """Whether ``t`` lies on the grid (within ``tolerance`` seconds)."""
        if unit in (None, "none"):
            return True
        step = self.step(unit)
        k = round((t - self.origin) / step)
        return abs(self.origin + k * step - t) <= tolerance

    def where(self, t: float) -> str:
        """'bar 12 beat 1' (counted from 1) for the console."""
        beats = (t - self.origin) / self.beat
        bar = math.floor(beats / self.beats_per_bar + EPS)
        beat = beats - bar * self.beats_per_bar
        return f"bar {bar + 1} beat {beat + 1:.3g}"


@dataclass(eq=False, slots=True)
class _Sched:
    """One note as scheduled (its duration shrinks when it is cut)."""

    t: float
    output: str
    channel: int
    key: int
    duration: float
    play: int
    cut: bool = False

    @property
    def end(self) -> float:
        return self.t + self.duration


@dataclass(eq=False, slots=True)
class Planned:
    """A phrase or note action scheduled on an output."""

    id: int
    output: str
    name: str
    trigger: str
    firing: int
    start: float
    end: float
    notes: list[_Sched] = field(default_factory=list)


class Voices:
    """The voices of a piece's MIDI outputs (see the module docstring).

    policies: output -> queue | layer | replace | ignore. emit: where events go
    (the runtime's output list). counts: the runtime's counters; ``notes`` is
    kept as the notes that sound (scheduled minus cancelled), ``cancelled`` and
    ``shortened`` count the cuts.
    """

    def __init__(self, policies: dict[str, str], emit: Callable[[Event], None],
                 counts: dict[str, int]) -> None:
        self.policies = dict(policies)
        self.emit = emit
        self.counts = counts
        for key in ("notes", "cancelled", "shortened", "skipped"):
            counts.setdefault(key, 0)
        self.planned: list[Planned] = []
        self._keys: dict[tuple[str, int, int], list[_Sched]] = {}
        self._ids = 0
        #: (output, channel) -> last value sent per controller, for the ending's fade
        self.controls: dict[tuple[str, int, int], int] = {}
        self.channels: set[tuple[str, int]] = set()
        #: AllNotesOff still to come (t, output, channel, why): the MIDI view will end the
        #: notes sounding then, even those scheduled after it
        self._cuts: list[tuple[float, str | None, int | None, str]] = []

    # ------------------------------------------------------------ reading
    def busy_until(self, output: str | None = None) -> float:
        """When what sounds and waits on ``output`` (None: every output) ends; -inf if nothing."""
        return max((p.end for p in self.planned if output is None or p.output == output),
                   default=float("-inf"))

    def last_note_end(self) -> float:
        """When the last scheduled note ends (-inf if none)."""
        return max((s.end for v in self._keys.values() for s in v), default=float("-inf"))

    def would_skip(self, output: str, policy: str | None, trigger: str, firing: int,
                   now: float) -> str:
        """Why a phrase on ``output`` would not be played now ("" if it would)."""
        policy = policy or self.policy(output)
        mine = [p for p in self.planned if p.output == output and p.end > now - EPS]
        if policy == "ignore" and any(p.end > now + EPS for p in mine):
            return f"'{output}' is still playing (ignore)"
        if policy == "queue" and any(p.trigger == trigger and p.firing != firing
                                     and p.start > now + EPS for p in mine):
            return "its previous phrase is still waiting (queue)"
        return ""

    def policy(self, output: str) -> str:
        return self.policies.get(output, "queue")

    # ------------------------------------------------------------ playing
    def play(self, *, output: str, name: str, length: float, now: float, grid: Grid,
             quantize: str | None, render: Callable[[float, int], list[Note]],
             trigger: str, firing: int, section: str, policy: str | None = None,
             channel: int | None = None) -> tuple[Planned | None, str]:
        """Schedule a phrase: ``render(start, id)`` gives its notes once its start is known.

        length: its musical length in seconds (when the next may start). Returns
        (the planned phrase, "") or (None, why it was not played).
        """
        self.prune(now)
        policy = policy or self.policy(output)
        start = grid.next(now, quantize)
        busy = self.busy_until(output)
        why = self.would_skip(output, policy, trigger, firing, now)
        if not why and policy == "queue" and busy > start + EPS:
            start = grid.next(busy, quantize)
        if why:
            self.counts["skipped"] += 1
            self.emit(PhraseSkipped(now, output, name, section, trigger, why))
            return None, why
        if policy == "replace" and busy > start + EPS:
            self.cut(start, output, channel, f"replaced by {name}")
        self._ids += 1
        notes = render(start, self._ids)
        planned = Planned(self._ids, output, name, trigger, firing, start, start + length)
        self.emit(PhrasePlayed(start, output, name, self._ids, section, trigger, start + length,
                               len(notes), now, policy))
        for note in notes:
            sched = _Sched(note.t, note.output, note.channel, note.note, note.duration, note.play)
            self.emit(note)
            self._strike(sched, name)
            self._later_cut(sched)
            planned.notes.append(sched)
            self._keys.setdefault((note.output, note.channel, note.note), []).append(sched)
            self.channels.add((note.output, note.channel))
        self.counts["notes"] += len(notes)
        self.planned.append(planned)
        return planned, ""

    def _strike(self, new: _Sched, name: str) -> None:
        """A key struck while another note holds it: the MIDI view ends the earlier one."""
        for other in self._keys.get((new.output, new.channel, new.key), ()):
            if other.cut and other.duration <= 0.0:
                continue
            if other.t - EPS <= new.t < other.end - EPS:
                self._shorten(other, new.t, f"struck again by {name}")
            elif new.t < other.t < new.end - EPS:   # ``other`` will strike the new one
                self._shorten(new, other.t, "struck again")

    def _later_cut(self, new: _Sched) -> None:
        """A note scheduled after an AllNotesOff that will come while it sounds."""
        for t, output, channel, why in self._cuts:
            if (output is None or output == new.output) and \
                    (channel is None or channel == new.channel) and new.t < t < new.end - EPS:
                self._shorten(new, t, why)
                return

    def _shorten(self, s: _Sched, t: float, why: str) -> None:
        sounded = max(0.0, t - s.t)
        self.emit(NoteCut(t, s.output, s.channel, s.key, s.t, s.duration, sounded, s.play, why))
        if sounded <= EPS:
            self.counts["cancelled"] += 1
            self.counts["notes"] -= 1
            sounded = 0.0
        else:
            self.counts["shortened"] += 1
        s.duration, s.cut = sounded, True

    def cut(self, t: float, output: str | None, channel: int | None, why: str) -> None:
        """Silence ``output`` (None: all) from ``t``: an AllNotesOff, and the honest account."""
        self._cuts.append((t, output, channel, why))
        for notes in self._keys.values():
            for s in notes:
                if (output is not None and s.output != output) or \
                        (channel is not None and s.channel != channel):
                    continue
                if s.end > t + EPS and not (s.cut and s.duration <= 0.0):
                    self._shorten(s, t, why)
        self.emit(AllNotesOff(t, output, channel))
        kept = []
        for p in self.planned:
            hit = (output is None or p.output == output) and (
                channel is None or all(n.channel == channel for n in p.notes))
            if hit and p.start >= t - EPS:
                continue                 # it had not begun: nothing of it will sound
            if hit and p.end > t:
                p.end = t
            kept.append(p)
        self.planned = kept

    def retract(self, t: float, trigger: str, firing: int, why: str) -> int:
        """Cut short, from ``t``, what firing number ``firing`` of ``trigger`` played (its notes
        not yet ended: a NoteCut each, which the MIDI view honours); returns how many."""
        cut = 0
        kept = []
        for p in self.planned:
            if p.trigger == trigger and p.firing == firing:
                for s in p.notes:
                    if s.end > t + EPS and not (s.cut and s.duration <= 0.0):
                        self._shorten(s, t, why)
                        cut += 1
                if p.start >= t - EPS:
                    continue
                p.end = min(p.end, t)
            kept.append(p)
        self.planned = kept
        return cut

    def prune(self, now: float) -> None:
        """Forget what has ended (a show may run for weeks)."""
        self.planned = [p for p in self.planned if p.end > now - EPS]
        self._cuts = [c for c in self._cuts if c[0] > now]
        old = now - KEEP_S
        if any(s.end < old for notes in self._keys.values() for s in notes[:1]):
            self._keys = {k: kept for k, v in self._keys.items()
                          if (kept := [s for s in v if s.end >= old])}

    # ------------------------------------------------------------ the ending
    def ending(self, now: float, last_end: float, fade: float) -> float:
        """Hold the last notes (sustain) and fade them (expression) from ``last_end``.

        Returns when the fade is over. The notes sounding when the last onset before
        ``last_end`` begins are held; expression falls from its last value to 0 in
        steps of ``FADE_STEP_S``, then the pedal lifts (the held notes end, silent).
        """
        if fade <= 0.0:
            return last_end
        notes = [s for v in self._keys.values() for s in v
                 if s.duration > 0.0 and s.t < last_end - EPS]
        onset = max((s.t for s in notes), default=now)
        pedal = max(now, onset + 0.02)
        held = sorted({(s.output, s.channel) for s in notes if s.end > pedal})
        targets = held or sorted(self.channels)
        stop = last_end + fade
        steps = max(1, int(round(fade / FADE_STEP_S)))
        for output, channel in targets:
            if held:
                self.emit(ControlChange(pedal, output, channel, SUSTAIN, 127))
            start = self.controls.get((output, channel, EXPRESSION), 127)
            for k in range(1, steps + 1):
                u = k / steps
                self.emit(ControlChange(last_end + u * fade, output, channel, EXPRESSION,
                                        int(round(start * (1.0 - u)))))
            if held:
                self.emit(ControlChange(stop, output, channel, SUSTAIN, 0))
        return stop

    def restore(self, t: float) -> None:
        """Expression back to its value before the fade (the synthesizer outlives the piece)."""
        for output, channel in sorted(self.channels):
            self.emit(ControlChange(t, output, channel, EXPRESSION,
                                    self.controls.get((output, channel, EXPRESSION), 127)))

    def note_control(self, event: ControlChange) -> None:
        """Remember a control change the piece sent (the fade starts from the last value)."""
        self.controls[(event.output, event.channel, event.control)] = event.value
