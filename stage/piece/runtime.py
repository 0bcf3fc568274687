"""The piece at play time: an engine listener that turns fused bodies into events.

``PieceRuntime`` runs on the engine thread (``engine.listeners``): per frame
it updates zone occupancy, evaluates the current section's triggers and
mappings (and the piece-wide ones), runs the actions of the triggers that
fire and hands one list of ``stage.events`` to the sink. Phrase notes carry
their future times and durations; the views schedule them. Time comes only
from frames (``frame.t``) and ``tick(t)``, so an offline run with a manual
clock gives the same events every time for the same seed.

Thread rule: call ``on_frame``/``__call__``, ``tick``, ``goto`` and ``stop``
from one thread only (the engine's; other threads go through
``engine.call_soon``).
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ..frames import FusedFrame
from ..events import ControlChange, Event, EventSink, SectionChange, TriggerFired, ZoneState
from .actions import Actions, FireContext, holds
from .anticipation import anticipate, confirmed, contradicted
from .mappings import MappingRun
from .model import Piece, Section, Trigger, joint_label
from .music import meter_beats
from .sinks import FanoutSink, RecordingSink
from .triggers import ClockDetector, Detector, Firing, Person, PresenceDetector, detector_for
from .voices import EPS, Grid, Voices

log = logging.getLogger("stage.piece")

__all__ = ["PieceRuntime", "RecordingSink", "FanoutSink", "Narrator"]

#: narrator(t, text): readable lines for the console ("what fires")
Narrator = Callable[[float, str], None]


class _TriggerRun:
    """A trigger with its detector and the state that decides whether a firing sounds."""

    __slots__ = ("trigger", "detector", "last", "fired_in_visit", "ahead", "pending", "waiting")

    def __init__(self, trigger: Trigger) -> None:
        self.trigger = trigger
        self.detector: Detector = detector_for(trigger)
        self.last: dict = {}
        self.fired_in_visit = False
        #: anticipation: the same detector on the bodies predicted ahead, and the firings
        #: made on a prediction the measurements have not yet confirmed:
        #: (person, joint) -> (fired at, contradicted unless measured by, firing number)
        self.ahead: Detector | None = detector_for(trigger) if trigger.anticipate else None
        self.pending: dict[tuple, tuple[float, float, int]] = {}
        #: predicted crossings not yet sure enough to fire: (person, joint) -> first seen at
        self.waiting: dict[tuple, list] = {}

    def cooldown_key(self, f: Firing):
        scope = self.trigger.cooldown_per
        return None if scope == "trigger" else f.person if scope == "performer" else (f.person,
                                                                                     f.joint)

    def reset(self) -> None:
        self.detector.reset()
        self.fired_in_visit = False
        if self.ahead is not None:
            self.ahead.reset()
            self.pending.clear()
            self.waiting.clear()


class PieceRuntime:
    """Evaluates a piece against fused frames; an ``engine.listeners`` entry.

    piece: a loaded Piece. sink: where events go (``.emit(list)``, must not
    block). seed: the aleatoric choices (None: the piece's seed, else 0).
    """

    def __init__(self, piece: Piece, sink: EventSink, seed: int | None = None,
                 narrator: Narrator | None = None) -> None:
        self.piece, self.sink, self.narrator = piece, sink, narrator
        self.seed = seed if seed is not None else (piece.seed if piece.seed is not None else 0)
        self.rng = np.random.default_rng(self.seed)
        self.min_conf = piece.defaults.min_confidence
        self.section: Section = piece.section(piece.start)
        self.started = False
        self.ending = False         # 'goto: end' happened: the last phrase plays, then the fade
        self.ended = False          # the piece is over: its last notes have rung out
        self.ends_at = float("inf")  # when it will be over (once ending)
        self.started_at = 0.0
        self.section_start = 0.0
        self.arrivals: dict[int, float] = {}
        self.persons: dict[int, Person] = {}
        self.before: dict[int, Person] = {}     # the frame before's
        self._chosen: dict = {}                 # performer selector -> persons, this frame
        self.empty_since: float | None = None
        self.zone_members: dict[str, set[int]] = {name: set() for name in piece.zones}
        self._global = [_TriggerRun(t) for t in piece.triggers]
        self._global_maps = [MappingRun(m) for m in piece.mappings]
        self._runs: dict[int, list[_TriggerRun]] = {
            s.index: [_TriggerRun(t) for t in s.triggers] for s in piece.sections}
        self._maps: dict[int, list[MappingRun]] = {
            s.index: [MappingRun(m) for m in s.mappings] for s in piece.sections}
        self.actions = Actions(self)
        self._pending_goto: tuple[str, str, bool] | None = None
        #: a section change waiting for the sounding phrases: (target, cause, when)
        self.transition: tuple[str, str, float] | None = None
        self._out: list[Event] = []
        self.visited: list[str] = []
        #: "notes" counts the notes that sound (scheduled, less those cancelled before
        #: their onset); "cancelled", "shortened" and "skipped" (phrases) are the rest
        self.counts = {"frames": 0, "fired": 0, "notes": 0, "cancelled": 0, "shortened": 0,
                       "skipped": 0, "errors": 0, "section_changes": 0, "idle": 0,
                       # anticipation (docs/anticipation.md): fired on a prediction, then
                       # confirmed or contradicted by the measurements; predicted crossings
                       # too uncertain to fire on; frames without the forecast asked for
                       "anticipated": 0, "confirmed": 0, "contradicted": 0, "unsure": 0,
                       "forecast_missing": 0}
        #: the piece sees every body this far past its capture time (0: as measured)
        self.forecast_s = piece.forecast_s
        self._ahead: dict[float, dict[int, Person]] = {}   # this frame's predicted persons
        self._frame: FusedFrame | None = None
        self.voices = Voices(piece.overlap, self._emit, self.counts)
        self.grid = Grid(0.0, piece.tempo, float(meter_beats(piece.meter)) if piece.meter else 4.0)
        self._firings = 0
        self._before_idle: str | None = None    # the section the idle section interrupted
        self._last_error_log = float("-inf")

    @property
    def last_note_end(self) -> float:
        """Engine time when the last note scheduled so far ends (-inf if none)."""
        return self.voices.last_note_end()

    def _emit(self, event: Event) -> None:
        self._out.append(event)

    # ------------------------------------------------------------ entry points
    def __call__(self, frame: FusedFrame) -> None:
        self.on_frame(frame)

    def start(self, t: float) -> None:
        """Enter the start section (emits SectionChange(cause="start") and its on_enter)."""
        if self.started:
            return
        self.started, self.started_at = True, t
        self.grid.origin = t
        self._enter(self.section, None, t, "start")
        self._flush()

    def on_frame(self, frame: FusedFrame) -> None:
        """Evaluate one fused frame. Never raises: a bug is logged and the show goes on."""
        try:
            self._on_frame(frame)
        except Exception:
            self._error(frame.t, "frame skipped")

    def tick(self, t: float) -> None:
        """Time passes without frames (nobody on stage): time-based triggers."""
        try:
            if not self.started:
                self.start(t)
            if self.ended:
                return
            self._due(t)
            if self.ended:
                self._flush()
                return
            contradicted(self, t)
            self._clock_triggers(t, self._active_runs())
            self._idle(t)
            self._apply_goto(t)
            self._flush()
        except Exception:
            self._error(t, "tick skipped")

    def goto(self, target: str, t: float, cause: str = "operator") -> bool:
        """Force a section change at once (the cellist's or operator's safety); 'end' begins
        the ending. False if nothing changed."""
        try:
            if not self.started:
                self.start(t)
            if self.ending or self.ended:
                return False
            if target == "end":
                self._begin_ending(t, cause, now=False)
                self._flush()
                return True
            self.transition = None
            changed = self._change_section(target, t, cause)
            self._flush()
            return changed
        except Exception:
            self._error(t, "section change failed")
            return False

    def _error(self, t: float, what: str) -> None:
        """A bug must not end the show: count it, log the first of each minute with its traceback."""
        self.counts["errors"] += 1
        self._out.clear()
        if t - self._last_error_log >= 60.0:
            self._last_error_log = t
            log.exception("piece runtime error at t=%.3f (%s; %d so far, the next ones are "
                          "logged once a minute)", t, what, self.counts["errors"])

    def stop(self, t: float) -> None:
        """End of the show: cancel pending notes and silence every output (each cut logged)."""
        self.voices.cut(t, None, None, "stop")
        self._flush()

    # ------------------------------------------------------------ frame
    def _active_runs(self) -> list[_TriggerRun]:
        if self.transition is not None or self.ending:
            return self._global     # the section has said its last word
        return self._runs[self.section.index] + self._global

    def _on_frame(self, frame: FusedFrame) -> None:
        t = frame.t
        if not self.started:
            self.start(t)
        self.counts["frames"] += 1
        if self.ended:
            return
        self._due(t)
        if self.ended:
            self._flush()
            return
        min_conf, arrivals = self.min_conf, self.arrivals
        persons = {}
        bodies = frame.bodies
        if self.forecast_s > 0:
            ahead = frame.forecasts.get(self.forecast_s)
            if ahead is None:
                self.counts["forecast_missing"] += 1   # the engine was not asked: as measured
            else:
                bodies = ahead
        self._frame = frame
        self._ahead = {}
        for pid, body in bodies.items():
            since = arrivals.get(pid)
            if since is None:
                since = arrivals[pid] = t
            persons[pid] = Person(body, min_conf, since)
        self.before, self.persons = self.persons, persons   # anticipation looks for jumps
        self._chosen = {}
        if frame.lost:
            for pid in frame.lost:
                arrivals.pop(pid, None)
            for run in self._all_runs():
                run.detector.forget(frame.lost)
                if run.ahead is not None:
                    run.ahead.forget(frame.lost)
                    for key in [k for k in run.pending if k[0] in frame.lost]:
                        del run.pending[key]   # the person is gone: nothing to contradict
                    for key in [k for k in run.waiting if k[0] in frame.lost]:
                        del run.waiting[key]
        if persons:
            self.empty_since = None
        elif self.empty_since is None:
            self.empty_since = t
        if self.zone_members:
            self._zones(t, persons)
        runs = self._active_runs()
        plist = list(persons.values())
        firings: list[Firing] = []
        for run in runs:
            trig = run.trigger
            det = run.detector
            if isinstance(det, PresenceDetector):
                det.presence(frame.new, frame.lost, firings)
            elif isinstance(det, ClockDetector):
                continue
            else:
                chosen = plist if trig.performer == "any" else self._select(trig.performer)
                if chosen:
                    det.frame(t, chosen, firings)
                    if run.ahead is not None:
                        anticipate(self, run, t, chosen)
            if firings:
                for f in firings:
                    if run.waiting:
                        run.waiting.pop((f.person, f.joint), None)   # measured: no more waiting
                    if run.pending and run.pending.pop((f.person, f.joint), None) is not None:
                        confirmed(self, run, f, t)   # measured as predicted: fired already
                        continue
                    self._consider(run, f, t)
                firings.clear()
        contradicted(self, t)
        self._clock_triggers(t, runs)
        for mrun in (*self._maps[self.section.index], *self._global_maps):
            if self.ending and mrun.mapping.kind == "cc":
                continue      # the ending's fade owns the sound; OSC mappings go on
            mrun.update(self, t)
        self._idle(t)
        self._apply_goto(t)
        self._flush()

    def _all_runs(self):
        for runs in self._runs.values():
            yield from runs
        yield from self._global

    def _select(self, performer) -> list[Person]:
        chosen = self._chosen.get(performer)
        if chosen is None:
            chosen = self._chosen[performer] = self._choose(performer)
        return chosen

    def _choose(self, performer) -> list[Person]:
        persons = self.persons
        if not persons:
            return []
        if isinstance(performer, int):
            p = persons.get(performer)
            return [p] if p is not None else []
        if performer == "first":
            return [min(persons.values(), key=lambda p: (p.since, p.id))]
        return [max(persons.values(), key=lambda p: (p.since, p.id))]  # newest

    def _zones(self, t: float, persons: dict[int, Person]) -> None:
        for name, zone in self.piece.zones.items():
            members = self.zone_members[name]
            now = set()
            for pid, p in persons.items():
                x, y, z = p.position
                if zone.contains(x, y, z, zone.hysteresis if pid in members else 0.0):
                    now.add(pid)
            if now != members:
                self.zone_members[name] = now
                if bool(now) != bool(members) or now:
                    self._out.append(ZoneState(t, name, bool(now), tuple(sorted(now))))

    def _clock_triggers(self, t: float, runs: list[_TriggerRun]) -> None:
        if not self.persons and self.empty_since is None:
            self.empty_since = t
        firings: list[Firing] = []
        for run in runs:
            if isinstance(run.detector, ClockDetector):
                run.detector.check(t, self.section_start, self.empty_since, firings)
                for f in firings:
                    self._consider(run, f, t)
                firings.clear()

    # ------------------------------------------------------------ firing
    def _consider(self, run: _TriggerRun, f: Firing, t: float, anticipated: float = 0.0) -> bool:
        """Whether the firing sounds (cooldown, once, after, while, probability), and if so
        its actions."""
        trig = run.trigger
        if trig.after and t - self.section_start < trig.after:
            return False
        if trig.once and run.fired_in_visit:
            return False
        person = self.persons.get(f.person) if f.person is not None else None
        if trig.condition is not None and not holds(trig.condition, person, f.joint):
            return False
        key = run.cooldown_key(f)
        last = run.last.get(key)
        if last is not None and t - last < trig.cooldown:
            return False
        run.last[key] = t
        if trig.probability < 1.0 and self.rng.random() >= trig.probability:
            self._narrate(t, f"[{self.section.index + 1}] {trig.name}: (silence, by chance)")
            return False
        run.fired_in_visit = True
        self.counts["fired"] += 1
        self._firings += 1
        joint = None if f.joint is None else joint_label(f.joint)
        self._out.append(TriggerFired(t, self.section.name, trig.name, f.person, joint,
                                      None if f.value is None else round(float(f.value), 4),
                                      anticipated))
        quantize = trig.quantize or self.section.quantize or self.piece.quantize
        ctx = FireContext(t, self, trig.name, f.person, person, f.joint, f.value, f.speed,
                          quantize, self._firings, f.detail)
        done = [self.actions.act(a, ctx) for a in trig.actions]
        who = "" if f.person is None else f" [person {f.person}" + (
            f", {joint}" if joint else "") + (f" {f.value:.2f}" if f.value is not None else "") + "]"
        ahead = f" (predicted {anticipated * 1000:.0f} ms ahead)" if anticipated else ""
        self._narrate(t, f"[{self.section.index + 1}] {trig.name}{who}{ahead} -> "
                         f"{'; '.join(d for d in done if d)}")
        return True

    # ------------------------------------------------------------ sections
    def _idle(self, t: float) -> None:
        """The piece's attract section: entered when the room has been empty ``after`` s,
        left (``back``) as soon as someone is on stage. A goto asked for in this frame wins."""
        idle = self.piece.idle
        if idle is None or self._pending_goto is not None:
            return
        in_idle = self.section.name == idle.section
        if not in_idle and not self.persons and self.empty_since is not None \
                and t - self.empty_since >= idle.after:
            self._before_idle = self.section.name
            self.counts["idle"] += 1
            self._pending_goto = (idle.section, "idle", False)   # the phrase may finish
        elif in_idle and self.persons and self._before_idle is not None:
            back = idle.back
            target = (self.piece.start if back == "start" else
                      self._before_idle if back == "previous" else back)
            self._before_idle = None
            if target != self.section.name:
                self._pending_goto = (target, "someone arrived", True)   # answer a visitor at once

    def _apply_goto(self, t: float) -> None:
        if self._pending_goto is None:
            return
        target, cause, now = self._pending_goto
        self._pending_goto = None
        if self.ending or self.ended:
            return
        if target == "end":
            self._begin_ending(t, cause, now)
            return
        at = self.voices.busy_until()
        if now or at <= t + EPS:
            self.transition = None
            self._change_section(target, t, cause)
        elif self.transition is None:     # the first decision stands
            self.transition = (target, cause, at)
            self._narrate(t, f"[{self.section.index + 1}] {cause}: moving on ({target}) when "
                             f"the sounding phrase ends, in {at - t:.1f} s")

    def _due(self, t: float) -> None:
        """What the clock brings: a waiting section change, the end of the ending."""
        if self.transition is not None and t >= self.transition[2] - EPS:
            target, cause, at = self.transition
            self.transition = None
            self._change_section(target, t, cause, at)
        if self.ending and t >= self.ends_at - EPS:
            self.ended = True
            self._narrate(t, "== the end == the last notes have rung out; nothing acts any more")

    def _begin_ending(self, t: float, cause: str, now: bool) -> None:
        """'goto: end': the last phrase finishes, its last notes are held and faded, the room
        rings; triggers of the whole piece (exits) act until then."""
        ending = self.piece.ending
        last_end = t if now else max(t, self.voices.busy_until())
        fade_end = self.voices.ending(t, last_end, ending.fade)
        self.ending, self.transition = True, None
        self.ends_at = fade_end + ending.ring
        if fade_end > last_end:
            self.voices.restore(self.ends_at)
        self._narrate(t, f"== the ending == ({cause}): the last phrase ends in "
                         f"{last_end - t:.1f} s, fades for {ending.fade:g} s and rings for "
                         f"{ending.ring:g} s: over in {self.ends_at - t:.1f} s")

    def _change_section(self, target: str, t: float, cause: str,
                        at: float | None = None) -> bool:
        """Enter ``target`` now (``at``: the musical moment it was due, for the grid)."""
        sections = self.piece.sections
        current = self.section
        if self.ended or self.ending:
            return False
        if target == "next":
            if current.next is not None:
                new = self.piece.section(current.next)
            elif current.index + 1 < len(sections):
                new = sections[current.index + 1]
            else:
                self._narrate(t, f"{cause}: already in the last section")
                return False
        elif target == "previous":
            if current.index == 0:
                self._narrate(t, f"{cause}: already in the first section")
                return False
            new = sections[current.index - 1]
        else:
            try:
                new = self.piece.section(target)
            except KeyError:
                log.warning("no section called %r", target)
                return False
        for run in self._maps[current.index]:
            if run.active and run.mapping.otherwise is not None:
                run.send(self._out, t, run.mapping.otherwise, force=True)
            run.active, run.smoothed, run.sent = False, None, None
        self._enter(new, current, t, cause, at)
        return True

    def _enter(self, new: Section, previous: Section | None, t: float, cause: str,
               at: float | None = None) -> None:
        tempo = new.tempo or self.piece.tempo
        if tempo != self.grid.tempo:    # a new tempo: its grid starts with the section
            self.grid.origin, self.grid.tempo = (t if at is None else at), tempo
        self.section, self.section_start = new, t
        self.visited.append(new.name)
        if previous is not None:
            self.counts["section_changes"] += 1
        for run in self._runs[new.index]:
            run.reset()
        for run in self._global:
            if isinstance(run.detector, ClockDetector) and run.trigger.kind == "elapsed":
                run.detector.fired = False
        self._out.append(SectionChange(t, new.name, previous.name if previous else None,
                                       new.index, cause))
        n = len(self.piece.sections)
        self._narrate(t, f"== section {new.index + 1}/{n}: {new.name} =="
                         + (f" ({cause})" if cause != "start" else "")
                         + (f" -- {new.about}" if new.about else ""))
        self._firings += 1
        ctx = FireContext(t, self, "on_enter", None, None, None, None, 0.0,
                          new.quantize or self.piece.quantize, self._firings)
        done = [self.actions.act(a, ctx) for a in new.on_enter]
        if done:
            self._narrate(t, f"on entering {new.name} -> {'; '.join(done)}")

    # ------------------------------------------------------------ output
    def _narrate(self, t: float, text: str) -> None:
        if self.narrator is not None:
            try:
                self.narrator(t, text)
            except Exception:
                log.exception("narrator failed")

    def _flush(self) -> None:
        if self._out:
            events, self._out = self._out, []
            if not self.ending:   # the fade starts from the last expression the piece sent
                for e in events:
                    if isinstance(e, ControlChange):
                        self.voices.note_control(e)
            self.sink.emit(events)


