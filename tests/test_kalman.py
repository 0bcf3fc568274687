"""stage.kalman: the batched filter against filterpy, its pure functions, edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from stage.errors import ConfigError
from stage.engine.kalman import JointKalman, initial_state, predict, update
from stage.settings import KalmanSettings

SETTINGS = KalmanSettings()
H = np.zeros((3, 6))
H[[0, 1, 2], [0, 2, 4]] = 1.0  # state ordered [x, vx, y, vy, z, vz]


class FilterpyPoint:
    """One point tracked by filterpy the long way: a 6-state KalmanFilter with its own clock."""

    def __init__(self, settings: KalmanSettings) -> None:
        self.s = settings
        self.kf: KalmanFilter | None = None
        self.last = math.nan

    def step(self, t: float, z: np.ndarray, conf: float) -> None:
        if not (conf > 0 and np.isfinite(z).all()):
            return
        r = self.s.measurement_noise / conf
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
        self.kf.Q = Q_discrete_white_noise(dim=2, dt=dt, var=self.s.process_noise,
                                           block_size=3, order_by_dim=True)
        self.kf.predict()
        self.kf.update(z, R=r * np.eye(3))
        self.last = max(self.last, t)


def random_run(rng: np.random.Generator, n: int, steps: int):
    """Yield (t, z, conf): wandering points, random dt 20-50 ms, mixed confidences, gaps."""
    t = 0.0
    truth = rng.uniform(-1.0, 1.0, size=(n, 3))
    vel = rng.normal(0.0, 1.0, size=(n, 3))
    for k in range(steps):
        dt = rng.uniform(0.020, 0.050)
        t += dt
        vel += rng.normal(0.0, 3.0, size=(n, 3)) * dt
        truth = truth + vel * dt
        z = truth + rng.normal(0.0, 0.01, size=(n, 3))
        kind = rng.integers(0, 4, size=n)
        conf = np.choose(kind, [np.full(n, 0.5), np.ones(n), rng.uniform(0.05, 1.0, n), np.zeros(n)])
        if k < 10:  # points appear at different times
            conf[rng.permutation(n)[: n // 2]] = 0.0
        z[conf == 0] = np.nan  # unmeasured points may carry garbage; it must not matter
        yield t, z, conf


def test_matches_filterpy_per_point():
    rng = np.random.default_rng(1234)
    n = 25
    ours = JointKalman(n, SETTINGS)
    ref = [FilterpyPoint(SETTINGS) for _ in range(n)]
    skipped = 0
    for t, z, conf in random_run(rng, n, 300):
        est = ours.step(t, z, conf)
        skipped += int((conf == 0).sum())
        for i in range(n):
            ref[i].step(t, z[i], conf[i])
        for i in range(n):
            if ref[i].kf is None:
                assert not ours.initialised[i]
                assert np.isnan(est[i]).all()
                continue
            kf = ref[i].kf
            np.testing.assert_allclose(est[i], kf.x[0::2], rtol=0, atol=1e-9)
            np.testing.assert_allclose(ours.velocities[i], kf.x[1::2], rtol=0, atol=1e-9)
            for axis in range(3):  # the axes really do share one 2x2 covariance
                block = kf.P[2 * axis: 2 * axis + 2, 2 * axis: 2 * axis + 2]
                np.testing.assert_allclose(ours.covariance[i], block, rtol=0, atol=1e-9)
            off_axis = kf.P.copy()
            for axis in range(3):
                off_axis[2 * axis: 2 * axis + 2, 2 * axis: 2 * axis + 2] = 0.0
            assert np.abs(off_axis).max() == 0.0
            assert ours.last_time[i] == ref[i].last
    assert skipped > 1000  # the gaps were really exercised
    assert ours.initialised.all()


def test_pure_functions_agree_with_class():
    rng = np.random.default_rng(7)
    n, s = 25, SETTINGS
    ours = JointKalman(n, s)
    x = np.full((n, 2, 3), np.nan)
    P = np.full((n, 2, 2), np.nan)
    last = np.full(n, np.nan)
    for t, z, conf in random_run(rng, n, 200):
        ours.step(t, z, conf)
        valid = conf > 0
        r = s.measurement_noise / np.where(valid, conf, 1.0)
        init = ~np.isnan(last)
        upd = valid & init
        dt = np.where(upd, np.maximum(t - np.where(init, last, t), 0.0), 0.0)
        x, P = predict(x, P, dt, s.process_noise)
        x, P = update(x, P, z, r, upd)
        fresh = valid & ~init
        x[fresh], P[fresh] = initial_state(z[fresh], r[fresh], s.initial_velocity_var)
        last[valid] = t
        np.testing.assert_array_equal(ours.positions, x[:, 0])
        np.testing.assert_array_equal(ours.velocities, x[:, 1])
        np.testing.assert_array_equal(ours.covariance, P)


def test_pure_predict_and_update_closed_form():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 2, 3))
    A = rng.normal(size=(4, 2, 2))
    P = A @ A.transpose(0, 2, 1) + np.eye(2)
    dt, q = rng.uniform(0.0, 0.1, 4), 2.5
    xp, Pp = predict(x, P, dt, q)
    z, r = rng.normal(size=(4, 3)), rng.uniform(1e-4, 1e-2, 4)
    xu, Pu = update(xp, Pp, z, r)
    for i in range(4):
        F = np.array([[1.0, dt[i]], [0.0, 1.0]])
        Q = Q_discrete_white_noise(dim=2, dt=dt[i], var=q)
        np.testing.assert_allclose(xp[i], F @ x[i], atol=1e-12)
        np.testing.assert_allclose(Pp[i], F @ P[i] @ F.T + Q, atol=1e-12)
        h = np.array([[1.0, 0.0]])
        K = Pp[i] @ h.T / (Pp[i, 0, 0] + r[i])
        np.testing.assert_allclose(xu[i], xp[i] + K @ (z[i] - xp[i, 0])[None, :], atol=1e-12)
        np.testing.assert_allclose(Pu[i], (np.eye(2) - K @ h) @ Pp[i], atol=1e-12)
    # dt = 0 and a masked-out update are exact no-ops, even with NaN measurements
    x0, P0 = predict(x, P, np.zeros(4), q)
    np.testing.assert_array_equal(x0, x)
    np.testing.assert_array_equal(P0, P)
    mask = np.array([True, False, True, False])
    z[~mask] = np.nan
    xm, Pm = update(x, P, z, np.where(mask, r, 0.0), mask)
    np.testing.assert_array_equal(xm[~mask], x[~mask])
    np.testing.assert_array_equal(Pm[~mask], P[~mask])
    assert np.isfinite(xm).all() and not np.allclose(xm[mask], x[mask])


def started(n: int = 3) -> JointKalman:
    kf = JointKalman(n)
    kf.step(0.0, np.zeros((n, 3)), np.ones(n))
    kf.step(0.033, np.full((n, 3), 0.03), np.ones(n))
    return kf


def test_conf_zero_everywhere_leaves_state_untouched():
    kf = started()
    before = (kf.positions, kf.velocities, kf.covariance, kf.last_time)
    out = kf.step(1.0, np.full((3, 3), 5.0), np.zeros(3))
    out = kf.step(2.0, np.full((3, 3), 5.0), np.full(3, -1.0))
    after = (kf.positions, kf.velocities, kf.covariance, kf.last_time)
    for b, a in zip(before, after):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(out, before[0])


def test_time_going_backwards_does_not_extrapolate():
    kf = started()
    x, v, P, last = kf.positions, kf.velocities, kf.covariance, kf.last_time
    z = np.full((3, 3), 0.05)
    kf.step(0.010, z, np.ones(3))  # 23 ms before the last update
    # same as an update with no prediction at all
    state = np.stack([x, v], axis=1)
    xu, Pu = update(state, P, z, np.full(3, SETTINGS.measurement_noise))
    np.testing.assert_allclose(kf.positions, xu[:, 0], atol=1e-15)
    np.testing.assert_allclose(kf.covariance, Pu, atol=1e-15)
    np.testing.assert_array_equal(kf.last_time, last)  # the clock does not go back either
    np.testing.assert_array_equal(kf.predict_positions(0.0), kf.positions)


def test_nan_measurement_is_ignored_for_that_point_only():
    kf = started()
    before = kf.positions
    z = np.full((3, 3), 0.06)
    z[1, 2] = np.nan
    z[2, 0] = np.inf
    out = kf.step(0.066, z, np.ones(3))
    assert np.isfinite(out).all() and np.isfinite(kf.covariance).all()
    np.testing.assert_array_equal(out[1:], before[1:])
    np.testing.assert_array_equal(kf.last_time, [0.066, 0.033, 0.033])
    assert out[0, 0] > before[0, 0]


def test_predict_positions_and_reset():
    kf = started()
    p, v = kf.positions, kf.velocities
    np.testing.assert_allclose(kf.predict_positions(0.133), p + 0.1 * v, atol=1e-15)
    np.testing.assert_array_equal(kf.positions, p)  # no side effect
    kf.reset(np.array([True, False, False]))
    np.testing.assert_array_equal(kf.initialised, [False, True, True])
    assert np.isnan(kf.positions[0]).all() and np.isnan(kf.last_time[0])
    out = kf.step(0.066, np.full((3, 3), 2.0), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_array_equal(out[0], [2.0, 2.0, 2.0])  # re-initialised, not smoothed
    np.testing.assert_array_equal(kf.velocities[0], [0.0, 0.0, 0.0])
    kf.reset()
    assert not kf.initialised.any() and np.isnan(kf.covariance).all()


@pytest.mark.parametrize("field", ["process_noise", "measurement_noise", "initial_velocity_var"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf, "1", True])
def test_settings_validation(field, value):
    with pytest.raises(ConfigError, match=field):
        KalmanSettings(**{field: value})


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
