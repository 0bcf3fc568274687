"""The hand votes on one array per person (``engine.handbank``) against ``HandVoter``, the
reference: the same reports in, the same states reported, at the same moments."""

from __future__ import annotations

import numpy as np
import pytest

from stage.engine import handbank, jit
from stage.engine.handbank import ArrayHandVoter
from stage.engine.hands import HandVoter
from stage.joints import HandState


def _stream(seed: int, steps: int = 1500, frames=(1,)):
    """Reports, forgets and votes from up to seven sensors that misread often: times mostly
    rising at 30 Hz, some repeated and some out of order, weights 0-1; sensor k's reading
    lasts ``frames[k % len(frames)]`` frames."""
    rng = np.random.default_rng(seed)
    keys = [(f"s{k}", int(rng.integers(0, 3))) for k in range(7)]
    step = {key: 1.0 / frames[k % len(frames)] for k, key in enumerate(keys)}
    truth = [HandState.OPEN, HandState.OPEN]
    t = 0.0
    for _ in range(steps):
        r = rng.random()
        if r < 0.02:
            truth[int(rng.integers(2))] = HandState(int(rng.integers(2, 5)))
        if r < 0.01:
            yield ("forget", keys[int(rng.integers(len(keys)))])
            continue
        if r < 0.25:
            yield ("update", t + float(rng.choice([0.0, -0.02, 0.01])))
            continue
        t += float(rng.choice([0.0, 1 / 30, 1 / 90, 0.2])) if rng.random() < 0.9 else 1.5
        key = keys[int(rng.integers(len(keys)))]
        hand = int(rng.integers(2))
        state = truth[hand] if rng.random() < 0.6 else HandState(int(rng.integers(0, 5)))
        weight = float(rng.choice([1.0, 0.5, 0.0, rng.random()]))
        when = t - float(rng.choice([0.0, 0.0, 0.0, 0.05]))   # some out of order
        yield ("add", key, hand, state, weight, when, step[key])


def _play(voter, stream) -> list:
    out = []
    for event in stream:
        if event[0] == "add":
            voter.add(*event[1:])
        elif event[0] == "forget":
            voter.forget(event[1])
        else:
            t = event[1]
            out.append((voter.update(t), list(voter.reported), voter.vote(0, t),
                        voter.vote(1, t), voter.newest))
    return out


@pytest.mark.parametrize("frames", [(1,), (2,), (2, 1, 3)])   # (2, 1, 3): a mixed rig
@pytest.mark.parametrize("evidence", [True, False])
@pytest.mark.parametrize("seed", range(6))
def test_array_voter_reports_what_the_reference_reports(seed, evidence, frames):
    expected = _play(HandVoter(0.1, 0.1, evidence), _stream(seed, frames=frames))
    changes = sum(len(e[0]) for e in expected)
    assert changes > 20          # the stream does change the vote, often
    with jit.disabled():         # the plain functions
        assert _play(ArrayHandVoter(0.1, 0.1, evidence, slots=2),
                     _stream(seed, frames=frames)) == expected
    if not jit.ready():
        pytest.skip(f"compiled kernels unavailable: {jit.why_not()}")
    assert _play(ArrayHandVoter(0.1, 0.1, evidence, slots=2),
                 _stream(seed, frames=frames)) == expected


def test_array_voter_keeps_the_reference_floats():
    """Beyond the states reported: the evidence and the candidate's time, bit for bit."""
    ref, arr = HandVoter(0.1, 0.1), ArrayHandVoter(0.1, 0.1, slots=1)
    for event in _stream(11, 3000, frames=(2, 1, 3)):
        for v in (ref, arr):
            if event[0] == "add":
                v.add(*event[1:])
            elif event[0] == "forget":
                v.forget(event[1])
            else:
                v.update(event[1])
    S = handbank.slots_of(arr.buf)
    for hand in (0, 1):
        hb = handbank._hand(S, hand)
        assert list(arr.buf[hb + handbank.LEAD:hb + handbank.LEAD + 5]) == ref._lead[hand]
        assert list(arr.buf[hb + handbank.MARGIN:hb + handbank.MARGIN + 5]) == ref._margin[hand]
        assert list(arr.buf[hb + handbank.SINCE:hb + handbank.SINCE + 5]) == ref._since[hand]
        cand = ref._candidate[hand]
        assert (arr.buf[hb + handbank.CAND], arr.buf[hb + handbank.CAND_T] if cand else None) \
            == ((int(cand[0]), cand[1]) if cand else (-1.0, None))
        for key, k in arr.slots.items():
            entry = ref.reports[hand].get(key)
            if entry is None:
                continue
            b = handbank._slot(S, hand, k)
            assert list(arr.buf[b + handbank.SHARES:b + handbank.SHARES + 5]) == entry[1]
            assert arr.buf[b + handbank.NEWEST] == entry[0]


def test_a_frame_gives_both_hands_in_one_call():
    a, b = ArrayHandVoter(0.1, 0.1), ArrayHandVoter(0.1, 0.1)
    a.add(("s0", 1), 0, HandState.CLOSED, 0.7, 1.0)
    a.add(("s0", 1), 1, HandState.LASSO, 0.4, 1.0)
    b.add_frame(("s0", 1), HandState.CLOSED, 0.7, HandState.LASSO, 0.4, 1.0)
    assert np.array_equal(a.buf, b.buf, equal_nan=True)
    assert b.update(1.0) == [0, 1] and b.reported == [HandState.CLOSED, HandState.LASSO]
    # a sensor whose reports are half a reading each: its evidence weight halved, in both
    a.update(1.0)
    a.add(("s1", 0), 0, HandState.OPEN, 0.9, 1.1, 0.5)
    a.add(("s1", 0), 1, HandState.OPEN, 0.3, 1.1, 0.5)
    b.add_frame(("s1", 0), HandState.OPEN, 0.9, HandState.OPEN, 0.3, 1.1, 0.5)
    assert np.array_equal(a.buf, b.buf, equal_nan=True)
    S = handbank.slots_of(b.buf)
    assert b.buf[handbank._slot(S, 0, b.slots[("s1", 0)]) + handbank.P_W] == 0.45
