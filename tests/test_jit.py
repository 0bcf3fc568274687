"""The compiled kernels (stage/engine/jit.py) against the numpy code they replace."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import subprocess
import sys

import numpy as np
import pytest

from stage.engine import imm, jit
from stage.engine.kalman import (ACCEPTED, DOWNWEIGHTED, NOT_MEASURED, REJECTED, RESTARTED,
                                 STARTED, USED, FilterState, step, step_folded)
from stage.engine.fusion import _CHILDREN, _PARENTS, carry_untracked, carry_untracked_numpy
from stage.settings import KalmanSettings
from stage.testing.shows import three_dancers

from libm import c_library_math

needs_jit = pytest.mark.skipif(not jit.ready(), reason=f"no compiled kernels: {jit.why_not()}")


def _stack(rng: np.random.Generator, n: int) -> np.ndarray:
    S = np.empty((6, 2, n, 3))
    S[0], S[1] = rng.normal(0, 1, (2, n, 3)), rng.normal(0, 2, (2, n, 3))
    S[2] = rng.uniform(1e-5, 1e-2, (2, n, 3))
    S[3] = rng.uniform(-1e-4, 1e-4, (2, n, 3))
    S[4] = rng.uniform(0.1, 10.0, (2, n, 3))
    mu = rng.uniform(1e-6, 1.0 - 1e-6, (n, 3))
    S[5, 0], S[5, 1] = mu, 1.0 - mu
    return S


@needs_jit
@pytest.mark.parametrize("n", [1, 25, 150])
@pytest.mark.parametrize("scaled", [False, True])
def test_imm_kernel_gives_the_numpy_floats(n, scaled):
    """The compiled step against ``imm.fused_update`` and what ``step`` keeps of it, on
    rows near and far beyond the gate, with and without per-row noise scales; a
    non-contiguous state (a wave's rows) is taken as well."""
    rng = np.random.default_rng(n + 100 * scaled)
    s = KalmanSettings()
    S = _stack(rng, 2 * n)[:, :, ::2]                 # rows of a bigger block: not contiguous
    st = rng.uniform(0.0, 1.0, n)
    dt = rng.choice([0.0, 1 / 90, 1 / 30, 0.4], n)
    z = S[0, 0] + rng.normal(0, 0.01, (n, 3))
    z[::3] += rng.normal(0, 0.3, (len(z[::3]), 3))    # beyond the gate, some beyond reject
    r = rng.uniform(1e-6, 1e-3, n)
    q = rng.uniform(0.5, 2.0, n) if scaled else None
    want, want_d2 = imm.fused_update(S, dt, z, r, s, q, s.gate_sigma ** 2)
    # rows held already (rejected once before): a second rejection is for the caller to
    # restart; a first one is held by the kernel
    held_before = np.where(rng.random(n) < 0.5, rng.uniform(0.0, 1.0, n), np.nan)
    held_z_before = rng.normal(0, 1, (n, 3))
    block, t, held_z, held_t, outcome, used, counts, pos, vel = jit.step_rows(
        S, st, held_z_before, held_before, st + dt, z, r, s, q)
    n_again, n_fresh, n_down, n_held = counts
    # the position and velocity at t are FilterState.predicted's, bit for bit
    want_pos, want_vel = FilterState.of_block(block, t, np.full((n, 3), np.nan),
                                              held_t).predicted(st + dt)
    np.testing.assert_array_equal(pos, want_pos)
    np.testing.assert_array_equal(vel, want_vel)
    use = want_d2 <= s.reject_sigma ** 2
    np.testing.assert_allclose(block[:, :, use], want[:, :, use], rtol=1e-11, atol=1e-300)
    np.testing.assert_array_equal(block[:, :, ~use], S[:, :, ~use])      # kept as it was
    np.testing.assert_array_equal(t, np.where(use, st + dt, st))
    first = ~use & np.isnan(held_before)
    expected = np.where(use, np.where(want_d2 > s.gate_sigma ** 2, DOWNWEIGHTED, ACCEPTED),
                        np.where(first, REJECTED, RESTARTED))
    np.testing.assert_array_equal(outcome, expected)
    assert n < 150 or (first.any() and (~use & ~first).any())    # both cases were met
    assert n_again == int((~use & ~first).sum()) and n_held == int(first.sum())
    assert n_fresh == 0 and n_down == int((outcome == DOWNWEIGHTED).sum())
    np.testing.assert_array_equal(used, use)
    # accepted: nothing held; held now: this measurement; to restart: as it was
    np.testing.assert_array_equal(held_t, np.where(use, np.nan, np.where(first, st + dt,
                                                                         held_before)))
    np.testing.assert_array_equal(held_z, np.where(first[:, None], z, held_z_before))


@needs_jit
def test_compiled_step_is_the_numpy_step():
    """``kalman.step`` with and without the kernel over a minute of rows that start, are
    measured, skip frames, jump (rejected, then restarted) and come out of order; the
    outcomes are identical and the states a last bit apart at most."""
    rng = np.random.default_rng(11)
    s = KalmanSettings()
    n = 60
    states = [FilterState.empty(n), FilterState.empty(n)]
    truth = rng.normal(0, 1, (n, 3))
    seen = set()
    for k in range(600):
        t = k / 30 - rng.choice([0.0, 0.0, 0.0, 0.02], n)
        truth += rng.normal(0, 0.01, (n, 3))
        z = truth + rng.normal(0, 0.005, (n, 3))
        jump = rng.random(n) < 0.02
        z[jump] += 0.5                                    # two in a row restart the row
        r = np.full(n, 2.5e-5)
        r[rng.random(n) < 0.1] = np.nan                   # not measured
        r[: max(0, 8 - k)] = np.nan                       # rows that start late
        outcomes = []
        for compiled, state in zip((True, False), states):
            with (contextlib.nullcontext() if compiled else jit.disabled()):
                if k % 2:
                    outcomes.append(step(state, t, z, r, s))
                    continue
                # every other frame: step_folded, whose position and velocity are
                # state.predicted(t) after the step (from the kernel, or after a restart
                # or a start, from the state), bit for bit, and whose rows used and
                # counts are the outcome's
                before = state.shallow()
                outcome, pos, vel, used, counts = step_folded(state, t, z, r, s)
                np.testing.assert_array_equal(used, USED[outcome])
                assert counts == tuple(int((outcome == o).sum())
                                       for o in (DOWNWEIGHTED, REJECTED, RESTARTED))
                want_pos, want_vel = state.predicted(t)
                np.testing.assert_array_equal(pos, want_pos)
                np.testing.assert_array_equal(vel, want_vel)
                after = state.shallow()
                np.testing.assert_array_equal(step(before, t, z, r, s), outcome)
                for name in ("x", "P", "mu", "t", "held_z", "held_t"):
                    np.testing.assert_array_equal(getattr(before, name), getattr(after, name))
                outcomes.append(outcome)
        np.testing.assert_array_equal(outcomes[0], outcomes[1])
        seen |= set(outcomes[0].tolist())
        for name in ("x", "P", "mu", "t", "held_z", "held_t"):
            np.testing.assert_allclose(getattr(states[0], name), getattr(states[1], name),
                                       rtol=1e-9, atol=1e-300, err_msg=name)
    assert {NOT_MEASURED, STARTED, ACCEPTED, DOWNWEIGHTED, REJECTED, RESTARTED} <= seen


@needs_jit
def test_compiled_step_warns_of_nothing_even_on_absurd_measurements():
    """The compiled step runs without ``np.errstate`` (it costs 2 % of the engine): rows it
    rejects, restarts and starts, from coordinates near the float limit, raise no
    floating-point warning (a warning on the engine thread is a line on every frame)."""
    import warnings
    rng = np.random.default_rng(12)
    s = KalmanSettings()
    state = FilterState.empty(40)
    restarted = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for k in range(60):
            t = np.full(40, k / 30)
            z = rng.normal(0, 1, (40, 3)) * rng.choice([1.0, 1e150, 1e300], (40, 1))
            z[::4] = rng.choice([-1.5e308, 1.5e308], (10, 3))   # a jump beyond the float range
            r = rng.choice([2.5e-5, 1e-300, 1e300, 1e306], 40)
            r[rng.random(40) < 0.1] = np.nan
            outcome, pos, vel, _, _ = step_folded(state, t, z, r, s)
            restarted += int((outcome == RESTARTED).sum())
            with np.errstate(over="ignore"):                    # (the test's own overflow)
                far = z * 2.0
            step(state, t + 0.01, far, r, s)
    assert restarted > 0


@needs_jit
def test_carry_kernel_matches_numpy_on_random_bodies():
    rng = np.random.default_rng(3)
    moved = 0
    for _ in range(300):
        joints = rng.normal(0, 1, (25, 3))
        reported = rng.random(25) < 0.9
        tracked = rng.random(25) < 0.6
        offsets = rng.normal(0, 0.1, (25, 3))
        offsets[rng.random(25) < 0.2] = np.nan
        j1, o1, j2, o2 = joints.copy(), offsets.copy(), joints.copy(), offsets.copy()
        want = carry_untracked_numpy(j1, reported, tracked, o1)
        got = carry_untracked(j2, reported, tracked, o2)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(j2, j1)
        np.testing.assert_array_equal(o2, o1)
        moved += int(want.sum())
    assert moved > 300                                     # the carrying path was taken


@needs_jit
def test_carry_falls_back_to_numpy_for_arrays_the_kernel_does_not_take():
    joints = np.zeros((25, 3), dtype=np.float32)             # not float64: the numpy code
    offsets = np.full((25, 3), 0.1)
    reported = np.ones(25, dtype=bool)
    tracked = np.zeros(25, dtype=bool)
    carried = carry_untracked(joints, reported, tracked, offsets)
    assert carried[_CHILDREN].all() and not carried[0]
    np.testing.assert_allclose(joints[_CHILDREN[0]], joints[_PARENTS[0]] + 0.1)


def test_disabled_runs_the_numpy_code_and_restores():
    from stage.sensors import protocol

    before, scanner = jit.ready(), protocol._scanner
    assert (scanner is not None) == before        # the receiver's scanner comes with them
    with jit.disabled():
        assert not jit.ready() and not jit.ENABLED and protocol._scanner is None
    assert jit.ready() == before and protocol._scanner is scanner


def test_a_compiler_that_fails_leaves_one_line_and_the_numpy_code(monkeypatch, caplog):
    if not jit.ready():
        pytest.skip(f"no compiled kernels: {jit.why_not()}")

    def broken(*args, **kwargs):
        raise RuntimeError("LLVM ERROR: no target\nmore")
    monkeypatch.setattr(jit.numba, "njit", broken)
    with jit.disabled():                       # restores the kernels and ENABLED on the way out
        jit.ENABLED = True                     # as if numba had imported but cannot compile
        with caplog.at_level(logging.WARNING, logger="stage.engine"):
            assert jit.warm() is False
        assert not jit.ENABLED and not jit.ready()
        from stage.sensors import protocol
        assert protocol._scanner is None               # bundles walked in Python
        assert jit.why_not() == "compilation failed (logged)"
        lines = [r.getMessage() for r in caplog.records if "compiled kernels" in r.getMessage()]
        assert len(lines) == 1 and "\n" not in lines[0] and "LLVM ERROR: no target" in lines[0]


def test_stage_jit_0_turns_the_kernels_off():
    env = dict(os.environ, STAGE_JIT="0")
    out = subprocess.run([sys.executable, "-c", "from stage.engine import jit; "
                          "print(jit.ready(), jit.why_not())"],
                         env=env, capture_output=True, text=True, check=True).stdout
    assert out.startswith("False") and "STAGE_JIT=0" in out


def _show_engine(poses, native: bool):
    """(engine, its manual clock) with the rig of ``three_dancers``' sensors (``poses``)."""
    from stage.clock import ManualClock
    from stage.engine.engine import Engine
    from stage.rig import Rig, set_calibration
    rig = Rig(reference="s0")
    rig.fusion = dataclasses.replace(rig.fusion, native=native)
    rig.stage_frame = poses[0].to_stage
    inverse = np.linalg.inv(poses[0].to_stage)
    for k, p in enumerate(poses):
        set_calibration(rig, f"s{k}", inverse @ p.to_stage, "test")
    clock = ManualClock(0.0)
    return Engine(rig, clock), clock


def _run_engine(poses, data, snapshots: list) -> None:
    # the Python path's kernels are what these tests compare (the native core is held to
    # that path in tests/test_native.py)
    engine, clock = _show_engine(poses, native=False)
    for t, d in data:
        clock.set(t)
        engine.handle_datagram(d)
        engine.tick()
        snapshots.append({pid: (b.joints, b.conf, b.velocity, b.position, b.hands)
                          for pid, b in engine.bodies().items()})
    snapshots.append(engine.people.stats())


@needs_jit
@pytest.mark.parametrize("aligned", [False, True])
def test_the_engine_with_kernels_fuses_what_the_numpy_engine_fuses(aligned):
    """Whole shows through two engines, kernels on and off: the same persons, the same
    confidences, hands and filter outcomes, positions within a micrometre. Sensors in step
    (``aligned``) make every frame an instant whose views are checked against each other
    (the consistency and prior kernels), and replays when they disagree."""
    poses, data = three_dancers(aligned=aligned)
    on, off = [], []
    _run_engine(poses, data, on)
    with jit.disabled():
        _run_engine(poses, data, off)
    assert on[-1] == off[-1]                              # gate outcomes, replays, rejections
    assert on[-1]["joints_downweighted"] > 0
    if aligned:
        assert on[-1]["replays"] > 0 and on[-1]["joints_disagreeing"] > 0
    carried = 0
    for a, b in zip(on[:-1], off[:-1]):
        assert a.keys() == b.keys()
        for pid in a:
            (ja, ca, va, ma, ha), (jb, cb, vb, mb, hb) = a[pid], b[pid]
            np.testing.assert_array_equal(ca, cb)
            assert ha == hb
            np.testing.assert_allclose(ja, jb, rtol=0, atol=1e-6)
            np.testing.assert_allclose(va, vb, rtol=0, atol=1e-5)
            np.testing.assert_allclose(ma, mb, rtol=0, atol=1e-6)
            carried += int(((ca > 0) & (ca <= 0.5)).sum())
    assert len(on) > 500 and carried > 0


@needs_jit
def test_frame_kernel_transforms_and_unswaps_as_numpy_does():
    """Random calibrations and bodies whose arms or legs are crossed, swapped, partly
    unseen or inferred: the same joints (to rounding), confidences and traded bits."""
    from stage.engine.fusion import _LOOK, _TRADED, SWAP_MARGIN_M, apply_transform, unswap_limbs
    from stage.geometry import rot_y
    from stage.sensors.sim import standing_pose
    rng = np.random.default_rng(21)
    bits = set()
    for k in range(400):
        body = standing_pose((rng.uniform(-1, 1), rng.uniform(-1, 1)), rng.uniform(-3, 3),
                             rng.uniform(-2, 2), rng.uniform(-2, 2))
        conf = rng.choice([0.0, 0.5, 1.0, 1.0, 1.0], 25)
        if k % 3 == 0:                                    # a sensor that swapped a limb
            left, right = _TRADED[k % 2]
            body[np.r_[left, right]] = body[np.r_[right, left]]
        matrix = np.eye(4)
        matrix[:3, :3] = rot_y(rng.uniform(-3, 3))
        matrix[:3, 3] = rng.normal(0, 2, 3)
        want_j, want_c, want_bits = unswap_limbs(apply_transform(matrix, body), conf)
        got_j, got_c, got_bits, _, _, _ = jit.frame_r(matrix, body, conf, True, _LOOK,
                                                   _TRADED, SWAP_MARGIN_M, KalmanSettings(),
                                                   0.5)
        assert got_bits == want_bits
        np.testing.assert_array_equal(got_c, want_c)
        np.testing.assert_allclose(got_j, want_j, rtol=0, atol=1e-12)
        plain_j, plain_c, none, _, _, _ = jit.frame_r(matrix, body, conf, False, _LOOK,
                                                   _TRADED, SWAP_MARGIN_M, KalmanSettings(),
                                                   0.5)
        assert none == 0
        np.testing.assert_allclose(plain_j, apply_transform(matrix, body), rtol=0, atol=1e-12)
        bits.add(want_bits)
    assert {0, 1, 2} <= bits                              # arms, legs and nothing traded


@needs_jit
def test_frame_kernel_gives_the_batch_variances():
    """``jit.frame_r``'s variances are, bit for bit, what ``People._variances`` computes for
    the same stage-space joints (the kernel's own, which match numpy's to rounding), and its
    trunk length ``body_size``'s and its count of seen joints, including inferred, continuous
    and unseen confidences and joints within 1 m."""
    from types import SimpleNamespace

    from stage.engine.fusion import _LOOK, _TRADED, SWAP_MARGIN_M
    from stage.engine.people import People
    from stage.engine.tracking import body_size
    from stage.geometry import rot_y
    from stage.joints import INFERRED
    from stage.sensors.sim import standing_pose
    rng = np.random.default_rng(22)
    settings = [KalmanSettings(), KalmanSettings(measurement_noise=4e-4, noise_per_m=0.01,
                                                 inferred_sd_m=0.2)]
    near = sizes = 0
    for k in range(300):
        s = settings[k % 2]
        body = standing_pose((rng.uniform(-1, 1), rng.uniform(-1, 1)), rng.uniform(-3, 3),
                             rng.uniform(-2, 2), rng.uniform(-2, 2))
        conf = rng.choice([0.0, 0.3, 0.5, 0.9, 1.0], 25)
        matrix = np.eye(4)
        matrix[:3, :3] = rot_y(rng.uniform(-3, 3))
        matrix[:3, 3] = rng.normal(0, 1.5, 3)
        joints, c, _, r, size, seen = jit.frame_r(matrix, body, conf, k % 3 > 0, _LOOK,
                                                  _TRADED, SWAP_MARGIN_M, s, INFERRED)
        assert seen == np.count_nonzero(c > 0)            # what People.frame used to count
        view = SimpleNamespace(joints=joints, conf=c, r=None)
        People._variances(SimpleNamespace(smoothing=s), [(view, matrix[:3, 3])])
        np.testing.assert_array_equal(r, view.r)          # NaN where unseen, on both
        size = None if size != size else size             # NaN: body_size's None
        assert size == body_size(joints, c)               # the trunk, or None on both
        sizes += size is None
        near += int((np.linalg.norm(joints - matrix[:3, 3], axis=1) < 1.0).sum())
    assert near > 0 and 0 < sizes < 300


@needs_jit
def test_frame_kernel_of_many_frames_is_the_kernel_of_each():
    """``jit.frame_r_many`` on K frames gives, row by row, ``jit.frame_r``'s floats for each
    (swapped limbs, unseen joints, NaN coordinates, missing trunks included)."""
    from stage.engine.fusion import _LOOK, _TRADED, SWAP_MARGIN_M
    from stage.geometry import rot_y
    from stage.joints import INFERRED
    from stage.sensors.sim import standing_pose
    rng = np.random.default_rng(23)
    traded = 0
    for trial in range(60):
        s = KalmanSettings(measurement_noise=float(rng.uniform(1e-5, 1e-3)))
        matrix = np.eye(4)
        matrix[:3, :3] = rot_y(rng.uniform(-3, 3))
        matrix[:3, 3] = rng.normal(0, 1.5, 3)
        k = int(rng.integers(1, 8))
        joints = np.array([standing_pose((rng.uniform(-1, 1), rng.uniform(-1, 1)),
                                         rng.uniform(-3, 3), rng.uniform(-2, 2),
                                         rng.uniform(-2, 2)) for _ in range(k)])
        conf = rng.choice([0.0, 0.3, 0.5, 0.9, 1.0], (k, 25))
        if trial % 4 == 0:                                   # limbs crossed over: swapped
            joints[:, [4, 5, 6, 7, 8, 9, 10, 11]] = joints[:, [8, 9, 10, 11, 4, 5, 6, 7]]
        if trial % 5 == 0:
            joints[0, int(rng.integers(25))] = np.nan
        unswap = trial % 3 > 0
        many = jit.frame_r_many(matrix, joints, conf, unswap, _LOOK, _TRADED, SWAP_MARGIN_M, s,
                                INFERRED)
        for row in range(k):
            one = jit.frame_r(matrix, joints[row], conf[row], unswap, _LOOK, _TRADED,
                              SWAP_MARGIN_M, s, INFERRED)
            np.testing.assert_array_equal(many[0][row], one[0])
            np.testing.assert_array_equal(many[1][row], one[1])
            assert many[2][row] == one[2]
            np.testing.assert_array_equal(many[3][row], one[3])
            np.testing.assert_array_equal(many[4][row], [one[4], one[5]])
            traded += one[2] != 0
    assert traded > 0


@needs_jit
def test_frames_prepared_together_fuse_what_frames_taken_one_by_one_fuse(monkeypatch):
    """A batch's frames computed in one call (``People.prepare_frames``) give the engine the
    very floats it computes frame by frame: the same bodies to the bit."""
    from stage.engine.people import People
    poses, data = three_dancers(seconds=3.0)
    together, alone = [], []
    calls = []
    prepare = People.prepare_frames

    def counted(self, transform, frames):
        calls.append(len(frames))
        prepare(self, transform, frames)
    monkeypatch.setattr(People, "prepare_frames", counted)
    _run_engine(poses, data, together)
    monkeypatch.setattr(People, "prepare_frames", lambda self, transform, frames: None)
    _run_engine(poses, data, alone)
    assert len(calls) > 100 and max(calls) >= 2
    assert together[-1] == alone[-1]
    for a, b in zip(together[:-1], alone[:-1]):
        assert a.keys() == b.keys()
        for pid in a:
            for x, y in zip(a[pid], b[pid]):
                if isinstance(x, np.ndarray):
                    np.testing.assert_array_equal(x, y)
                else:
                    assert x == y


@needs_jit
def test_distance_kernel_is_persons_distance():
    from stage.engine.tracking import Person
    from stage.settings import FusionSettings
    rng = np.random.default_rng(5)
    results = set()
    for k in range(300):
        person = Person.new(1, 0.0, FusionSettings())
        person.joints = rng.normal(0, 1, (25, 3))
        person.velocity = rng.normal(0, 1, (25, 3))
        person.known = rng.random(25) < (0.3, 0.9, 1.0)[k % 3]
        person.t = rng.uniform(0, 1)
        joints = person.joints + rng.normal(0, 0.1, (25, 3))
        sparse = 0.6 * (k % 5 == 0)
        conf = rng.choice([0.0, 0.5, 1.0], 25, p=(0.2 + sparse, 0.2, 0.6 - sparse))
        t = rng.uniform(0, 1.5)
        got = person.distance(joints, conf, t)
        with jit.disabled():
            want = person.distance(joints, conf, t)
        assert (got is None) == (want is None)
        if want is not None:
            assert got == pytest.approx(want, rel=1e-12)
        results.add(want is None)
    assert results == {True, False}


def test_no_writable_cache_compiles_without_one(monkeypatch, caplog):
    """A read-only install whose user has no writable cache folder: numba refuses to cache;
    the kernels are compiled without a cache (one logged line), not given up."""
    if not jit.ready():
        pytest.skip(f"no compiled kernels: {jit.why_not()}")
    real = jit.numba.njit
    calls = []

    def no_cache(sig=None, cache=False, **kwargs):
        if sig is not None:       # (a kernel; helpers compiled into them have no signature)
            calls.append(cache)
        if cache:
            raise RuntimeError("cannot cache function '_step_rows': no locator available for "
                               "file '/opt/stage/jit.py'")
        return real(sig, cache=False, **kwargs)
    monkeypatch.setattr(jit.numba, "njit", no_cache)
    with jit.disabled():
        jit.ENABLED = True
        with caplog.at_level(logging.WARNING, logger="stage.engine"):
            assert jit.warm() is True
        assert calls[0] is True and len(calls) > 1 and not any(calls[1:])
        assert sum("no disk cache" in r.getMessage() for r in caplog.records) == 1


def test_a_scanner_that_cannot_cache_is_compiled_without_a_cache(monkeypatch, caplog):
    """The scanner lives in another package folder than the engine's kernels; should only
    that one have no writable cache, it is compiled without one (one logged line) and
    installed, and the kernels are kept."""
    if not jit.ready():
        pytest.skip(f"no compiled kernels: {jit.why_not()}")
    from stage.sensors import protocol
    real = jit.numba.njit
    calls = []

    def no_cache_for_scan(sig=None, cache=False, **kwargs):
        def decorate(fn):
            calls.append((fn.__name__, cache))
            if cache and fn.__name__ == "scan":
                raise RuntimeError("cannot cache function 'scan': no locator available for "
                                   "file '/opt/stage/sensors/scan.py'")
            return real(sig, cache=cache, **kwargs)(fn)
        return decorate
    monkeypatch.setattr(jit.numba, "njit", no_cache_for_scan)
    with jit.disabled():
        jit.ENABLED = True
        with caplog.at_level(logging.WARNING, logger="stage.engine"):
            assert jit.warm() is True
        assert jit.ready() and protocol._scanner is jit._compiled["scan"]
        # tried with a cache, then compiled without one (and so is every kernel after it)
        k = calls.index(("scan", True))
        assert calls[k + 1] == ("scan", False)
        assert not any(cache for _, cache in calls[k + 1:])
        assert sum("no disk cache" in r.getMessage() for r in caplog.records) == 1


@needs_jit
def _gate_rig(rng, people, frames=600):
    """The jump gate tests' show: ``people`` (4, J, 3) wander, a sensor of "abc" is bumped
    every 97 frames and sensors are trusted anew every 40; yields (frame, sensor, its
    offset now, its new trust or None) for each sensor's turn at each frame."""
    offset = {s: np.zeros(3) for s in "abc"}
    for f in range(frames):
        people += rng.normal(0, 0.01, (4, 1, 3))
        if f % 97 == 50:
            offset["abc"[f % 3]] = rng.normal(0, 0.4, 3)                   # a bump
        for s in "abc":
            yield f, s, offset[s], (bool(rng.random() < 0.85) if f % 40 == 0 else None)


def test_jump_gate_kernel_is_the_numpy_gate():
    """Two gates fed the same three sensors' views of four people for 20 s, in datagrams
    and one view at a time, while the sensors are trusted and untrusted and one is bumped
    now and then: the same jumps (sensors and distance), links and recorded state."""
    from stage.calibration.gate import JumpGate
    rng = np.random.default_rng(8)
    gates = [JumpGate(), JumpGate()]
    people = rng.uniform(-2, 2, (4, 1, 3)) + rng.normal(0, 0.15, (4, 5, 3))   # torso points
    jumps, drifted = 0, []
    for f, s, offset, trusted in _gate_rig(rng, people):
        if s == "a" and f and f % 10 == 0:
            # how far each sensor's views drifted from the others, chunk by chunk (the
            # chunk of frames f - 10 .. f - 1)
            a, b = gates
            assert a.apart.keys() == b.apart.keys()
            for sensor in a.apart:
                assert a.apart[sensor] == pytest.approx(b.apart[sensor], rel=1e-9)
            drifted.append(max(a.apart.values(), default=0.0) > 0.1)
            a.apart.clear()
            b.apart.clear()
        if trusted is not None:
            for g in gates:
                g.trust(s, trusted)
        users = [u for u in range(4) if rng.random() < 0.9]
        if not users:
            continue
        t = f / 30 + rng.uniform(0, 0.005)
        points = people[users] + offset + rng.normal(0, 0.01, (len(users), 5, 3))
        tracked = rng.random((len(users), 5)) < 0.8
        results = []
        for compiled, g in zip((True, False), gates):
            with (contextlib.nullcontext() if compiled else jit.disabled()):
                if f % 2:
                    results.append(g.check_many(s, users, t, points, tracked))
                else:
                    results.append([g.check(s, u, t, points[k], tracked[k])
                                    for k, u in enumerate(users)])
        for got, want in zip(*results):
            assert (got is None) == (want is None)
            if want is not None:
                jumps += 1
                assert got[0] == want[0] and got[1] == pytest.approx(want[1], rel=1e-9)

    a, b = gates
    n = len(a._index)
    for name in ("_t", "_x", "_v", "_links"):
        np.testing.assert_allclose(getattr(a, name)[:n], getattr(b, name)[:n], rtol=1e-9,
                                   atol=1e-12, err_msg=name)
    np.testing.assert_array_equal(a._m[:n], b._m[:n])
    assert jumps > 5
    # the sensors agree until the first bump (frame 50), and drift apart from it on
    assert drifted[:5] == [False] * 5 and drifted[5]


def test_jump_gate_of_a_datagram_is_the_gate_of_its_placed_views():
    """``JumpGate.check_frames`` (one compiled call on a datagram's skeletons as decoded)
    against the numpy gate fed what the calibrator computed from the same skeletons before
    (the torso joints tracked, placed by the sensor's transform; skeletons tracking none
    left out): the same jumps, the same ``apart``, the same recorded state, while the
    sensors are trusted and untrusted and bumped now and then."""
    from stage.calibration.gate import JumpGate
    from stage.joints import TORSO
    torso = np.array(TORSO)
    rng = np.random.default_rng(11)
    fast, slow = JumpGate(), JumpGate()
    # each sensor's transform: a turn about the vertical and a shift
    mats = {}
    for k, s in enumerate("abc"):
        a = 0.7 * k
        m = np.eye(4)
        m[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        m[:3, 3] = rng.normal(0, 1, 3)
        mats[s] = m
    people = rng.uniform(-2, 2, (4, 1, 3)) + rng.normal(0, 0.2, (4, 25, 3))  # stage space
    jumps, judged, left_out = 0, 0, 0
    for f, s, offset, trusted in _gate_rig(rng, people):
        if s == "a" and f and f % 10 == 0:      # the chunk of frames f - 10 .. f - 1
            assert fast.apart.keys() == slow.apart.keys()
            for sensor in fast.apart:
                assert fast.apart[sensor] == pytest.approx(slow.apart[sensor], rel=1e-9)
            fast.apart.clear()
            slow.apart.clear()
        if trusted is not None:
            fast.trust(s, trusted)
            slow.trust(s, trusted)
        users = tuple(u for u in range(4) if rng.random() < 0.9)
        if not users:
            continue
        t = f / 30 + rng.uniform(0, 0.005)
        m = mats[s]
        on_stage = people[list(users)] + offset + rng.normal(0, 0.01, (len(users), 25, 3))
        joints = np.ascontiguousarray((on_stage - m[:3, 3]) @ m[:3, :3])    # sensor space
        conf = rng.choice([0.0, 0.5, 1.0], (len(users), 25), p=[0.1, 0.1, 0.8])
        if f % 7 == 3:
            conf[0, torso] = 0.5                     # tracks no torso joint: left out
            left_out += 1
        got = fast.check_frames(s, users, t, joints, conf, m)
        tracked = conf[:, torso] >= 1.0
        seen = np.flatnonzero(tracked.any(axis=1))
        placed = joints[seen][:, torso] @ m[:3, :3].T + m[:3, 3]
        want = []
        if len(seen):     # (the calibrator calls the gate only with a view to judge)
            with jit.disabled():
                want = slow.check_many(s, [users[k] for k in seen], t, placed,
                                       tracked[seen])
        want = [(int(seen[r]), w) for r, w in enumerate(want) if w is not None]
        judged += len(seen)
        assert [r for r, _ in got] == [r for r, _ in want]
        for (_, g), (_, w) in zip(got, want):
            jumps += 1
            assert g[0] == w[0] and g[1] == pytest.approx(w[1], rel=1e-9)
    n = len(fast._index)
    assert n == len(slow._index)
    for name in ("_t", "_x", "_v", "_links"):
        np.testing.assert_allclose(getattr(fast, name)[:n], getattr(slow, name)[:n], rtol=1e-9,
                                   atol=1e-9, err_msg=name)
    np.testing.assert_array_equal(fast._m[:n], slow._m[:n])
    assert jumps > 5 and left_out > 50 and judged > 5000


def test_no_numba_is_one_line_and_the_numpy_engine():
    """A machine where numba will not import: building an engine logs one line and the
    engine fuses with the numpy code."""
    code = ("import sys, logging; sys.modules['numba'] = None\n"
            "logging.basicConfig(level=logging.WARNING, format='%(message)s')\n"
            "from stage.engine import jit\n"
            "from stage.engine.engine import Engine\n"
            "Engine()\n"
            "print('ready', jit.ready(), jit.why_not())\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, STAGE_JIT="1"))
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("ready False ModuleNotFoundError")
    lines = [line for line in done.stderr.splitlines() if "compiled kernels" in line]
    assert len(lines) == 1 and "numpy code" in lines[0]


@needs_jit
def test_a_person_whose_array_was_replaced_is_bound_to_the_bank_again():
    """A person whose hold offsets were replaced by an array of another dtype (no path makes
    one today) after it was bound to the person bank: its values are copied into the bank
    at the next settle, which goes on for it in the kernel."""
    poses, data = three_dancers(seconds=1.0)
    from stage.clock import ManualClock
    from stage.engine.engine import Engine
    from stage.rig import Rig, set_calibration
    rig = Rig(reference="s0")
    rig.fusion = dataclasses.replace(rig.fusion, native=False)   # (the person bank's binding)
    rig.stage_frame = poses[0].to_stage
    for k, p in enumerate(poses):
        set_calibration(rig, f"s{k}", np.linalg.inv(poses[0].to_stage) @ p.to_stage, "test")
    clock = ManualClock(0.0)
    engine = Engine(rig, clock)
    for t, d in data[:30]:
        clock.set(t)
        engine.handle_datagram(d)
    odd = next(iter(engine.people.persons.values()))
    bank = engine.people.bank
    assert odd.bank is bank and odd.hold.base is bank.hold
    odd.hold = odd.hold.astype(np.float32)
    want = np.array(odd.hold, dtype=float)
    before = odd.t
    clock.set(data[30][0])
    engine.handle_datagram(data[30][1])
    if odd.t > before:     # (settled in this datagram: its hold is the bank's again)
        assert odd.hold.base is bank.hold and odd.hold.dtype == np.float64
    for t, d in data[31:]:
        clock.set(t)
        engine.handle_datagram(d)
    assert odd.t > before and np.isfinite(odd.joints[odd.conf > 0]).all()
    assert odd.hold.base is bank.hold
    kept = np.isfinite(want) & np.isfinite(odd.hold)
    assert kept.any()                          # offsets it had are carried on (or renewed)


@needs_jit
def test_a_batch_the_kernel_refuses_is_settled_by_the_numpy_code(monkeypatch):
    """Should the batch kernel refuse its arrays (TypeError), the batch is settled by the
    numpy code: the same show as an engine whose kernel never refuses."""
    poses, data = three_dancers(seconds=2.0)
    ok, refused = [], []
    _run_engine(poses, data, ok)
    calls = []

    def refuse(*args, **kwargs):
        calls.append(1)
        raise TypeError("no matching definition")

    monkeypatch.setattr(jit, "settle_many", refuse)
    _run_engine(poses, data, refused)
    assert len(calls) > 100 and ok[-1] == refused[-1]
    for a, b in zip(ok[:-1], refused[:-1]):
        assert a.keys() == b.keys()
        for pid in a:
            np.testing.assert_array_equal(a[pid][1], b[pid][1])
            np.testing.assert_allclose(a[pid][0], b[pid][0], rtol=0, atol=1e-6)


@needs_jit
def test_view_joints_kernel_writes_the_encoders_bytes():
    """The compiled ``/jointCoordinates`` is byte for byte ``encode_view_joints``'s on random
    skeletons (joints dropped, NaN and inf coordinates, values beyond float32, every user
    id width), and python-osc reads it back."""
    from pythonosc.osc_message import OscMessage

    from stage.joints import JOINTS
    from stage.sensors.encode import encode_view_joints

    rng = np.random.default_rng(7)
    dropped = 0
    for k in range(2000):
        joints = rng.normal(0.0, 1.0, (25, 3)) * rng.choice([1e-3, 1.0, 5.0, 1e39])
        conf = rng.choice([0.0, 0.5, 1.0, 0.3, -1.0, np.nan], size=25)
        if k % 5 == 0:
            joints[rng.integers(25)] = rng.choice([np.nan, np.inf, -np.inf])
        if k % 97 == 0:
            conf[:] = 0.0
        user = int(rng.choice([0, 7, 2 ** 15, 2 ** 31 - 1]))
        with np.errstate(over="ignore"):                  # 1e39 is inf in float32
            expected = encode_view_joints(user, joints, conf)
        assert jit.view_joints(user, joints, conf) == expected
        dropped += int(not (conf > 0).all())
    assert dropped > 1000
    joints, conf = rng.normal(0.0, 1.0, (25, 3)), np.linspace(0.04, 1.0, 25)
    conf[3] = 0.0
    msg = OscMessage(jit.view_joints(12, joints, conf))
    params = msg.params
    assert msg.address == "/jointCoordinates" and params[0] == 12
    names = [JOINTS[j] for j in range(25) if j != 3]
    assert params[1::5] == names
    got = np.array([params[2 + 5 * m: 6 + 5 * m] for m in range(24)])
    want = np.column_stack([np.delete(joints, 3, axis=0), np.delete(conf, 3)])
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)


@needs_jit
def test_recent_confidence_is_the_best_of_the_views_of_the_last_stale_seconds():
    """A person's views come, go and fall silent; the output confidence (numpy and the
    settle kernel) is each joint's best among the views heard within ``stale`` s."""
    from stage.engine.people import INFERRED, People, _TORSO
    from stage.engine.tracking import Person
    from stage.settings import FusionSettings
    rng = np.random.default_rng(11)
    person = Person.new(1, 0.0, FusionSettings())
    live: dict = {}
    stale, t = 0.25, 0.0
    checked = 0
    for _ in range(400):
        t += float(rng.uniform(0.0, 0.05))
        key = (f"s{rng.integers(5)}", int(rng.integers(2)))
        if rng.random() < 0.15:
            person.forget(key)
            live.pop(key, None)
            continue
        conf = np.where(rng.random(25) < 0.3, 0.0, rng.uniform(0.0, 1.2, 25))
        person.remember(key, t, conf)
        live[key] = (t, conf)
        now = t + float(rng.uniform(0.0, 0.3))
        heard = [c for vt, c in live.values() if now - vt <= stale]
        want = np.max(heard, axis=0) if heard else np.zeros(25)
        np.testing.assert_array_equal(People._recent_conf(person, now, stale), want)
        pos = rng.normal(0, 1, (25, 3))
        out = jit.settle(pos, np.zeros((25, 3)), np.full(25, now), now, stale,
                         person.recent_conf, person.recent_t, np.zeros((25, 3)),
                         np.zeros(25, dtype=bool), np.zeros(25, dtype=bool),
                         np.full((25, 3), np.nan), False, False, INFERRED, _PARENTS,
                         _CHILDREN, _TORSO)
        np.testing.assert_array_equal(out[2], np.where(want > 0, np.minimum(want, 1.0), 0.0))
        checked += bool(heard)
    assert checked > 200 and len(person.recent_t) <= 16     # forgotten rows are used again


@needs_jit
def test_consistency_kernel_picks_the_numpy_views():
    """``jit.consistent`` against ``fusion.consistent_views``'s numpy code on random instants:
    2-6 views, unseen joints (NaN, inf), no prior, views that only infer a joint."""
    from stage.engine.fusion import consistent_views
    rng = np.random.default_rng(11)
    for _ in range(2000):
        G, J = int(rng.integers(2, 7)), int(rng.integers(1, 26))
        z = rng.normal(0, 0.05, (G, J, 3))
        r = rng.uniform(1e-4, 3e-3, (G, J))
        r[rng.random((G, J)) < 0.2] = np.nan
        r[rng.random((G, J)) < 0.05] = np.inf
        prior = np.full((J, 3), np.nan) if rng.random() < 0.3 else rng.normal(0, 0.05, (J, 3))
        var = rng.uniform(1e-4, 3e-3, J)
        tracked = rng.random((G, J)) < 0.7 if rng.random() < 0.5 else None
        got = jit.consistent(z, r, prior, var, 0.02 ** 2, 2.5 ** 2, tracked)
        with jit.disabled():
            want = consistent_views(z, r, prior, var, 0.02 ** 2, 2.5 ** 2, tracked)
        np.testing.assert_array_equal(got, want)


@needs_jit
def test_prior_kernel_gives_the_numpy_floats():
    """``jit.prior`` against the numpy ``fuser.prior_of``, bit for bit, rows never measured
    (NaN times) and times before a row's own included; on a block's rows (a strided view).
    numpy's expm1 is the C library's here, as the kernel's (``libm``)."""
    from stage.engine.fuser import prior_of
    from stage.engine.kalman import FilterState
    rng = np.random.default_rng(12)
    s = KalmanSettings()
    for _ in range(200):
        block = _stack(rng, 75)
        t = rng.uniform(0.0, 1.0, 75)
        t[rng.random(75) < 0.1] = np.nan
        state = FilterState.of_block(block, t, np.full((75, 3), np.nan),
                                     np.full(75, np.nan)).view_rows(25, 50)
        at = float(rng.uniform(0.8, 1.2))
        mean, var = jit.prior(state.stacked(), state.t, at, s)
        with jit.disabled(), c_library_math():
            want_mean, want_var = prior_of(state, at, s)
        np.testing.assert_array_equal(mean, want_mean)
        np.testing.assert_array_equal(var, want_var)


@needs_jit
def test_forecast_kernel_gives_the_numpy_floats():
    """``Forecaster.predict`` compiled against its numpy code, bit for bit: joints, velocity,
    s.d. and counts; bodies whose rows were updated at different times (some never: NaN),
    moving fast enough to be capped and to stretch bones (both walks of the bone mending),
    feet and hands with a velocity memory, unseen joints, a strided state (a block's rows);
    and the same stream of forecasts leaves the same statistics."""
    from stage.engine.forecast import BONES, Forecaster
    from stage.engine.kalman import FilterState
    from stage.settings import ForecastSettings
    from stage.testing.script import standing
    rng = np.random.default_rng(53)
    s, body = KalmanSettings(), standing()
    compiled = Forecaster(s, ForecastSettings(bone_tolerance=0.1))
    reference = Forecaster(s, ForecastSettings(bone_tolerance=0.1))
    moved = 0
    for k in range(300):
        block = _stack(rng, 75)
        rows = slice(25, 50)
        block[0, :, rows] = body[None] + rng.normal(0, 0.01 if k % 3 else 0.2, (2, 25, 3))
        block[1, :, rows] *= rng.choice([0.5, 3.0, 30.0])      # slow, fast, a glitch
        t = rng.uniform(0.9, 1.0, 75)
        t[rng.random(75) < 0.1] = np.nan
        block[:, :, rng.random(75) < 0.05] = np.nan             # rows never measured
        state = FilterState.of_block(block, t, np.full((75, 3), np.nan),
                                     np.full(75, np.nan)).view_rows(25, 50)
        now = body + rng.normal(0, 0.01, (25, 3))
        seen = rng.random(25) > 0.1
        horizon = float(rng.choice([0.0, 0.03, 0.05, 0.2]))
        at = float(rng.uniform(0.95, 1.05))
        got = compiled.predict(state, at, now, seen, horizon)
        with jit.disabled(), c_library_math():
            want = reference.predict(state, at, now, seen, horizon)
        for name in ("joints", "velocity", "sd"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        assert (got.speed_capped, got.bones_fixed, got.t, got.horizon) == \
            (want.speed_capped, want.bones_fixed, want.t, want.horizon)
        moved += got.bones_fixed > 0 and got.speed_capped > 0
    assert moved > 30                   # the caps and the bones were exercised
    assert compiled.stats()["made"] == reference.stats()["made"] == 300
    for key in ("speed_capped", "bones_fixed"):
        assert compiled.stats()[key] == reference.stats()[key]
    assert compiled.last_sd.keys() == reference.last_sd.keys()
    for h in compiled.last_sd:          # (a mean summed in another order: to the last bits)
        assert compiled.last_sd[h] == pytest.approx(reference.last_sd[h], rel=1e-12)
    assert len(BONES) == 24


@needs_jit
@pytest.mark.parametrize("native", [True, False])
def test_a_frames_forecasts_in_one_call_are_each_bodys_own(native):
    """With the kernels the engine predicts a frame's bodies in one compiled call
    (``Forecaster.predict_many``); one body at a time (``People._forecast_each``, through
    ``_forecast``) gives the same floats, bit for bit: joints, velocity, s.d., confidences,
    centres, and the same statistics. Three dancers walking in and out of three sensors'
    range, on the native core (persons on the Python path until it takes them) and on the
    Python path alone."""
    from stage.engine.forecast import Forecaster
    poses, data = three_dancers(seconds=4.0, timetags=True)
    engine, clock = _show_engine(poses, native)
    people = engine.people
    people.want_forecast(0.05)
    reference = Forecaster(people.forecaster.smoothing, people.forecaster.settings)
    batches = []
    many = people.forecaster.predict_many

    def counted(*args):
        batches.append(len(args[0]))
        return many(*args)

    people.forecaster.predict_many = counted
    compared = [0, 0]
    errors = []

    def check(frame):
        try:
            compare(frame)
        except Exception as exc:     # (the engine disables a listener that raises)
            errors.append(exc)

    def compare(frame):
        got = frame.forecasts[0.05]
        persons = [p for p in people.persons.values() if p.announced and p.centre is not None]
        batched, people.forecaster = people.forecaster, reference
        try:
            want = people._forecast_each(persons, 0.05)
        finally:
            people.forecaster = batched
            people._forecasts.clear()
        assert got.keys() == want.keys()
        for pid, body in got.items():
            ref = want[pid]
            for name in ("joints", "velocity", "sd", "conf", "position"):
                np.testing.assert_array_equal(getattr(body, name), getattr(ref, name),
                                              err_msg=name)
            assert (body.t, body.horizon, body.hands, body.sensors) == \
                (ref.t, ref.horizon, ref.hands, ref.sensors)
        compared[0] += 1
        compared[1] += len(got) > 1

    engine.listeners.append(check)
    for t, d in data:
        clock.set(t)
        engine.handle_datagram(d)
        engine.tick()
    assert not errors, errors[0]
    assert compared[1] > 100 and sum(batches) >= 2 * len(batches) > 200
    if native:
        assert people.core is not None and people.core.slot_of
    mine, theirs = people.forecaster.stats(), reference.stats()
    assert mine == theirs and mine["made"] >= sum(batches)
    assert people.forecaster.last_sd == reference.last_sd

@pytest.mark.parametrize("compiled", [True, False])
def test_views_stepped_in_one_call_are_the_steps_in_turn(compiled):
    """``kalman.step_views`` (a replay's views of one person, in one compiled call) against
    ``step`` called for each view in turn, bit for bit: states, outcomes, rows used; with
    rows that start (never measured) and restart (rejected twice) between the views, which
    the kernel leaves to Python part way."""
    from stage.engine.kalman import (DOWNWEIGHTED, REJECTED, RESTARTED, STARTED, USED,
                                     FilterState, step, step_views)
    if compiled and not jit.ready():
        pytest.skip(f"no compiled kernels: {jit.why_not()}")
    rng = np.random.default_rng(13)
    s = KalmanSettings()
    seen: set[int] = set()
    with (contextlib.nullcontext() if compiled else jit.disabled()):
        for trial in range(150):
            n = 25
            block = _stack(rng, n)
            t0 = rng.uniform(0.0, 0.5, n)
            t0[rng.random(n) < 0.1] = np.nan                   # never measured: started
            held_t = np.where(rng.random(n) < 0.2, 0.45, np.nan)
            held_z = block[0, 0] + 2.0
            state = FilterState.of_block(block, t0, held_z, held_t)
            G = int(rng.integers(1, 7))
            t = np.sort(rng.uniform(0.5, 0.6, G))
            z = block[0, 0][None] + rng.normal(0, 0.01, (G, n, 3))
            z[:, rng.random(n) < 0.15] += 2.0                  # rejected: held, then restarted
            r = rng.uniform(1e-4, 1e-3, (G, n))
            r[rng.random((G, n)) < 0.1] = np.nan
            q_scale = rng.uniform(0.5, 2.0, n) if trial % 2 else None
            states, outcome, used, counts, last = step_views(state, t, z, r, s, q_scale)
            ref = state.shallow()
            for g in range(G):
                o = step(ref, np.full(n, t[g]), z[g], r[g], s, q_scale)
                np.testing.assert_array_equal(outcome[g], o)
                np.testing.assert_array_equal(used[g], USED[o])
                assert counts[g].tolist() == [np.count_nonzero(o == k) for k in
                                              (RESTARTED, STARTED, DOWNWEIGHTED, REJECTED)]
                for name in ("x", "P", "mu", "t", "held_z", "held_t"):
                    np.testing.assert_array_equal(getattr(states[g], name), getattr(ref, name))
                seen.update(o.tolist())
            if last is not None:                               # the kernel's estimate
                for got, want in zip(last, ref.predicted(t[-1])):
                    np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(state.t, t0)         # the state given is unchanged
    assert {STARTED, RESTARTED} <= seen


@needs_jit
def test_consistency_kernel_refuses_shapes_that_do_not_match():
    """The kernel reads without bounds checks: arrays whose shapes disagree go to the numpy
    code (which broadcasts or raises), never into the kernel."""
    from stage.engine.fusion import consistent_views
    z = np.zeros((3, 1, 3))
    r = np.full((3, 1), 1e-3)
    with pytest.raises(TypeError):
        jit.consistent(z, r, np.zeros((25, 3)), np.ones(25), 4e-4, 6.25, None)
    with pytest.raises(TypeError):
        jit.consistent(z, r, np.zeros((1, 3)), np.ones(1), 4e-4, 6.25, np.ones((2, 1), bool))
    with jit.disabled():
        want = consistent_views(z, r, np.zeros((1, 3)), np.ones(1), 4e-4, 6.25)
    np.testing.assert_array_equal(consistent_views(z, r, np.zeros((1, 3)), np.ones(1), 4e-4,
                                                   6.25), want)
