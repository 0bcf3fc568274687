"""Batched constant-velocity Kalman smoothing of 3-D points (a person's 25 joints).

Every point is an independent filter. Per axis the state is [position, velocity]
with a white-noise-acceleration model::

    F = [[1, dt], [0, 1]]     Q = q * [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]
    H = [1, 0]                R = measurement_noise / confidence

which is filterpy's ``Q_discrete_white_noise(dim=2, dt=dt, var=q)``. Model and R
are the same for x, y and z, so the three axes of a point always share one 2x2
covariance: we store ``x`` as (N, 2, 3) [point, pos/vel, axis] and ``P`` as
(N, 2, 2), and write the 2x2 algebra in closed form over all points at once
(no Python loop, no ``np.linalg``), which is what keeps a step in microseconds.

Points not yet measured (or forgotten by ``reset``) hold NaN state.
"""

from __future__ import annotations

import numpy as np

from ..settings import KalmanSettings

__all__ = ["KalmanSettings", "JointKalman", "initial_state", "predict", "update"]


def initial_state(z: np.ndarray, r: np.ndarray, velocity_var: float) -> tuple[np.ndarray, np.ndarray]:
    """State of newly seen points: at ``z`` at rest, with covariance diag(r, velocity_var).

    z: (N, 3) metres; r: (N,) m^2 measurement variance; returns x (N, 2, 3), P (N, 2, 2).
    """
    n = z.shape[0]
    x = np.zeros((n, 2, 3))
    x[:, 0] = z
    P = np.zeros((n, 2, 2))
    P[:, 0, 0] = r
    P[:, 1, 1] = velocity_var
    return x, P


def predict(x: np.ndarray, P: np.ndarray, dt: np.ndarray | float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Propagate states by ``dt`` seconds: ``x' = F x``, ``P' = F P F^T + Q``.

    x: (N, 2, 3); P: (N, 2, 2); dt: (N,) or scalar, seconds >= 0 (0 leaves a point
    exactly unchanged); q: acceleration variance, (m/s^2)^2. Returns new arrays.
    """
    dt = np.asarray(dt, dtype=float)
    a, b, c = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    x_new = x.copy()
    x_new[:, 0] += dt[..., None] * x[:, 1]
    dt2 = dt * dt
    qdt2 = q * dt2
    P_new = np.empty_like(P)
    P_new[:, 0, 0] = a + dt * (2.0 * b + dt * c) + 0.25 * qdt2 * dt2
    P_new[:, 0, 1] = P_new[:, 1, 0] = b + dt * c + 0.5 * qdt2 * dt
    P_new[:, 1, 1] = c + qdt2
    return x_new, P_new


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, r: np.ndarray | float,
           mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Correct states with position measurements ``z`` of per-axis variance ``r``.

    x: (N, 2, 3); P: (N, 2, 2); z: (N, 3) metres; r: (N,) or scalar, m^2, > 0;
    mask: (N,) bool, points to correct; the others come back exactly unchanged
    and their z and r are ignored (may be NaN). Returns new arrays.
    """
    a, b, c = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    y = z - x[:, 0]
    if mask is not None:
        r = np.where(mask, r, 1.0)
    s = a + r
    k0 = a / s
    k1 = b / s
    # 1 - k0 computed as r/s: no cancellation when the prior is much wider than r.
    g = r / s
    if mask is not None:
        # Zero gain (and zero innovation, which may be NaN) makes skipped points exact no-ops.
        k0 = np.where(mask, k0, 0.0)
        k1 = np.where(mask, k1, 0.0)
        g = np.where(mask, g, 1.0)
        y = np.where(mask[:, None], y, 0.0)
    x_new = np.empty_like(x)
    x_new[:, 0] = x[:, 0] + k0[:, None] * y
    x_new[:, 1] = x[:, 1] + k1[:, None] * y
    # (I - K H) P, equal to filterpy's Joseph form for the optimal gain.
    P_new = np.empty_like(P)
    P_new[:, 0, 0] = a * g
    P_new[:, 0, 1] = P_new[:, 1, 0] = b * g
    P_new[:, 1, 1] = c - k1 * b
    return x_new, P_new


class JointKalman:
    """Constant-velocity filters for ``n`` points, each with its own last-update time.

    Owned by one thread (the engine's); not thread-safe.
    """

    def __init__(self, n: int, settings: KalmanSettings = KalmanSettings()) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n must be a non-negative int, got {n!r}")
        self._n = int(n)
        self._settings = settings
        self._x = np.full((self._n, 2, 3), np.nan)
        self._P = np.full((self._n, 2, 2), np.nan)
        self._last = np.full(self._n, np.nan)
        self._init = np.zeros(self._n, dtype=bool)

    @property
    def n(self) -> int:
        return self._n

    @property
    def settings(self) -> KalmanSettings:
        return self._settings

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) metres, NaN for points never measured."""
        return self._x[:, 0].copy()

    @property
    def velocities(self) -> np.ndarray:
        """(n, 3) m/s, NaN for points never measured."""
        return self._x[:, 1].copy()

    @property
    def covariance(self) -> np.ndarray:
        """(n, 2, 2) covariance of [position, velocity], shared by the three axes."""
        return self._P.copy()

    @property
    def initialised(self) -> np.ndarray:
        """(n,) bool, points that have a state."""
        return self._init.copy()

    @property
    def last_time(self) -> np.ndarray:
        """(n,) seconds, time each point's state refers to; NaN if never measured."""
        return self._last.copy()

    def step(self, t: float, z: np.ndarray, conf: np.ndarray) -> np.ndarray:
        """Fold in one measurement set taken at ``t`` and return the filtered positions.

        z: (n, 3) metres; conf: (n,) confidence, > 0 to use a point (variance
        ``measurement_noise / conf``). Points with conf <= 0 or a non-finite z or
        conf keep their state and time. A ``t`` before a point's last time is
        treated as that time: the filter never extrapolates backwards.
        Returns (n, 3) metres, a copy.
        """
        z = np.asarray(z, dtype=float)
        conf = np.asarray(conf, dtype=float)
        if z.shape != (self._n, 3) or conf.shape != (self._n,):
            raise ValueError(f"expected z ({self._n}, 3) and conf ({self._n},), "
                             f"got {z.shape} and {conf.shape}")
        t = float(t)
        # One bad coordinate makes the whole point unusable: Kinect reports NaN/inf
        # for lost joints, and a NaN must never get into the state.
        valid = (conf > 0.0) & (conf < np.inf) & np.isfinite(z).all(axis=1)
        fresh = valid & ~self._init
        upd = valid & self._init
        r = self._settings.measurement_noise / np.where(valid, conf, 1.0)
        if upd.any():
            mask = None if upd.all() else upd
            dt = np.maximum(t - self._last, 0.0)
            if mask is not None:
                dt = np.where(mask, dt, 0.0)
            x, P = predict(self._x, self._P, dt, self._settings.process_noise)
            self._x, self._P = update(x, P, z, r, mask)
        if fresh.any():
            self._x[fresh], self._P[fresh] = initial_state(
                z[fresh], r[fresh], self._settings.initial_velocity_var)
            self._init |= fresh
        self._last = np.where(valid, np.fmax(self._last, t), self._last)
        return self._x[:, 0].copy()

    def predict_positions(self, t: float) -> np.ndarray:
        """(n, 3) metres: where each point would be at ``t`` (never before its last time).

        Leaves the state unchanged; NaN for points never measured.
        """
        dt = np.maximum(float(t) - self._last, 0.0)
        return self._x[:, 0] + dt[:, None] * self._x[:, 1]

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Forget the points in ``mask`` ((n,) bool), or all points when None."""
        if mask is None:
            mask = np.ones(self._n, dtype=bool)
        else:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != (self._n,):
                raise ValueError(f"expected mask ({self._n},), got {mask.shape}")
        self._x[mask] = np.nan
        self._P[mask] = np.nan
        self._last[mask] = np.nan
        self._init[mask] = False
