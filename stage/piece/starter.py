"""``stage new``: a commented starter piece and the rehearsal that plays it.

``write_starter("dusk.yaml")`` writes ``dusk.yaml`` -- two sections, one
gesture each, a transition, an ending, every line explained -- and
``dusk.sim.yaml`` beside it, a simulated dancer who does what the piece's
triggers wait for, so ``stage play dusk.yaml --sim`` sounds at once. The
piece's first line points the YAML language server at the user's copy of the
schema (``install_user_copy``), an absolute path that works wherever the file
is.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..errors import ConfigError
from ..yamlio import write_atomic
from .schema import install_user_copy, modeline

PIECE = """\
{modeline}
#
# {title} -- a piece for stage, written by `stage new`. Check and rehearse it:
#
#     stage check {name}.yaml {name}.sim.yaml
#     stage play {name}.yaml --sim --audio {name}.wav --score {name}.png
#
# --sim plays it with the simulated dancer of {name}.sim.yaml (no hardware); --audio
# renders what sounds through FluidSynth, --score draws it. With sensors and a synthesizer:
#     stage play {name}.yaml --midi "FluidSynth" --osc 127.0.0.1:9000
# Every key is explained in docs/pieces.md; your editor completes them from the schema
# named on the first line (`stage schema --install` refreshes it).

piece: {title}
tempo: 72                # quarter notes a minute
meter: 3/4               # lets phrases be written in bars, and quantize to bars
quantize: beat           # phrases start on the next beat of that pulse
rehearsal: {name}.sim.yaml
ending: {{fade: 3, ring: 1}}   # the last note is held and faded over 3 s, then the room rings

outputs:
  voice:                 # a General MIDI synthesizer (--midi PORT, --audio, --synth)
    type: midi
    overlap: queue       # one player: a phrase asked for while another sounds waits for it
  space: osc             # for visuals or spatialisation (--osc HOST:PORT)

defaults:
  cooldown: 1.0          # nothing the dancer does repeats faster than once a second
  arpeggiate: 0.05       # chords are broken bottom up, 50 ms a voice

zones:
  centre: {{shape: cylinder, centre: [0, 0], radius: 0.8, about: "the middle of the stage"}}

phrases:
  call: {{bars: ["D4 1, F#4, A4", "G4 2, rest 1"], about: "a question"}}
  answer: {{bars: ["A3 1/2, B3, C#4 1, E4", "D3+A3+D4 3"], about: "and its answer"}}

sections:
  - name: calling
    about: The right hand raised above the head calls; walking to the centre moves on.
    on_enter:
      - program: 73      # General MIDI flute (74, counted from 0)
    triggers:
      - name: hand up
        joint: HandRight
        rises_above: Head          # above her own head, whatever her height
        do:
          - play: call
      - name: to the centre
        dwells: centre
        for: 1.5                   # arriving, not passing through
        do:
          - goto: next             # when the sounding phrase has ended

  - name: answering
    about: Each step answers; kneeling ends the piece.
    triggers:
      - name: step
        step: true                 # a foot put down after a swing
        cooldown: 2
        do:
          - play: {{phrase: answer, velocity: speed}}   # louder the faster the step
      - name: kneel
        joint: Head
        falls_below: 1.1
        once: true
        do:
          - goto: end              # the answer ends, rings and fades: the end

triggers:                          # in every section, until the piece has ended
  - name: arrives
    appears: true
    do:
      - osc: {{address: /{slug}/dancer, args: [$person, 1]}}
  - name: leaves
    disappears: true
    do:
      - osc: {{address: /{slug}/dancer, args: [$person, 0]}}

mappings:
  - name: pan
    joint: body
    measure: x
    in_range: [-3, 3]
    out_range: [-1, 1]
    smoothing: 0.25
    osc: /{slug}/pan
"""

REHEARSAL = """\
# Rehearsal of {title}: a simulated dancer who does what its triggers wait for.
# `stage play {name}.yaml --sim` uses it (the piece names it under 'rehearsal');
# `stage check {name}.sim.yaml` prints each step with its time. The moves, the
# sensors and the format: docs/sources.md.
name: {slug}
description: one dancer through the sections of {title}
duration: 60             # at most; the rehearsal ends when the piece has ended

sensors:
  ring: {{count: 3, radius: 2.5, height: 0.8}}   # three Kinects round the stage

performers:
  - name: dancer
    height: 1.70
    position: [-1.8, 0.0]
    facing: 90           # towards the centre (+x)
    timeline:
      # calling: the right hand rises above the head, twice
      - {{wait: 1.5}}
      - {{raise: right, to: 175, over: 0.8}}
      - {{wait: 1.0}}
      - {{lower: right, over: 1.0}}
      - {{wait: 2.5}}
      - {{raise: right, to: 175, over: 0.8}}
      - {{wait: 1.0}}
      - {{lower: right, over: 1.0}}
      # ...then she walks to the centre and stays (the section changes when the call ends)
      - {{walk: [0.0, 0.0], speed: 0.8}}
      - {{wait: 5.0}}
      # answering: a walk round the centre; each step answers
      - {{walk: [[1.0, 0.6], [0.0, 1.2], [-1.0, 0.6], [0.0, 0.0]], speed: 0.6}}
      # ...and she kneels: the end
      - {{crouch: 0.8, over: 1.5}}
      - {{wait: 2.0}}
      - {{stand: true, over: 1.5}}
      - {{walk: [-2.6, 0.0], speed: 1.0}}
      - {{leave: true}}
"""


def write_starter(path: str | os.PathLike, force: bool = False) -> tuple[Path, Path, Path]:
    """Write the starter piece at ``path`` and its rehearsal beside it.

    Returns (piece, rehearsal, schema). ConfigError (one line) when a file exists
    (unless ``force``), the folder does not, or the name is not a .yaml file.
    """
    piece = Path(path)
    if piece.suffix not in (".yaml", ".yml"):
        raise ConfigError(f"{path}: a piece is a .yaml file (e.g. stage new dusk.yaml)")
    if not piece.parent.is_dir():
        raise ConfigError(f"{path}: folder '{piece.parent}' does not exist")
    stem = piece.name[: -len(piece.suffix)]
    rehearsal = piece.with_name(f"{stem}.sim.yaml")
    for p in (piece, rehearsal):
        if p.exists() and not force:
            raise ConfigError(f"{p} exists; choose another name or give --force")
    schema, _ = install_user_copy()
    slug = re.sub(r"[^a-z0-9]+", "-", stem.lower()).strip("-") or "piece"
    title = stem.replace("_", " ").replace("-", " ").strip().capitalize() or "Untitled"
    words = {"modeline": modeline(schema), "title": title, "name": stem, "slug": slug}
    write_atomic(piece, PIECE.format(**words))
    write_atomic(rehearsal, REHEARSAL.format(**words))
    return piece, rehearsal, schema
