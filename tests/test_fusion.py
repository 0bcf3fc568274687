"""Pure fusion maths: weighted averaging, outlier rejection, the hand vote."""

from __future__ import annotations

import numpy as np
import pytest

from stage.engine.fusion import apply_transform, fuse_joints, torso_centre, vote_hand
from stage.joints import HandState

O, C, L = HandState.OPEN, HandState.CLOSED, HandState.LASSO


def test_average_is_weighted_by_confidence_and_skips_untracked():
    pos = np.array([[[0.0, 0, 0]], [[1.0, 0, 0]], [[9.0, 9, 9]]])
    conf = np.array([[1.0], [0.5], [0.0]])
    fused, weight, used = fuse_joints(pos, conf, outlier_m=10.0)
    np.testing.assert_allclose(fused[0], [1 / 3, 0, 0])
    assert weight[0] == pytest.approx(1.5)
    assert used[:, 0].tolist() == [True, True, False]


def test_a_joint_nobody_tracks_has_zero_weight():
    fused, weight, used = fuse_joints(np.ones((2, 3, 3)), np.zeros((2, 3)))
    assert (weight == 0).all() and not used.any() and (fused == 0).all()


def test_outlier_beyond_median_spread_is_rejected_with_three_views():
    rng = np.random.default_rng(3)
    truth = rng.uniform(-1, 1, size=(25, 3))
    pos = truth[None] + rng.normal(0, 0.01, size=(4, 25, 3))
    pos[2, 5] += [0.0, 0.0, 0.4]     # one sensor's elbow is 40 cm off
    conf = np.ones((4, 25))
    fused, weight, used = fuse_joints(pos, conf, outlier_m=0.10)
    assert not used[2, 5]
    assert used.sum() == 4 * 25 - 1
    assert np.linalg.norm(fused[5] - truth[5]) < 0.03
    # without rejection the same joint would be dragged ~10 cm away
    naive = pos[:, 5].mean(axis=0)
    assert np.linalg.norm(naive - truth[5]) > 0.08


def test_two_disagreeing_views_keep_the_more_confident_one():
    pos = np.array([[[0.0, 1.0, 2.0]], [[0.0, 1.0, 2.5]]])
    fused, _, used = fuse_joints(pos, np.array([[1.0], [0.5]]))
    assert used[:, 0].tolist() == [True, False]
    np.testing.assert_allclose(fused[0], [0, 1, 2])
    # equal confidence: nobody to blame, both kept
    fused, _, used = fuse_joints(pos, np.array([[1.0], [1.0]]))
    assert used.all()
    np.testing.assert_allclose(fused[0], [0, 1, 2.25])


def test_close_views_are_all_kept():
    rng = np.random.default_rng(0)
    pos = rng.normal(0, 0.02, size=(5, 25, 3))
    _, _, used = fuse_joints(pos, np.ones((5, 25)))
    assert used.all()


@pytest.mark.parametrize("states, expected", [
    ([O, O, C], O),
    ([O, C], C),                               # tie goes to the higher code
    ([O, C, L, O, C], C),                      # 2-2-1 tie between open and closed -> closed
    ([HandState.UNKNOWN, HandState.NOT_TRACKED, O], O),   # those two do not vote
    ([HandState.NOT_TRACKED, HandState.UNKNOWN], HandState.NOT_TRACKED),
    ([HandState.UNKNOWN], HandState.UNKNOWN),
    ([], HandState.UNKNOWN),
])
def test_majority_vote(states, expected):
    assert vote_hand(states) == expected


def test_confidence_weighted_vote_can_overrule_the_count():
    assert vote_hand([O, O, C], weights=[0.3, 0.3, 1.0]) == C
    assert vote_hand([O, O, C], weights=[1.0, 1.0, 1.0]) == O


def test_torso_centre_falls_back_to_any_tracked_joint():
    joints = np.arange(75, dtype=float).reshape(25, 3)
    conf = np.zeros(25)
    assert torso_centre(joints, conf) is None
    conf[3] = 1.0  # only the head
    np.testing.assert_allclose(torso_centre(joints, conf), joints[3])


def test_apply_transform_matches_homogeneous_product():
    rng = np.random.default_rng(2)
    m = np.eye(4)
    m[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    m[:3, 3] = [1, 2, 3]
    pts = rng.normal(size=(25, 3))
    expect = (m @ np.c_[pts, np.ones(25)].T).T[:, :3]
    np.testing.assert_allclose(apply_transform(m, pts), expect)
