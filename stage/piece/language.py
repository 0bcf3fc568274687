"""The piece format, written down once: the loader checks files with it and the
JSON Schema shipped for editors is generated from it (``stage.piece.schema``).

Words a composer meets (see docs/pieces.md for the tutorial):

* **outputs** are named (``cello: midi``, ``space: osc``) and bound to MIDI ports
  or OSC targets when the piece is played; a piece never names sensors.
* **zones** are boxes, cylinders (floor circles with a height) and spheres in
  stage metres (y up, the audience towards +z).
* **phrases** are notes with durations in beats (a beat is a quarter note) or
  seconds, at a tempo.
* **sections** come in order; each has its phrases, **triggers** (a joint does
  something -> actions) and **mappings** (a joint's value drives a control).
"""

from __future__ import annotations

from ..joints import HAND_STATE_NAMES, HandState
from .spec import (AnyOf, Boolean, Choice, Field, Integer, JointName, ListOf, MapOf, Number, Obj,
                   Text)

SECONDS = Number(minimum=0.0, unit="seconds")
METRES = Number(unit="metres")
NAME = Text(expected="a name")
PITCHES = r"\s*(?:[A-Ga-g](?:#|##|b|bb)?-?\d|\d{1,3})(?:\s*\+\s*(?:[A-Ga-g](?:#|##|b|bb)?-?\d|\d{1,3}))*\s*"
HAND_STATES = tuple(HAND_STATE_NAMES[s] for s in (HandState.OPEN, HandState.CLOSED, HandState.LASSO))
DIRECTIONS = ("up", "down", "downstage", "upstage", "stage_left", "stage_right")
#: words ``play:`` understands instead of a phrase name
PICKS = ("random", "next", "shuffle")
CURVES = ("linear", "exp", "log", "smooth")
#: voice policies: what a phrase does when another still sounds (or waits) on its output
OVERLAPS = ("queue", "layer", "replace", "ignore")
MEASURES = ("x", "y", "z", "height", "speed", "distance", "angle")

JOINT = JointName(extra=("body",), doc="A joint (HandLeft, Head, ...), a group (hands, feet, "
                  "...) or 'body' (the torso centre).")
SINGLE_JOINT = JointName(groups=False, extra=("body",),
                         doc="One joint (HandLeft, Head, ...) or 'body' (the torso centre).")
HEIGHT = AnyOf((Number(unit="metres above the floor"), SINGLE_JOINT),
               says="a height in metres or a joint name (e.g. Head)",
               doc="A height in metres, or a joint of the same performer (e.g. Head).")
CHANNEL = Integer(1, 16, doc="MIDI channel 1-16.")
MIDI_VALUE = Integer(0, 127)
VELOCITY = AnyOf((Integer(1, 127), Choice(("speed",))), says="1-127 or speed",
                 doc="1-127, or 'speed': from how fast the joint moved (defaults.speed_range "
                     "-> defaults.velocity_range).")
PERFORMER = AnyOf((Choice(("any", "first", "newest")), Integer(0)),
                  doc="'any' performer, 'first' (on stage longest), 'newest', or a person id.",
                  says="any, first, newest or a person id")
ONE_PERFORMER = AnyOf((Choice(("first", "newest")), Integer(0)),
                      doc="'first' (on stage longest), 'newest', or a person id.",
                      says="first, newest or a person id")
VECTOR2 = ListOf(Number(), 2, 2, doc="[x, z] metres on the floor.")
VECTOR3 = ListOf(Number(), 3, 3, doc="[x, y, z] metres.")
RANGE = ListOf(Number(), 2, 2, doc="[from, to].")
OUTPUT_NAME = Text(expected="an output name", doc="An output declared under 'outputs'.")
QUANTIZE = Choice(("beat", "bar", "none"),
                  doc="Start phrases and notes on the next beat or bar line of the piece's grid "
                      "(its tempo and meter, counted from the start), or at once (none). The "
                      "trigger's, else the section's, else the piece's; default none.")
OVERLAP = Choice(OVERLAPS, doc="What a phrase does when another still sounds or waits on its "
                               "output: queue (default: it starts when they end; a trigger "
                               "whose phrase still waits is not heard again), layer (it sounds "
                               "with them), replace (it cuts them) or ignore (it is not played).")
ARPEGGIATE = Number(minimum=0.0, unit="seconds",
                    doc="Break chords as a cellist does: the voices enter this far apart, "
                        "bottom up; each lower voice gives way after the next one, the top "
                        "voice is held (default 0: struck together).")


def _named(kind_word: str):
    def label(value: dict, what: str) -> str:
        name = value.get("name")
        return f"{kind_word} '{name}'" if isinstance(name, (str, int)) else what
    return label


OUTPUT = AnyOf((
    Choice(("midi", "osc"), doc="Shorthand: the target is chosen when the piece is played."),
    Obj("Output", {
        "type": Field(Choice(("midi", "osc")), required=True),
        "target": Field(Text(), doc="A MIDI port name, or HOST:PORT for OSC. Left out: from the "
                                    "command line (--midi, --midi-file, --osc)."),
    "overlap": Field(OVERLAP, doc="midi: the voice policy of this output (default queue)."),
    "skeletons": Field(Boolean(), doc="osc: also send the skeleton stream (the Server-to-View "
                                      "API) to this output's target (default false: only the "
                                      "piece's messages)."),
    }, doc="Where events of this name go."),
))

#: the longest anticipation or forecast a piece may ask for (the rig's forecast: max_s default)
MAX_AHEAD_S = 0.2
AHEAD = Number(minimum=0.0, maximum=MAX_AHEAD_S, unit="seconds")
ANTICIPATE = AnyOf((AHEAD, Obj("Anticipate", {
    "ahead": Field(AHEAD, required=True, doc="How far ahead of the measurements to look."),
    "max_sd": Field(Number(exclusive_minimum=0.0, unit="metres"),
                    doc="A predicted crossing fires only while the prediction's position s.d. "
                        "is at most this (default 0.1)."),
    "within": Field(Number(exclusive_minimum=0.0, unit="seconds"),
                    doc="A predicted crossing the measurements have not made this long after "
                        "the predicted moment counts as contradicted (default 0.1)."),
    "cut": Field(Boolean(), doc="Cut short what a contradicted firing played (default false)."),
    "min_p": Field(Number(0.0, 1.0),
                   doc="A predicted crossing fires only once the probability that the joint is "
                       "past the border at the predicted moment (Gaussian: the predicted margin "
                       "over its s.d.) is at least this; until then it waits (default: "
                       "docs/anticipation.md)."),
    "trend": Field(Number(unit="m/s"),
                   doc="A predicted crossing fires only while the measured joint moves towards "
                       "the border at least this fast, m/s (default: the joint group's, "
                       "docs/anticipation.md)."),
    "persist": Field(Integer(1, 10),
                     doc="A predicted crossing fires only once it has been sure enough on this "
                         "many frames in a row (default: docs/anticipation.md)."),
}, doc="How boldly a trigger fires on what the filter predicts.")),
    says="seconds ahead (0 to 0.2), or {ahead, max_sd, within, cut, min_p, trend, persist}",
    doc="Fire on a crossing predicted this far ahead (enters, leaves, rises_above, "
        "falls_below; docs/anticipation.md). 0: off.")

DEFAULTS = Obj("Defaults", {
    "cooldown": Field(SECONDS, doc="A trigger does not fire again for this long (default 0.5)."),
    "hysteresis": Field(Number(minimum=0.0, unit="metres"),
                        doc="How far past a border a joint must go back before it counts as "
                            "having left (default 0.05)."),
    "dwell": Field(SECONDS, doc="How long a new state must last before it counts (default 0)."),
    "hand_dwell": Field(SECONDS, doc="The same for hand states, which flicker (default 0.1)."),
    "min_confidence": Field(Number(0.0, 1.0), doc="Joints seen with less confidence are "
                                                   "ignored (default 0.5: inferred counts)."),
    "channel": Field(CHANNEL),
    "velocity": Field(Integer(1, 127)),
    "gate": Field(Number(exclusive_minimum=0.0, maximum=1.0),
                  doc="Fraction of each note's value that sounds (default 0.9)."),
    "speed_range": Field(RANGE, doc="Joint speeds (m/s) mapped to velocity_range (default [0.3, 3])."),
    "velocity_range": Field(RANGE, doc="Velocities for 'velocity: speed' (default [40, 120])."),
    "arpeggiate": Field(ARPEGGIATE),
    "anticipate": Field(ANTICIPATE, doc="Every trigger that can anticipate does, unless it "
                                        "says otherwise (default 0: none)."),
}, doc="Defaults for every trigger and phrase of the piece.")

ZONE = Obj("Zone", {
    "shape": Field(Choice(("box", "cylinder", "sphere")), required=True),
    "centre": Field(ListOf(Number(), 2, 3), doc="cylinder: [x, z] on the floor; sphere: [x, y, z]."),
    "radius": Field(Number(exclusive_minimum=0.0, unit="metres")),
    "height": Field(Number(exclusive_minimum=0.0, unit="metres"),
                    doc="cylinder: its top, above 'bottom' (default 3)."),
    "bottom": Field(METRES, doc="cylinder: height of its base (default 0, the floor)."),
    "min": Field(VECTOR3, doc="box: its lowest corner [x, y, z]."),
    "max": Field(VECTOR3, doc="box: its highest corner [x, y, z]."),
    "hysteresis": Field(Number(minimum=0.0, unit="metres")),
    "about": Field(Text()),
}, doc="A region of the stage, in metres (y up, origin on the floor).")

NOTE_ITEM = AnyOf((Text(expected="a note like 'G2 1', 'F#3+A3 1/2 v90' or 'rest 1'"),
                   Integer(0, 127)))

PHRASE = Obj("Phrase", {
    "notes": Field(ListOf(NOTE_ITEM, 1), doc="Notes in order: 'PITCH [BEATS] [vVELOCITY]', "
                   "chords with '+', 'rest 1'; a note without a duration keeps the previous one."),
    "bars": Field(ListOf(Text(expected="a bar of notes separated by commas"), 1),
                  doc="The same, one bar per item (comma-separated); each bar must fill the meter."),
    "tempo": Field(Number(exclusive_minimum=0.0, unit="quarter notes per minute")),
    "meter": Field(Text(pattern=r"\d+/(1|2|4|8|16)", expected="a meter like 3/4")),
    "unit": Field(Choice(("beats", "seconds")), doc="What durations count (default beats)."),
    "output": Field(OUTPUT_NAME),
    "channel": Field(CHANNEL),
    "velocity": Field(Integer(1, 127)),
    "gate": Field(Number(exclusive_minimum=0.0, maximum=1.0)),
    "transpose": Field(Integer(-48, 48), doc="Semitones."),
    "arpeggiate": Field(ARPEGGIATE),
    "about": Field(Text()),
}, one_of=("notes", "bars"), doc="A musical phrase; notes get their own note-offs.")

CONDITION = Obj("Condition", {
    "joint": Field(SINGLE_JOINT, doc="Default: the trigger's or mapping's joint."),
    "in": Field(NAME, doc="The joint is inside this zone."),
    "not_in": Field(NAME, doc="The joint is outside this zone."),
    "above": Field(HEIGHT),
    "below": Field(HEIGHT),
    "hand": Field(Choice(HAND_STATES), doc="The hand (of the joint's side, else either) is in this state."),
}, doc="Holds while every key given is true, for the same performer.")

PLAY = AnyOf((
    Text(expected="a phrase name, random, next or shuffle"),
    Obj("Play", {
        "phrase": Field(NAME, doc="A fixed phrase."),
        "pick": Field(Choice(PICKS), doc="How to choose among 'from' (default random: never the "
                                         "same twice in a row)."),
        "from": Field(ListOf(NAME, 1), doc="Phrases to choose from (default: the section's)."),
        "weights": Field(ListOf(Number(minimum=0.0), 1), doc="For pick: random, one per phrase."),
        "velocity": Field(VELOCITY, doc="Scales the phrase's velocities so its loudest note has this."),
        "transpose": Field(Integer(-48, 48)),
        "interrupt": Field(Boolean(), doc="Silence the phrase's channel first (the same as "
                                          "overlap: replace, for this channel only)."),
        "overlap": Field(OVERLAP, doc="This phrase's policy instead of its output's."),
    }),
))

NOTE_ACTION = AnyOf((
    Text(pattern=PITCHES, expected="a pitch like G3 or a chord like G2+D3+B3"),
    Integer(0, 127),
    Obj("NoteAction", {
        "pitch": Field(AnyOf((Text(pattern=PITCHES, expected="a pitch like G3 or a chord like "
                                                           "G2+D3+B3"), Integer(0, 127))),
                       required=True),
        "beats": Field(Number(exclusive_minimum=0.0), doc="Length at the section's tempo (default 1)."),
        "seconds": Field(Number(exclusive_minimum=0.0)),
        "velocity": Field(VELOCITY),
        "channel": Field(CHANNEL),
        "output": Field(OUTPUT_NAME),
        "arpeggiate": Field(ARPEGGIATE),
        "overlap": Field(OVERLAP, doc="This note's policy instead of its output's."),
    }),
))

GOTO = AnyOf((
    Text(expected="next, previous, end or a section name"),
    Obj("Goto", {
        "to": Field(Text(expected="next, previous, end or a section name"), required=True),
        "now": Field(Boolean(), doc="Do not wait for the sounding phrase to end (default "
                                    "false)."),
    }),
), says="next, previous, end, a section name, or {to: ..., now: true}")

OSC_ARG = AnyOf((Integer(), Number(), Text(), Boolean()),
                doc="A value, or a reference: $x $y $z $speed $value $person $joint $section "
                    "$trigger $time, or $Joint.x/.y/.z/.speed of the same performer.")

ACTION = Obj("Action", {
    "play": Field(PLAY, doc="Play a phrase: its name, or random / next / shuffle among the "
                            "section's phrases."),
    "note": Field(NOTE_ACTION, doc="One note or chord."),
    "cc": Field(Obj("ControlChange", {
        "control": Field(MIDI_VALUE, required=True),
        "value": Field(AnyOf((MIDI_VALUE, Choice(("speed",)))), required=True),
        "channel": Field(CHANNEL),
        "output": Field(OUTPUT_NAME),
    }), doc="A MIDI control change."),
    "program": Field(AnyOf((MIDI_VALUE, Obj("ProgramChange", {
        "program": Field(MIDI_VALUE, required=True),
        "channel": Field(CHANNEL),
        "output": Field(OUTPUT_NAME),
    }))), doc="A MIDI program change (0-127)."),
    "osc": Field(AnyOf((Text(pattern=r"/\S*", expected="an OSC address like /cue"),
                        Obj("OscAction", {
                            "address": Field(Text(pattern=r"/\S*", expected="an OSC address "
                                                                              "like /cue"),
                                             required=True),
                            "args": Field(ListOf(OSC_ARG)),
                            "output": Field(OUTPUT_NAME),
                        }))), doc="An OSC message."),
    "goto": Field(GOTO, doc="Move to another section: next, previous or its name, when the "
                            "phrases sounding and waiting have ended ({to: next, now: true}: at "
                            "once); 'end' ends the piece: the last phrase finishes, its last "
                            "notes ring and fade (see 'ending'), then nothing acts any more."),
    "silence": Field(Text(expected="an output name or all"),
                     doc="Stop every note of an output (or all), pending ones included."),
}, one_of=("play", "note", "cc", "program", "osc", "goto", "silence"),
    doc="One thing to do; write each as its own list item.")

ACTIONS = ListOf(ACTION, 1, item_word="action")

TRIGGER_KINDS = ("enters", "leaves", "dwells", "speed_above", "moves", "rises_above",
                 "falls_below", "hand", "step", "appears", "disappears", "stage_empty", "elapsed")

TRIGGER = Obj("Trigger", {
    "name": Field(NAME, doc="Shown on the console and in event logs."),
    "joint": Field(JOINT, doc="Default: body for zones, hands for hand, feet for step."),
    "performer": Field(PERFORMER),
    "enters": Field(NAME, doc="The joint enters this zone."),
    "leaves": Field(NAME, doc="The joint leaves this zone."),
    "dwells": Field(NAME, doc="The joint has stayed in this zone for 'for' seconds."),
    "speed_above": Field(Number(exclusive_minimum=0.0, unit="m/s")),
    "moves": Field(AnyOf((Choice(DIRECTIONS), VECTOR3)),
                   doc="Moves this way faster than 'speed' (up, down, downstage (+z), upstage, "
                       "stage_left (+x), stage_right, or a vector)."),
    "rises_above": Field(HEIGHT),
    "falls_below": Field(HEIGHT),
    "hand": Field(Choice(HAND_STATES), doc="A hand becomes open, closed or lasso (pointing)."),
    "step": Field(AnyOf((Boolean(), Choice(("gait",))), says="true or gait"),
                  doc="true: a foot is put down after a swing. gait: a walking step as gait "
                      "analysis counts it (seed 003): one foot passes the other; $value is the "
                      "step length (m), $step_width, $step_time, $speed the walking speed."),
    "appears": Field(Boolean(), doc="A performer is seen for the first time."),
    "disappears": Field(Boolean(), doc="A performer is lost."),
    "stage_empty": Field(SECONDS, doc="Nobody has been on stage for this long."),
    "elapsed": Field(SECONDS, doc="This long after the section began."),
    "for": Field(SECONDS, doc="dwells: how long (default 2)."),
    "speed": Field(Number(exclusive_minimum=0.0, unit="m/s"),
                   doc="moves: how fast (default 1); step: the swing speed (default 0.8)."),
    "dwell": Field(SECONDS, doc="The new state must last this long before it fires."),
    "hysteresis": Field(Number(minimum=0.0, unit="metres, or m/s for speeds")),
    "cooldown": Field(SECONDS),
    "cooldown_per": Field(Choice(("trigger", "performer", "joint")),
                          doc="What the cooldown applies to (default trigger: any performer)."),
    "after": Field(SECONDS, doc="Ignored until the section has lasted this long."),
    "once": Field(Boolean(), doc="At most once per visit to the section."),
    "probability": Field(Number(0.0, 1.0), doc="Chance that a firing sounds (seeded)."),
    "while": Field(CONDITION, doc="Fires only while this holds."),
    "quantize": Field(QUANTIZE),
    "anticipate": Field(ANTICIPATE),
    "do": Field(ACTIONS, required=True),
}, one_of=TRIGGER_KINDS, one_of_what=" (what to watch for)", label=_named("trigger"),
    doc="When a joint does something, do these actions.")

CC_TARGET = AnyOf((MIDI_VALUE, Obj("MappingCC", {
    "control": Field(MIDI_VALUE, required=True),
    "channel": Field(CHANNEL),
    "output": Field(OUTPUT_NAME),
})))
OSC_TARGET = AnyOf((Text(pattern=r"/\S*", expected="an OSC address like /pan"), Obj("MappingOsc", {
    "address": Field(Text(pattern=r"/\S*", expected="an OSC address like /pan"), required=True),
    "output": Field(OUTPUT_NAME),
})))

MAPPING = Obj("Mapping", {
    "name": Field(NAME),
    "joint": Field(SINGLE_JOINT, required=True),
    "measure": Field(Choice(MEASURES), doc="What of the joint (default height); angle: the "
                                            "angle at an elbow, knee, shoulder or hip (degrees)."),
    "to_joint": Field(SINGLE_JOINT, doc="measure: distance, between 'joint' and this one."),
    "performer": Field(ONE_PERFORMER),
    "in_range": Field(RANGE, required=True, doc="Input range (metres, m/s, or degrees for "
                                               "angle); clamped."),
    "out_range": Field(RANGE, doc="Output range (default 0-127 for cc, 0-1 for osc)."),
    "curve": Field(AnyOf((Choice(CURVES), Number(exclusive_minimum=0.0))),
                   doc="linear, exp, log, smooth, or a power."),
    "smoothing": Field(SECONDS, doc="Time constant of a low-pass on the value (default 0)."),
    "while": Field(CONDITION),
    "otherwise": Field(Number(), doc="Sent once when the condition stops holding or the "
                                     "performer leaves."),
    "cc": Field(CC_TARGET, doc="Send as a MIDI control change."),
    "osc": Field(OSC_TARGET, doc="Send as an OSC message with the value."),
}, one_of=("cc", "osc"), label=_named("mapping"), doc="A continuous control.")

SECTION = Obj("Section", {
    "name": Field(NAME, required=True),
    "about": Field(Text(), doc="What happens here (shown when the section begins)."),
    "tempo": Field(Number(exclusive_minimum=0.0, unit="quarter notes per minute")),
    "phrases": Field(ListOf(NAME), doc="Phrases of this section (names from 'phrases')."),
    "triggers": Field(ListOf(TRIGGER, item_word="trigger")),
    "mappings": Field(ListOf(MAPPING, item_word="mapping")),
    "on_enter": Field(ACTIONS, doc="Done when the section begins."),
    "next": Field(NAME, doc="Where 'goto: next' leads (default the following section)."),
    "quantize": Field(QUANTIZE),
}, label=_named("section"), doc="A part of the piece.")

ENDING = Obj("Ending", {
    "fade": Field(SECONDS, doc="After the last phrase, its last notes are held (sustain, CC 64) "
                               "and faded out over expression (CC 11) for this long (default 3)."),
    "ring": Field(SECONDS, doc="Then this long for the room to ring (reverb tails) before the "
                               "piece has ended (default 1)."),
}, doc="How the piece ends ('goto: end'). Triggers of the whole piece act until it has ended.")

SAFETY = Obj("Safety", {
    "keys": Field(Boolean(), doc="n / p + Enter on the console: next / previous section."),
    "osc_port": Field(Integer(1, 65535), doc="UDP port for /stage/section next|previous|NAME."),
}, doc="Ways for the cellist or the operator to force a section change.")

IDLE = Obj("Idle", {
    "after": Field(Number(exclusive_minimum=0.0, unit="seconds"), required=True,
                   doc="Nobody on stage for this long starts the idle section."),
    "section": Field(NAME, required=True, doc="The attract section (a section of the piece)."),
    "back": Field(NAME, doc="Where the piece goes when someone arrives: 'start' (default), "
                            "'previous' (the section it left) or a section name."),
}, doc="An attract/idle section for unattended exhibits: played while the room is empty.")

PIECE = Obj("Piece", {
    "piece": Field(Text(), required=True, doc="The title."),
    "composer": Field(Text()),
    "about": Field(Text()),
    "tempo": Field(Number(exclusive_minimum=0.0, unit="quarter notes per minute"),
                   doc="Default 60."),
    "meter": Field(Text(pattern=r"\d+/(1|2|4|8|16)", expected="a meter like 3/4")),
    "quantize": Field(QUANTIZE),
    "forecast_s": Field(AHEAD, doc="Triggers and mappings see every body predicted this far "
                                   "past its capture time (default 0: as measured; "
                                   "docs/anticipation.md)."),
    "ending": Field(ENDING),
    "seed": Field(Integer(0), doc="Seed of the aleatoric choices (--seed overrides)."),
    "rehearsal": Field(Text(), doc="Simulator scenario for 'stage play --sim' (relative to "
                                   "this file)."),
    "outputs": Field(MapOf(OUTPUT, what_item="output"), doc="Default: one MIDI output 'midi'."),
    "defaults": Field(DEFAULTS),
    "zones": Field(MapOf(ZONE, what_item="zone")),
    "phrases": Field(MapOf(PHRASE, what_item="phrase")),
    "start": Field(NAME, doc="The first section (default the first listed)."),
    "sections": Field(ListOf(SECTION, 1, item_word="section"),
                      required=True),
    "triggers": Field(ListOf(TRIGGER, item_word="trigger"),
                      doc="Active in every section."),
    "mappings": Field(ListOf(MAPPING, item_word="mapping"),
                      doc="Active in every section."),
    "safety": Field(SAFETY),
    "idle": Field(IDLE),
}, doc="A piece for stage: sections of triggers, phrases and mappings over tracked bodies.")
