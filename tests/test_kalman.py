"""stage.engine.kalman: the batched IMM filter against filterpy, its pure functions, the gate."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import IMMEstimator, KalmanFilter

from stage.engine import jit
from stage.engine.kalman import (ACCEPTED, DOWNWEIGHTED, REJECTED, RESTARTED, STARTED,
                                 FilterState, JointKalman, combine, gate_distance, initial_mu,
                                 measurement_variance, mix, predict, step, transition, update)
from stage.errors import ConfigError
from stage.settings import KalmanSettings

#: no gating: every measurement at face value, so filterpy (which has no gate) is comparable
UNGATED = dict(gate_sigma=1e6, reject_sigma=1e6)
SETTINGS = KalmanSettings(**UNGATED)
H = np.zeros((3, 6))
H[[0, 1, 2], [0, 2, 4]] = 1.0  # state ordered [x, vx, y, vy, z, vz]


class FilterpyPoint:
    """One point tracked by filterpy the long way: a 6-state KalmanFilter with its own clock."""

    def __init__(self, settings: KalmanSettings, q: float) -> None:
        self.s, self.q = settings, q
        self.kf: KalmanFilter | None = None
        self.last = math.nan

    def step(self, t: float, z: np.ndarray, r: float) -> None:
        if not (r > 0 and np.isfinite(r) and np.isfinite(z).all()):
            return
        if self.kf is None:
            self.kf = KalmanFilter(dim_x=6, dim_z=3)
            self.kf.x = np.zeros(6)
            self.kf.x[0::2] = z
            self.kf.P = np.kron(np.eye(3), np.diag([r, self.s.initial_velocity_var]))
            self.kf.H = H
            self.last = t
            return
        dt = max(t - self.last, 0.0)
        self.kf.F = np.kron(np.eye(3), np.array([[1.0, dt], [0.0, 1.0]]))
        self.kf.Q = Q_discrete_white_noise(dim=2, dt=dt, var=self.q, block_size=3,
                                           order_by_dim=True)
        self.kf.predict()
        self.kf.update(z, R=r * np.eye(3))
        self.last = max(self.last, t)


class FilterpyImmAxis:
    """One axis of one point as filterpy's IMMEstimator of two constant-velocity filters."""

    def __init__(self, settings: KalmanSettings) -> None:
        self.s = settings
        self.imm: IMMEstimator | None = None
        self.last = math.nan

    def step(self, t: float, z: float, r: float) -> None:
        s = self.s
        if self.imm is None:
            filters = []
            for _ in range(2):
                kf = KalmanFilter(dim_x=2, dim_z=1)
                kf.x = np.array([z, 0.0])
                kf.P = np.diag([r, s.initial_velocity_var])
                kf.H = np.array([[1.0, 0.0]])
                filters.append(kf)
            self.imm = IMMEstimator(filters, initial_mu(s).copy(), np.eye(2))
            self.last = t
            return
        dt = max(t - self.last, 0.0)
        p01, p10 = (float(p[0]) for p in transition(np.array([dt]), s))
        self.imm.M = np.array([[1.0 - p01, p01], [p10, 1.0 - p10]])
        # filterpy mixes with the transition matrix given at the previous update: recompute
        # its mixing probabilities for this step's dt
        self.imm._compute_mixing_probabilities()
        for kf, q in zip(self.imm.filters, (s.quiet_noise, s.fast_noise)):
            kf.F = np.array([[1.0, dt], [0.0, 1.0]])
            kf.Q = Q_discrete_white_noise(dim=2, dt=dt, var=q)
            kf.R = np.array([[r]])
        self.imm.predict()
        self.imm.update(np.array([z]))
        self.last = max(self.last, t)


def random_run(rng: np.random.Generator, n: int, steps: int, same_time_p: float = 0.0,
               kick_p: float = 0.0):
    """Yield (t, z, conf): wandering points, random dt 5-50 ms (or 0 with ``same_time_p``:
    another sensor's view of the same instant), mixed confidences, gaps; with ``kick_p``
    a point's velocity sometimes jumps by metres per second."""
    t = 0.0
    truth = rng.uniform(-1.0, 1.0, size=(n, 3))
    vel = rng.normal(0.0, 1.0, size=(n, 3))
    for k in range(steps):
        dt = 0.0 if rng.random() < same_time_p else rng.uniform(0.005, 0.050)
        t += dt
        vel += rng.normal(0.0, 3.0, size=(n, 3)) * dt
        vel += (rng.random((n, 1)) < kick_p) * rng.normal(0.0, 3.0, size=(n, 3))
        truth = truth + vel * dt
        z = truth + rng.normal(0.0, 0.01, size=(n, 3))
        kind = rng.integers(0, 4, size=n)
        conf = np.choose(kind, [np.full(n, 0.5), np.ones(n), rng.uniform(0.05, 1.0, n), np.zeros(n)])
        if k < 10:  # points appear at different times
            conf[rng.permutation(n)[: n // 2]] = 0.0
        z[conf == 0] = np.nan  # unmeasured points may carry garbage; it must not matter
        yield t, z, conf


def test_with_equal_modes_it_is_filterpys_constant_velocity_filter_per_point():
    s = KalmanSettings(quiet_noise=4.0, fast_noise=4.0, **UNGATED)
    rng = np.random.default_rng(1234)
    n = 25
    ours = JointKalman(n, s)
    ref = [FilterpyPoint(s, 4.0) for _ in range(n)]
    skipped = 0
    for t, z, conf in random_run(rng, n, 300):
        r = measurement_variance(np.where(conf > 0, conf, 1.0), 1.0, s)
        est = ours.step(t, z, conf)
        skipped += int((conf == 0).sum())
        for i in range(n):
            ref[i].step(t, z[i], r[i] if conf[i] > 0 else 0.0)
        for i in range(n):
            if ref[i].kf is None:
                assert not ours.initialised[i]
                assert np.isnan(est[i]).all()
                continue
            kf = ref[i].kf
            np.testing.assert_allclose(est[i], kf.x[0::2], rtol=0, atol=1e-9)
            np.testing.assert_allclose(ours.velocities[i], kf.x[1::2], rtol=0, atol=1e-9)
            for axis in range(3):  # the axes really are independent 2x2 filters
                block = kf.P[2 * axis: 2 * axis + 2, 2 * axis: 2 * axis + 2]
                a, b, c = ours.covariance[i, axis]
                np.testing.assert_allclose([[a, b], [b, c]], block, rtol=0, atol=1e-9)
            assert ours.last_time[i] == ref[i].last
    assert skipped > 1000  # the gaps were really exercised
    assert ours.initialised.all()


@pytest.mark.parametrize("same_time_p", [0.0, 0.5])
def test_matches_filterpys_imm_estimator_on_every_axis(same_time_p):
    """Two modes, mixed and weighted exactly as filterpy's IMMEstimator does it; with
    ``same_time_p`` half the measurements are further views of the same instant, folded in
    one after the other (the engine's sequential update of several sensors)."""
    s = SETTINGS
    rng = np.random.default_rng(99)
    n = 4
    ours = JointKalman(n, s)
    ref = [[FilterpyImmAxis(s) for _ in range(3)] for _ in range(n)]
    fast = []
    for t, z, conf in random_run(rng, n, 150, same_time_p, kick_p=0.05):
        r = measurement_variance(np.where(conf > 0, conf, 1.0), 1.0, s)
        ours.step(t, z, conf)
        x, P, mu = ours.state.x, ours.state.P, ours.state.mu
        for i in range(n):
            for axis in range(3):
                if conf[i] > 0:
                    ref[i][axis].step(t, z[i, axis], r[i])
                imm = ref[i][axis].imm
                if imm is None:
                    continue
                np.testing.assert_allclose(ours.positions[i, axis], imm.x[0], rtol=0, atol=1e-9)
                np.testing.assert_allclose(ours.velocities[i, axis], imm.x[1], rtol=0, atol=1e-8)
                np.testing.assert_allclose(mu[:, i, axis], imm.mu, rtol=0, atol=1e-9)
                for m, kf in enumerate(imm.filters):
                    np.testing.assert_allclose(x[:, m, i, axis], kf.x, rtol=0, atol=1e-8)
                    a, b, c = P[:, m, i, axis]
                    np.testing.assert_allclose([[a, b], [b, c]], kf.P, rtol=1e-9, atol=1e-12)
        fast.append(ours.mode_probabilities[ours.initialised])
    fast = np.concatenate(fast)
    assert fast.max() > 0.9 and fast.min() < 0.1  # both modes had their turn


def test_two_views_of_one_instant_in_turn_equal_filterpys_joint_update():
    """Sequential updates at the same time are the batch update with both measurements
    (the engine folds in each sensor's frame as it comes)."""
    s = KalmanSettings(quiet_noise=4.0, fast_noise=4.0, **UNGATED)
    rng = np.random.default_rng(5)
    ours = JointKalman(1, s)
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.H = np.array([[1.0, 0.0], [1.0, 0.0]])
    z0 = 0.3
    ours.step(0.0, np.full((1, 3), z0), np.ones(1), r=np.full(1, 1e-4))
    kf.x = np.array([z0, 0.0])
    kf.P = np.diag([1e-4, s.initial_velocity_var])
    t = 0.0
    for _ in range(40):
        t += 1 / 30
        za, zb = rng.normal(0.3 + t, 0.01, 2)
        ra, rb = rng.uniform(1e-4, 5e-4, 2)
        ours.step(t, np.full((1, 3), za), np.ones(1), r=np.full(1, ra))
        ours.step(t, np.full((1, 3), zb), np.ones(1), r=np.full(1, rb))
        kf.F = np.array([[1.0, 1 / 30], [0.0, 1.0]])
        kf.Q = Q_discrete_white_noise(dim=2, dt=1 / 30, var=4.0)
        kf.predict()
        kf.update(np.array([za, zb]), R=np.diag([ra, rb]))
        np.testing.assert_allclose(ours.positions[0], kf.x[0], rtol=0, atol=1e-10)
        np.testing.assert_allclose(ours.velocities[0], kf.x[1], rtol=0, atol=1e-8)


def test_pure_functions_against_the_matrix_algebra():
    rng = np.random.default_rng(3)
    n = 4
    x = rng.normal(size=(2, 2, n, 3))                       # [pos/vel, mode, point, axis]
    A = rng.normal(size=(2, n, 3, 2, 2))
    Pm = A @ A.swapaxes(-1, -2) + np.eye(2)                 # [mode, point, axis] 2x2
    P = np.stack([Pm[..., 0, 0], Pm[..., 0, 1], Pm[..., 1, 1]])
    mu = rng.uniform(0.1, 1.0, size=(2, n, 3))
    mu /= mu.sum(axis=0)
    dt = rng.uniform(0.0, 0.1, n)
    p01, p10 = transition(dt, SETTINGS)
    x0, P0, cbar = mix(x, P, mu, p01, p10)
    xp, Pp = predict(x0, P0, dt, np.array([2.0, 300.0]))
    z, r = rng.normal(size=(n, 3)), rng.uniform(1e-4, 1e-2, n)
    xu, Pu, muu = update(xp, Pp, cbar, z, r)
    for i in range(n):
        T = np.array([[1 - p01[i], p01[i]], [p10[i], 1 - p10[i]]])
        for a in range(3):
            cb = T.T @ mu[:, i, a]
            np.testing.assert_allclose(cbar[:, i, a], cb)
            F = np.array([[1.0, dt[i]], [0.0, 1.0]])
            lik = []
            for j, q in enumerate((2.0, 300.0)):
                w = T[:, j] * mu[:, i, a] / cb[j]
                xs = [x[:, k, i, a] for k in range(2)]
                xm = w[0] * xs[0] + w[1] * xs[1]
                Pmix = sum(w[k] * (Pm[k, i, a] + np.outer(xs[k] - xm, xs[k] - xm)) for k in range(2))
                np.testing.assert_allclose(x0[:, j, i, a], xm, atol=1e-12)
                Q = Q_discrete_white_noise(dim=2, dt=dt[i], var=q)
                xpr, Ppr = F @ xm, F @ Pmix @ F.T + Q
                np.testing.assert_allclose(xp[:, j, i, a], xpr, atol=1e-12)
                np.testing.assert_allclose(Pp[:, j, i, a], [Ppr[0, 0], Ppr[0, 1], Ppr[1, 1]],
                                           atol=1e-12)
                h = np.array([[1.0, 0.0]])
                S = Ppr[0, 0] + r[i]
                K = Ppr @ h.T / S
                y = z[i, a] - xpr[0]
                np.testing.assert_allclose(xu[:, j, i, a], xpr + (K * y)[:, 0], atol=1e-12)
                Ppost = (np.eye(2) - K @ h) @ Ppr
                np.testing.assert_allclose(Pu[:, j, i, a], [Ppost[0, 0], Ppost[0, 1], Ppost[1, 1]],
                                           atol=1e-12)
                lik.append(math.exp(-0.5 * y * y / S) / math.sqrt(2 * math.pi * S))
            post = cb * np.array(lik)
            np.testing.assert_allclose(muu[:, i, a], post / post.sum(), atol=1e-12)
    # dt = 0 predicts nothing
    xz, Pz = predict(x, P, np.zeros(n), np.array([2.0, 300.0]))
    np.testing.assert_array_equal(xz, x)
    np.testing.assert_array_equal(Pz, P)
    # the estimate: modes weighted by mu, spread included
    xm, Pc = combine(x, P, mu)
    for i in range(n):
        for a in range(3):
            xs = [x[:, k, i, a] for k in range(2)]
            mean = mu[0, i, a] * xs[0] + mu[1, i, a] * xs[1]
            cov = sum(mu[k, i, a] * (Pm[k, i, a] + np.outer(xs[k] - mean, xs[k] - mean))
                      for k in range(2))
            np.testing.assert_allclose(xm[:, i, a], mean, atol=1e-12)
            np.testing.assert_allclose(Pc[:, i, a], [cov[0, 0], cov[0, 1], cov[1, 1]], atol=1e-12)
    # the gate: squared Mahalanobis distance from the mixture's prediction, over three axes
    d2 = gate_distance(xp, Pp, cbar, z, r)
    for i in range(n):
        total = 0.0
        for a in range(3):
            mean = cbar[:, i, a] @ xp[0, :, i, a]
            var = cbar[:, i, a] @ (Pp[0, :, i, a] + (xp[0, :, i, a] - mean) ** 2)
            total += (z[i, a] - mean) ** 2 / (var + r[i])
        assert d2[i] == pytest.approx(total, rel=1e-12)


def settled(n: int = 3, s: KalmanSettings = KalmanSettings()) -> JointKalman:
    """A filter that has followed points at rest at the origin for a second at 30 Hz."""
    kf = JointKalman(n, s)
    rng = np.random.default_rng(0)
    for k in range(30):
        kf.step(k / 30, rng.normal(0.0, 0.01, (n, 3)), np.ones(n))
    return kf


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "jit"])
@pytest.mark.parametrize("scaled", [False, True])
def test_step_is_the_pure_functions_composed_bit_for_bit(scaled, compiled):
    """``step`` runs mix, predict, the gate and update fused into one pass over the stacked
    state (fewer numpy calls); it must give exactly the floats the pure functions give, so
    that the pure functions' filterpy tests cover it and replays do not drift. The compiled
    kernel (``jit``) does the same operations in the same order; only exp, log and expm1
    come from another library than numpy's, a last bit apart at most."""
    if compiled and not jit.ready():
        pytest.skip(f"compiled kernels unavailable: {jit.why_not()}")
    with (contextlib.nullcontext() if compiled else jit.disabled()):
        _step_against_pure_functions(scaled, compiled)


def _step_against_pure_functions(scaled: bool, compiled: bool) -> None:
    if compiled:
        def same(actual, desired):
            np.testing.assert_allclose(actual, desired, rtol=1e-11, atol=1e-300)
    else:
        same = np.testing.assert_array_equal
    s = KalmanSettings()
    rng = np.random.default_rng(7)
    n = 40
    q_scale = rng.uniform(0.5, 2.0, n) if scaled else None
    state = FilterState.empty(n)
    t = 0.0
    seen: set[int] = set()
    for k in range(60):
        t += (0.0, 1 / 30, 1 / 90, 0.25)[k % 4]
        z = rng.normal(0.0, 0.02 if k % 9 else 0.6, (n, 3))     # some beyond the gate
        r = rng.uniform(1e-5, 1e-3, n)
        r[rng.random(n) < 0.1] = np.nan                           # not measured
        times = t - rng.choice([0.0, 0.0, 0.0, 0.05], n)          # some older than the row
        before = state.copy()
        outcome = step(state, times, z, r, s, q_scale)
        if np.isnan(before.t).all():
            continue
        q = np.array([s.quiet_noise, s.fast_noise])
        q = q if q_scale is None else q[:, None] * q_scale[None]
        dt = np.where(np.isnan(before.t), 0.0, np.maximum(times - before.t, 0.0))
        x0, P0, cbar = mix(before.x, before.P, before.mu, *transition(dt, s))
        xp, Pp = predict(x0, P0, dt, q)
        d2 = gate_distance(xp, Pp, cbar, z, r)
        xu, Pu, muu = update(xp, Pp, cbar, z, r * np.maximum(d2 / s.gate_sigma ** 2, 1.0))
        kept = np.isin(outcome, (ACCEPTED, DOWNWEIGHTED))
        idle = outcome == 0
        seen |= set(np.unique(outcome).tolist())
        same(state.x[:, :, kept], xu[:, :, kept])
        same(state.P[:, :, kept], Pu[:, :, kept])
        same(state.mu[:, kept], muu[:, kept])
        np.testing.assert_array_equal(state.x[:, :, idle], before.x[:, :, idle])
        np.testing.assert_array_equal(state.P[:, :, idle], before.P[:, :, idle])
    assert {0, ACCEPTED, DOWNWEIGHTED, REJECTED} <= seen      # every path was taken


def test_a_measurement_beyond_the_gate_counts_less_than_at_face_value():
    gated, ungated = KalmanSettings(), KalmanSettings(**UNGATED)
    for jump, outcome in ((0.02, ACCEPTED), (0.05, ACCEPTED), (0.1, DOWNWEIGHTED),
                          (0.2, DOWNWEIGHTED)):
        moved = []
        for s in (gated, ungated):
            kf = settled(1, s)
            before = kf.positions[0, 0]
            kf.step(1.0, np.array([[jump, 0.0, 0.0]]), np.ones(1))
            moved.append(kf.positions[0, 0] - before)
        assert kf.last_outcome[0] == ACCEPTED
        kf = settled(1, gated)
        kf.step(1.0, np.array([[jump, 0.0, 0.0]]), np.ones(1))
        assert kf.last_outcome[0] == outcome
        if outcome == ACCEPTED:
            assert moved[0] == moved[1]
        else:
            assert 0.0 < moved[0] < moved[1], (jump, moved)


def test_a_gross_error_is_rejected_and_twice_in_a_row_restarts_the_point():
    s = KalmanSettings()
    kf = settled(2, s)
    before = kf.state.copy()
    far = np.array([[1.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    kf.step(1.0, far, np.ones(2))
    assert list(kf.last_outcome) == [REJECTED, ACCEPTED]
    np.testing.assert_array_equal(kf.state.x[:, :, 0], before.x[:, :, 0])  # untouched
    assert kf.state.t[0] == before.t[0]
    kf.step(1.0 + 1 / 30, far + [[0.05, 0, 0], [0, 0, 0]], np.ones(2))
    assert list(kf.last_outcome) == [RESTARTED, ACCEPTED]
    np.testing.assert_allclose(kf.positions[0], [1.55, 0.0, 0.0])
    np.testing.assert_allclose(kf.velocities[0], [1.5, 0.0, 0.0])   # from the two rejected
    np.testing.assert_allclose(kf.mode_probabilities[0], 1.0)       # in the fast mode
    # an accepted measurement in between clears the held one: an isolated outlier
    kf = settled(1, s)
    kf.step(1.0, np.array([[1.5, 0.0, 0.0]]), np.ones(1))
    kf.step(1.0 + 1 / 30, np.zeros((1, 3)), np.ones(1))
    kf.step(1.0 + 2 / 30, np.array([[1.5, 0.0, 0.0]]), np.ones(1))
    assert kf.last_outcome[0] == REJECTED


def test_unmeasured_points_keep_their_state_exactly():
    kf = settled()
    before = kf.state.copy()
    out = kf.step(2.0, np.full((3, 3), 5.0), np.zeros(3))
    kf.step(3.0, np.full((3, 3), 5.0), np.full(3, -1.0))
    for name in ("x", "P", "mu", "t"):
        np.testing.assert_array_equal(getattr(kf.state, name), getattr(before, name))
    np.testing.assert_array_equal(out, before.estimate()[0])


def test_time_going_backwards_does_not_extrapolate():
    kf = settled()
    last = kf.last_time
    state = kf.state.copy()
    z = np.full((3, 3), 0.01)
    kf.step(0.5, z, np.ones(3))  # half a second before the last update
    # the same as an update with dt = 0: no prediction, no mode switching
    s = kf.settings
    r = measurement_variance(np.ones(3), 1.0, s)
    x0, P0, cbar = mix(state.x, state.P, state.mu, *transition(np.zeros(3), s))
    np.testing.assert_array_equal(x0, state.x)
    xu, Pu, muu = update(x0, P0, cbar, z, r)
    np.testing.assert_allclose(kf.state.x, xu, atol=1e-15)
    np.testing.assert_array_equal(kf.last_time, last)  # the clock does not go back either
    np.testing.assert_array_equal(kf.predict_positions(0.0), kf.positions)


def test_nan_measurement_is_ignored_for_that_point_only():
    kf = settled()
    before = kf.positions
    z = np.full((3, 3), 0.01)
    z[1, 2] = np.nan
    z[2, 0] = np.inf
    out = kf.step(1.0, z, np.ones(3))
    assert np.isfinite(out).all() and np.isfinite(kf.state.P).all()
    np.testing.assert_array_equal(out[1:], before[1:])
    assert list(kf.last_time) == [1.0, 29 / 30, 29 / 30]


def test_predict_positions_and_reset():
    kf = settled()
    p, v = kf.positions, kf.velocities
    np.testing.assert_allclose(kf.predict_positions(29 / 30 + 0.1), p + 0.1 * v, atol=1e-15)
    np.testing.assert_array_equal(kf.positions, p)  # no side effect
    kf.reset(np.array([True, False, False]))
    np.testing.assert_array_equal(kf.initialised, [False, True, True])
    assert np.isnan(kf.positions[0]).all() and np.isnan(kf.last_time[0])
    out = kf.step(2.0, np.full((3, 3), 2.0), np.array([1.0, 0.0, 0.0]))
    assert kf.last_outcome[0] == STARTED
    np.testing.assert_array_equal(out[0], [2.0, 2.0, 2.0])  # started afresh, not smoothed
    np.testing.assert_array_equal(kf.velocities[0], [0.0, 0.0, 0.0])
    kf.reset()
    assert not kf.initialised.any() and np.isnan(kf.state.P).all()


def test_state_rows_concatenate_and_split_back():
    a, b = settled(2).state, settled(3).state
    both = FilterState.concat([a, b])
    assert both.n == 5
    back = both.rows(2, 5)
    for name in ("x", "P", "mu", "t"):
        np.testing.assert_array_equal(getattr(back, name), getattr(b, name))
    t = np.full(5, 2.0)
    step(both, t, np.zeros((5, 3)), np.full(5, 1e-4), KalmanSettings())
    alone = b.copy()
    step(alone, t[:3], np.zeros((3, 3)), np.full(3, 1e-4), KalmanSettings())
    np.testing.assert_array_equal(both.rows(2, 5).x, alone.x)  # rows never mix


def test_measurement_variance_grows_with_distance_and_falls_with_confidence():
    # inferred_sd_m 0: the confidence rule alone (variance / c), as before issue 11 stop 22
    s = KalmanSettings(measurement_noise=1e-4, noise_per_m=0.004, inferred_sd_m=0.0)
    r = measurement_variance(np.array([1.0, 1.0, 0.5]), np.array([0.8, 3.5, 3.5]), s)
    np.testing.assert_allclose(r, [1e-4, 0.02 ** 2, 2 * 0.02 ** 2])
    # the default adds (1/c - 1) * (10 cm)^2: an inferred joint is a guess (that change was
    # asked for: guesses 10-30 cm off pulled the fused body; tests/test_fusion_inferred.py)
    r = measurement_variance(np.array([1.0, 0.5]), 3.5, KalmanSettings())
    np.testing.assert_allclose(r, [0.02 ** 2, 2 * 0.02 ** 2 + 0.1 ** 2])


@pytest.mark.parametrize("field", ["quiet_noise", "fast_noise", "measurement_noise",
                                   "initial_velocity_var", "gate_sigma"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf, "1", True])
def test_settings_validation(field, value):
    with pytest.raises(ConfigError, match=field):
        KalmanSettings(**{field: value})


def test_reject_must_not_be_inside_the_gate():
    with pytest.raises(ConfigError, match="reject_sigma"):
        KalmanSettings(gate_sigma=4.0, reject_sigma=3.0)


def test_bad_shapes_raise():
    kf = JointKalman(3)
    with pytest.raises(ValueError, match="expected z"):
        kf.step(0.0, np.zeros((4, 3)), np.ones(3))


def test_smooths_without_lag_at_constant_velocity():
    rng = np.random.default_rng(42)
    fps, speed = 30.0, 1.0
    direction = np.array([1.0, 0.2, -0.4]) / np.linalg.norm([1.0, 0.2, -0.4])
    t = np.arange(600) / fps + rng.uniform(-0.003, 0.003, 600)
    truth = np.array([0.0, 1.0, 2.5]) + speed * t[:, None] * direction
    z = truth + rng.normal(0.0, 0.01, truth.shape)
    kf = JointKalman(1)
    est = np.array([kf.step(tk, zk[None], np.ones(1))[0] for tk, zk in zip(t, z)])
    keep = t > 2.0
    rms_raw = np.sqrt(np.mean(np.sum((z - truth)[keep] ** 2, axis=1)))
    rms_filt = np.sqrt(np.mean(np.sum((est - truth)[keep] ** 2, axis=1)))
    lag_frames = -np.mean((est - truth)[keep] @ direction) / (speed / fps)
    assert rms_filt < 0.8 * rms_raw, (rms_filt, rms_raw)
    assert abs(lag_frames) < 1.0, lag_frames


def test_only_joints_at_or_below_the_inferred_level_get_a_guess_s_variance():
    s = KalmanSettings()
    base = s.measurement_noise
    r = measurement_variance(np.array([1.0, 0.9, 0.6, 0.5, 0.25]), 1.0, s)
    # tracked, and above the inferred level (a landmark's visibility 0.9): noise / c only
    np.testing.assert_allclose(r[:3], [base, base / 0.9, base / 0.6])
    # Kinect's inferred level and below: a guess, (1/c - 1) inferred_sd_m^2 on top
    np.testing.assert_allclose(r[3:], [base / 0.5 + 1.0 * s.inferred_sd_m ** 2,
                                       base / 0.25 + 3.0 * s.inferred_sd_m ** 2])
    # a continuous 0.9 weighs about as much as a tracked joint, not ten times less
    assert r[1] < 1.2 * r[0]
