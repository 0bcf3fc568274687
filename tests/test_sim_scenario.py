"""Scenario files and choreography: what a composer writes is what the performer does."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from stage.errors import ConfigError
from stage.joints import JOINT_INDEX as J
from stage.joints import HandState
from stage.sensors.sim import Simulator, builtin_names, load_scenario, parse_scenario
from stage.testing.walks import cmu_file
from stage.yamlio import loads_marked

#: $STAGE_CMU_DIR, else shared/data/cmu beside the checkout or above it (a worktree too)
CMU = cmu_file("131_01")


def performer(timeline: str, extra: str = "", path: str = "test.yaml"):
    """A ring of three sensors and one performer 'p' with this timeline (YAML list text)."""
    extra = textwrap.dedent(extra)
    given = {line.split(":")[0].strip() for line in extra.splitlines() if ":" in line}
    defaults = "".join(f"{k}: {v}\n" for k, v in (("height", "1.75"), ("position", "[0, 0]"),
                                                 ("facing", "0")) if k not in given)
    text = textwrap.dedent("""
        sensors:
          ring: {count: 3}
        performers:
          - name: p
        """) + textwrap.indent(defaults + extra, " " * 4) + \
        "    timeline:\n" + textwrap.indent(textwrap.dedent(timeline), " " * 6)
    sc = parse_scenario(loads_marked(text, path), path)
    return sc, sc.performers[0]


def same_angle(a: float, b: float, tol: float = 1e-6) -> bool:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi) <= tol


def joints(p, t: float) -> np.ndarray:
    return p.state(t)[0]


def heading_of(j: np.ndarray) -> float:
    left = j[J["HipLeft"]] - j[J["HipRight"]]
    return math.atan2(-left[2], left[0])


def test_walk_reaches_its_target_at_its_speed_facing_the_way():
    _, p = performer("- {walk: [0, 2], speed: 1.0}\n- {walk: [[1, 2], [1, 0]], over: 4}")
    assert joints(p, 2.0)[J["SpineBase"]][[0, 2]] == pytest.approx([0, 2], abs=1e-6)
    mid = joints(p, 1.0)
    assert mid[J["SpineBase"]][[0, 2]] == pytest.approx([0, 1], abs=1e-6)
    assert heading_of(mid) == pytest.approx(0.0, abs=0.05)
    # stride: the feet are apart while walking, together standing
    gap = abs(mid[J["AnkleLeft"], 2] - mid[J["AnkleRight"], 2])
    assert gap > 0.2 or abs(joints(p, 1.2)[J["AnkleLeft"], 2] - joints(p, 1.2)[J["AnkleRight"], 2]) > 0.2
    assert joints(p, 6.0)[J["SpineBase"]][[0, 2]] == pytest.approx([1, 0], abs=1e-6)
    assert same_angle(heading_of(joints(p, 5.0)), math.pi, 0.05)  # walking towards -z
    still = joints(p, 7.0)
    assert abs(still[J["AnkleLeft"], 2] - still[J["AnkleRight"], 2]) < 1e-6
    assert p.length == pytest.approx(6.0)


def test_feet_stay_on_the_floor_while_walking():
    _, p = performer("- {walk: [0, 3], speed: 1.2}")
    lowest = [min(joints(p, t)[J["AnkleLeft"], 1], joints(p, t)[J["AnkleRight"], 1])
              for t in np.arange(0.3, 2.2, 0.05)]
    assert np.allclose(lowest, lowest[0], atol=1e-9)


def test_raise_lower_arms_by_angle_and_plane():
    _, p = performer("""
        - {raise: left, to: 90, over: 1}
        - {raise: right, to: 180, over: 1, with: previous}
        - {raise: both, to: 90, plane: front, over: 1}
        - {lower: both, over: 0.5}
        """)
    j = joints(p, 1.0)
    shoulder = j[J["ShoulderLeft"]]
    assert j[J["HandLeft"], 1] == pytest.approx(shoulder[1], abs=0.01)
    assert j[J["HandLeft"], 0] > shoulder[0] + 0.5  # out to the performer's left (+x facing +z)
    assert j[J["HandRight"], 1] > j[J["Head"], 1] + 0.3
    j = joints(p, 2.0)
    assert j[J["HandLeft"], 2] > j[J["ShoulderLeft"], 2] + 0.5  # straight ahead
    j = joints(p, 2.5)
    assert j[J["HandLeft"], 1] < j[J["ShoulderLeft"], 1] - 0.5
    half = joints(p, 0.5)[J["HandLeft"], 1]
    assert j[J["HandLeft"], 1] < half < joints(p, 1.0)[J["HandLeft"], 1]  # eased, not a jump


def test_reach_puts_the_hand_on_a_stage_point_and_keeps_it_there():
    target = [-0.25, 1.3, 0.4]  # within the right arm's reach
    _, p = performer(f"""
        - {{reach: right, to: {target}, over: 0.8}}
        - {{turn: 20, over: 1}}
        - {{crouch: 0.1, over: 1, with: previous}}
        """)
    assert np.linalg.norm(joints(p, 0.8)[J["HandRight"]] - target) < 1e-6
    # the body turns and lowers; the hand stays on the point
    assert np.linalg.norm(joints(p, 1.4)[J["HandRight"]] - target) < 1e-6
    assert np.linalg.norm(joints(p, 2.0)[J["HandRight"]] - target) < 1e-6


def test_point_aims_the_straight_arm_at_a_sensor():
    sc, p = performer("- {point: left, to: kinect-b, over: 0.5}")
    j = joints(p, 1.0)
    arm = j[J["HandLeft"]] - j[J["ShoulderLeft"]]
    towards = sc.sensors[1].pose.position - j[J["ShoulderLeft"]]
    cos = arm @ towards / np.linalg.norm(arm) / np.linalg.norm(towards)
    assert cos > 0.999


def test_crouch_jump_step_turn_face():
    sc, p = performer("""
        - {crouch: 0.35, over: 1}
        - {stand: true, over: 1}
        - {jump: 0.3}
        - {step: forward}
        - {turn: 90, over: 1}
        - {step: left, size: 0.5}
        - {face: kinect-a, over: 1}
        """)
    head0 = joints(p, 0.0)[J["Head"], 1]
    low = joints(p, 1.0)
    assert low[J["Head"], 1] < head0 - 0.25
    assert min(low[J["AnkleLeft"], 1], low[J["AnkleRight"], 1]) == pytest.approx(
        joints(p, 0.0)[J["AnkleLeft"], 1], abs=1e-9)
    airtime = 2 * math.sqrt(2 * 0.3 / 9.81)
    top = joints(p, 2.0 + airtime / 2)
    assert top[J["AnkleLeft"], 1] > joints(p, 0)[J["AnkleLeft"], 1] + 0.25
    t = 2.0 + airtime
    assert joints(p, t + 0.6)[J["SpineBase"]][[0, 2]] == pytest.approx([0, 0.6], abs=1e-6)
    assert heading_of(joints(p, t + 1.6)) == pytest.approx(math.pi / 2, abs=1e-6)
    # facing +x, the performer's left is -z
    assert joints(p, t + 2.2)[J["SpineBase"]][[0, 2]] == pytest.approx([0, 0.1], abs=1e-6)
    a = sc.sensors[0].pose.position
    end = joints(p, t + 3.5)
    want = math.atan2(a[0] - end[J["SpineBase"], 0], a[2] - end[J["SpineBase"], 2])
    assert same_angle(heading_of(end), want)


def test_hand_states_follow_the_timeline_and_loop():
    _, p = performer("""
        - {close: right}
        - {wait: 1}
        - {hands: {left: lasso, right: open}}
        - {wait: 1}
        - {hands: closed}
        - {wait: 1}
        """, extra="loop: true\n")
    assert p.state(0.5)[1] == (HandState.OPEN, HandState.CLOSED)
    assert p.state(1.5)[1] == (HandState.LASSO, HandState.OPEN)
    assert p.state(2.5)[1] == (HandState.CLOSED, HandState.CLOSED)
    assert p.state(3.5)[1] == (HandState.OPEN, HandState.CLOSED)  # second time round


def test_loop_repeats_the_body_exactly():
    _, p = performer("- {circle: [0, 1], turns: 1, speed: 1}", extra="loop: true\n")
    assert p.period == pytest.approx(2 * math.pi)
    np.testing.assert_allclose(joints(p, 1.0), joints(p, 1.0 + p.period), atol=1e-9)
    np.testing.assert_allclose(joints(p, 0.0)[J["SpineBase"]][[0, 2]], [0, 0], atol=1e-9)
    np.testing.assert_allclose(joints(p, p.period - 1e-6)[J["SpineBase"]][[0, 2]], [0, 0],
                               atol=1e-5)


def test_at_and_with_previous_schedule_parallel_steps():
    _, p = performer("""
        - {walk: [0, 4], over: 4}
        - {raise: left, to: 90, over: 0.5, at: 1}
        - {close: left, with: previous}
        - {lower: left, over: 0.5}
        """)
    assert p.state(0.9)[1][0] == HandState.OPEN
    assert p.state(1.0)[1][0] == HandState.CLOSED
    j = joints(p, 1.5)
    assert j[J["HandLeft"], 1] == pytest.approx(j[J["ShoulderLeft"], 1], abs=0.02)
    assert p.length == pytest.approx(4.5)  # the lower starts when everything before is done


def test_enter_leave_and_scenario_events():
    text = textwrap.dedent("""
        sensors: {ring: {count: 3}}
        performers:
          - {name: a, present: false, timeline: [{enter: [1, 0], at: 1}, {leave: true, at: 3}]}
          - {name: b}
        events:
          - {at: 2, leave: b}
          - {at: 4, enter: b, position: [-1, 0]}
        """)
    sim = Simulator(parse_scenario(loads_marked(text, "e.yaml"), "e.yaml"))
    assert set(sim.truth(0.5)) == {"b"}
    assert set(sim.truth(1.5)) == {"a", "b"}
    assert sim.truth(1.5)["a"][0][J["SpineBase"]][[0, 2]] == pytest.approx([1, 0])
    assert set(sim.truth(2.5)) == {"a"}
    assert set(sim.truth(3.5)) == set()
    assert sim.truth(4.5)["b"][0][J["SpineBase"]][[0, 2]] == pytest.approx([-1, 0])


@pytest.mark.parametrize("timeline, message, line", [
    ("- {wlak: [1, 1]}", "unknown key 'wlak' in a timeline step; did you mean 'walk'?", 10),
    ("- {walk: [1, 1]}\n- {raise: middle}", "'raise' takes left, right or both", 11),
    ("- {face: kinect-z}", "'kinect-z' is not a sensor", 10),
    ("- {walk: [1, 1], at: 5}\n- {open: left, at: 2}", "before the step above it", 11),
    ("- {walk: [1, 1], raise: left}", "a step needs exactly one action", 10),
    ("- {hands: fist}", "'fist' is not a hand state", 10),
    ("- {jump: 3}", "'jump' takes a height in metres", 10),
    ("- {bvh: missing.bvh}", "BVH file 'missing.bvh' not found", 10),
    ("- {walk: [1, 1], speed: -1}", "'speed' must be greater than 0", 10),
])
def test_errors_are_one_line_with_file_line_column(timeline, message, line):
    with pytest.raises(ConfigError) as err:
        performer(timeline, path="piece.sim.yaml")
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(f"piece.sim.yaml:{line}:"), text
    assert message in text


def test_broken_yaml_and_bad_top_level_keys(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sensors:\n  ring: {count: 3\nperformers: []\n")
    with pytest.raises(ConfigError, match=r"bad.yaml:\d+:\d+: YAML syntax"):
        load_scenario(str(bad))
    bad.write_text("sensor:\n  ring: {}\n")
    with pytest.raises(ConfigError, match="bad.yaml:1:1: unknown key 'sensor'.*'sensors'"):
        load_scenario(str(bad))
    bad.write_text("events:\n  - {at: 1, bump: kinect-q}\n")
    with pytest.raises(ConfigError, match="bad.yaml:2:19: 'kinect-q' is not a sensor"):
        load_scenario(str(bad))
    with pytest.raises(ConfigError, match="no built-in scenario 'nope'"):
        load_scenario("nope")


def test_a_webcam_client_sensor_reads_hands_every_frame_unless_the_scenario_says(tmp_path):
    # the engine counts a webcam-mediapipe sensor's hand reports as whole readings (rule 6 of
    # docs/osc-api.md): the simulated one reads them every frame, as the client does
    def frames_of(text: str) -> dict:
        path = tmp_path / "s.yaml"
        path.write_text(textwrap.dedent(text))
        sensors = load_scenario(str(path)).sensors
        return {s.id: (s.type, s.model.hand_update_frames) for s in sensors}

    cams = """\
        sensors:
          kin: {position: [0, 1, -3], look_at: [0, 1, 0]}
          cam: {position: [3, 1, 0], look_at: [0, 1, 0], type: webcam-mediapipe}
        """
    assert frames_of(cams) == {"kin": ("kinect2", 2), "cam": ("webcam-mediapipe", 1)}
    assert frames_of(cams + "kinect: {hand_update_frames: 3}\n") == \
        {"kin": ("kinect2", 3), "cam": ("webcam-mediapipe", 3)}
    assert frames_of(cams.replace("type: webcam-mediapipe",
                                  "type: webcam-mediapipe, kinect: {hand_update_frames: 2}")) == \
        {"kin": ("kinect2", 2), "cam": ("webcam-mediapipe", 2)}


def test_builtin_scenarios_load_and_the_default_matches_the_spec():
    assert "default" in builtin_names()
    for name in builtin_names():
        load_scenario(name)
    sc = load_scenario(None)
    assert len(sc.sensors) == 3 and len(sc.performers) == 1
    yaws = sorted(math.degrees(s.pose.yaw) % 360 for s in sc.sensors)
    assert np.diff(yaws) == pytest.approx([120, 120])  # seed 004: 120 degrees apart
    assert sc.performers[0].period is not None


def _tiny_bvh(tmp_path: Path) -> Path:
    """A small CMU-named skeleton marching forward 1 m/s with a swinging left leg."""
    frames = []
    for k in range(121):
        t = k / 60
        z = t * 100.0
        swing = 20 * math.sin(2 * math.pi * t)
        frames.append(f"0 95 {z:.4f} 0 0 0  0 0 {swing:.4f}  0 0 0  0 0 0  0 0 0  0 0 0")
    hierarchy = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT LeftHip
  {
    OFFSET 9 -3 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT LeftKnee { OFFSET 0 -42 0 CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT LeftAnkle { OFFSET 0 -42 0 CHANNELS 0 End Site { OFFSET 0 -8 12 } } }
  }
  JOINT RightHip
  {
    OFFSET -9 -3 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT RightKnee { OFFSET 0 -42 0 CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT RightAnkle { OFFSET 0 -42 0 CHANNELS 0 End Site { OFFSET 0 -8 12 } } }
  }
  JOINT Chest2
  {
    OFFSET 0 45 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT Head { OFFSET 0 20 0 CHANNELS 0 End Site { OFFSET 0 22 0 } }
    JOINT LeftShoulder { OFFSET 18 -2 0 CHANNELS 0
      JOINT LeftElbow { OFFSET 0 -28 0 CHANNELS 0 JOINT LeftWrist { OFFSET 0 -24 0 CHANNELS 0 End Site { OFFSET 0 -8 0 } } } }
    JOINT RightShoulder { OFFSET -18 -2 0 CHANNELS 0
      JOINT RightElbow { OFFSET 0 -28 0 CHANNELS 0 JOINT RightWrist { OFFSET 0 -24 0 CHANNELS 0 End Site { OFFSET 0 -8 0 } } } }
  }
}
MOTION
Frames: %d
Frame Time: %f
""" % (len(frames), 1 / 60)
    path = tmp_path / "march.bvh"
    path.write_text(hierarchy + "\n".join(frames) + "\n")
    return path


def test_bvh_performer_is_placed_turned_and_scaled(tmp_path):
    bvh = _tiny_bvh(tmp_path)
    _, p = performer(f"- {{bvh: {bvh}, facing: 90}}\n- {{wait: 1}}",
                     extra="position: [1, -1]\nheight: 1.82\n")
    start = joints(p, 0.0)
    assert start[J["SpineBase"]][[0, 2]] == pytest.approx([1, -1], abs=0.05)
    later = joints(p, 1.0)
    # the skeleton is 182 units tall: at 1.82 m a unit is 1 cm and the clip marches 1 m a
    # second along its +z; turned to face +x it goes along +x
    moved = later[J["SpineBase"]] - start[J["SpineBase"]]
    assert moved[[0, 2]] == pytest.approx([1.0, 0.0], abs=0.02)
    assert min(start[J["AnkleLeft"], 1], start[J["AnkleRight"], 1]) >= -1e-9
    # the clip lasts 2 s; afterwards the performer stands where it ended
    assert p.state(2.5)[0][J["SpineBase"]][[0, 2]] == pytest.approx([3, -1], abs=0.05)


@pytest.mark.skipif(CMU is None, reason="CMU motion capture not found ($STAGE_CMU_DIR or "
                    "shared/data/cmu above the checkout)")
def test_cmu_walk_drives_a_performer_seen_by_the_sensors(tmp_path):
    text = textwrap.dedent(f"""
        sensors: {{ring: {{count: 3, radius: 3.5}}}}
        performers:
          - {{name: walker, height: 1.75, position: [0, -1.2], motion: {CMU}}}
        """)
    sim = Simulator(parse_scenario(loads_marked(text, "cmu.yaml"), "cmu.yaml"), seed=1)
    j = sim.truth(2.0)["walker"][0]
    assert 1.5 < j[J["Head"], 1] < 1.85
    assert j[:, 1].min() > -0.02
    users = {sid for _, sid, d in sim.datagrams(3.0) if b"/jointCoordinates" in d}
    assert users == {"kinect-a", "kinect-b", "kinect-c"}


def test_default_scenario_with_any_number_of_sensors():
    from stage.sensors.sim import default_scenario
    for n in (1, 6):
        sc = default_scenario(n)
        assert [s.id for s in sc.sensors][-1] == f"kinect-{chr(ord('a') + n - 1)}"
        assert sc.reference == "kinect-a" and len(Simulator(sc).rig().sensors) == n
