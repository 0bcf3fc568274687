"""The example pieces do what their comments say, on scripted visitors and performers."""

from __future__ import annotations

import math
from pathlib import Path

from stage.events import AllNotesOff, ControlChange, Note, OscOut, SectionChange, TriggerFired
from stage.joints import HandState
from stage.piece import PieceRuntime, RecordingSink, load_piece
from stage.testing.script import ScriptedStage, standing

REPO = Path(__file__).resolve().parents[1]
OPEN, CLOSED = HandState.OPEN, HandState.CLOSED


def play(name: str):
    piece = load_piece(REPO / "pieces" / name)
    sink = RecordingSink()
    runtime = PieceRuntime(piece, sink, seed=1)
    return runtime, sink, ScriptedStage(runtime)


def test_circles_wakes_plays_for_several_visitors_and_resets_when_the_room_empties():
    runtime, sink, stage = play("circles.yaml")
    runtime.start(0.0)
    stage.run(0.0, 1.0, lambda t: {1: standing(0.0, 2.5)})                # someone comes in
    assert runtime.section.name == "playing"
    # a second visitor comes in; both stop in a circle; the first closes a hand there
    stage.run(1.0, 1.5, lambda t: {1: standing(-1.5, 0.0), 2: standing(3.0, 0.0)})
    stage.run(1.5, 3.0, lambda t: {1: standing(-1.5, 0.0), 2: standing(1.5, 0.0)})
    stage.run(3.0, 4.0, lambda t: {1: (standing(-1.5, 0.0), (CLOSED, OPEN)),
                                   2: standing(1.5, 0.0)})
    fired = [(e.trigger, e.person) for e in sink.of(TriggerFired)]
    assert ("west stand", 1) in fired and ("east stand", 2) in fired
    assert ("close in west", 1) in fired and ("close in east", 1) not in fired
    lights = [(o.address, o.args) for o in sink.of(OscOut)]
    assert ("/lights/west", (1,)) in lights and ("/lights/east", (1,)) in lights
    channels = {n.channel for n in sink.of(Note)}
    assert {0, 2, 3} <= channels                          # west, east, the welcome
    # everyone leaves; 20 s later the installation resets itself
    stage.frame(4.0, {})
    for k in range(1, 500):
        runtime.tick(4.0 + k * 0.05)
    assert runtime.section.name == "waiting"
    assert sink.of(SectionChange)[-1].cause == "room empty"
    assert any(o.output is None for o in sink.of(AllNotesOff))
    assert ("/lights/all", (0,)) in [(o.address, o.args) for o in sink.of(OscOut)]


def test_arms_drive_control_changes_inside_the_square_only():
    runtime, sink, stage = play("arms.yaml")
    stage.run(0.0, 0.5, lambda t: {1: standing(-2.5, 0.0)})               # outside: nothing
    assert sink.of(ControlChange) == [] and sink.of(Note) == []
    # inside, the arms rise from the sides to overhead over 2 s
    stage.run(0.5, 3.0, lambda t: {1: standing(0.0, 0.0, left_arm=math.pi * min(1, (t - 0.5) / 2),
                                               right_arm=math.pi * min(1, (t - 0.5) / 2))})
    drone = sink.of(Note)
    assert [n.note for n in drone] == [38, 45, 50] and drone[0].duration > 60
    cc = {}
    for c in sink.of(ControlChange):
        cc.setdefault(c.control, []).append(c.value)
    assert set(cc) == {1, 74, 11, 71}
    assert cc[1][-1] > 100 and cc[74][-1] > 100            # hands high: modulation, cutoff
    assert max(cc[11]) > cc[11][0]                         # arms spread: expression rises
    n = len(sink.of(ControlChange))
    stage.run(3.0, 4.0, lambda t: {1: standing(-2.5, 0.0)})               # steps out
    rest = {c.control: c.value for c in sink.of(ControlChange)[n:]}
    assert rest == {1: 0, 74: 64, 11: 100, 71: 0}          # each back to its 'otherwise'
    assert sink.of(AllNotesOff)[-1].output == "synth"     # the drone stops
    pans = [o.args[0] for o in sink.of(OscOut) if o.address == "/arms/pan"]
    assert pans and min(pans) == -1.0                      # clamped at the stage-right edge
