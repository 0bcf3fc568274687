"""Pure fusion maths: which views of an instant agree, the hand vote, geometry helpers."""

from __future__ import annotations

import numpy as np
import pytest

from stage.engine import jit
from stage.engine.fusion import apply_transform, consistent_views, torso_centre
from stage.engine.handbank import ArrayHandVoter
from stage.engine.hands import CadenceWatch, HandVoter
from stage.joints import HandState

O, C, L = HandState.OPEN, HandState.CLOSED, HandState.LASSO
U, NT = HandState.UNKNOWN, HandState.NOT_TRACKED
R = 1e-4          # 1 cm per axis
BIAS = 0.02 ** 2
CHI2 = 9.0
NO_PRIOR = (np.full((25, 3), np.nan), np.full(25, np.nan))


def test_an_outlier_among_three_or_more_views_is_left_out():
    rng = np.random.default_rng(3)
    truth = rng.uniform(-1, 1, size=(25, 3))
    pos = truth[None] + rng.normal(0, 0.01, size=(4, 25, 3))
    pos[2, 5] += [0.0, 0.0, 0.4]     # one sensor's elbow is 40 cm off
    used = consistent_views(pos, np.full((4, 25), R), *NO_PRIOR, BIAS, CHI2)
    assert not used[2, 5]
    assert used.sum() == 4 * 25 - 1
    # whichever view comes first
    used = consistent_views(pos[[2, 0, 1, 3]], np.full((4, 25), R), *NO_PRIOR, BIAS, CHI2)
    assert not used[0, 5] and used.sum() == 4 * 25 - 1


def test_two_disagreeing_views_are_settled_by_the_prior_then_by_certainty():
    pos = np.array([[[0.0, 1.0, 2.0]], [[0.0, 1.0, 2.5]]])
    r = np.array([[R], [2 * R]])                      # the second one inferred (conf 0.5)
    near_second = (np.array([[0.0, 1.0, 2.48]]), np.array([4e-4]))
    used = consistent_views(pos, r, *near_second, BIAS, CHI2)
    assert used[:, 0].tolist() == [False, True]       # the filter's prediction breaks the tie
    wide = (np.array([[0.0, 1.0, 2.25]]), np.array([1.0]))
    used = consistent_views(pos, r, *wide, BIAS, CHI2)
    assert used[:, 0].tolist() == [True, False]       # no help from the prior: more certain wins
    # two views agreeing outvote the prior
    three = np.array([[[0.0, 1.0, 2.0]], [[0.0, 1.0, 2.01]], [[0.0, 1.0, 2.5]]])
    used = consistent_views(three, np.full((3, 1), R), *near_second, BIAS, CHI2)
    assert used[:, 0].tolist() == [True, True, False]


def test_views_that_agree_are_all_used_and_unseen_joints_never():
    rng = np.random.default_rng(0)
    pos = rng.normal(0, 0.01, size=(5, 25, 3))
    r = np.full((5, 25), R)
    r[1, 3] = np.nan                                  # sensor 1 does not see joint 3
    used = consistent_views(pos, r, *NO_PRIOR, BIAS, CHI2)
    assert used.sum() == 5 * 25 - 1 and not used[1, 3]
    one = consistent_views(pos[:1], r[:1], *NO_PRIOR, BIAS, CHI2)
    assert one.all()
    # a joint only one view sees is used whatever the prior says: the gate judges it
    r2 = np.full((2, 25), np.nan)
    r2[0, 0] = R
    far = (np.zeros((25, 3)) + 5.0, np.full(25, 1e-4))
    used = consistent_views(pos[:2], r2, *far, BIAS, CHI2)
    assert used[0, 0] and used.sum() == 1


@pytest.fixture(params=["reference", "array"])
def Voter(request):
    """The voter class: ``hands.HandVoter``, and ``handbank.ArrayHandVoter`` on the compiled
    kernels (the engine's when they compile; the plain functions otherwise)."""
    if request.param == "reference":
        return HandVoter
    jit.ready()
    return ArrayHandVoter


def vote_once(states, weights=None, Voter=HandVoter):
    voter = Voter(memory_s=0.05, hold_s=0.1)
    for k, state in enumerate(states):
        voter.add((f"s{k}", 0), 0, state, 1.0 if weights is None else weights[k], 0.0)
    return voter.vote(0, 0.0)


@pytest.mark.parametrize("states, expected", [
    ([O, O, C], O),
    ([O, C], C),                               # a tie between known states: the higher code
    ([O, C, L, O, C], C),                      # 2-2-1 tie between open and closed -> closed
    ([U, NT, O], O),                           # unknown and notTracked never outvote a state
    ([U, U, U, O], O),
    ([NT, U], NT),
    ([U], U),
    ([], U),
])
def test_one_instant_is_a_majority_vote(states, expected, Voter):
    assert vote_once(states, Voter=Voter) == expected


def test_confidence_weighted_vote_can_overrule_the_count(Voter):
    assert vote_once([O, O, C], weights=[0.3, 0.3, 1.0], Voter=Voter) == C
    assert vote_once([O, O, C], weights=[1.0, 1.0, 1.0], Voter=Voter) == O
    assert vote_once([C, O], weights=[0.6, 0.61], Voter=Voter) == O   # no higher-code rule


def test_a_misread_frame_does_not_flicker_and_a_real_change_is_reported_after_the_hold(Voter):
    voter = Voter(memory_s=0.05, hold_s=0.1)
    reported = []
    t = 0.0
    # three sensors 11 ms apart; sensor 2 misreads "closed" for two frames at 0.3 s
    for k in range(60):
        t = k / 90
        sensor = k % 3
        truth = O if t < 0.5 else C
        state = C if sensor == 2 and 0.3 <= t < 0.37 else truth
        voter.add((f"s{sensor}", 0), 0, state, 1.0, t)
        voter.update(t)
        reported.append((t, voter.reported[0]))
    states = [s for _, s in reported]
    changes = [(t, s) for (t, s), (_, before) in zip(reported[1:], reported) if s != before]
    assert states[0] == O
    assert len(changes) == 1 and changes[0][1] == C         # the misread never went out
    assert 0.5 + 0.1 <= changes[0][0] <= 0.5 + 0.15           # the change: held 100 ms


def two_sensors(voter, frames, steps=(1.0, 1.0)):
    """Feed (t, state of sensor 0, state of sensor 1) frames, sensor 1 5 ms after sensor 0,
    each report ``steps[k]`` of a reading; returns the (t, state) changes reported."""
    out = []
    for t, a, b in frames:
        for k, (dt, state) in enumerate(((0.0, a), (0.005, b))):
            voter.add((f"s{k}", 0), 0, state, 1.0, t + dt, steps[k])
            if voter.update(t + dt):
                out.append((t + dt, voter.reported[0]))
    return out


def test_a_change_two_sensors_dispute_is_reported_on_the_evidence_before_the_hold(Voter):
    # open until 0.5 s, then closed; two sensors at 30 Hz, each reading the hand every frame
    # and misreading a fifth of the time (seeded: a draw where the vote hovers near a tie
    # after the change). The hold alone reports the change 200 ms after it; the reports'
    # evidence makes the case at 138 ms (a lead of 4 readings, a margin of 2.5), and at
    # 172 ms when each report is taken for half a reading (reading_frames 2, a Kinect v2's)
    rng = np.random.default_rng(262)
    frames = []
    for k in range(40):
        truth = O if k / 30 < 0.5 else C
        states = [truth if rng.random() >= 0.2 else
                  [x for x in (O, C, L) if x != truth][int(rng.integers(2))] for _ in range(2)]
        frames.append((k / 30, *states))
    changes = two_sensors(Voter(memory_s=0.03, hold_s=0.1), frames)
    assert changes[0] == (0.0, O) and len(changes) == 2
    t, state = changes[1]
    assert state == C and t == pytest.approx(0.5 + 4 / 30 + 0.005)
    halves = two_sensors(Voter(memory_s=0.03, hold_s=0.1), frames, steps=(0.5, 0.5))
    assert [s for _, s in halves] == [O, C] and halves[1][0] == pytest.approx(0.5 + 5 / 30 + 0.005)
    # a rig of one of each: each sensor's reports count by its own cadence, so the case
    # falls between the two (here at 0.5 + 5/30, on sensor 0's report; 138 ms when the
    # halves are sensor 0's instead, whose misreads then weigh less)
    mixed = two_sensors(Voter(memory_s=0.03, hold_s=0.1), frames, steps=(1.0, 0.5))
    assert [s for _, s in mixed] == [O, C] and mixed[1][0] == pytest.approx(0.5 + 5 / 30)
    mixed = two_sensors(Voter(memory_s=0.03, hold_s=0.1), frames, steps=(0.5, 1.0))
    assert mixed[1] == changes[1]
    hold_only = two_sensors(Voter(memory_s=0.03, hold_s=0.1, evidence=False), frames)
    assert [s for _, s in hold_only] == [O, C] and hold_only[1][0] == pytest.approx(0.7)


def test_a_lead_back_at_exactly_0_keeps_its_start():
    # open until 0.5 s, then closed. Sensor 0 misreads the old state twice just after the
    # change (0.5 s, 0.567 s), sensor 1 once (0.538 s). Closed's lead (+1 for closed, -1 for
    # open) goes 0, 1 (0.505 s), 2, 1, 0 (0.567 s: back to 0 but never under it), 1, 2, ...
    # Its run began at 0.505 s and still does after 0.567 s (stop 19's rule restarted it at
    # 0.572 s): the evidence's hold counts from the change's first report
    frames = [(k / 30, O, O) for k in range(15)]
    s0 = [O, C, O] + [C] * 7
    s1 = [C, O, C] + [C] * 7
    voter = HandVoter(memory_s=0.03, hold_s=0.1)
    starts = []
    for t, a, b in frames + [(0.5 + k / 30, a, b) for k, (a, b) in enumerate(zip(s0, s1))]:
        for k, (dt, state) in enumerate(((0.0, a), (0.005, b))):
            voter.add((f"s{k}", 0), 0, state, 1.0, t + dt)
            voter.update(t + dt)
            if voter.reported[0] == O and t >= 0.5:
                starts.append((round(t + dt, 3), voter._lead[0][C], voter._since[0][C]))
    assert (0.567, 0.0, 0.505) in starts                      # back at 0: the start is kept
    assert [since for _, _, since in starts if since >= 0] == [0.505] * \
        len([1 for _, _, since in starts if since >= 0])       # and never moves
    assert voter.reported[0] == C


def test_a_run_of_misreads_into_a_third_state_makes_no_case(Voter):
    # open until 0.5 s, then lasso, but at first the sensors say closed as often as lasso:
    # the reports against open favour closed as much as lasso (nothing says open any more);
    # closed never leads lasso, so it makes no case: lasso is reported, closed never
    voter = Voter(memory_s=0.03, hold_s=0.1)
    frames = [(k / 30, O, O) for k in range(15)]
    s0 = [C, L, C, L, C, L] + [L] * 8
    s1 = [L, C, L, C, L, C] + [L] * 8
    frames += [(0.5 + k / 30, a, b) for k, (a, b) in enumerate(zip(s0, s1))]
    changes = two_sensors(voter, frames)
    assert [state for _, state in changes] == [O, L]


def test_a_hand_that_nobody_sees_goes_unknown_after_the_hold_and_comes_back_at_once(Voter):
    voter = Voter(memory_s=0.05, hold_s=0.1)
    voter.add(("s0", 0), 0, O, 1.0, 0.0)
    assert voter.update(0.0) == [0, 1] and voter.reported == [O, U]
    voter.add(("s0", 0), 0, NT, 1.0, 0.05)       # an old "open" still counts: no change
    assert voter.update(0.05) == []
    for t in (0.25, 0.3, 0.36):                     # "open" forgotten (older than 0.2 s)
        voter.add(("s0", 0), 0, NT, 1.0, t)
        changed = voter.update(t)
    assert changed == [0] and voter.reported[0] == NT
    voter.add(("s0", 0), 0, L, 1.0, 0.4)
    assert voter.update(0.4) == [0] and voter.reported[0] == L   # the first known state: at once
    voter.forget(("s0", 0))
    assert voter.vote(0, 0.4) == U


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


def _watch(states: list[tuple], watch: CadenceWatch | None = None):
    """Feed a track's (left, right) states frame by frame; (watch, the frame it decided)."""
    watch = watch or CadenceWatch()
    run = [None, None, -1, -1]
    decided = None
    for k, hands in enumerate(states):
        if watch.frame(run, list(hands)) and decided is None:
            decided = k
    return watch, decided


def test_a_sensor_repeating_readings_over_two_frames_is_told_from_one_reading_every_frame():
    U = HandState.UNKNOWN
    # the first run (begun with the track) and runs longer than 8 frames are not counted
    watch, _ = _watch([(U, O)] * 3 + [(O, O)] * 9 + [(C, O)] * 2 + [(O, O)])
    assert (watch.runs, watch.even) == (1, 1)      # only closed's 2 frames: left's 9 too long
    # runs of 2 frames (a reading repeated, as a Kinect v2 does): 40 of them decide 2
    pairs = [(O, O), (O, O), (C, C), (C, C)] * 11
    watch, at = _watch(pairs)
    assert watch.verdict == 2 and watch.stats() == {"short_runs": 40, "even": 40,
                                                    "looks_like": 2}
    assert at == 42    # changes every 2nd frame; the first (frame 2) ends the uncounted run
    # one reading a frame, misread now and then: runs of 1 and 3 frames
    frames = [(O, O), (C, C), (O, O), (O, O), (O, O), (L, L)] * 14
    watch, _ = _watch(frames)
    assert watch.verdict == 1 and watch.even == 0
    # half and half: nothing said
    frames = [(C, C), (C, C), (O, O)] * 30          # runs of 1 and 2 frames, alternately
    watch, _ = _watch(frames)
    assert watch.verdict == 0 and watch.runs == 40 and watch.even == 20
    # once decided, the watch counts no more
    watch, _ = _watch(pairs * 2)
    assert watch.runs == 40
