"""Each trigger kind on scripted skeleton streams with an injected clock.

Frames come from ``stage.testing.script.ScriptedStage`` at 30 Hz with exact,
scripted times; the runtime's events go to a RecordingSink.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stage.events import ControlChange, Note, NoteCut, OscOut, SectionChange, TriggerFired
from stage.joints import JOINT_INDEX, HandState
from stage.piece import PieceRuntime, RecordingSink, loads_piece
from stage.testing.script import ScriptedStage, standing, with_joint

FPS = 30.0
OPEN, CLOSED, LASSO, UNKNOWN = HandState.OPEN, HandState.CLOSED, HandState.LASSO, HandState.UNKNOWN

HEAD = """
piece: test
outputs: {cello: midi, space: osc}
zones:
  centre: {shape: cylinder, centre: [0, 0], radius: 0.8}
  halo: {shape: sphere, centre: [0, 1.6, 0.5], radius: 0.3}
  front: {shape: box, min: [-2, 0, 1], max: [2, 3, 2]}
phrases:
  a: {notes: [G3 1]}
  b: {notes: [A3 1]}
  c: {notes: [B3 1]}
"""


def make(triggers: str, seed: int = 1, extra: str = "", sections: str | None = None):
    """A one-section piece with ``triggers`` (YAML list items), its runtime, sink and stage."""
    body = sections if sections is not None else f"""
sections:
  - name: one
    phrases: [a, b, c]
    triggers:
{triggers}
"""
    piece = loads_piece(HEAD + extra + body)
    sink = RecordingSink()
    runtime = PieceRuntime(piece, sink, seed=seed)
    return runtime, sink, ScriptedStage(runtime)


def fired(sink: RecordingSink, name: str | None = None) -> list[TriggerFired]:
    return [e for e in sink.of(TriggerFired) if name is None or e.trigger == name]


def swing_arm(t, starts):
    """Arm angle: a quick swing up (0.5 s, the hand at about 4 m/s) from each start time,
    held for 0.5 s, then lowered slowly (2 s, under 1 m/s)."""
    for start in starts:
        if start <= t < start + 0.5:
            return math.pi * (t - start) / 0.5
        if start + 0.5 <= t < start + 1.0:
            return math.pi
        if start + 1.0 <= t < start + 3.0:
            return math.pi * (1.0 - (t - start - 1.0) / 2.0)
    return 0.0


def walk(x0, x1, t0, t1):
    """x position at time t for a walk from x0 (at t0) to x1 (at t1), z = 0."""
    def at(t):
        u = min(1.0, max(0.0, (t - t0) / (t1 - t0)))
        return x0 + u * (x1 - x0)
    return at


# ------------------------------------------------------------------ zones
def test_enters_and_leaves_a_cylinder_fire_once_each_at_the_border():
    runtime, sink, stage = make("""
      - {name: in, enters: centre, cooldown: 0, do: [play: a]}
      - {name: out, leaves: centre, cooldown: 0, do: [play: b]}
""")
    x = walk(-2.0, 2.0, 0.0, 4.0)          # 1 m/s through the centre, r = 0.8
    stage.run(0.0, 5.0, lambda t: {1: standing(x(t), 0.0)})
    (enter,), (leave,) = fired(sink, "in"), fired(sink, "out")
    # the torso centre reaches x = -0.8 at t = 1.2 s and x = +0.8 + 0.05 (hysteresis) at 2.85 s
    assert enter.t == pytest.approx(1.2, abs=1 / FPS + 1e-9)
    assert leave.t == pytest.approx(2.85, abs=1 / FPS + 1e-9)
    assert enter.person == 1 and enter.joint == "body"


def test_a_jittering_joint_on_a_zone_border_fires_once_not_forty_times():
    runtime, sink, stage = make("""
      - {name: touch, joint: HandLeft, enters: halo, cooldown: 0, do: [play: a]}
""")
    still = standing(0.0, 0.0)
    border = np.array([0.0, 1.6, 0.5 - 0.3])        # the sphere's nearest point
    rng = np.random.default_rng(7)

    def people(t):
        # the hand comes to the border in half a second and hovers there for 2 s:
        # +-2 cm of sensor jitter each frame, about forty crossings
        approach = max(0.0, 0.3 * (1.0 - t / 0.5))
        jitter = rng.uniform(-0.02, 0.02)
        return {1: with_joint(still, "HandLeft", border + [0.0, 0.0, jitter - approach])}
    stage.run(0.0, 2.5, people)
    assert len(fired(sink, "touch")) == 1
    # without hysteresis the same hand would have fired on most crossings
    runtime, sink, stage = make("""
      - {name: touch, joint: HandLeft, enters: halo, hysteresis: 0, cooldown: 0, do: [play: a]}
""")
    rng = np.random.default_rng(7)
    stage.run(0.0, 2.5, people)
    assert len(fired(sink, "touch")) > 10


def test_cooldown_limits_a_trigger_that_keeps_crossing():
    runtime, sink, stage = make("""
      - {name: touch, joint: HandLeft, enters: halo, hysteresis: 0, cooldown: 1.0, do: [play: a]}
""")
    still = standing(0.0, 0.0)
    inside, outside = np.array([0.0, 1.6, 0.5]), np.array([0.0, 1.6, -0.5])

    def people(t):  # in and out every other frame for 3.5 s
        return {1: with_joint(still, "HandLeft", inside if int(round(t * FPS)) % 2 else outside)}
    stage.run(0.0, 3.5, people)
    times = [e.t for e in fired(sink, "touch")]
    assert len(times) == 4
    assert all(b - a >= 1.0 for a, b in zip(times, times[1:]))


def test_min_dwell_ignores_a_brief_visit():
    runtime, sink, stage = make("""
      - {name: in, joint: HandLeft, enters: halo, dwell: 0.5, do: [play: a]}
""")
    still = standing(0.0, 0.0)
    inside, outside = np.array([0.0, 1.6, 0.5]), np.array([0.0, 1.6, -0.5])
    stage.run(0.0, 1.0, lambda t: {1: with_joint(still, "HandLeft", outside)})
    stage.run(1.0, 1.3, lambda t: {1: with_joint(still, "HandLeft", inside)})   # 0.3 s: too short
    stage.run(1.3, 2.0, lambda t: {1: with_joint(still, "HandLeft", outside)})
    assert fired(sink) == []
    stage.run(2.0, 3.0, lambda t: {1: with_joint(still, "HandLeft", inside)})   # 1 s
    (event,) = fired(sink)
    assert event.t == pytest.approx(2.5, abs=1e-9)


def test_dwells_fires_after_the_time_inside_once_per_visit():
    runtime, sink, stage = make("""
      - {name: stay, dwells: front, for: 2, do: [play: a]}
""")
    stage.run(0.0, 1.0, lambda t: {1: standing(0.0, 0.0)})
    stage.run(1.0, 5.0, lambda t: {1: standing(0.0, 1.5)})
    stage.run(5.0, 6.0, lambda t: {1: standing(0.0, 0.0)})
    stage.run(6.0, 9.0, lambda t: {1: standing(0.0, 1.5)})
    times = [e.t for e in fired(sink, "stay")]
    assert times == pytest.approx([3.0, 8.0], abs=1e-9)
    assert fired(sink)[0].value == pytest.approx(2.0, abs=1e-9)


def test_box_zone_and_no_firing_for_someone_already_inside_when_the_section_starts():
    runtime, sink, stage = make("""
      - {name: in, enters: front, do: [play: a]}
""")
    stage.run(0.0, 2.0, lambda t: {1: standing(0.0, 1.5)})     # already downstage
    assert fired(sink) == []
    stage.run(2.0, 3.0, lambda t: {1: standing(0.0, 0.0)})
    stage.run(3.0, 4.0, lambda t: {1: standing(0.0, 1.5)})
    assert len(fired(sink)) == 1


# ------------------------------------------------------------------ heights, speeds
def test_rises_above_a_height_and_above_the_head_and_re_arms_below_with_hysteresis():
    runtime, sink, stage = make("""
      - {name: high, joint: HandLeft, rises_above: 1.5, cooldown: 0, do: [play: a]}
      - {name: over head, joint: HandRight, rises_above: Head, cooldown: 0, do: [play: b]}
""")
    def arm(t):  # both arms swing up and down twice: 0 -> pi -> 0 in 2 s
        a = math.pi * (0.5 - 0.5 * math.cos(2 * math.pi * t / 2.0))
        return {1: standing(0.0, 0.0, left_arm=a, right_arm=a)}
    stage.run(0.0, 4.0, arm)
    assert len(fired(sink, "high")) == 2
    assert len(fired(sink, "over head")) == 2
    high = fired(sink, "high")[0]
    assert high.joint == "HandLeft" and high.value > 1.5


def test_falls_below_and_a_hand_already_up_at_section_start_does_not_fire():
    runtime, sink, stage = make("""
      - {name: up, joint: HandLeft, rises_above: 1.5, do: [play: a]}
      - {name: bow, joint: Head, falls_below: 1.3, do: [play: b]}
""")
    stage.run(0.0, 1.0, lambda t: {1: standing(0.0, 0.0, left_arm=math.pi)})
    assert fired(sink, "up") == []
    head = JOINT_INDEX["Head"]

    def bow(t):
        j = standing(0.0, 0.0)
        j[head, 1] = 1.65 - 0.5 * min(1.0, t - 1.0)   # down to 1.15 m over a second
        return {1: j}
    stage.run(1.0, 2.5, bow)
    (event,) = fired(sink, "bow")
    assert event.value <= 1.3 and 1.6 < event.t < 1.75


def test_speed_above_fires_per_swing_and_re_arms_when_slow():
    runtime, sink, stage = make("""
      - {name: fast, joint: HandRight, speed_above: 2.0, cooldown: 0, do: [{note: {pitch: G3, velocity: speed}}]}
""")
    stage.run(0.0, 8.0, lambda t: {1: standing(0.0, 0.0, right_arm=swing_arm(t, (0.5, 4.0)))})
    events = fired(sink, "fast")
    assert len(events) == 2
    assert all(e.value > 2.0 for e in events)
    notes = [e for e in sink.events if type(e).__name__ == "Note"]
    assert len(notes) == 2 and all(40 <= n.velocity <= 120 for n in notes)


def test_moves_in_a_direction_only_that_way():
    runtime, sink, stage = make("""
      - {name: lift, joint: HandLeft, moves: up, speed: 1.0, cooldown: 0, do: [play: a]}
      - {name: forward, joint: body, moves: downstage, speed: 0.5, do: [play: b]}
""")
    hand = JOINT_INDEX["HandLeft"]

    def people(t):
        j = standing(0.0, 0.0)
        if 1.0 <= t < 1.5:
            j[hand, 1] = 0.8 - 2.0 * (t - 1.0)          # down fast: no firing
        elif 1.5 <= t < 2.0:
            j[hand, 1] = -0.2 + 2.0 * (t - 1.5)         # up fast: fires
        return {1: j}
    stage.run(0.0, 3.0, people)
    (event,) = fired(sink, "lift")
    assert 1.5 <= event.t < 1.6
    stage.run(3.0, 5.0, lambda t: {1: standing(0.0, (t - 3.0) * 1.0)})   # walks downstage
    assert len(fired(sink, "forward")) == 1


# ------------------------------------------------------------------ hands, steps, presence
def test_hand_state_becomes_closed_with_flicker_and_unknown_frames():
    runtime, sink, stage = make("""
      - {name: grip, joint: HandRight, hand: closed, cooldown: 0, do: [play: a]}
      - {name: point, hand: lasso, cooldown: 0, do: [play: b]}
""")
    j = standing(0.0, 0.0)
    script = ([OPEN] * 30 + [CLOSED] + [OPEN] * 10 +          # one-frame flicker: ignored
              [CLOSED] * 10 + [UNKNOWN] * 5 + [CLOSED] * 10 +  # unknown in between: one firing
              [OPEN] * 10 + [CLOSED] * 10)                     # open again, closed again: second
    for k, state in enumerate(script):
        stage.frame(k / FPS, {1: (j, (OPEN, state))})
    events = fired(sink, "grip")
    assert len(events) == 2
    assert events[0].t == pytest.approx((41 + 3) / FPS)      # after 0.1 s of dwell
    assert events[0].joint == "HandRight"
    stage.frame(len(script) / FPS, {1: (j, (LASSO, OPEN))})
    for k in range(1, 6):
        stage.frame((len(script) + k) / FPS, {1: (j, (LASSO, OPEN))})
    (point,) = fired(sink, "point")
    assert point.joint == "HandLeft"


def test_step_fires_when_a_foot_is_put_down_after_a_swing():
    runtime, sink, stage = make("""
      - {name: step, joint: FootRight, step: true, cooldown: 0, do: [play: a]}
""")
    foot = JOINT_INDEX["FootRight"]

    def people(t):
        j = standing(0.0, 0.0)
        k = t % 1.0                          # a step a second: 0.4 s swing, 0.6 s planted
        phase = min(k / 0.4, 1.0)
        z = 0.1 + 0.5 * (math.floor(t) + (0.5 - 0.5 * math.cos(math.pi * phase)))
        j[foot] = [-0.1, 0.02 + 0.08 * math.sin(math.pi * phase), z]
        return {1: j}
    stage.run(0.0, 3.0, people)
    events = fired(sink, "step")
    assert len(events) == 3
    assert all(e.value > 1.0 for e in events)              # the swing's peak speed
    assert all(0.4 <= e.t % 1.0 <= 0.45 for e in events)   # when the foot stops


def test_step_gait_fires_once_per_walking_step_with_its_length_width_and_time():
    # a walk with a set gait (the simulator's planted-feet walker): 8 placements of 0.65 m,
    # 0.15 m apart sideways, at 100 steps a minute, left foot first
    from stage.sensors.sim.gait import GaitClip
    walk = GaitClip(8, step_length=0.65, step_width=0.15, cadence=100.0)
    runtime, sink, stage = make("""
      - {name: stride, step: gait, cooldown: 0,
         do: [{osc: {address: /step, args: [$joint, $value, $step_width, $step_time, $speed]}}]}
      - {name: left only, joint: FootLeft, step: gait, cooldown: 0, do: [play: a]}
      - {name: swing, step: true, cooldown: 0, do: [play: b]}
""")
    stage.run(0.0, walk.duration, lambda t: {1: walk.joints(t)})
    steps = [o.args for o in sink.events if type(o).__name__ == "OscOut" and o.address == "/step"]
    # placements 2-8 each end a step (the first has none before it); the last placement, the
    # closing foot never passes, so it is never a foot event: 6 steps
    assert len(steps) == 6
    # left foot first: the right passes the standing left (its placement, no step before it),
    # then the left passes the right, which ended the first step: right, left, right, ...
    assert [a[0] for a in steps] == ["FootRight", "FootLeft"] * 3
    for k, (joint, length, width, step_time, speed) in enumerate(steps):
        assert length == pytest.approx(0.65, abs=0.005)
        # the first step's walking direction still sees the start of the walk
        assert width == pytest.approx(0.15, abs=0.01 if k == 0 else 0.002)
        assert step_time == pytest.approx(0.6, abs=0.05 if k == 0 else 1 / FPS)
        assert speed == pytest.approx(length / step_time)
    assert len(fired(sink, "left only")) == 3
    # the same walk with step: true (a foot swings and is put down): every landing, both feet
    assert len(fired(sink, "swing")) >= 8


def test_step_gait_is_checked_when_the_piece_loads():
    from stage.errors import ConfigError
    with pytest.raises(ConfigError, match="'step' in trigger 1 of section 'one' must be true or "
                                          "gait, got 'walk'"):
        make("      - {step: walk, do: [play: a]}")
    with pytest.raises(ConfigError, match="'speed' is the swing speed"):
        make("      - {step: gait, speed: 1.0, do: [play: a]}")


def test_appears_and_disappears():
    runtime, sink, stage = make("""
      - {name: hello, appears: true, do: [{osc: {address: /hello, args: [$person]}}]}
      - {name: bye, disappears: true, cooldown: 0, do: [{osc: {address: /bye, args: [$person]}}]}
""")
    stage.run(0.0, 1.0, lambda t: {1: standing(0, 0)})
    stage.run(1.0, 2.0, lambda t: {1: standing(0, 0), 2: standing(1, 0)})
    stage.run(2.0, 3.0, lambda t: {2: standing(1, 0)})
    assert [(e.trigger, e.person) for e in fired(sink)] == [("hello", 1), ("hello", 2), ("bye", 1)]
    osc = [e for e in sink.events if type(e).__name__ == "OscOut"]
    assert [(o.address, o.args) for o in osc] == [("/hello", (1,)), ("/hello", (2,)), ("/bye", (1,))]


def test_stage_empty_and_elapsed_fire_on_ticks_without_frames():
    runtime, sink, stage = make("""
      - {name: empty, stage_empty: 5, do: [play: a]}
      - {name: late, elapsed: 3, do: [play: b]}
""")
    runtime.start(0.0)
    stage.run(0.0, 1.0, lambda t: {1: standing(0, 0)})
    stage.frame(1.0, {})                       # the dancer is lost at 1 s
    for k in range(1, 121):
        runtime.tick(1.0 + k * 0.05)           # 6 s of nothing
    assert [e.t for e in fired(sink, "late")] == pytest.approx([3.0])
    assert [e.t for e in fired(sink, "empty")] == pytest.approx([6.0])


# ------------------------------------------------------------------ gating
def test_cooldown_per_performer_lets_two_people_play_together():
    runtime, sink, stage = make("""
      - {name: in, enters: centre, cooldown: 10, cooldown_per: performer, do: [play: a]}
""")
    stage.run(0.0, 0.5, lambda t: {1: standing(-2, 0), 2: standing(2, 0)})
    stage.run(0.5, 1.0, lambda t: {1: standing(0, 0), 2: standing(0.3, 0.3)})
    assert sorted(e.person for e in fired(sink)) == [1, 2]


def test_once_after_and_performer_selection():
    runtime, sink, stage = make("""
      - {name: once, enters: centre, once: true, cooldown: 0, do: [play: a]}
      - {name: later, joint: HandLeft, rises_above: 1.5, after: 2, cooldown: 0, do: [play: b]}
      - {name: newest only, enters: front, performer: newest, cooldown: 0, do: [play: c]}
""")
    x = lambda t: -2.0 + 4.0 * (t % 1.0)     # through the centre once a second
    stage.run(0.0, 3.0, lambda t: {1: standing(x(t), 0), 2: standing(3, -1.5)})
    assert len(fired(sink, "once")) == 1
    # raised at 1 s (too early: consumed), again at 2.5 s: fires
    up = lambda t: math.pi if (1.0 <= t < 1.5 or 2.5 <= t < 3.0) else 0.0
    runtime2, sink2, stage2 = make("""
      - {name: later, joint: HandLeft, rises_above: 1.5, after: 2, cooldown: 0, do: [play: b]}
""")
    stage2.run(0.0, 3.5, lambda t: {1: standing(0, 0, left_arm=up(t))})
    assert [round(e.t, 2) for e in fired(sink2, "later")] == [2.5]
    # person 1 (first) walks downstage: nothing; person 2 (newest) does: fires
    stage.run(3.0, 4.0, lambda t: {1: standing(-1, 1.5), 2: standing(3, -1.5)})
    assert fired(sink, "newest only") == []
    stage.run(4.0, 5.0, lambda t: {1: standing(-1, 1.5), 2: standing(1, 1.5)})
    assert [e.person for e in fired(sink, "newest only")] == [2]


def test_while_condition_gates_a_trigger():
    runtime, sink, stage = make("""
      - name: low and fast
        joint: HandRight
        speed_above: 2.0
        cooldown: 0
        while: {joint: Head, below: 1.3}
        do: [play: a]
""")
    head = JOINT_INDEX["Head"]

    def people(t, crouched):
        j = standing(0.0, 0.0, right_arm=swing_arm(t, (0.5, 4.5)))
        if crouched:
            j[head, 1] = 1.1
        return {1: j}
    stage.run(0.0, 4.0, lambda t: people(t, False))     # standing tall: the swing is silent
    assert fired(sink) == []
    stage.run(4.0, 8.0, lambda t: people(t, True))      # crouched: the same swing sounds
    assert len(fired(sink)) == 1 and 4.5 < fired(sink)[0].t < 5.0


def test_probability_is_reproducible_with_a_seed():
    def run(seed):
        runtime, sink, stage = make("""
      - {name: maybe, joint: HandLeft, rises_above: 1.5, probability: 0.5, cooldown: 0, do: [play: a]}
""", seed=seed)
        up = lambda t: math.pi if (t % 1.0) < 0.5 else 0.0
        stage.run(0.0, 40.0, lambda t: {1: standing(0, 0, left_arm=up(t))})
        return [round(e.t, 3) for e in fired(sink)]
    a, b, c = run(3), run(3), run(4)
    assert a == b and a != c
    assert 10 < len(a) < 30


# ------------------------------------------------------------------ choice and sections
def _picks(seed, pick):
    runtime, sink, stage = make(f"""
      - {{name: p, joint: HandLeft, rises_above: 1.5, cooldown: 0, do: [{{play: {{pick: {pick}}}}}]}}
""", seed=seed)
    up = lambda t: math.pi if (t % 1.0) >= 0.5 else 0.0
    stage.run(0.0, 30.0, lambda t: {1: standing(0, 0, left_arm=up(t))})
    names = {55: "a", 57: "b", 59: "c"}
    return [names[n.note] for n in sink.events if type(n).__name__ == "Note"]


def test_random_choice_is_reproducible_with_a_seed_and_never_repeats_at_once():
    a, b, c = _picks(11, "random"), _picks(11, "random"), _picks(12, "random")
    assert len(a) == 30 and a == b and a != c
    assert all(x != y for x, y in zip(a, a[1:]))
    assert set(a) == {"a", "b", "c"}


def test_next_cycles_and_shuffle_plays_each_before_repeating():
    assert _picks(1, "next")[:7] == ["a", "b", "c", "a", "b", "c", "a"]
    s = _picks(5, "shuffle")
    for k in range(0, 27, 3):
        assert sorted(s[k:k + 3]) == ["a", "b", "c"]
    assert all(x != y for x, y in zip(s, s[1:]))


# 'now': move on at once (issue 12: a plain 'goto' now waits for the sounding phrase;
# these transitions test the movement, so they say 'now')
SECTIONS = """
sections:
  - name: one
    phrases: [a]
    on_enter: [{program: 42}]
    triggers:
      - {name: to two, enters: centre, do: [play: a, goto: {to: next, now: true}]}
  - name: two
    phrases: [b]
    triggers:
      - {name: back, leaves: centre, do: [goto: previous]}
      - {name: jump, joint: HandLeft, rises_above: 1.5, do: [goto: three]}
  - name: three
    triggers:
      - {name: beyond, joint: HandLeft, falls_below: 1.0, do: [goto: next]}
"""


def test_section_transitions_driven_by_movement():
    runtime, sink, stage = make("", sections=SECTIONS)
    stage.run(0.0, 1.0, lambda t: {1: standing(-2, 0)})
    stage.run(1.0, 2.0, lambda t: {1: standing(0, 0)})          # into the centre: one -> two
    stage.run(2.0, 3.0, lambda t: {1: standing(-2, 0)})         # out again: two -> one
    stage.run(3.0, 4.0, lambda t: {1: standing(0, 0)})          # one -> two
    stage.run(4.0, 5.0, lambda t: {1: standing(0, 0, left_arm=math.pi)})  # two -> three
    stage.run(5.0, 6.0, lambda t: {1: standing(0, 0)})          # three: next = nothing after
    changes = sink.of(SectionChange)
    assert [(c.section, c.previous, c.cause) for c in changes] == [
        ("one", None, "start"), ("two", "one", "to two"), ("one", "two", "back"),
        ("two", "one", "to two"), ("three", "two", "jump")]
    assert [c.index for c in changes] == [0, 1, 0, 1, 2]
    programs = [e for e in sink.events if type(e).__name__ == "ProgramChange"]
    assert [p.t for p in programs] == [0.0, 2.0]                 # on_enter of 'one', each visit
    assert runtime.section.name == "three"


def test_operator_safety_forces_sections():
    runtime, sink, stage = make("", sections=SECTIONS)
    runtime.start(0.0)
    assert runtime.goto("next", 1.0) and runtime.section.name == "two"
    assert runtime.goto("three", 2.0) and runtime.section.name == "three"
    assert not runtime.goto("next", 3.0)
    assert runtime.goto("previous", 4.0) and runtime.section.name == "two"
    assert sink.of(SectionChange)[-1].cause == "operator"


def test_goto_end_lets_the_last_phrase_finish_ring_and_fade_then_ends():
    """Issue 12: 'goto: end' used to end everything at once (the last phrase cut, exit
    messages never sent); now the last phrase finishes, its last note is held (CC 64)
    and faded (CC 11), the room rings, and the piece's own triggers act until the end."""
    runtime, sink, stage = make("""
      - {name: finish, enters: centre, do: [play: a, goto: end]}
      - {name: more, joint: HandLeft, rises_above: 1.5, cooldown: 0, do: [play: b]}
""", extra="""ending: {fade: 2, ring: 0.5}
triggers:
  - {name: gone, disappears: true, do: [osc: /gone]}
mappings:
  - {name: swell, joint: HandRight, in_range: [0, 2], cc: 11}
  - {name: where, joint: body, measure: x, in_range: [-3, 3], osc: /x}
""")
    stage.run(0.0, 1.0, lambda t: {1: standing(-2, 0)})
    stage.run(1.0, 2.0, lambda t: {1: standing(0, 0)})
    (finish,) = fired(sink)
    assert finish.trigger == "finish" and runtime.ending and not runtime.ended
    (note,) = sink.of(Note)
    assert runtime.ends_at == pytest.approx(note.t + 1.0 + 2.0 + 0.5)   # phrase, fade, ring
    ccs = [(c.t - note.t, c.control, c.value) for c in sink.of(ControlChange)
           if c.t > note.t]                          # the ending's (...and is restored to it)
    assert ccs[0] == (pytest.approx(0.02), 64, 127)                 # held from its onset
    fade = [(t, v) for t, c, v in ccs if c == 11]
    assert fade[0][0] > 1.0 and fade[-2] == (pytest.approx(3.0), 0)  # after it, down to 0
    assert all(a[1] >= b[1] for a, b in zip(fade, fade[1:-1]))
    swell = [c.value for c in sink.of(ControlChange) if c.control == 11 and c.t <= finish.t][-1]
    assert fade[0][1] < swell                       # it falls from the mapping's last value...
    assert (pytest.approx(3.0), 64, 0) in ccs and fade[-1] == (pytest.approx(3.5), swell)
    swells = len([c for c in sink.of(ControlChange) if c.control == 11])
    xs = len([o for o in sink.of(OscOut) if o.address == "/x"])
    stage.run(2.0, 3.5, lambda t: {1: standing(0.5 * t - 1.0, 0, left_arm=math.pi * (t > 2.5),
                                               right_arm=t)})
    assert [e.trigger for e in fired(sink)] == ["finish"]          # the section has finished
    assert len([c for c in sink.of(ControlChange) if c.control == 11]) == swells  # the fade's
    assert len([o for o in sink.of(OscOut) if o.address == "/x"]) > xs             # she moves
    assert not runtime.goto("next", 3.5)
    stage.run(3.5, 4.0, lambda t: {})                             # she leaves: the exit sounds
    assert [e.trigger for e in fired(sink)] == ["finish", "gone"]
    assert not runtime.ended
    runtime.tick(note.t + 3.5)
    assert runtime.ended
    stage.run(4.6, 5.0, lambda t: {1: standing(0, 0)})
    assert [e.trigger for e in fired(sink)] == ["finish", "gone"]  # nothing acts any more
    assert len(sink.of(Note)) == 1 and not sink.of(NoteCut)        # it rang out whole


def test_goto_waits_for_the_sounding_phrase_unless_now():
    runtime, sink, stage = make("", sections="""
sections:
  - name: one
    triggers:
      - {name: go, enters: centre, do: [play: a, goto: next]}
  - name: two
    triggers:
      - {name: hurry, joint: HandLeft, rises_above: 1.5,
         do: [play: b, goto: {to: three, now: true}]}
  - name: three
""")
    stage.run(0.0, 1.0, lambda t: {1: standing(-2, 0)})
    stage.run(1.0, 3.0, lambda t: {1: standing(0, 0)})
    (go,) = fired(sink)
    change = sink.of(SectionChange)[1]
    assert change.section == "two" and change.cause == "go"
    assert go.t + 1.0 <= change.t < go.t + 1.0 + 0.034            # when 'a' (1 beat) has ended
    stage.run(3.0, 4.0, lambda t: {1: standing(0, 0, left_arm=math.pi * (t > 3.2))})
    hurry = fired(sink)[-1]
    assert hurry.trigger == "hurry" and sink.of(SectionChange)[-1].t == hurry.t  # at once


def test_a_persons_joints_read_as_floats_whatever_the_order_they_are_asked_in():
    """The runtime's view of a body makes a joint's floats when first asked for: every
    joint reads as the body has it, a low-confidence joint is None through ``xyz`` and still
    readable through ``joint`` (a phrase's $x of the joint that fired)."""
    from stage.frames import Body
    from stage.piece.model import BODY
    from stage.piece.triggers import Person
    rng = np.random.default_rng(3)
    joints, conf = rng.normal(0.0, 1.0, (25, 3)), np.ones(25)
    conf[[4, 11]] = 0.2
    body = Body(1, joints, conf, np.zeros((25, 3)), (HandState.OPEN, HandState.OPEN),
                joints[:3].mean(axis=0), ("s0",))
    p = Person(body, 0.5, 0.0)
    for j in rng.permutation(25):
        assert p.joint(j) == joints[j].tolist()
        assert p.joint(j) is p.joint(j)            # made once
        assert p.xyz(j) == (None if j in (4, 11) else joints[j].tolist())
    assert p.xyz(BODY) == body.position.tolist()


def test_a_persons_velocities_read_as_floats_whatever_the_order_they_are_asked_in():
    """The same for a joint's velocity and speed, made when first asked for: every joint's
    as the body has it, and the torso centre's (``BODY``) that of SpineMid."""
    from stage.frames import Body
    from stage.joints import JOINT_INDEX
    from stage.piece.model import BODY
    from stage.piece.triggers import Person
    rng = np.random.default_rng(4)
    joints, vel = rng.normal(0.0, 1.0, (25, 3)), rng.normal(0.0, 2.0, (25, 3))
    body = Body(1, joints, np.ones(25), vel, (HandState.OPEN, HandState.OPEN),
                joints[:3].mean(axis=0), ("s0",))
    p = Person(body, 0.5, 0.0)
    assert p.vel(BODY) == vel[JOINT_INDEX["SpineMid"]].tolist()
    for j in rng.permutation(25):
        assert p.vel(j) == vel[j].tolist() and p.vel(j) is p.vel(j)
        assert p.speed(j) == pytest.approx(float(np.linalg.norm(vel[j])), rel=1e-12)
