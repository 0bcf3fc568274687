"""Body features on constructed poses: joint angles, distances, height, lean, centre of mass,
and the features that need time (speed, acceleration, quantity of motion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stage.analysis.features import (ANGLE_BY_INDEX, ANGLE_JOINTS, ANGLES, FeatureTracker,
                                     angle_at, body_height, centre_of_mass, hand_distances,
                                     joint_angle, joint_angles, lean, series, snapshot)
from stage.geometry import rot_x, rot_y, rot_z
from stage.joints import JOINT_INDEX as J
from stage.sensors.sim.kinematics import (ArmPose, BodyState, crouch_angles, proportions,
                                          skeleton, standing_pose)

PROPS = proportions(1.75)


def posed(left=ArmPose(), right=ArmPose(), crouch: float = 0.0) -> np.ndarray:
    return skeleton(BodyState(arms=(left, right), crouch=crouch), PROPS)


@pytest.mark.parametrize("bend", [0.0, 30.0, 45.0, 90.0, 135.0])
def test_elbow_angle_is_180_minus_the_bend_of_the_forearm(bend):
    j = posed(ArmPose(math.radians(60), math.radians(30), math.radians(bend)),
              ArmPose(math.radians(120), 0.0, math.radians(bend / 2)))
    assert joint_angle(j, "ElbowLeft") == pytest.approx(180.0 - bend, abs=1e-6)
    assert joint_angle(j, "ElbowRight") == pytest.approx(180.0 - bend / 2, abs=1e-6)


@pytest.mark.parametrize("elevation", [0.0, 45.0, 90.0, 150.0, 180.0])
def test_shoulder_angle_is_the_arm_elevation_from_the_trunk(elevation):
    for azimuth in (0.0, 45.0, 90.0):       # out to the side, diagonal, straight ahead
        j = posed(ArmPose(math.radians(elevation), math.radians(azimuth), 0.0))
        assert joint_angle(j, "ShoulderLeft") == pytest.approx(elevation, abs=1e-6)
        assert joint_angle(j, "ShoulderRight") == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("depth", [0.0, 0.15, 0.3, 0.5])
def test_knee_and_hip_angles_of_a_crouch(depth):
    j = posed(crouch=depth)
    hip_flex, knee_flex = crouch_angles(depth, PROPS)
    lean_deg = math.degrees(0.5 * hip_flex)   # the simulator leans the trunk half the hip flexion
    for side in ("Left", "Right"):
        assert joint_angle(j, "Knee" + side) == pytest.approx(180 - math.degrees(knee_flex),
                                                              abs=1e-6)
        assert joint_angle(j, "Hip" + side) == pytest.approx(
            180 - math.degrees(hip_flex) - lean_deg, abs=1e-6)
    assert lean(j)["lean_forward"] == pytest.approx(lean_deg, abs=1e-6)
    assert lean(j)["lean_side"] == pytest.approx(0.0, abs=1e-6)


def test_angles_of_a_hand_built_arm_at_any_place_and_turn():
    j = standing_pose()
    j[J["ShoulderLeft"]] = [0.0, 0.0, 0.0]
    j[J["ElbowLeft"]] = [0.3, 0.0, 0.0]
    j[J["WristLeft"]] = [0.3 + 0.25 * math.cos(math.radians(70)), 0.25 * math.sin(math.radians(70)),
                         0.0]                                  # the forearm 70 deg off straight
    assert joint_angle(j, "ElbowLeft") == pytest.approx(110.0, abs=1e-9)
    rng = np.random.default_rng(3)
    for _ in range(5):
        r = rot_y(rng.uniform(-3, 3)) @ rot_x(rng.uniform(-3, 3)) @ rot_z(rng.uniform(-3, 3))
        moved = j @ r.T + rng.uniform(-5, 5, 3)
        for name in ANGLES:
            assert joint_angle(moved, name) == pytest.approx(joint_angle(j, name), abs=1e-7)


def test_angle_at_from_points_agrees_with_the_array_version_and_needs_every_joint():
    j = posed(ArmPose(1.0, 0.4, 0.7), ArmPose(2.0, 0.9, 1.2), crouch=0.2)
    points = {k: tuple(j[k]) for k in range(25)}
    for name, (a, b) in ANGLES.items():
        assert angle_at(points, J[name]) == pytest.approx(float(joint_angle(j, name)), abs=1e-9)
        assert set(ANGLE_JOINTS[J[name]]) == {*a, *b}
    hidden = {**points, J["WristLeft"]: None}
    assert angle_at(hidden, J["ElbowLeft"]) is None
    assert angle_at(hidden, J["ElbowRight"]) is not None
    assert set(ANGLE_BY_INDEX) == {J[n] for n in ANGLES}


def test_angles_of_many_frames_and_missing_joints():
    frames = np.stack([posed(ArmPose(math.radians(e), 0, 0)) for e in (0, 90, 180)])
    frames[1, J["ElbowLeft"]] = np.nan
    a = joint_angles(frames)["ShoulderLeft"]
    assert a[0] == pytest.approx(0, abs=1e-6) and math.isnan(a[1]) and a[2] == pytest.approx(180)
    with pytest.raises(KeyError, match="no angle is defined at 'HandLeft'"):
        joint_angle(frames, "HandLeft")


def test_distances_height_and_lean():
    j = standing_pose(left_arm=math.pi / 2, right_arm=math.pi / 2)
    d = hand_distances(j)
    assert d["hand_to_hand"] == pytest.approx(abs(j[J["HandLeft"], 0] - j[J["HandRight"], 0]))
    assert d["hand_left_to_head"] == pytest.approx(np.linalg.norm(j[J["HandLeft"]] - j[J["Head"]]))
    assert body_height(j) == pytest.approx(j[J["Head"], 1] - min(j[J["FootLeft"], 1],
                                                                  j[J["AnkleLeft"], 1]))
    assert body_height(posed(crouch=0.4)) < body_height(posed()) - 0.3
    # the upper body tilted 20 degrees to the performer's left about SpineBase
    tilted = j.copy()
    upper = [J[n] for n in ("SpineMid", "SpineShoulder", "Neck", "Head")]
    base = j[J["SpineBase"]]
    tilted[upper] = (j[upper] - base) @ rot_z(math.radians(-20)).T + base
    f = lean(tilted)
    assert f["lean"] == pytest.approx(20, abs=1e-6)
    assert f["lean_side"] == pytest.approx(20, abs=1e-6)      # +x is the performer's left
    assert f["lean_forward"] == pytest.approx(0, abs=1e-6)


def test_centre_of_mass_of_a_symmetric_body_and_a_raised_arm():
    j = standing_pose((1.0, -2.0))
    com = centre_of_mass(j)
    assert com[0] == pytest.approx(1.0, abs=1e-9)
    assert 0.9 < com[1] < 1.1                  # about 55-57 % of a 1.75 m body's height
    raised = standing_pose((1.0, -2.0), left_arm=math.pi)
    assert centre_of_mass(raised)[1] > com[1] + 0.02   # the arm (5 % of the mass) goes up 0.6 m
    j[J["HandLeft"]] = np.nan                  # a missing hand: the rest re-weighted
    assert np.isfinite(centre_of_mass(j)).all()


def test_tracker_speed_acceleration_and_quantity_of_motion():
    tracker = FeatureTracker(window=1.0)
    j0 = standing_pose()
    v = np.array([0.6, 0.0, 0.8])              # 1 m/s
    out = None
    for k in range(60):                         # 2 s at constant velocity
        out = tracker.update(k / 30, j0 + v * k / 30)
    assert out.speed == pytest.approx(np.full(25, 1.0))
    assert np.allclose(out.acceleration, 0.0, atol=1e-9)
    assert out["com_speed"] == pytest.approx(1.0)
    assert out["com_speed_horizontal"] == pytest.approx(1.0)
    assert out["quantity_of_motion"] == pytest.approx(1.0)
    a = np.array([2.0, 0.0, 0.0])               # then accelerating at 2 m/s^2 along x
    x0 = j0 + v * 2.0
    for k in range(1, 31):
        t = k / 30
        out = tracker.update(2.0 + t, x0 + v * t + 0.5 * a * t * t)
    assert out.acceleration == pytest.approx(np.full(25, 2.0), rel=1e-6)
    for k in range(1, 31):                      # standing still for a second
        out = tracker.update(3.0 + k / 30, x0 + v + 0.5 * a)
    assert out["quantity_of_motion"] == pytest.approx(0.0, abs=1e-12)
    # a frame too close to the last one refreshes the pose but not the speeds
    again = tracker.update(4.0 + 0.001, x0 + v + 0.5 * a + [0, 0.5, 0])
    assert again.speed == pytest.approx(out.speed) and again["com_y"] > out["com_y"] + 0.4


def test_unseen_joints_are_missing_not_stale():
    tracker = FeatureTracker()
    j = standing_pose(left_arm=1.0)
    conf = np.ones(25)
    conf[J["WristLeft"]] = 0.0
    f = tracker.update(0.0, j, conf)
    assert math.isnan(f["angle_ElbowLeft"]) and not math.isnan(f["angle_ElbowRight"])
    assert set(snapshot(j)) <= set(f.values)


def test_series_gives_speeds_by_central_differences():
    t = np.arange(0, 1, 1 / 30)
    frames = np.stack([standing_pose((0.5 * tk, 0.0)) for tk in t])
    s = series(t, frames)
    assert s["speed"].shape == (30, 25)
    assert s["speed"] == pytest.approx(np.full((30, 25), 0.5))
    assert s["com_speed_horizontal"] == pytest.approx(np.full(30, 0.5))


def test_series_quantity_of_motion_is_the_mean_joint_speed_over_the_last_window():
    t = np.arange(0, 3, 1 / 30)
    x = np.where(t < 1.5, 0.6 * t, 0.9)        # walks at 0.6 m/s for 1.5 s, then stands
    frames = np.stack([standing_pose((xk, 0.0)) for xk in x])
    qom = series(t, frames, window=1.0)["quantity_of_motion"]
    assert qom[(t > 0.2) & (t < 1.4)] == pytest.approx(0.6, abs=1e-6)
    assert qom[t > 2.6] == pytest.approx(0.0, abs=1e-9)
