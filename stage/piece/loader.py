"""Load a piece file: check it against the language, then resolve names and music.

Every problem is a ``ConfigError`` whose message is one line,
``file:line:column: what is wrong; what was expected`` (with a spelling
suggestion where one is likely); the first problem found is reported.
"""

from __future__ import annotations

import os
from typing import Any

from ..errors import ConfigError, MusicError
from ..analysis.features import ANGLES
from ..events import OutputDecl
from ..joints import JOINT_INDEX, JOINTS, parse_hand_state
from ..network import parse_hostport
from ..yamlio import Mark, Where, load_marked, loads_marked
from . import language as L
from .model import (ANTICIPATING, Anticipation, Condition, Defaults, Ending, Idle, Mapping, Phrase, Piece, Safety,
                    Section, Trigger, Zone, curve_function)
from .loader_actions import ActionCompiler, joint_indices as _joint_indices, m as _m
from .music import phrase_notes
from .spec import did_you_mean

_DIRECTIONS = {"up": (0.0, 1.0, 0.0), "down": (0.0, -1.0, 0.0), "downstage": (0.0, 0.0, 1.0),
               "upstage": (0.0, 0.0, -1.0), "stage_left": (1.0, 0.0, 0.0),
               "stage_right": (-1.0, 0.0, 0.0)}
_HAND_JOINTS = {"HandLeft", "HandRight", "HandTipLeft", "HandTipRight", "ThumbLeft", "ThumbRight",
                "WristLeft", "WristRight", "hands", "wrists"}
_FOOT_JOINTS = {"FootLeft", "FootRight", "AnkleLeft", "AnkleRight", "feet", "ankles"}
_JOINTLESS = ("appears", "disappears", "stage_empty", "elapsed")


def load_piece(path: str | os.PathLike) -> Piece:
    """Read, check and compile a piece file. ConfigError (one line, file:line:column) if wrong."""
    path = str(path)
    return _Compiler(path).compile(load_marked(path))


def loads_piece(text: str, path: str = "<piece>") -> Piece:
    """The same from text (tests, editors)."""
    return _Compiler(path).compile(loads_marked(text, path))


class _Compiler(ActionCompiler):
    def __init__(self, path: str) -> None:
        self.path = path
        self.where = Where(path)
        self.defaults = Defaults()
        self.zones: dict[str, Zone] = {}
        self.phrases: dict[str, Phrase] = {}
        self.outputs: dict[str, OutputDecl] = {}
        self.overlap: dict[str, str] = {}
        self.section_names: list[str] = []
        self.meter: str | None = None

    def error(self, message: str, mark: Mark | None) -> ConfigError:
        return self.where.error(message, mark)

    def compile(self, raw: Any) -> Piece:
        if raw is None:
            raise self.error("the file is empty; a piece needs at least 'piece' and 'sections'",
                             None)
        data = L.PIECE.check(raw, getattr(raw, "mark", None), "the piece", self.where)
        self.defaults = self._defaults(data.get("defaults"))
        self.outputs = self._outputs(data)
        self.meter = data.get("meter")
        self.tempo = data.get("tempo", 60.0)
        quantize = self._quantize(data, "the piece") or "none"
        self.zones = {name: self._zone(name, z) for name, z in data.get("zones", {}).items()}
        phrases = data.get("phrases", {})
        self.phrases = {name: self._phrase(name, p, getattr(phrases, "marks", {}).get(name))
                        for name, p in phrases.items()}
        sections = data["sections"]
        seen: dict[str, Mark | None] = {}
        for s in sections:
            if s["name"] in seen:
                raise self.error(f"two sections are called '{s['name']}'; names must differ",
                                 _m(s, "name"))
            seen[s["name"]] = _m(s, "name")
        self.section_names = [s["name"] for s in sections]
        piece = Piece(
            title=data["piece"], path=self.path, outputs=self.outputs, zones=self.zones,
            phrases=self.phrases, composer=data.get("composer", ""), about=data.get("about", ""),
            tempo=self.tempo, meter=self.meter, seed=data.get("seed"), defaults=self.defaults,
            quantize=quantize, overlap=dict(self.overlap), forecast_s=data.get("forecast_s", 0.0),
            sections=[self._section(k, s) for k, s in enumerate(sections)])
        if "ending" in data:
            e = data["ending"]
            piece.ending = Ending(fade=e.get("fade", Ending.fade), ring=e.get("ring", Ending.ring))
        piece.triggers = [self._trigger(t, None) for t in data.get("triggers", [])]
        piece.mappings = [self._mapping(m) for m in data.get("mappings", [])]
        piece.start = data.get("start", sections[0]["name"])
        if piece.start not in self.section_names:
            raise self.error(self._unknown("section", piece.start, self.section_names),
                             _m(data, "start"))
        if "rehearsal" in data:
            base = os.path.dirname(os.path.abspath(self.path)) if os.path.exists(self.path) else ""
            piece.rehearsal = os.path.join(base, data["rehearsal"]) if base else data["rehearsal"]
        if "safety" in data:
            s = data["safety"]
            piece.safety = Safety(keys=s.get("keys", False), osc_port=s.get("osc_port"))
        if "idle" in data:
            idle = data["idle"]
            for key in ("section", "back"):
                name = idle.get(key)
                if name is not None and name not in self.section_names and not (
                        key == "back" and name in ("start", "previous")):
                    raise self.error(self._unknown("section", name, self.section_names),
                                     _m(idle, key))
            piece.idle = Idle(float(idle["after"]), idle["section"], idle.get("back", "start"))
        return piece

    # ------------------------------------------------------------ top level
    def _defaults(self, d: dict | None) -> Defaults:
        if not d:
            return Defaults()
        values = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()
                  if not k.startswith("__")}
        for key in ("speed_range", "velocity_range"):
            if key in values and values[key][0] == values[key][1]:
                raise self.error(f"'{key}' in 'defaults' needs two different numbers", _m(d, key))
        if "velocity_range" in values and not all(1 <= v <= 127 for v in values["velocity_range"]):
            raise self.error("'velocity_range' in 'defaults' must be within 1-127",
                             _m(d, "velocity_range"))
        if "anticipate" in values:
            values["anticipate"] = self._anticipation(d["anticipate"])
        return Defaults(**values)

    def _anticipation(self, value) -> Anticipation | None:
        """``anticipate:`` as written (seconds, or a mapping), None for 0."""
        if isinstance(value, dict):
            min_p, trend, persist = value.get("min_p"), value.get("trend"), value.get("persist")
            a = Anticipation(float(value["ahead"]), float(value.get("max_sd", Anticipation.max_sd)),
                             float(value.get("within", Anticipation.within)),
                             bool(value.get("cut", False)),
                             None if min_p is None else float(min_p),
                             None if trend is None else float(trend),
                             None if persist is None else int(persist))
        else:
            a = Anticipation(float(value))
        return a if a.ahead > 0 else None

    def _quantize(self, d: dict, what: str) -> str | None:
        """The ``quantize`` of a piece, section or trigger (None when not given)."""
        value = d.get("quantize")
        if value == "bar" and self.meter is None:
            raise self.error(f"'quantize: bar' in {what} needs the piece's 'meter' (e.g. "
                             "meter: 3/4)", _m(d, "quantize"))
        return value

    def _outputs(self, data: dict) -> dict[str, OutputDecl]:
        if "outputs" not in data or not data["outputs"]:
            self.overlap = {"midi": "queue"}
            return {"midi": OutputDecl("midi", "midi")}
        out = {}
        marks = data["outputs"]
        for name, value in data["outputs"].items():
            if isinstance(value, str):
                out[name] = OutputDecl(name, value)
                if value == "midi":
                    self.overlap[name] = "queue"
                continue
            for key, kind in (("overlap", "midi"), ("skeletons", "osc")):
                if key in value and value["type"] != kind:
                    raise self.error(f"output '{name}': '{key}' applies to {kind} outputs only",
                                     _m(value, key))
            if value["type"] == "midi":
                self.overlap[name] = value.get("overlap", "queue")
            target = value.get("target")
            if value["type"] == "osc" and target is not None:
                try:
                    host, port = parse_hostport(target)
                except ValueError as exc:
                    raise self.error(f"output '{name}': {exc}", _m(value, "target")) from None
                target = f"{host}:{port}"
            out[name] = OutputDecl(name, value["type"], target, value.get("skeletons", False))
        del marks
        return out

    def _output(self, name: str | None, kind: str, mark: Mark | None, what: str) -> str:
        if name is None:
            for decl in self.outputs.values():
                if decl.kind == kind:
                    return decl.name
            example = "cello: midi" if kind == "midi" else "space: osc"
            article = "an" if kind == "osc" else "a"
            raise self.error(f"{what} needs {article} {kind.upper()} output; declare one under 'outputs' "
                             f"(e.g. {example})", mark)
        decl = self.outputs.get(name)
        if decl is None:
            raise self.error(self._unknown("output", name, self.outputs), mark)
        if decl.kind != kind:
            article = "an" if kind == "osc" else "a"
            raise self.error(f"output '{name}' is {decl.kind.upper()}; {what} needs {article} "
                             f"{kind.upper()} output", mark)
        return name

    def _unknown(self, what: str, name: str, known) -> str:
        known = list(known)
        hint = did_you_mean(name, known)
        if not hint:
            hint = f"; defined: {', '.join(known)}" if known else f"; there are no {what}s"
        return f"{what} '{name}' is not defined{hint}"

    def _zone(self, name: str, z: dict) -> Zone:
        shape = z["shape"]
        allowed = {"cylinder": ("centre", "radius", "height", "bottom"),
                   "sphere": ("centre", "radius"), "box": ("min", "max")}[shape]
        needed = {"cylinder": ("centre", "radius"), "sphere": ("centre", "radius"),
                  "box": ("min", "max")}[shape]
        for key in ("centre", "radius", "height", "bottom", "min", "max"):
            if key in z and key not in allowed:
                raise self.error(f"a {shape} has no '{key}'; zone '{name}' takes "
                                 f"{', '.join(allowed)}", z["__keymarks__"].get(key))
        for key in needed:
            if key not in z:
                raise self.error(f"zone '{name}' ({shape}) needs '{key}'", z["__mark__"])
        hysteresis = z.get("hysteresis", self.defaults.hysteresis)
        about = z.get("about", "")
        if shape == "box":
            low, high = tuple(z["min"]), tuple(z["max"])
            if not all(a < b for a, b in zip(low, high)):
                raise self.error(f"zone '{name}': every 'min' coordinate must be below 'max'",
                                 _m(z, "max"))
            return Zone(name, shape, low=low, high=high, hysteresis=hysteresis, about=about)
        centre = tuple(z["centre"])
        want = 2 if shape == "cylinder" else 3
        if len(centre) != want:
            form = "[x, z] on the floor" if shape == "cylinder" else "[x, y, z]"
            raise self.error(f"zone '{name}': a {shape}'s 'centre' is {form}, got {len(centre)} "
                             "numbers", _m(z, "centre"))
        if shape == "sphere":
            return Zone(name, shape, centre=centre, radius=z["radius"], hysteresis=hysteresis,
                        about=about)
        bottom = z.get("bottom", 0.0)
        return Zone(name, shape, centre=centre, radius=z["radius"], bottom=bottom,
                    top=bottom + z.get("height", 3.0), hysteresis=hysteresis, about=about)

    def _phrase(self, name: str, p: dict, mark: Mark | None) -> Phrase:
        if name in L.PICKS:
            raise self.error(f"a phrase cannot be called '{name}': 'play: {name}' chooses "
                             "among phrases", mark)
        key = "bars" if "bars" in p else "notes"
        meter = p.get("meter", self.meter)
        if key == "bars" and meter is None:
            raise self.error(f"phrase '{name}' is written in bars but the piece has no 'meter' "
                             "(e.g. meter: 3/4)", _m(p, "bars"))
        items = p[key]
        try:
            notes = phrase_notes(items, key == "bars", meter)
        except MusicError as exc:
            index = getattr(exc, "index", 0)
            raise self.error(f"phrase '{name}': {exc}", items.marks[index]) from None
        if p.get("unit") == "seconds" and "tempo" in p:
            raise self.error(f"phrase '{name}' counts seconds; 'tempo' means nothing here",
                             _m(p, "tempo"))
        return Phrase(name, notes, unit=p.get("unit", "beats"), tempo=p.get("tempo"),
                      output=self._output(p.get("output"), "midi", _m(p, "output") if "output" in p
                                          else p["__mark__"], f"phrase '{name}'"),
                      channel=p.get("channel", self.defaults.channel),
                      velocity=p.get("velocity", self.defaults.velocity),
                      gate=p.get("gate", self.defaults.gate), transpose=p.get("transpose", 0),
                      arpeggiate=p.get("arpeggiate", self.defaults.arpeggiate),
                      about=p.get("about", ""))

    # ------------------------------------------------------------ sections
    def _section(self, index: int, s: dict) -> Section:
        names = list(s.get("phrases", []))
        for k, name in enumerate(names):
            if name not in self.phrases:
                raise self.error(self._unknown("phrase", name, self.phrases),
                                 s["phrases"].marks[k])
        nxt = s.get("next")
        if nxt is not None and nxt not in self.section_names:
            raise self.error(self._unknown("section", nxt, self.section_names), _m(s, "next"))
        section = Section(name=s["name"], index=index, about=s.get("about", "").strip(),
                          tempo=s.get("tempo"), phrases=tuple(names), next=nxt,
                          quantize=self._quantize(s, f"section '{s['name']}'"))
        self.current = section
        section.on_enter = tuple(self._action(a, section, f"'on_enter' of section '{s['name']}'")
                                 for a in s.get("on_enter", []))
        section.triggers = [self._trigger(t, section) for t in s.get("triggers", [])]
        section.mappings = [self._mapping(m) for m in s.get("mappings", [])]
        return section

    def _trigger(self, t: dict, section: Section | None) -> Trigger:
        kind = next(k for k in L.TRIGGER_KINDS if k in t)
        label = f"trigger '{t['name']}'" if "name" in t else "this trigger"
        d = self.defaults
        trig = Trigger(name=t.get("name", ""), kind=kind, performer=t.get("performer", "any"),
                       dwell=t.get("dwell", d.hand_dwell if kind == "hand" else d.dwell),
                       cooldown=t.get("cooldown", d.cooldown),
                       cooldown_per=t.get("cooldown_per", "trigger"), after=t.get("after", 0.0),
                       once=t.get("once", False), probability=t.get("probability", 1.0),
                       line=(t["__mark__"] or (0, 0))[0], quantize=self._quantize(t, label))
        value, vmark = t[kind], _m(t, kind)
        if "anticipate" in t:
            trig.anticipate = self._anticipation(t["anticipate"])
            if trig.anticipate is not None and kind not in ANTICIPATING:
                raise self.error(f"'anticipate' applies to {', '.join(ANTICIPATING)} triggers "
                                 f"(a predicted crossing of a position), not '{kind}'",
                                 _m(t, "anticipate"))
        elif kind in ANTICIPATING:
            trig.anticipate = d.anticipate
        if kind in ("appears", "disappears") and value is not True:
            raise self.error(f"write '{kind}: true' to use this trigger", vmark)
        if kind == "step" and value not in (True, "gait"):
            raise self.error("write 'step: true' (a foot is put down after a swing) or "
                             "'step: gait' (a walking step: one foot passes the other)", vmark)
        if kind == "step" and value == "gait" and "speed" in t:
            raise self.error("'speed' is the swing speed of 'step: true'; 'step: gait' takes "
                             "none", _m(t, "speed"))
        for key, owners in (("for", ("dwells",)), ("speed", ("moves", "step"))):
            if key in t and kind not in owners:
                raise self.error(f"'{key}' only applies to {' and '.join(owners)} triggers",
                                 _m(t, key))
        joint = t.get("joint")
        if kind in _JOINTLESS:
            if joint is not None:
                raise self.error(f"'{kind}' watches the whole stage; remove 'joint'", _m(t, "joint"))
        elif joint is None:
            if kind in ("enters", "leaves", "dwells"):
                joint = "body"
            elif kind == "hand":
                joint = "hands"
            elif kind == "step":
                joint = "feet"
            else:
                raise self.error(f"{label} needs 'joint' (which joint to watch for "
                                 f"'{kind}')", t["__mark__"])
        if kind == "hand" and joint not in _HAND_JOINTS:
            raise self.error(f"a hand trigger watches a hand: use HandLeft, HandRight or hands, "
                             f"not '{joint}'", _m(t, "joint"))
        if kind == "step" and joint not in _FOOT_JOINTS:
            raise self.error(f"a step trigger watches feet: use FootLeft, FootRight or feet, "
                             f"not '{joint}'", _m(t, "joint"))
        if joint is not None:
            trig.joints = _joint_indices(joint)
        if kind in ("enters", "leaves", "dwells"):
            trig.zone = self._zone_ref(value, vmark)
            trig.hysteresis = t.get("hysteresis", trig.zone.hysteresis)
            trig.duration = t.get("for", 2.0)
        elif kind in ("speed_above", "moves"):
            trig.threshold = value if kind == "speed_above" else t.get("speed", 1.0)
            trig.hysteresis = t.get("hysteresis", 0.3 * trig.threshold)
            if kind == "moves":
                vec = _DIRECTIONS[value] if isinstance(value, str) else tuple(value)
                norm = sum(v * v for v in vec) ** 0.5
                if norm == 0:
                    raise self.error("a direction cannot be [0, 0, 0]", vmark)
                trig.direction = tuple(v / norm for v in vec)
        elif kind in ("rises_above", "falls_below"):
            if isinstance(value, str):
                if value == "body" or value not in JOINT_INDEX:
                    raise self.error(f"'{kind}' takes a height or one joint, not '{value}'", vmark)
                trig.threshold_joint = JOINT_INDEX[value]
            else:
                trig.threshold = value
            trig.hysteresis = t.get("hysteresis", d.hysteresis)
        elif kind == "hand":
            trig.hand_state = parse_hand_state(value)
        elif kind == "step":
            trig.threshold = t.get("speed", 0.8)
            trig.gait = value == "gait"
        elif kind in ("stage_empty", "elapsed"):
            trig.threshold = value
        if "while" in t:
            trig.condition = self._condition(t["while"], f"'while' of {label}")
        where = f"{label}"
        trig.actions = tuple(self._action(a, section, where) for a in t["do"])
        if not trig.name:
            trig.name = trig.describe().split(" -> ")[0]
        return trig

    def _zone_ref(self, name: str, mark: Mark | None) -> Zone:
        zone = self.zones.get(name)
        if zone is None:
            raise self.error(self._unknown("zone", name, self.zones), mark)
        return zone

    def _condition(self, c: dict, what: str) -> Condition:
        keys = ("in", "not_in", "above", "below", "hand")
        if not any(k in c for k in keys):
            raise self.error(f"{what} needs at least one of: {', '.join(keys)}", c["__mark__"])
        joint = c.get("joint")
        out: dict[str, Any] = {"joint": None if joint is None else _joint_indices(joint)[0]}
        if "in" in c:
            out["inside"] = self._zone_ref(c["in"], _m(c, "in"))
        if "not_in" in c:
            out["outside"] = self._zone_ref(c["not_in"], _m(c, "not_in"))
        for key in ("above", "below"):
            if key in c:
                value = c[key]
                if isinstance(value, str):
                    if value == "body":
                        raise self.error(f"'{key}' takes a height or one joint", _m(c, key))
                    out[key], out[f"{key}_joint"] = JOINT_INDEX[value], True
                else:
                    out[key] = value
        if "hand" in c:
            out["hand"] = parse_hand_state(c["hand"])
        return Condition(**out)

    # ------------------------------------------------------------ mappings
    def _mapping(self, m: dict) -> Mapping:
        measure = m.get("measure", "height")
        label = f"mapping '{m['name']}'" if "name" in m else "this mapping"
        if measure == "distance" and "to_joint" not in m:
            raise self.error(f"{label} measures a distance: give 'to_joint'", _m(m, "measure"))
        if "to_joint" in m and measure != "distance":
            raise self.error("'to_joint' only applies to measure: distance", _m(m, "to_joint"))
        if measure == "angle" and m["joint"] not in ANGLES:
            raise self.error(f"{label} measures an angle: 'joint' must be where two segments "
                             f"meet: {', '.join(ANGLES)}", _m(m, "joint"))
        lo, hi = m["in_range"]
        if lo == hi:
            raise self.error(f"'in_range' of {label} needs two different numbers", _m(m, "in_range"))
        kind = "cc" if "cc" in m else "osc"
        target = m[kind]
        out_range = tuple(m.get("out_range", (0.0, 127.0) if kind == "cc" else (0.0, 1.0)))
        if kind == "cc" and not all(0 <= v <= 127 for v in out_range):
            raise self.error("'out_range' of a cc mapping must be within 0-127", _m(m, "out_range"))
        curve = m.get("curve", "linear")
        mapping = Mapping(
            name=m.get("name", ""), joint=_joint_indices(m["joint"])[0], measure=measure,
            to_joint=_joint_indices(m["to_joint"])[0] if "to_joint" in m else None,
            performer=m.get("performer", "first"), in_range=(lo, hi), out_range=out_range,
            curve=curve_function(curve), curve_name=str(curve), smoothing=m.get("smoothing", 0.0),
            otherwise=m.get("otherwise"), kind=kind)
        if "while" in m:
            mapping.condition = self._condition(m["while"], f"'while' of {label}")
        if kind == "cc":
            spec = target if isinstance(target, dict) else {"control": target}
            mapping.control = spec["control"]
            mapping.channel = spec.get("channel", self.defaults.channel)
            mapping.output = self._output(spec.get("output"), "midi", _m(m, "cc"), label)
        else:
            spec = target if isinstance(target, dict) else {"address": target}
            mapping.address = spec["address"]
            mapping.output = self._output(spec.get("output"), "osc", _m(m, "osc"), label)
        if not mapping.name:
            mapping.name = f"{m['joint']} {measure}"
        return mapping


__all__ = ["load_piece", "loads_piece", "JOINTS"]
