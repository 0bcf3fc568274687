"""The runtime's actions, phrases, mappings and zone states, and the runtime as a
real engine listener (Engine + ManualClock + datagrams)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stage.clock import ManualClock
from stage.engine.engine import Engine
from stage.events import (AllNotesOff, ControlChange, MappingValue, Note, OscOut, ProgramChange,
                          SectionChange, TriggerFired, ZoneState)
from stage.joints import JOINT_INDEX
from stage.piece import PieceRuntime, RecordingSink, loads_piece
from stage.testing.script import ScriptedStage, standing
from stage.sensors.protocol import encode_client_joints, encode_message

HEAD = """
piece: test
tempo: 120
outputs: {cello: midi, synth: midi, space: osc}
zones:
  centre: {shape: cylinder, centre: [0, 0], radius: 0.8}
  front: {shape: box, min: [-2, 0, 1], max: [2, 3, 2]}
phrases:
  motif: {notes: ["G3 1", "A3 1/2 v100", "B3+D4 3/2", "rest 1", "C4 1/2"], channel: 2}
  secs: {notes: ["C4 0.25", "D4"], unit: seconds, output: synth, gate: 1.0}
  slow: {notes: ["G2 1"], tempo: 30}
"""


def make(body: str, seed: int = 1):
    piece = loads_piece(HEAD + body)
    sink = RecordingSink()
    runtime = PieceRuntime(piece, sink, seed=seed)
    return runtime, sink, ScriptedStage(runtime)


def one_section(triggers: str = "", mappings: str = "", extra: str = "") -> str:
    return f"""
sections:
  - name: one
    phrases: [motif]
{extra}    triggers:
{triggers or "      []"}
    mappings:
{mappings or "      []"}
"""


def raise_left(stage, t0=0.0, t1=2.0):
    up = lambda t: math.pi if t >= t0 + 0.5 else 0.0
    stage.run(t0, t1, lambda t: {1: standing(0, 0, left_arm=up(t))})


# ------------------------------------------------------------------ phrases
def test_a_phrase_is_emitted_with_future_times_durations_and_channel():
    runtime, sink, stage = make(one_section("""
      - {name: go, joint: HandLeft, rises_above: 1.5, do: [play: motif]}"""))
    raise_left(stage)
    notes = sink.of(Note)
    t0 = sink.of(TriggerFired)[0].t
    beat = 0.5                                                # tempo 120
    assert [(round(n.t - t0, 6), n.note, n.velocity, round(n.duration, 6)) for n in notes] == [
        (0.0, 55, 80, 0.9 * beat), (1 * beat, 57, 100, 0.9 * 0.5 * beat),
        (1.5 * beat, 59, 80, 0.9 * 1.5 * beat), (1.5 * beat, 62, 80, 0.9 * 1.5 * beat),
        (4 * beat, 60, 80, 0.9 * 0.5 * beat)]
    assert {n.channel for n in notes} == {1} and {n.output for n in notes} == {"cello"}


def test_phrase_tempo_units_velocity_scaling_and_transposition():
    runtime, sink, stage = make(one_section("""
      - {name: a, joint: HandLeft, rises_above: 1.5, do: [play: secs, play: slow,
          {play: {phrase: motif, velocity: 50, transpose: 12}}]}"""))
    raise_left(stage)
    t0 = sink.of(TriggerFired)[0].t
    notes = sink.of(Note)
    secs = [n for n in notes if n.output == "synth"]
    assert [(round(n.t - t0, 6), n.duration) for n in secs] == [(0.0, 0.25), (0.25, 0.25)]
    slow = [n for n in notes if n.note == 43]
    assert slow[0].duration == pytest.approx(0.9 * 2.0)          # its own tempo: 30
    motif = [n for n in notes if n.channel == 1]
    assert motif[0].note == 55 + 12
    assert max(n.velocity for n in motif) == 50                   # the loudest gets 50...
    assert motif[0].velocity == round(80 * 50 / 100)              # ...the others keep the ratio


def test_phrases_overlap_unless_interrupted():
    runtime, sink, stage = make(one_section("""
      - {name: a, joint: HandLeft, rises_above: 1.5, cooldown: 0, do: [play: motif]}
      - {name: b, joint: HandRight, rises_above: 1.5, cooldown: 0,
         do: [{play: {phrase: motif, interrupt: true}}]}"""))
    up = lambda t, at: math.pi if t >= at else 0.0
    stage.run(0.0, 2.0, lambda t: {1: standing(0, 0, left_arm=up(t, 0.5), right_arm=up(t, 1.0))})
    offs = sink.of(AllNotesOff)
    assert [(o.output, o.channel) for o in offs] == [("cello", 1)]
    assert offs[0].t == sink.of(TriggerFired)[1].t
    assert len(sink.of(Note)) == 10


# ------------------------------------------------------------------ actions
def test_note_cc_program_osc_and_silence_actions():
    runtime, sink, stage = make(one_section("""
      - name: all
        joint: HandLeft
        rises_above: 1.5
        do:
          - note: {pitch: G2+D3, beats: 2, velocity: speed, channel: 3, output: synth}
          - cc: {control: 11, value: speed}
          - cc: {control: 91, value: 40, channel: 2}
          - program: {program: 42, channel: 2}
          - osc: {address: /hit, args: [$x, $y, $z, $speed, $person, $joint, $section, $trigger, $Head.y, 7, text]}
          - silence: all"""))
    raise_left(stage)
    (fire,) = sink.of(TriggerFired)
    notes = sink.of(Note)
    assert [(n.note, n.channel, n.output, n.duration) for n in notes] == [
        (43, 2, "synth", pytest.approx(0.9 * 1.0)), (50, 2, "synth", pytest.approx(0.9 * 1.0))]
    assert 40 < notes[0].velocity <= 120 and notes[0].velocity == notes[1].velocity
    ccs = sink.of(ControlChange)
    assert [(c.control, c.channel) for c in ccs] == [(11, 0), (91, 1)] and ccs[1].value == 40
    assert sink.of(ProgramChange)[0].program == 42
    (osc,) = sink.of(OscOut)
    hand = standing(0, 0, left_arm=math.pi)[JOINT_INDEX["HandLeft"]]
    assert osc.output == "space" and osc.address == "/hit"
    assert osc.args[:3] == pytest.approx(tuple(hand), abs=1e-9)
    assert osc.args[3] > 1.0 and osc.args[4:8] == (1, "HandLeft", "one", "all")
    assert osc.args[8] == pytest.approx(standing(0, 0)[JOINT_INDEX["Head"], 1])
    assert osc.args[9:] == (7, "text")
    assert sink.of(AllNotesOff)[-1].output is None


def test_trigger_fired_events_come_before_what_they_caused():
    runtime, sink, stage = make(one_section("""
      - {name: go, joint: HandLeft, rises_above: 1.5, do: [play: motif]}"""))
    raise_left(stage)
    kinds = [type(e).__name__ for e in sink.events]
    assert kinds.index("TriggerFired") < kinds.index("Note")


# ------------------------------------------------------------------ mappings
def test_cc_mapping_with_range_clamping_and_only_on_change():
    runtime, sink, stage = make(one_section(mappings="""
      - {name: lift, joint: HandRight, measure: height, in_range: [1.0, 2.0], cc: {control: 1}}"""))
    hand = JOINT_INDEX["HandRight"]
    heights = [0.5, 1.0, 1.5, 1.5, 1.75, 2.0, 2.5]
    for k, h in enumerate(heights):
        j = standing(0, 0)
        j[hand, 1] = h
        stage.frame(k / 30, {1: j})
    values = [c.value for c in sink.of(ControlChange)]
    assert values == [0, 64, 95, 127]                      # clamped, and only changes are sent
    assert [m.value for m in sink.of(MappingValue)] == [0.0, 64.0, 95.0, 127.0]
    assert {m.mapping for m in sink.of(MappingValue)} == {"lift"}


def test_osc_mapping_curve_and_smoothing():
    runtime, sink, stage = make(one_section(mappings="""
      - {name: x, joint: body, measure: x, in_range: [-2, 2], out_range: [0, 1], curve: 2,
         smoothing: 0.5, osc: /x}"""))
    stage.frame(0.0, {1: standing(0.0, 0.0)})
    for k in range(1, 31):                                # a step to x = 2 at t = 0
        stage.frame(k / 30, {1: standing(2.0, 0.0)})
    values = [o.args[0] for o in sink.of(OscOut)]
    assert values[0] == pytest.approx(0.25)               # (0.5) ** 2
    # one-pole low-pass: after 1 s, u = 1 - 0.5 * exp(-1 / 0.5)
    assert values[-1] == pytest.approx((1 - 0.5 * math.exp(-2.0)) ** 2, abs=1e-6)
    assert all(a < b for a, b in zip(values, values[1:]))


def test_mapping_only_while_its_condition_holds_then_otherwise():
    runtime, sink, stage = make(one_section(mappings="""
      - {name: lift, joint: HandRight, in_range: [0.5, 2.0], while: {joint: body, in: centre},
         otherwise: 0, cc: 7}"""))
    stage.run(0.0, 0.5, lambda t: {1: standing(-2, 0, right_arm=math.pi)})   # outside: silent
    assert sink.of(ControlChange) == []
    stage.run(0.5, 1.0, lambda t: {1: standing(0, 0, right_arm=math.pi)})    # inside: sends
    assert sink.of(ControlChange)[-1].value > 100
    stage.run(1.0, 1.5, lambda t: {1: standing(-2, 0, right_arm=math.pi)})   # out: otherwise
    assert sink.of(ControlChange)[-1].value == 0
    n = len(sink.of(ControlChange))
    stage.run(1.5, 2.0, lambda t: {1: standing(0, 0, right_arm=math.pi)})
    stage.frame(2.0, {})                                                     # leaves: otherwise
    assert sink.of(ControlChange)[-1].value == 0 and len(sink.of(ControlChange)) == n + 2


def test_distance_and_speed_mappings():
    runtime, sink, stage = make(one_section(mappings="""
      - {name: span, joint: HandLeft, measure: distance, to_joint: HandRight, in_range: [0, 2],
         out_range: [0, 2], osc: /span}
      - {name: speed, joint: HandRight, measure: speed, in_range: [0, 4], out_range: [0, 4], osc: /v}"""))
    j = standing(0, 0, left_arm=math.pi / 2, right_arm=math.pi / 2)
    stage.frame(0.0, {1: j})
    span = [o.args[0] for o in sink.of(OscOut) if o.address == "/span"]
    d = np.linalg.norm(j[JOINT_INDEX["HandLeft"]] - j[JOINT_INDEX["HandRight"]])
    assert span == [pytest.approx(d)]
    stage.frame(0.1, {1: j + [0.2, 0, 0]})               # everything moves 2 m/s
    speeds = [o.args[0] for o in sink.of(OscOut) if o.address == "/v"]
    assert speeds[-1] == pytest.approx(2.0)


def test_angle_mapping_follows_the_elbow_and_holds_while_a_joint_is_unseen():
    from stage.sensors.sim.kinematics import ArmPose, BodyState, proportions, skeleton
    runtime, sink, stage = make(one_section(mappings="""
      - {name: bend, joint: ElbowRight, measure: angle, in_range: [0, 180], out_range: [0, 180],
         osc: /elbow}
      - {name: arm, joint: ShoulderRight, measure: angle, in_range: [0, 180], cc: {control: 7}}"""))

    def arm(elbow_deg, elevation_deg):
        state = BodyState(arms=(ArmPose(), ArmPose(math.radians(elevation_deg), 0.0,
                                                   math.radians(elbow_deg))))
        return skeleton(state, proportions(1.75))
    for k, bend in enumerate((0, 30, 60, 90, 120)):   # the forearm bends, the arm rises
        stage.frame(k * 0.1, {1: arm(bend, 3 * bend / 2)})
    elbow = [o.args[0] for o in sink.of(OscOut) if o.address == "/elbow"]
    assert elbow == pytest.approx([180, 150, 120, 90, 60], abs=1e-6)   # the angle at the elbow
    cc = [c.value for c in sink.of(ControlChange) if c.control == 7]
    assert cc == [round(127 * a / 180) for a in (0, 45, 90, 135, 180)]
    unseen = np.ones(25)
    unseen[JOINT_INDEX["WristRight"]] = 0.0                             # the wrist is lost
    stage.frame(0.5, {1: (arm(10, 0), ((2, 2)), unseen)})
    assert [o.args[0] for o in sink.of(OscOut) if o.address == "/elbow"] == elbow   # held
    with pytest.raises(Exception, match="must be where two segments meet"):
        make(one_section(mappings="""
      - {joint: HandLeft, measure: angle, in_range: [0, 180], cc: 1}"""))


def test_mappings_of_a_section_stop_when_it_ends():
    runtime, sink, stage = make("""
sections:
  - name: one
    triggers:
      - {name: next, enters: centre, do: [goto: next]}
    mappings:
      - {name: a, joint: HandRight, in_range: [0, 2], otherwise: 5, cc: 20}
  - name: two
""")
    stage.run(0.0, 0.5, lambda t: {1: standing(-2, 0)})
    stage.run(0.5, 1.0, lambda t: {1: standing(0, 0)})
    after = [c for c in sink.of(ControlChange) if c.t >= sink.of(SectionChange)[1].t]
    assert [c.value for c in after] == [5]


# ------------------------------------------------------------------ zones, robustness
def test_zone_state_on_occupancy_change():
    runtime, sink, stage = make(one_section())
    stage.run(0.0, 0.5, lambda t: {1: standing(-2, 0)})
    stage.run(0.5, 1.0, lambda t: {1: standing(0, 0)})
    stage.run(1.0, 1.5, lambda t: {1: standing(0, 0), 2: standing(0.3, 0)})
    stage.run(1.5, 2.0, lambda t: {2: standing(0.3, 0)})
    stage.run(2.0, 2.5, lambda t: {2: standing(0.3, 1.5)})
    states = [(e.zone, e.occupied, e.persons) for e in sink.of(ZoneState)]
    assert states == [("centre", True, (1,)), ("centre", True, (1, 2)), ("centre", True, (2,)),
                      ("centre", False, ()), ("front", True, (2,))]


def test_the_runtime_never_raises_into_the_engine():
    runtime, sink, stage = make(one_section("""
      - {name: go, joint: HandLeft, rises_above: 1.5, do: [play: motif]}"""))

    class Broken:
        def emit(self, events):
            raise RuntimeError("a view crashed")
    runtime.sink = Broken()
    raise_left(stage)                                     # must not raise
    assert runtime.counts["errors"] >= 1
    runtime.sink = sink
    stage.run(2.0, 3.0, lambda t: {1: standing(0, 0)})
    raise_left(stage, 3.0, 5.0)
    assert sink.of(TriggerFired)                           # and it goes on working


def test_unseen_joints_do_not_move_triggers():
    runtime, sink, stage = make(one_section("""
      - {name: go, joint: HandLeft, rises_above: 1.5, do: [play: motif]}"""))
    conf = np.ones(25)
    conf[JOINT_INDEX["HandLeft"]] = 0.0                   # no sensor sees the hand
    for k in range(30):
        stage.frame(k / 30, {1: (standing(0, 0, left_arm=math.pi * (k > 10)),
                                 (1, 1), conf)})
    assert sink.of(TriggerFired) == []


def test_a_real_engine_feeds_the_runtime():
    """Sensor datagrams -> Engine (ManualClock) -> PieceRuntime listener -> events."""
    piece = loads_piece(HEAD + one_section("""
      - {name: go, joint: HandLeft, rises_above: 1.5, do: [play: motif]}"""))
    clock = ManualClock(100.0)
    engine = Engine(clock=clock)
    sink = RecordingSink()
    runtime = PieceRuntime(piece, sink, seed=1)
    engine.listeners.append(runtime)
    engine.handle_datagram(encode_message("/registerDevice", "k1", "kinect2"))
    for k in range(60):
        clock.advance(1 / 30)
        arm = math.pi if k >= 30 else 0.0
        joints = standing(0.0, 1.0, left_arm=arm)
        engine.handle_datagram(encode_client_joints("k1", 0, joints, np.ones(25)))
    (fire,) = sink.of(TriggerFired)
    assert fire.person == 1 and 101.0 < fire.t < 101.3
    assert sink.of(SectionChange)[0].t == pytest.approx(100.0 + 1 / 30)
    assert len(sink.of(Note)) == 5 and sink.of(Note)[0].t == fire.t
