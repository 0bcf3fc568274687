"""A piece after loading: plain objects the runtime evaluates (no YAML left).

Joint references are indices into ``stage.joints.JOINTS``; ``BODY`` (-1)
means the person's torso centre (``Body.position``). Heights and positions
are stage metres, y up; times are seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any, Callable

from ..events import Note, OutputDecl
from ..joints import JOINTS, HandState
from .music import PhraseNote, pitch_name

BODY = -1


def joint_label(index: int) -> str:
    return "body" if index == BODY else JOINTS[index]


@dataclass(frozen=True)
class Anticipation:
    """A trigger that fires on a crossing predicted ``ahead`` s past the measurements."""

    ahead: float
    max_sd: float = 0.1         # m: the prediction's position s.d. must be at most this
    within: float = 0.1         # s after the predicted moment before it counts as contradicted
    cut: bool = False           # cut short what a contradicted firing played
    #: the probability (Gaussian: the predicted margin past the border over its s.d.) that
    #: the joint is past the border at the predicted moment must be at least this
    #: (None: its joint group's default, ``anticipation.GROUP_DEFAULTS``)
    min_p: float | None = None
    #: m/s the measured joint must move towards the border (None: its group's default)
    trend: float | None = None
    #: on how many frames in a row the predicted crossing must be sure enough before it
    #: fires (None: its group's default)
    persist: int | None = None


#: trigger kinds that can anticipate (a crossing of a position: zones and heights)
ANTICIPATING = ("enters", "leaves", "rises_above", "falls_below")


@dataclass(frozen=True)
class Defaults:
    cooldown: float = 0.5
    hysteresis: float = 0.05
    dwell: float = 0.0
    hand_dwell: float = 0.1
    min_confidence: float = 0.5
    channel: int = 1
    velocity: int = 80
    gate: float = 0.9
    speed_range: tuple[float, float] = (0.3, 3.0)
    velocity_range: tuple[float, float] = (40.0, 120.0)
    arpeggiate: float = 0.0          # seconds between the voices of a chord (0: together)
    anticipate: Anticipation | None = None

    def velocity_for(self, speed: float) -> int:
        """A note velocity from a joint speed (m/s), linear over the two ranges, clamped."""
        lo, hi = self.speed_range
        u = 0.0 if hi == lo else min(1.0, max(0.0, (speed - lo) / (hi - lo)))
        v_lo, v_hi = self.velocity_range
        return int(min(127, max(1, round(v_lo + u * (v_hi - v_lo)))))


@dataclass(frozen=True)
class Zone:
    """A region of the stage. ``contains`` grows the zone by ``margin`` metres (hysteresis)."""

    name: str
    shape: str                        # "box" | "cylinder" | "sphere"
    centre: tuple[float, ...] = ()    # cylinder (x, z); sphere (x, y, z)
    radius: float = 0.0
    bottom: float = 0.0               # cylinder
    top: float = 0.0                  # cylinder
    low: tuple[float, float, float] = (0.0, 0.0, 0.0)    # box
    high: tuple[float, float, float] = (0.0, 0.0, 0.0)   # box
    hysteresis: float = 0.05
    about: str = ""

    def contains(self, x: float, y: float, z: float, margin: float = 0.0) -> bool:
        if self.shape == "cylinder":
            dx, dz = x - self.centre[0], z - self.centre[1]
            r = self.radius + margin
            return dx * dx + dz * dz <= r * r and self.bottom - margin <= y <= self.top + margin
        if self.shape == "sphere":
            dx, dy, dz = x - self.centre[0], y - self.centre[1], z - self.centre[2]
            r = self.radius + margin
            return dx * dx + dy * dy + dz * dz <= r * r
        lo, hi = self.low, self.high
        return (lo[0] - margin <= x <= hi[0] + margin and lo[1] - margin <= y <= hi[1] + margin
                and lo[2] - margin <= z <= hi[2] + margin)

    def scene(self) -> dict:
        """The zone as views draw it: {"name", "shape", + parameters in stage metres}."""
        out: dict[str, Any] = {"name": self.name, "shape": self.shape}
        if self.shape == "cylinder":
            out.update(centre=list(self.centre), radius=self.radius, bottom=self.bottom,
                       height=self.top - self.bottom)
        elif self.shape == "sphere":
            out.update(centre=list(self.centre), radius=self.radius)
        else:
            out.update(min=list(self.low), max=list(self.high))
        return out

    def describe(self) -> str:
        if self.shape == "cylinder":
            return (f"cylinder r {self.radius:g} m at ({self.centre[0]:g}, {self.centre[1]:g}), "
                    f"{self.bottom:g}-{self.top:g} m high")
        if self.shape == "sphere":
            return f"sphere r {self.radius:g} m at ({', '.join(f'{v:g}' for v in self.centre)})"
        return (f"box ({', '.join(f'{v:g}' for v in self.low)}) to "
                f"({', '.join(f'{v:g}' for v in self.high)})")


@dataclass
class Phrase:
    name: str
    notes: list[PhraseNote]
    unit: str = "beats"              # "beats" | "seconds"
    tempo: float | None = None       # None: the section's or the piece's
    output: str = "midi"
    channel: int = 1                 # 1-16
    velocity: int = 80
    gate: float = 0.9
    transpose: int = 0
    arpeggiate: float = 0.0          # seconds between a chord's voices, bottom up (0: together)
    about: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def sounding(self) -> int:
        return sum(len(n.pitches) for n in self.notes)

    def length_beats(self) -> Fraction:
        return sum((n.length for n in self.notes), Fraction(0))

    def seconds(self, tempo: float) -> float:
        """The phrase's musical length (the sum of its note values) in seconds at ``tempo``."""
        scale = 60.0 / tempo if self.unit == "beats" else 1.0
        return float(self.length_beats()) * scale

    def schedule(self, tempo: float) -> list[tuple[float, float, int, int]]:
        """(onset s, sounding length s, MIDI note, velocity) at ``tempo``, cached per tempo."""
        key = tempo if self.unit == "beats" else 0.0
        cached = self._cache.get(key)
        if cached is not None:
            return cached
        scale = 60.0 / tempo if self.unit == "beats" else 1.0
        out = []
        for n in self.notes:
            pitches = [p + self.transpose for p in n.pitches if 0 <= p + self.transpose <= 127]
            value = float(n.length) * scale
            for onset, length, note in voice_times(float(n.onset) * scale, value, self.gate,
                                                   pitches, self.arpeggiate):
                out.append((onset, length, note, n.velocity or self.velocity))
        self._cache[key] = out
        return out

    def render(self, t: float, tempo: float, velocity: int | None = None,
               transpose: int = 0, play: int = 0) -> list[Note]:
        """Note events for a performance starting at engine time ``t`` (seconds).

        ``velocity``: the loudest note gets this, the others keep their ratio to it.
        """
        schedule = self.schedule(tempo)
        scale = 1.0
        if velocity is not None and schedule:
            loudest = max(v for _, _, _, v in schedule)
            scale = velocity / loudest
        ch = self.channel - 1
        return [Note(t + onset, self.output, ch, min(127, max(0, note + transpose)),
                     min(127, max(1, round(v * scale))), length, play)
                for onset, length, note, v in schedule]

    def describe(self) -> str:
        pitches = [pitch_name(p) for n in self.notes for p in n.pitches[-1:]]
        head = " ".join(pitches[:6]) + (" ..." if len(pitches) > 6 else "")
        return f"{len(self.notes)} notes ({head})"


def voice_times(onset: float, value: float, gate: float, pitches: list[int],
                arpeggiate: float = 0.0) -> list[tuple[float, float, int]]:
    """(onset s, sounding length s, MIDI note) of each voice of a note or chord.

    ``value``: the note's value in seconds; it sounds ``gate`` of it. With
    ``arpeggiate`` > 0 a chord is broken as a cellist does: voice k (from the
    bottom) enters ``k * arpeggiate`` late; each lower voice sounds with the one
    above it and gives way (2 x arpeggiate), the top voice is held to the end.
    """
    end = onset + max(0.01, value * gate)
    if arpeggiate <= 0.0 or len(pitches) < 2:
        return [(onset, end - onset, p) for p in pitches]
    voices = sorted(pitches)
    # never let the top voice enter after half of the note's value
    step = min(arpeggiate, 0.5 * value / (len(voices) - 1))
    out = []
    for k, p in enumerate(voices):
        start = onset + k * step
        stop = end if k == len(voices) - 1 else min(end, start + 2.0 * step)
        out.append((start, max(0.01, stop - start), p))
    return out


@dataclass(frozen=True)
class Condition:
    joint: int | None                       # None: the trigger's joint
    inside: Zone | None = None
    outside: Zone | None = None
    above: float | int | None = None        # float metres, or ("joint", index) via above_joint
    above_joint: bool = False
    below: float | int | None = None
    below_joint: bool = False
    hand: HandState | None = None

    def describe(self) -> str:
        parts = []
        who = "" if self.joint is None else joint_label(self.joint) + " "
        if self.inside is not None:
            parts.append(f"{who}in {self.inside.name}")
        if self.outside is not None:
            parts.append(f"{who}not in {self.outside.name}")
        if self.above is not None:
            ref = JOINTS[int(self.above)] if self.above_joint else f"{self.above:g} m"
            parts.append(f"{who}above {ref}")
        if self.below is not None:
            ref = JOINTS[int(self.below)] if self.below_joint else f"{self.below:g} m"
            parts.append(f"{who}below {ref}")
        if self.hand is not None:
            parts.append(f"hand {self.hand.wire_name}")
        return " and ".join(parts)


# ------------------------------------------------------------------ actions
@dataclass(frozen=True)
class Play:
    phrase: str | None = None                 # fixed phrase
    pick: str = "random"                      # random | next | shuffle
    pool: tuple[str, ...] | None = None       # None: the section's phrases
    weights: tuple[float, ...] | None = None
    velocity: int | str | None = None         # number, "speed" or None
    transpose: int = 0
    interrupt: bool = False
    overlap: str | None = None                # None: the output's policy

    def describe(self) -> str:
        if self.phrase:
            return f"play {self.phrase}"
        return f"play {self.pick}" + (f" of {', '.join(self.pool)}" if self.pool else "")


@dataclass(frozen=True)
class PlayNote:
    pitches: tuple[int, ...]
    beats: float | None = 1.0
    seconds: float | None = None
    velocity: int | str | None = None
    channel: int = 1
    output: str = "midi"
    arpeggiate: float = 0.0
    overlap: str | None = None

    def describe(self) -> str:
        return "note " + "+".join(pitch_name(p) for p in self.pitches)


@dataclass(frozen=True)
class SendCC:
    control: int
    value: int | str                  # 0-127 or "speed"
    channel: int = 1
    output: str = "midi"

    def describe(self) -> str:
        return f"cc {self.control} = {self.value}"


@dataclass(frozen=True)
class SendProgram:
    program: int
    channel: int = 1
    output: str = "midi"

    def describe(self) -> str:
        return f"program {self.program}"


@dataclass(frozen=True)
class SendOsc:
    address: str
    args: tuple[Callable[[Any], Any], ...] = ()   # each takes the firing context
    output: str = "osc"
    arg_text: tuple[str, ...] = ()

    def describe(self) -> str:
        return f"osc {self.address}" + (f" {' '.join(self.arg_text)}" if self.arg_text else "")


@dataclass(frozen=True)
class Goto:
    target: str                       # "next" | "previous" | "end" | a section name
    now: bool = False                 # False: when the phrases sounding and waiting have ended

    def describe(self) -> str:
        return f"go to {self.target}" + (" now" if self.now else "")


@dataclass(frozen=True)
class Silence:
    output: str | None                # None: all outputs

    def describe(self) -> str:
        return f"silence {self.output or 'all'}"


Action = Play | PlayNote | SendCC | SendProgram | SendOsc | Goto | Silence


# ------------------------------------------------------------------ rules
@dataclass
class Trigger:
    name: str
    kind: str                          # one of language.TRIGGER_KINDS
    joints: tuple[int, ...] = ()       # joint indices (BODY for the torso centre)
    performer: str | int = "any"
    zone: Zone | None = None
    threshold: float = 0.0             # m, m/s or s depending on kind
    threshold_joint: int | None = None  # rises_above/falls_below a joint of the same person
    direction: tuple[float, float, float] = (0.0, 1.0, 0.0)
    hand_state: HandState | None = None
    duration: float = 2.0              # dwells: seconds
    dwell: float = 0.0
    hysteresis: float = 0.05
    cooldown: float = 0.5
    cooldown_per: str = "trigger"
    after: float = 0.0
    once: bool = False
    probability: float = 1.0
    condition: Condition | None = None
    actions: tuple[Action, ...] = ()
    line: int = 0
    quantize: str | None = None        # beat | bar | none; None: the section's or piece's
    gait: bool = False                 # step: gait (seed 003's foot events), not step: true
    anticipate: Anticipation | None = None

    def describe(self) -> str:
        joints = "+".join(joint_label(j) for j in self.joints) if self.joints else ""
        k = self.kind
        if k in ("enters", "leaves"):
            what = f"{joints} {k} {self.zone.name}"
        elif k == "dwells":
            what = f"{joints} stays {self.duration:g} s in {self.zone.name}"
        elif k == "speed_above":
            what = f"{joints} faster than {self.threshold:g} m/s"
        elif k == "moves":
            what = f"{joints} moves {_direction_name(self.direction)} > {self.threshold:g} m/s"
        elif k in ("rises_above", "falls_below"):
            ref = JOINTS[self.threshold_joint] if self.threshold_joint is not None \
                else f"{self.threshold:g} m"
            what = f"{joints} {k.replace('_', ' ')} {ref}"
        elif k == "hand":
            what = f"{joints} {self.hand_state.wire_name}"
        elif k == "step":
            what = f"{joints} {'gait ' if self.gait else ''}step"
        elif k in ("appears", "disappears"):
            what = f"a performer {k}"
        elif k == "stage_empty":
            what = f"nobody on stage for {self.threshold:g} s"
        else:
            what = f"{self.threshold:g} s into the section"
        if self.condition is not None:
            what += f" while {self.condition.describe()}"
        return f"{what} -> {'; '.join(a.describe() for a in self.actions)}"


def _direction_name(d: tuple[float, float, float]) -> str:
    names = {(0.0, 1.0, 0.0): "up", (0.0, -1.0, 0.0): "down", (0.0, 0.0, 1.0): "downstage",
             (0.0, 0.0, -1.0): "upstage", (1.0, 0.0, 0.0): "stage_left",
             (-1.0, 0.0, 0.0): "stage_right"}
    return names.get(tuple(round(v, 6) for v in d), "[" + ", ".join(f"{v:g}" for v in d) + "]")


@dataclass
class Mapping:
    name: str
    joint: int
    measure: str = "height"           # x | y | z | height | speed | distance | angle
    to_joint: int | None = None
    performer: str | int = "first"
    in_range: tuple[float, float] = (0.0, 1.0)
    out_range: tuple[float, float] = (0.0, 127.0)
    curve: Callable[[float], float] = lambda u: u
    curve_name: str = "linear"
    smoothing: float = 0.0
    condition: Condition | None = None
    otherwise: float | None = None
    kind: str = "cc"                  # "cc" | "osc"
    control: int = 0
    channel: int = 1
    address: str = ""
    output: str = "midi"

    def describe(self) -> str:
        src = f"{joint_label(self.joint)} {self.measure}"
        if self.measure == "distance" and self.to_joint is not None:
            src = f"distance {joint_label(self.joint)}-{joint_label(self.to_joint)}"
        dst = (f"cc {self.control} ch {self.channel} on {self.output}" if self.kind == "cc"
               else f"osc {self.address} on {self.output}")
        text = (f"{src} {self.in_range[0]:g}..{self.in_range[1]:g} -> {dst} "
                f"{self.out_range[0]:g}..{self.out_range[1]:g}")
        if self.curve_name != "linear":
            text += f" ({self.curve_name})"
        if self.condition is not None:
            text += f" while {self.condition.describe()}"
        return text


@dataclass
class Section:
    name: str
    index: int
    about: str = ""
    tempo: float | None = None
    phrases: tuple[str, ...] = ()
    triggers: list[Trigger] = field(default_factory=list)
    mappings: list[Mapping] = field(default_factory=list)
    on_enter: tuple[Action, ...] = ()
    next: str | None = None
    quantize: str | None = None        # None: the piece's


@dataclass(frozen=True)
class Ending:
    """How the piece ends: the last notes held and faded over CC 11, then the room rings."""

    fade: float = 3.0                 # seconds
    ring: float = 1.0                 # seconds


@dataclass
class Safety:
    keys: bool = False
    osc_port: int | None = None


@dataclass
class Idle:
    """The attract section: ``section`` after ``after`` s with nobody on stage; someone
    arriving goes ``back`` ('start', 'previous' or a section name)."""

    after: float
    section: str
    back: str = "start"


@dataclass
class Piece:
    title: str
    path: str
    sections: list[Section]
    outputs: dict[str, OutputDecl]
    zones: dict[str, Zone] = field(default_factory=dict)
    phrases: dict[str, Phrase] = field(default_factory=dict)
    triggers: list[Trigger] = field(default_factory=list)      # active everywhere
    mappings: list[Mapping] = field(default_factory=list)      # active everywhere
    start: str = ""
    composer: str = ""
    about: str = ""
    tempo: float = 60.0
    meter: str | None = None
    quantize: str = "none"           # beat | bar | none
    ending: Ending = field(default_factory=Ending)
    #: MIDI output -> voice policy (queue, layer, replace, ignore)
    overlap: dict[str, str] = field(default_factory=dict)
    seed: int | None = None
    rehearsal: str | None = None     # absolute path of the simulator scenario, if any
    defaults: Defaults = field(default_factory=Defaults)
    safety: Safety = field(default_factory=Safety)
    idle: Idle | None = None
    forecast_s: float = 0.0          # triggers and mappings see bodies this far ahead

    def horizons(self) -> set[float]:
        """Every forecast (s) the piece needs from the engine."""
        out = {self.forecast_s}
        for trig in self.triggers + [t for s in self.sections for t in s.triggers]:
            if trig.anticipate is not None:
                out.add(trig.anticipate.ahead)
        out.discard(0.0)
        return out

    def section(self, name: str) -> Section:
        for s in self.sections:
            if s.name == name:
                return s
        raise KeyError(name)

    def scene(self) -> tuple[list[dict], list[str]]:
        """What views draw: (zone dicts, section names in order)."""
        return [z.scene() for z in self.zones.values()], [s.name for s in self.sections]


def curve_function(curve: str | float) -> Callable[[float], float]:
    """u in [0, 1] -> [0, 1]. exp/log bend towards the ends (about 24 dB of range)."""
    if isinstance(curve, (int, float)):
        power = float(curve)
        return lambda u: u ** power
    if curve == "exp":
        return lambda u: (math.pow(16.0, u) - 1.0) / 15.0
    if curve == "log":
        return lambda u: math.log1p(15.0 * u) / math.log(16.0)
    if curve == "smooth":
        return lambda u: u * u * (3.0 - 2.0 * u)
    return lambda u: u
