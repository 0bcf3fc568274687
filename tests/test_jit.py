"""The compiled kernels (stage/engine/jit.py) against the numpy code they replace."""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys

import numpy as np
import pytest

from stage.engine import imm, jit
from stage.engine.kalman import (ACCEPTED, DOWNWEIGHTED, NOT_MEASURED, REJECTED, RESTARTED,
                                 STARTED, FilterState, step)
from stage.engine.fusion import _CHILDREN, _PARENTS, carry_untracked, carry_untracked_numpy
from stage.settings import KalmanSettings

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
    block, t, held_t, outcome, n_bad, n_fresh = jit.step_rows(
        S, st, np.full(n, np.nan), st + dt, z, r, s, q)
    use = want_d2 <= s.reject_sigma ** 2
    np.testing.assert_allclose(block[:, :, use], want[:, :, use], rtol=1e-11, atol=1e-300)
    np.testing.assert_array_equal(block[:, :, ~use], S[:, :, ~use])      # kept as it was
    np.testing.assert_array_equal(t, np.where(use, st + dt, st))
    expected = np.where(use, np.where(want_d2 > s.gate_sigma ** 2, DOWNWEIGHTED, ACCEPTED),
                        REJECTED)
    np.testing.assert_array_equal(outcome, expected)
    assert n_bad == int((~use).sum()) and n_fresh == 0
    assert np.isnan(held_t).all()


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
                outcomes.append(step(state, t, z, r, s))
        np.testing.assert_array_equal(outcomes[0], outcomes[1])
        seen |= set(outcomes[0].tolist())
        for name in ("x", "P", "mu", "t", "held_z", "held_t"):
            np.testing.assert_allclose(getattr(states[0], name), getattr(states[1], name),
                                       rtol=1e-9, atol=1e-300, err_msg=name)
    assert {NOT_MEASURED, STARTED, ACCEPTED, DOWNWEIGHTED, REJECTED, RESTARTED} <= seen


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
    before = jit.ready()
    with jit.disabled():
        assert not jit.ready() and not jit.ENABLED
    assert jit.ready() == before


def test_a_compiler_that_fails_leaves_one_line_and_the_numpy_code(monkeypatch, caplog):
    if jit.numba is None:
        pytest.skip("numba is not installed")

    def broken(*args, **kwargs):
        raise RuntimeError("LLVM ERROR: no target\nmore")
    monkeypatch.setattr(jit.numba, "njit", broken)
    with jit.disabled():                       # restores the kernels and ENABLED on the way out
        jit.ENABLED = True                     # as if numba had imported but cannot compile
        with caplog.at_level(logging.WARNING, logger="stage.engine"):
            assert jit.warm() is False
        assert not jit.ENABLED and not jit.ready()
        assert jit.why_not() == "compilation failed (logged)"
        lines = [r.getMessage() for r in caplog.records if "compiled kernels" in r.getMessage()]
        assert len(lines) == 1 and "\n" not in lines[0] and "LLVM ERROR: no target" in lines[0]


def test_stage_jit_0_turns_the_kernels_off():
    env = dict(os.environ, STAGE_JIT="0")
    out = subprocess.run([sys.executable, "-c", "from stage.engine import jit; "
                          "print(jit.ready(), jit.why_not())"],
                         env=env, capture_output=True, text=True, check=True).stdout
    assert out.startswith("False") and "STAGE_JIT=0" in out
