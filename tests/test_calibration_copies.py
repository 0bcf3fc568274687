"""``gate.CopyDetector``: bit-identical skeletons from two sensors are a copied stream; a
skeleton with fewer than three tracked joints is no evidence."""

from __future__ import annotations

import numpy as np

from stage.calibration.gate import CopyDetector


def _frames(rng, n: int, tracked: int = 25):
    out = []
    for _ in range(n):
        joints = rng.normal(size=(25, 3))
        conf = np.zeros(25)
        conf[:tracked] = 1.0
        out.append((joints, conf))
    return out


def test_the_fifth_identical_frame_names_the_pair_once():
    rng = np.random.default_rng(3)
    det = CopyDetector(frames=5)
    found = []
    for k, (joints, conf) in enumerate(_frames(rng, 8)):
        t = k / 30
        assert det.check("a", t, joints, conf) is None
        found.append(det.check("b", t + 0.01, joints.copy(), conf.copy()))
    assert found[:4] == [None] * 4 and found[4] == ("a", "b") and found[5:] == [None] * 3


def test_near_copies_frames_far_apart_and_one_sensor_repeating_itself_are_not_copies():
    rng = np.random.default_rng(4)
    det = CopyDetector(frames=5, within_s=2.0)
    for k, (joints, conf) in enumerate(_frames(rng, 10)):
        t = k / 30
        assert det.check("a", t, joints, conf) is None
        assert det.check("a", t + 0.01, joints, conf) is None          # itself again
        off = joints.copy()
        off[3, 1] = np.nextafter(off[3, 1], np.inf)                    # one bit apart
        assert det.check("b", t, off, conf) is None
        assert det.check("c", t + 2.5, joints, conf) is None            # too late
    assert det.pairs == {}


def test_skeletons_with_fewer_than_three_tracked_joints_are_no_evidence():
    rng = np.random.default_rng(5)
    det = CopyDetector(frames=2)
    for k, (joints, conf) in enumerate(_frames(rng, 6, tracked=2)):
        det.check("a", k / 30, joints, conf)
        assert det.check("b", k / 30, joints, conf) is None
    empty = (np.zeros((25, 3)), np.zeros(25))       # the same empty skeleton everywhere
    for k in range(6):
        for sensor in "abc":
            assert det.check(sensor, k / 30, *empty) is None
    assert det.pairs == {}
    found = []
    for k, (joints, conf) in enumerate(_frames(rng, 2, tracked=3)):   # three are enough
        det.check("a", 1.0 + k / 30, joints, conf)
        found.append(det.check("b", 1.0 + k / 30, joints, conf))
    assert found == [None, ("a", "b")]
