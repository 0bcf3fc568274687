"""Seed 003's agreement statistics and seed 004's KPIs on inputs with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stage.analysis.agreement import agreement, category, icc_a1
from stage.analysis.kpi import body_frame, hull_volume, kpis
from stage.analysis.trajectory import Trajectory
from stage.joints import JOINT_INDEX as J
from stage.sensors.sim.kinematics import standing_pose

# Shrout and Fleiss (1979), Table 2: six targets rated by four judges; their ICC(2,1) -- the
# two-way, absolute agreement, single-measure coefficient McGraw and Wong call ICC(A,1) -- is 0.29
SHROUT_FLEISS = np.array([[9, 2, 5, 8], [6, 1, 3, 2], [8, 4, 6, 8], [7, 1, 2, 6], [10, 5, 6, 9],
                          [6, 2, 4, 7]], float)


def test_icc_a1_of_the_published_example_and_of_extreme_cases():
    assert icc_a1(SHROUT_FLEISS) == pytest.approx(0.2898, abs=5e-4)
    truth = np.linspace(0.5, 0.8, 20)
    assert icc_a1(np.column_stack([truth, truth])) == pytest.approx(1.0)
    # a constant offset is not absolute agreement: the ICC drops, the correlation does not
    shifted = icc_a1(np.column_stack([truth + 0.1, truth]))
    v = truth.var(ddof=1)     # rows vary by 2v, the two columns differ by 0.1 for all 20 rows
    assert shifted == pytest.approx(2 * v / (2 * v + 2 * (20 * 2 * 0.05 ** 2) / 20))
    assert shifted < 0.7
    assert agreement(truth + 0.1, truth)["r"] == pytest.approx(1.0)
    rng = np.random.default_rng(1)
    noise = icc_a1(np.column_stack([rng.normal(size=200), rng.normal(size=200)]))
    assert abs(noise) < 0.2
    assert math.isnan(icc_a1(np.ones((1, 2))))


def test_bias_rpc_cv_as_seed_003_defines_them():
    truth = np.array([0.70, 0.72, 0.68, 0.75, 0.71])
    diff = np.array([0.01, -0.02, 0.03, 0.00, 0.02])
    a = agreement(truth + diff, truth)
    assert a["n"] == 5
    assert a["bias"] == pytest.approx(diff.mean())
    assert a["rpc"] == pytest.approx(1.96 * diff.std(ddof=1))
    both = np.concatenate([truth + diff, truth]).mean()
    assert a["cv"] == pytest.approx(100 * diff.std(ddof=1) / both)
    assert a["rmse"] == pytest.approx(math.sqrt((diff ** 2).mean()))
    assert a["truth_mean"] == pytest.approx(truth.mean())
    assert agreement(np.array([np.nan, 1.0]), np.array([1.0, 1.0]))["n"] == 1
    assert [category(v) for v in (0.2, 0.5, 0.7, 0.9, math.nan)] == \
        ["poor", "fair", "good", "excellent", "n/a"]


def test_body_frame_ignores_where_the_body_is_and_which_way_it_faces():
    a = standing_pose((0.0, 0.0), 0.0, left_arm=1.0)
    b = standing_pose((2.0, -3.0), 2.2, left_arm=1.0)
    fa, fb = body_frame(a[None]), body_frame(b[None])
    assert fa == pytest.approx(fb, abs=1e-9)
    assert fa[0, J["HandLeft"], 0] > 0.3           # the left hand is on the body's left (+x)


def arm_circles(seconds: float, turns_per_s: float, rate: float = 30.0,
                slow_second_half: bool = False) -> Trajectory:
    """The left arm swinging round in the frontal plane while the walker moves along +z."""
    t = np.arange(0, seconds, 1 / rate)
    frames = []
    phase = 0.0
    for k, tk in enumerate(t):
        speed = turns_per_s * (0.5 if slow_second_half and tk >= seconds / 2 else 1.0)
        if k:
            phase += 2 * math.pi * speed / rate
        frames.append(standing_pose((0.0, 0.8 * tk), 0.0,
                                    left_arm=math.pi / 2 + 0.8 * math.sin(phase)))
    return Trajectory(t, np.stack(frames))


def test_kpis_amplitudes_speeds_angles_envelope_and_fatigue():
    k = kpis(arm_circles(8.0, 0.5, slow_second_half=True))
    hand = k["joints"]["HandLeft"]
    # the straight arm (shoulder to hand 0.62 m) sweeps +-0.8 rad: the hand moves in the
    # body's frontal plane, not forwards (the 6.4 m walked is not an amplitude)
    assert hand["amplitude_forward_m"] < 0.01
    assert 0.7 < hand["amplitude_vertical_m"] < 0.9
    assert k["joints"]["HandRight"]["amplitude_m"] < 0.01
    # the hand moves at about the walking speed plus its sweep; half as fast sweeping later
    assert hand["speed_mean"] > 0.8
    assert hand["fatigue_delta"] < -0.1 and hand["fatigue_percent"] < -10
    assert k["joints"]["HandRight"]["fatigue_percent"] == pytest.approx(0.0, abs=1.0)
    sh = k["angles"]["ShoulderLeft"]
    assert sh["min"] == pytest.approx(math.degrees(math.pi / 2 - 0.8), abs=1.0)
    assert sh["max"] == pytest.approx(math.degrees(math.pi / 2 + 0.8), abs=1.0)
    # a hand moving in a plane spans no volume
    assert k["envelope_m3"]["HandLeft"] == pytest.approx(0.0, abs=1e-4)


def test_working_envelope_is_the_volume_of_the_reached_points():
    rng = np.random.default_rng(4)
    cube = rng.uniform(0.0, 0.5, size=(4000, 3))
    assert hull_volume(cube) == pytest.approx(0.125, rel=0.04)   # the hull lies inside
    ball = rng.normal(size=(4000, 3))
    ball = 0.3 * ball / np.linalg.norm(ball, axis=1, keepdims=True)
    assert hull_volume(ball) == pytest.approx(4 / 3 * math.pi * 0.3 ** 3, rel=0.04)
    assert hull_volume(np.zeros((3, 3))) == 0.0
    assert hull_volume(np.full((10, 3), np.nan)) == 0.0


def test_icc_and_r_say_nothing_when_the_truth_does_not_vary():
    rng = np.random.default_rng(2)
    truth = np.full(30, 0.70)                   # a gait set in the simulator
    a = agreement(truth + rng.normal(0, 0.01, 30), truth)
    assert math.isnan(a["icc"]) and math.isnan(a["r"])
    assert a["rpc"] == pytest.approx(1.96 * 0.01, rel=0.4) and math.isfinite(a["bias"])
