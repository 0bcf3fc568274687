"""Actions: what a firing trigger does, turned into events (the runtime's helpers).

``Actions.act`` appends events to the runtime's output list and returns a
readable description for the console. The aleatoric state (which phrase was
picked last, the shuffle bags) lives here, fed by the runtime's seeded
generator, so a seed reproduces every choice.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..events import ControlChange, Note, OscOut, PhraseSkipped, ProgramChange
from ..joints import JOINTS
from .model import (BODY, Action, Condition, Goto, Phrase, Play, PlayNote, SendCC, SendOsc,
                    SendProgram, Silence, joint_label, voice_times)
from .triggers import Person


@dataclass(slots=True)
class FireContext:
    """What an action knows about the firing that caused it (for $references)."""

    t: float
    runtime: Any
    trigger: str
    pid: int | None            # the performer's id (also when they just left)
    person: Person | None
    joint: int | None
    value: float | None
    speed: float
    quantize: str | None = None    # beat | bar | none: where phrases and notes start
    firing: int = 0                # which firing (a trigger's phrases queue per firing)
    detail: dict | None = None     # step: gait's step_length, step_width, step_time

    def ref(self, name: str):
        if name in ("x", "y", "z"):
            if self.person is None:
                return 0.0
            pos = self.person.xyz(self.joint if self.joint is not None else BODY) \
                or self.person.joint(self.joint)
            return float(pos["xyz".index(name)])
        if name == "speed":
            return float(self.speed)
        if name == "value":
            return 0.0 if self.value is None else float(self.value)
        if name == "person":
            return -1 if self.pid is None else int(self.pid)
        if name == "joint":
            return "" if self.joint is None else joint_label(self.joint)
        if name == "section":
            return self.runtime.section.name
        if name == "trigger":
            return self.trigger
        if name.startswith("step_"):
            value = (self.detail or {}).get(name)
            return 0.0 if value is None else float(value)
        return float(self.t - self.runtime.started_at)  # "time"

    def joint_ref(self, j: int, axis: str):
        if self.person is None:
            return 0.0
        if axis == "speed":
            return float(self.person.speed(j))
        return float(self.person.joint(j)["xyz".index(axis)])


def holds(cond: Condition, person: Person | None, joint: int | None) -> bool:
    """Whether a ``while:`` condition holds for ``person`` (``joint``: the trigger's)."""
    if person is None:
        return False
    j = cond.joint if cond.joint is not None else (joint if joint is not None else BODY)
    pos = person.xyz(j)
    if pos is None:
        return False
    x, y, z = pos
    if cond.inside is not None and not cond.inside.contains(x, y, z):
        return False
    if cond.outside is not None and cond.outside.contains(x, y, z):
        return False
    for level, is_joint, sign in ((cond.above, cond.above_joint, 1.0),
                                  (cond.below, cond.below_joint, -1.0)):
        if level is None:
            continue
        if is_joint:
            ref = person.xyz(int(level))
            if ref is None:
                return False
            level = ref[1]
        if sign * (y - level) <= 0.0:
            return False
    if cond.hand is not None:
        name = JOINTS[j] if j != BODY else ""
        sides = (0,) if name.endswith("Left") else (1,) if name.endswith("Right") else (0, 1)
        if not any(person.hands[s] == cond.hand for s in sides):
            return False
    return True


class Actions:
    """Runs actions for a PieceRuntime (``rt``): its piece, section, generator and output."""

    def __init__(self, runtime: Any) -> None:
        self.rt = runtime
        self.picks: dict[tuple, list] = {}     # pool -> [last picked, cycle index, shuffle bag]

    def act(self, action: Action, ctx: FireContext) -> str:
        """Do one action: its events go to the runtime's output; returns what it did, in words."""
        t, out, rt = ctx.t, self.rt._out, self.rt
        if isinstance(action, Play):
            return self.play(action, ctx)
        if isinstance(action, PlayNote):
            return self.note(action, ctx)
        if isinstance(action, SendCC):
            value = action.value if isinstance(action.value, int) else \
                min(127, max(0, self.velocity("speed", ctx, 0)))
            out.append(ControlChange(t, action.output, action.channel - 1, action.control, value))
            return f"cc {action.control} = {value}"
        if isinstance(action, SendProgram):
            out.append(ProgramChange(t, action.output, action.channel - 1, action.program))
            return action.describe()
        if isinstance(action, SendOsc):
            args = tuple(f(ctx) for f in action.args)
            out.append(OscOut(t, action.output, action.address, args))
            return f"osc {action.address}" + (f" {' '.join(_fmt(a) for a in args)}" if args else "")
        if isinstance(action, Goto):
            if rt._pending_goto is None:  # one section change per frame: the first wins
                rt._pending_goto = (action.target, ctx.trigger, action.now)
            return action.describe()
        if isinstance(action, Silence):
            rt.voices.cut(t, action.output, None, "silence")
            return action.describe()
        raise TypeError(f"unknown action {action!r}")

    def velocity(self, spec, ctx: FireContext, default: int) -> int:
        """A number, "speed" (from the firing's speed via defaults) or None (``default``)."""
        if spec is None:
            return default
        if spec == "speed":
            return self.rt.piece.defaults.velocity_for(ctx.speed)
        return int(spec)

    def tempo(self, phrase: Phrase | None) -> float:
        if phrase is not None and phrase.tempo is not None:
            return phrase.tempo
        return self.rt.section.tempo or self.rt.piece.tempo

    def note(self, action: PlayNote, ctx: FireContext) -> str:
        rt = self.rt
        name = action.describe()
        velocity = self.velocity(action.velocity, ctx, rt.piece.defaults.velocity)
        value = action.seconds if action.seconds is not None else \
            action.beats * 60.0 / self.tempo(None)
        gate, channel = rt.piece.defaults.gate, action.channel - 1

        def render(start: float, play: int) -> list[Note]:
            return [Note(onset, action.output, channel, pitch, velocity, length, play)
                    for onset, length, pitch in voice_times(start, value, gate,
                                                            list(action.pitches),
                                                            action.arpeggiate)]
        if rt.ending:
            return self._skip(action.output, name, ctx, "the piece is ending")
        planned, why = rt.voices.play(
            output=action.output, name=name, length=value, now=ctx.t, grid=rt.grid,
            quantize=ctx.quantize, render=render, trigger=ctx.trigger, firing=ctx.firing,
            section=rt.section.name, policy=action.overlap, channel=channel)
        if planned is None:
            return f"{name} not played: {why}"
        return f"{name} v{velocity}" + self._when(planned.start, ctx)

    def play(self, action: Play, ctx: FireContext) -> str:
        rt = self.rt
        policy = "replace" if action.interrupt else action.overlap
        fixed = rt.piece.phrases[action.phrase] if action.phrase else None
        pool = action.pool if action.pool is not None else rt.section.phrases
        outputs = sorted({fixed.output} if fixed else {rt.piece.phrases[p].output for p in pool})
        what = action.phrase or action.pick
        if rt.ending and outputs:
            return self._skip(outputs[0], what, ctx, "the piece is ending")
        if len(outputs) == 1:   # decide before choosing: a phrase not played is not 'next'
            why = rt.voices.would_skip(outputs[0], policy, ctx.trigger, ctx.firing, ctx.t)
            if why:
                return self._skip(outputs[0], what, ctx, why)
        name = action.phrase or self.pick(action)
        if name is None:
            return "nothing to play (the section has no phrases)"
        phrase = rt.piece.phrases[name]
        velocity = None if action.velocity is None else \
            self.velocity(action.velocity, ctx, phrase.velocity)
        tempo = self.tempo(phrase)

        def render(start: float, play: int) -> list[Note]:
            return phrase.render(start, tempo, velocity, action.transpose, play)
        planned, why = rt.voices.play(
            output=phrase.output, name=name, length=phrase.seconds(tempo), now=ctx.t,
            grid=rt.grid, quantize=ctx.quantize, render=render, trigger=ctx.trigger,
            firing=ctx.firing, section=rt.section.name, policy=policy,
            channel=phrase.channel - 1 if action.interrupt else None)
        if planned is None:
            return f"phrase {name} not played: {why}"
        return (f"phrase {name} ({len(planned.notes)} notes"
                + (f", v{velocity}" if velocity else "") + ")" + self._when(planned.start, ctx))

    def _skip(self, output: str, what: str, ctx: FireContext, why: str) -> str:
        """A phrase not played: counted, logged (PhraseSkipped) and said."""
        self.rt.counts["skipped"] += 1
        self.rt._out.append(PhraseSkipped(ctx.t, output, what, self.rt.section.name,
                                          ctx.trigger, why))
        return f"{what} not played: {why}"

    def _when(self, start: float, ctx: FireContext) -> str:
        """' in 0.6 s (bar 4 beat 1)' when a phrase does not start at once."""
        if start <= ctx.t + 1e-6:
            return ""
        return f" in {start - ctx.t:.1f} s ({self.rt.grid.where(start)})"

    def pick(self, action: Play) -> str | None:
        """The phrase to play: random (weighted, never twice in a row), next, or shuffle."""
        pool = action.pool if action.pool is not None else self.rt.section.phrases
        if not pool:
            return None
        key = (pool, action.pick)
        state = self.picks.get(key)
        if state is None:
            state = self.picks[key] = [None, -1, []]
        if len(pool) == 1:
            choice = pool[0]
        elif action.pick == "next":
            state[1] = (state[1] + 1) % len(pool)
            choice = pool[state[1]]
        elif action.pick == "shuffle":
            if not state[2]:
                order = [pool[k] for k in self.rt.rng.permutation(len(pool))]
                if order[0] == state[0]:  # no repeat across the refill either
                    order.append(order.pop(0))
                state[2] = order
            choice = state[2].pop(0)
        else:
            weights = np.asarray(action.weights if action.weights else [1.0] * len(pool), float)
            if state[0] is not None and len(pool) > 1:
                weights = weights * np.array([p != state[0] for p in pool], float)
            if weights.sum() <= 0:
                weights = np.ones(len(pool))
            choice = pool[int(self.rt.rng.choice(len(pool), p=weights / weights.sum()))]
        state[0] = choice
        return choice


def _fmt(value) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)
