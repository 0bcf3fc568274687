"""Compiling a piece's actions (what a firing trigger does): the loader's part for ``do:``.

``ActionCompiler`` is mixed into the loader's compiler; it uses its ``error``,
``defaults``, ``phrases``, ``outputs``, ``section_names``, ``_output`` and
``_unknown``. Errors are one-line ``ConfigError``s at ``file:line:column``.
"""

from __future__ import annotations

from typing import Any

from ..errors import MusicError
from ..joints import GROUPS, JOINT_INDEX, suggest_joint
from ..yamlio import Mark
from . import language as L
from .model import (BODY, Action, Goto, Play, PlayNote, Section, SendCC, SendOsc, SendProgram,
                    Silence)
from .music import parse_chord

_REFS = ("x", "y", "z", "speed", "value", "person", "joint", "section", "trigger", "time",
         "step_length", "step_width", "step_time")


def m(d: dict, key: str) -> Mark | None:
    """Where the value of ``key`` was written in a checked mapping."""
    return d.get("__marks__", {}).get(key, d.get("__mark__"))


def joint_indices(name: str) -> tuple[int, ...]:
    if name == "body":
        return (BODY,)
    if name in GROUPS:
        return tuple(JOINT_INDEX[j] for j in GROUPS[name])
    return (JOINT_INDEX[name],)


_m = m


class ActionCompiler:
    """The ``do:`` lists of triggers and ``on_enter`` of sections, compiled to model actions."""

    def _action(self, a: dict, section: Section | None, where: str) -> Action:
        kind = next(k for k in ("play", "note", "cc", "program", "osc", "goto", "silence")
                    if k in a)
        value, mark = a[kind], _m(a, kind)
        d = self.defaults
        if kind == "play":
            return self._play(value, mark, section)
        if kind == "note":
            spec = value if isinstance(value, dict) else {"pitch": value, "__mark__": mark,
                                                          "__marks__": {}}
            try:
                pitches = parse_chord(spec["pitch"])
            except MusicError as exc:
                raise self.error(str(exc), _m(spec, "pitch")) from None
            if "beats" in spec and "seconds" in spec:
                raise self.error("a note takes 'beats' or 'seconds', not both", _m(spec, "seconds"))
            return PlayNote(pitches, beats=spec.get("beats", None if "seconds" in spec else 1.0),
                            seconds=spec.get("seconds"), velocity=spec.get("velocity"),
                            channel=spec.get("channel", d.channel),
                            output=self._output(spec.get("output"), "midi", mark, "a note"),
                            arpeggiate=spec.get("arpeggiate", d.arpeggiate),
                            overlap=spec.get("overlap"))
        if kind == "cc":
            return SendCC(value["control"], value["value"], value.get("channel", d.channel),
                          self._output(value.get("output"), "midi", mark, "a control change"))
        if kind == "program":
            spec = value if isinstance(value, dict) else {"program": value}
            return SendProgram(spec["program"], spec.get("channel", d.channel),
                               self._output(spec.get("output"), "midi", mark, "a program change"))
        if kind == "osc":
            spec = value if isinstance(value, dict) else {"address": value}
            args = spec.get("args", [])
            marks = getattr(args, "marks", [mark] * len(args))
            funcs = tuple(self._osc_arg(arg, marks[k]) for k, arg in enumerate(args))
            return SendOsc(spec["address"], funcs,
                           self._output(spec.get("output"), "osc", mark, "an OSC message"),
                           tuple(str(x) for x in args))
        if kind == "goto":
            spec = value if isinstance(value, dict) else {"to": value}
            target = spec["to"]
            if target not in ("next", "previous", "end") and target not in self.section_names:
                where = _m(spec, "to") if isinstance(value, dict) else mark
                raise self.error(self._unknown("section", target, self.section_names)
                                 + " (or next, previous, end)", where)
            return Goto(target, now=spec.get("now", False))
        if value != "all" and value not in self.outputs:
            raise self.error(self._unknown("output", value, self.outputs) + " (or all)", mark)
        return Silence(None if value == "all" else value)

    def _play(self, value: Any, mark: Mark | None, section: Section | None) -> Play:
        spec = value if isinstance(value, dict) else (
            {"pick": value} if value in L.PICKS else {"phrase": value})
        if "phrase" in spec and ("pick" in spec or "from" in spec):
            raise self.error("'play' takes a fixed 'phrase' or 'pick'/'from', not both", mark)
        pool = spec.get("from")
        for k, name in enumerate(pool or []):
            if name not in self.phrases:
                raise self.error(self._unknown("phrase", name, self.phrases), pool.marks[k])
        if "phrase" in spec and spec["phrase"] not in self.phrases:
            where = _m(spec, "phrase") if isinstance(value, dict) else mark
            raise self.error(self._unknown("phrase", spec["phrase"], self.phrases), where)
        if "phrase" not in spec and pool is None and section is not None and not section.phrases:
            raise self.error(f"section '{section.name}' has no phrases to {spec.get('pick', 'random')}"
                             " from; list them under its 'phrases' or give 'from'", mark)
        if spec.get("interrupt") and "overlap" in spec:
            raise self.error("'interrupt' is 'overlap: replace' for the phrase's channel; give "
                             "one of them", _m(spec, "overlap"))
        weights = spec.get("weights")
        if weights is not None:
            count = len(pool) if pool is not None else len(section.phrases) if section else None
            if spec.get("pick", "random") != "random":
                raise self.error("'weights' only apply to pick: random", _m(spec, "weights"))
            if count is not None and len(weights) != count:
                raise self.error(f"'weights' needs one number per phrase ({count}), got "
                                 f"{len(weights)}", _m(spec, "weights"))
            if sum(weights) <= 0:
                raise self.error("'weights' must not all be 0", _m(spec, "weights"))
        return Play(phrase=spec.get("phrase"), pick=spec.get("pick", "random"),
                    pool=tuple(pool) if pool is not None else None,
                    weights=tuple(weights) if weights is not None else None,
                    velocity=spec.get("velocity"), transpose=spec.get("transpose", 0),
                    interrupt=spec.get("interrupt", False), overlap=spec.get("overlap"))

    def _osc_arg(self, arg: Any, mark: Mark | None):
        if not isinstance(arg, str) or not arg.startswith("$"):
            return lambda ctx, v=arg: v
        ref = arg[1:]
        if ref in _REFS:
            return lambda ctx, r=ref: ctx.ref(r)
        joint, _, axis = ref.partition(".")
        if joint not in JOINT_INDEX:
            hint = suggest_joint(joint)
            if hint in JOINT_INDEX:
                raise self.error(f"unknown joint '{joint}' in '{arg}'; did you mean "
                                 f"'${hint}.{axis or 'y'}'?", mark)
            raise self.error(f"'{arg}' is not a reference; expected ${', $'.join(_REFS)} or "
                             "$Joint.x/.y/.z/.speed (e.g. $HandLeft.y)", mark)
        if axis not in ("x", "y", "z", "speed"):
            raise self.error(f"'{arg}': a joint reference ends in .x, .y, .z or .speed", mark)
        index = JOINT_INDEX[joint]
        return lambda ctx, j=index, a=axis: ctx.joint_ref(j, a)
