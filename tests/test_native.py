"""The native core (``stage.engine.native``) held to the engine's Python path, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from stage.engine import jit
from stage.testing.native_shadow import replay, shadow_engine
from stage.testing.shows import three_dancers

needs_jit = pytest.mark.skipif(not jit.ready(), reason=f"no compiled kernels: {jit.why_not()}")
pytestmark = needs_jit


@pytest.fixture(scope="module")
def spread():
    return three_dancers()


def test_the_core_sends_and_keeps_what_the_engine_does(spread):
    """Three dancers walking to the edge of three Kinects' range (joints rejected,
    restarted, inferred and carried): every datagram the core accepts gives the engine's
    encoded skeletons and leaves the engine's filter states and output rows, to the bit."""
    poses, data = spread
    shadow = replay(shadow_engine(poses), data)
    stats = shadow.engine.people.stats()
    assert stats["joints_restarted"] > 0 and stats["joints_rejected"] > 0   # not only easy rows
    assert shadow.mismatches == []
    assert shadow.accepted > 0.9 * len(data)
    assert shadow.compared >= 2.5 * shadow.accepted         # (three persons a datagram)
    assert shadow.declined > 0                              # restarts left to Python


def test_sensors_in_step_the_core_takes_only_an_instants_first_views():
    """Aligned sensors: each person's views of a frame form an instant, checked against each
    other by the Python path; the core takes the first datagram of each and declines the
    rest, and what it took is the engine's."""
    poses, data = three_dancers(seconds=3.0, aligned=True)
    shadow = replay(shadow_engine(poses), data)
    assert shadow.mismatches == []
    assert 0.2 * len(data) < shadow.accepted < 0.5 * len(data)
    assert shadow.declined > shadow.accepted


def test_a_small_ring_and_one_slot_to_start_with_change_nothing(spread):
    """A ring of three states wraps every other step; one slot grows to hold everyone."""
    poses, data = spread
    shadow = replay(shadow_engine(poses, depth=3, slots=1), data[:240])
    assert shadow.mismatches == [] and shadow.accepted > 200
    assert len(shadow.core.owners) >= 3


@pytest.mark.parametrize("what", ["state", "bytes"])
def test_the_comparison_sees_a_core_that_differs(spread, what):
    """The shadow's comparison is not blind: a core whose process noise is 1 % higher, or
    whose joint names are spelt wrong, is caught."""
    poses, data = spread
    shadow = shadow_engine(poses)
    if what == "state":
        shadow.core.q = shadow.core.q * 1.01
    else:
        shadow.core.names = shadow.core.names.copy()
        shadow.core.names[0] ^= 0x20
    replay(shadow, data[:120])
    assert shadow.accepted > 50
    wanted = "state differs" if what == "state" else "encoded skeleton differs"
    assert any(wanted in m for m in shadow.mismatches)


def _arrays(core) -> dict:
    out = {n: getattr(core, n).copy() for n in core._arrays()}
    for name in ("ring", "ring_t", "ring_hz", "ring_ht"):
        for s in range(len(core.owners)):        # the entry after the newest is scratch
            out[name][s, (core.head[s] + 1) % core.depth] = 0.0
    return out


def _same(a: dict, b: dict) -> bool:
    return all(np.array_equal(a[n], b[n], equal_nan=True) for n in a)


@pytest.mark.parametrize("case", ["nothing amiss", "same instant", "one person twice", "unknown view",
                                  "row to start", "row to restart"])
def test_a_declined_datagram_changes_nothing(spread, case):
    """What the core leaves to Python it declines before changing anything (but the ring's
    scratch entry): the heads, states, output rows and views' rows stay as they were. (The
    same views with nothing amiss are taken.)"""
    poses, data = spread
    shadow = replay(shadow_engine(poses), data[:90])
    core = shadow.core
    persons = shadow.engine.persons
    pids = [pid for pid in core.slot_of if pid in persons][:2]
    assert len(pids) == 2
    keys = [next(iter(core.recent[core.slot_of[pid]])) for pid in pids]
    s0 = core.slot_of[pids[0]]
    t = np.array([core.newest[core.slot_of[pid]] + 0.02 for pid in pids])
    z = np.array([core.joints[core.slot_of[pid]] for pid in pids])
    r = np.full((2, 25), 1e-4)
    conf = np.ones((2, 25))
    if case == "same instant":
        t[0] = core.newest[s0] + 0.5 * shadow.engine.rig.fusion.group_s
    elif case == "one person twice":
        pids[1], keys[1] = pids[0], keys[0]
    elif case == "unknown view":
        keys[1] = ("nobody", 9)
    elif case == "nothing amiss":
        pass
    elif case == "row to start":
        core.ring[s0, core.head[s0], :, :, 7] = np.nan
        core.ring_t[s0, core.head[s0], 7] = np.nan
    else:                                            # one rejection held, a second far off
        core.ring_ht[s0, core.head[s0], 7] = core.newest[s0]
        z[0, 7] += 3.0
    before = _arrays(core)
    out = core.fold(pids, keys, t, z, r, conf)
    if case == "nothing amiss":
        assert out is not None and len(out) == 2
        assert not _same(before, _arrays(core))
        return
    assert out is None
    assert _same(before, _arrays(core))
    assert core.declined >= 1


def test_the_core_refuses_to_start_without_kernels():
    from stage.engine.native import NativeCore
    from stage.settings import FusionSettings, KalmanSettings
    with jit.disabled():
        with pytest.raises(RuntimeError, match="compiled kernels"):
            NativeCore(KalmanSettings(), FusionSettings())
