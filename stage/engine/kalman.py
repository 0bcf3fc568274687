"""Batched smoothing of 3-D points: a two-mode interacting multiple model (IMM) Kalman filter.

Every point (a joint) and every axis of it is an independent filter whose
state is [position, velocity]. Two constant-velocity motion models run side
by side -- *quiet* (small white-noise acceleration: standing, swaying) and
*fast* (large: kicks, hops, arm swings) -- and the filter mixes them by
how well each has predicted the recent measurements (Blom and Bar-Shalom's
IMM, as in filterpy's ``IMMEstimator``). Per mode and axis::

    F = [[1, dt], [0, 1]]     Q = q_mode * [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]
    H = [1, 0]                R = r (per measurement: confidence and distance)

which is filterpy's ``Q_discrete_white_noise(dim=2, dt=dt, var=q_mode)``. The
chance of switching mode within ``dt`` is ``1 - exp(-rate * dt)``, so the
filter behaves the same whatever the rate of measurements (one sensor at
30 Hz or six interleaved).

Arrays, for N points (rows) and M = 2 modes (0 quiet, 1 fast)::

    x   (M, N, 3, 2)  position, velocity per mode and axis; metres, m/s
    P   (M, N, 3, 3)  covariance per mode and axis, packed [pp, pv, vv]
    mu  (M, N, 3)     mode probabilities per axis
    t   (N,)          time the row's state refers to, s; NaN = never measured

The 2x2 algebra is written in closed form over all rows at once (no Python
loop, no ``np.linalg``). The pure functions (``transition``, ``mix``,
``predict``, ``update``, ``gate_distance``, ``combine``) are tested against
filterpy; ``step`` strings them together the way the engine and the
benchmarks use them, with the outlier gate:

- the innovation of each point against the mixture's prediction is measured
  as a squared Mahalanobis distance d^2 (chi-square with 3 degrees of
  freedom for a good measurement);
- beyond ``gate_sigma`` (d > gate_sigma) the measurement's variance is
  multiplied by d^2 / gate_sigma^2: a distant measurement pulls the estimate
  less the further out it is (a soft gate; a hard one would also throw away
  the first frame of every real kick);
- beyond ``reject_sigma`` it is not used at all; a point whose measurement is
  rejected twice in a row with none accepted in between is started afresh
  from those two measurements (the filter, not the sensor, was wrong).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..settings import KalmanSettings

__all__ = ["KalmanSettings", "FilterState", "JointKalman", "transition", "mix", "predict",
           "update", "gate_distance", "combine", "step", "initial_mu", "measurement_variance"]

M = 2  # modes: 0 quiet, 1 fast


def initial_mu(s: KalmanSettings) -> np.ndarray:
    """(M,) mode probabilities of a new point: the chain's stationary distribution."""
    fast = s.quiet_to_fast_per_s / (s.quiet_to_fast_per_s + s.fast_to_quiet_per_s)
    return np.array([1.0 - fast, fast])


def measurement_variance(conf: np.ndarray, distance: np.ndarray | float,
                         s: KalmanSettings) -> np.ndarray:
    """Per-axis variance (m^2) of joints seen with ``conf`` (>0) at ``distance`` m from the sensor.

    The s.d. of a confidence-1 joint is ``sqrt(measurement_noise)`` up to 1 m
    and grows by ``noise_per_m`` per metre beyond; a joint of confidence c
    has c times the inverse variance (an inferred joint, c = 0.5, counts half).
    """
    sd = math.sqrt(s.measurement_noise) + s.noise_per_m * np.maximum(
        np.asarray(distance, dtype=float) - 1.0, 0.0)
    return sd * sd / np.asarray(conf, dtype=float)


def transition(dt: np.ndarray, s: KalmanSettings) -> np.ndarray:
    """T (M, M, N): T[i, j] = P(mode j after ``dt`` | mode i now), dt (N,) seconds >= 0."""
    p01 = -np.expm1(-s.quiet_to_fast_per_s * dt)
    p10 = -np.expm1(-s.fast_to_quiet_per_s * dt)
    return np.stack([np.stack([1.0 - p01, p01]), np.stack([p10, 1.0 - p10])])


def mix(x: np.ndarray, P: np.ndarray, mu: np.ndarray, T: np.ndarray,
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMM mixing: (x0, P0, cbar), the mixed initial condition of each mode and the
    predicted mode probabilities ``cbar[j] = sum_i T[i, j] mu[i]`` (M, N, 3)."""
    Tn = T[:, :, :, None]                                    # (M, M, N, 1)
    cbar = np.einsum("ijn,ina->jna", T, mu)
    w = Tn * mu[:, None] / cbar[None]                        # w[i, j] = P(was i | now j)
    x0 = np.einsum("ijna,inak->jnak", w, x)
    d = x[:, None] - x0[None]                                # (i, j, N, 3, 2)
    P0 = np.empty_like(P)
    P0[..., 0] = np.einsum("ijna,ijna->jna", w, P[:, None, ..., 0] + d[..., 0] * d[..., 0])
    P0[..., 1] = np.einsum("ijna,ijna->jna", w, P[:, None, ..., 1] + d[..., 0] * d[..., 1])
    P0[..., 2] = np.einsum("ijna,ijna->jna", w, P[:, None, ..., 2] + d[..., 1] * d[..., 1])
    return x0, P0, cbar


def predict(x: np.ndarray, P: np.ndarray, dt: np.ndarray, q: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray]:
    """Propagate by ``dt`` (N,) seconds with acceleration variance ``q`` per mode, (M,) or
    (M, N), (m/s^2)^2: ``x' = F x``, ``P' = F P F^T + Q``. dt = 0 is an exact no-op."""
    q = np.asarray(q, dtype=float)
    q = q[:, None, None] if q.ndim == 1 else q[:, :, None]
    dt = np.asarray(dt, dtype=float)[None, :, None]
    a, b, c = P[..., 0], P[..., 1], P[..., 2]
    x_new = x.copy()
    x_new[..., 0] += dt * x[..., 1]
    dt2 = dt * dt
    qdt2 = q * dt2
    P_new = np.empty_like(P)
    P_new[..., 0] = a + dt * (2.0 * b + dt * c) + 0.25 * qdt2 * dt2
    P_new[..., 1] = b + dt * c + 0.5 * qdt2 * dt
    P_new[..., 2] = c + qdt2
    return x_new, P_new


def update(x: np.ndarray, P: np.ndarray, cbar: np.ndarray, z: np.ndarray, r: np.ndarray,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correct every mode with position measurements ``z`` (N, 3) of variance ``r`` (N,) m^2,
    and the mode probabilities by each mode's likelihood. Returns (x, P, mu)."""
    a, b, c = P[..., 0], P[..., 1], P[..., 2]
    r3 = np.asarray(r, dtype=float)[None, :, None]
    y = z[None] - x[..., 0]                                  # (M, N, 3)
    s = a + r3
    k0 = a / s
    k1 = b / s
    g = r3 / s                                               # 1 - k0 without cancellation
    x_new = np.empty_like(x)
    x_new[..., 0] = x[..., 0] + k0 * y
    x_new[..., 1] = x[..., 1] + k1 * y
    P_new = np.empty_like(P)
    P_new[..., 0] = a * g                                    # (I - K H) P, filterpy's Joseph
    P_new[..., 1] = b * g                                    # form for the optimal gain
    P_new[..., 2] = c - k1 * b
    log_l = -0.5 * (np.log(2.0 * np.pi * s) + y * y / s)
    log_l -= log_l.max(axis=0)                               # no underflow for big innovations
    mu = cbar * np.exp(log_l)
    mu /= mu.sum(axis=0)
    return x_new, P_new, mu


def combine(x: np.ndarray, P: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The IMM estimate: (N, 3, 2) mean [position, velocity] and (N, 3, 3) packed covariance."""
    xm = np.einsum("mna,mnak->nak", mu, x)
    d = x - xm[None]
    Pm = np.empty(P.shape[1:])
    Pm[..., 0] = np.einsum("mna,mna->na", mu, P[..., 0] + d[..., 0] * d[..., 0])
    Pm[..., 1] = np.einsum("mna,mna->na", mu, P[..., 1] + d[..., 0] * d[..., 1])
    Pm[..., 2] = np.einsum("mna,mna->na", mu, P[..., 2] + d[..., 1] * d[..., 1])
    return xm, Pm


def gate_distance(xp: np.ndarray, Pp: np.ndarray, cbar: np.ndarray, z: np.ndarray,
                  r: np.ndarray) -> np.ndarray:
    """(N,) squared Mahalanobis distance of ``z`` from the mixture's predicted position
    (the modes' predictions weighted by ``cbar``, their spread included), over 3 axes."""
    mean = np.einsum("mna,mna->na", cbar, xp[..., 0])
    var = np.einsum("mna,mna->na", cbar, Pp[..., 0] + (xp[..., 0] - mean[None]) ** 2)
    y = z - mean
    return (y * y / (var + np.asarray(r, dtype=float)[:, None])).sum(axis=1)


@dataclass
class FilterState:
    """The state of N points (see the module docstring for shapes), plus the gate's memory:
    ``held_z`` (N, 3) / ``held_t`` (N,) the last rejected measurement since the last
    accepted one (NaN: none)."""

    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    t: np.ndarray
    held_z: np.ndarray
    held_t: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "FilterState":
        return cls(np.full((M, n, 3, 2), np.nan), np.full((M, n, 3, 3), np.nan),
                   np.full((M, n, 3), np.nan), np.full(n, np.nan), np.full((n, 3), np.nan),
                   np.full(n, np.nan))

    @property
    def n(self) -> int:
        return len(self.t)

    def copy(self) -> "FilterState":
        return FilterState(self.x.copy(), self.P.copy(), self.mu.copy(), self.t.copy(),
                           self.held_z.copy(), self.held_t.copy())

    @classmethod
    def concat(cls, states: list["FilterState"]) -> "FilterState":
        if len(states) == 1:
            return states[0].copy()
        return cls(np.concatenate([s.x for s in states], axis=1),
                   np.concatenate([s.P for s in states], axis=1),
                   np.concatenate([s.mu for s in states], axis=1),
                   np.concatenate([s.t for s in states]),
                   np.concatenate([s.held_z for s in states]),
                   np.concatenate([s.held_t for s in states]))

    def rows(self, start: int, stop: int) -> "FilterState":
        """Rows start..stop as a new state (copies)."""
        return FilterState(self.x[:, start:stop].copy(), self.P[:, start:stop].copy(),
                           self.mu[:, start:stop].copy(), self.t[start:stop].copy(),
                           self.held_z[start:stop].copy(), self.held_t[start:stop].copy())

    def view_rows(self, start: int, stop: int) -> "FilterState":
        """Rows start..stop as views into this state's arrays (no copy: for a state that
        will not be changed again)."""
        return FilterState(self.x[:, start:stop], self.P[:, start:stop], self.mu[:, start:stop],
                           self.t[start:stop], self.held_z[start:stop], self.held_t[start:stop])

    def assign(self, other: "FilterState", mask: np.ndarray | None = None) -> None:
        """Take ``other``'s rows (all, or where ``mask`` (N,) is true) in place."""
        if mask is None:
            self.x[...], self.P[...], self.mu[...] = other.x, other.P, other.mu
            self.t[...], self.held_z[...], self.held_t[...] = other.t, other.held_z, other.held_t
            return
        self.x[:, mask], self.P[:, mask], self.mu[:, mask] = (other.x[:, mask], other.P[:, mask],
                                                              other.mu[:, mask])
        self.t[mask], self.held_z[mask], self.held_t[mask] = (other.t[mask], other.held_z[mask],
                                                              other.held_t[mask])

    @property
    def initialised(self) -> np.ndarray:
        return ~np.isnan(self.t)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) position m, (N, 3) velocity m/s) at each row's own time; NaN if unmeasured."""
        xm = np.einsum("mna,mnak->nak", self.mu, self.x)
        return xm[..., 0], xm[..., 1]

    def predicted(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity at ``t`` (never extrapolated backwards), NaN if unmeasured."""
        pos, vel = self.estimate()
        dt = np.maximum(np.asarray(t, dtype=float) - self.t, 0.0)
        return pos + dt[:, None] * vel, vel


#: what ``step`` did with each row's measurement
NOT_MEASURED, STARTED, ACCEPTED, DOWNWEIGHTED, REJECTED, RESTARTED = range(6)


def step(state: FilterState, t: np.ndarray, z: np.ndarray, r: np.ndarray,
         s: KalmanSettings, q_scale: np.ndarray | None = None) -> np.ndarray:
    """Fold one measurement per row into ``state``, in place; returns what happened (N,) int8.

    t: (N,) capture time of each row's measurement, s; z: (N, 3) metres; r: (N,) per-axis
    variance, m^2 -- rows with r <= 0, r = inf, NaN or a non-finite z are not measured and
    keep their state exactly. A measurement older than its row's state is applied at the
    row's time (the engine replays out-of-order frames before this happens). ``q_scale``
    (N,): per-row factor on both modes' process noise (default 1).
    """
    n = state.n
    z = np.asarray(z, dtype=float)
    r = np.asarray(r, dtype=float)
    t = np.broadcast_to(np.asarray(t, dtype=float), (n,))
    valid = (r > 0) & np.isfinite(r) & np.isfinite(z).all(axis=1) & np.isfinite(t)
    outcome = np.zeros(n, dtype=np.int8)
    init = state.initialised
    fresh = valid & ~init
    upd = valid & init
    if upd.any():
        rows = np.flatnonzero(upd) if not upd.all() else slice(None)
        x, P, mu = state.x[:, rows], state.P[:, rows], state.mu[:, rows]
        tz, zz, rr = t[rows], z[rows], r[rows]
        dt = np.maximum(tz - state.t[rows], 0.0)
        q = np.array([s.quiet_noise, s.fast_noise])
        if q_scale is not None:
            q = q[:, None] * np.asarray(q_scale, dtype=float)[rows][None]
        x0, P0, cbar = mix(x, P, mu, transition(dt, s))
        xp, Pp = predict(x0, P0, dt, q)
        d2 = gate_distance(xp, Pp, cbar, zz, rr)
        gate2 = s.gate_sigma ** 2
        soft = d2 > gate2
        r_eff = np.where(soft, rr * d2 / gate2, rr)
        xu, Pu, muu = update(xp, Pp, cbar, zz, r_eff)
        keep = d2 <= s.reject_sigma ** 2
        result = np.where(soft, DOWNWEIGHTED, ACCEPTED).astype(np.int8)
        if keep.all():
            state.x[:, rows], state.P[:, rows], state.mu[:, rows] = xu, Pu, muu
            state.t[rows] = np.maximum(tz, state.t[rows])
            state.held_t[rows] = np.nan
        else:
            idx = np.arange(n)[rows]
            ok, bad = idx[keep], idx[~keep]
            state.x[:, ok], state.P[:, ok], state.mu[:, ok] = xu[:, keep], Pu[:, keep], muu[:, keep]
            state.t[ok] = np.maximum(tz[keep], state.t[ok])
            state.held_t[ok] = np.nan
            again = bad[~np.isnan(state.held_t[bad])]
            first = bad[np.isnan(state.held_t[bad])]
            result[~keep] = REJECTED
            state.held_z[first], state.held_t[first] = z[first], t[first]
            if len(again):
                _restart(state, again, z[again], t[again], r[again], s)
                result[np.searchsorted(idx, again)] = RESTARTED
        outcome[rows] = result
    if fresh.any():
        _start(state, np.flatnonzero(fresh), z[fresh], t[fresh], r[fresh], s)
        outcome[fresh] = STARTED
    return outcome


def _start(state: FilterState, rows: np.ndarray, z: np.ndarray, t: np.ndarray, r: np.ndarray,
           s: KalmanSettings, v: np.ndarray | None = None, dt: np.ndarray | None = None) -> None:
    """New points: at ``z`` (k, 3), position variance ``r`` (k,), at rest with velocity variance
    from the settings -- or, with ``v`` (k, 3) and ``dt`` (k,), a two-point start (velocity
    from two measurements ``dt`` apart, covariance [[r, r/dt], [r/dt, 2r/dt^2]])."""
    k = len(rows)
    x = np.zeros((M, k, 3, 2))
    x[..., 0] = z[None]
    P = np.zeros((M, k, 3, 3))
    P[..., 0] = r[None, :, None]
    if v is None:
        P[..., 2] = s.initial_velocity_var
        mu = np.broadcast_to(initial_mu(s)[:, None, None], (M, k, 3))
    else:
        x[..., 1] = v[None]
        P[..., 1] = (r / dt)[None, :, None]
        P[..., 2] = (2.0 * r / (dt * dt))[None, :, None]
        mu = np.broadcast_to(np.array([0.0, 1.0])[:, None, None], (M, k, 3))
    state.x[:, rows], state.P[:, rows], state.mu[:, rows] = x, P, mu
    state.t[rows] = t
    state.held_t[rows] = np.nan


def _restart(state: FilterState, rows: np.ndarray, z: np.ndarray, t: np.ndarray, r: np.ndarray,
             s: KalmanSettings) -> None:
    """Points whose filter lost them: start again from the held and the new measurement, in
    the fast mode, with the velocity from their difference when they are at least 20 ms
    apart (closer, the difference is mostly noise: at rest with a wide velocity variance)."""
    held_z, held_t = state.held_z[rows], state.held_t[rows]
    dt = t - held_t
    apart = dt >= 0.02
    if (~apart).any():
        _start(state, rows[~apart], z[~apart], np.maximum(t, held_t)[~apart], r[~apart], s)
    if apart.any():
        d = dt[apart]
        _start(state, rows[apart], z[apart], t[apart], r[apart], s,
               (z[apart] - held_z[apart]) / d[:, None], d)


class JointKalman:
    """The filter for ``n`` points fed one measurement set at a time (benchmarks, tools).

    The engine drives ``FilterState`` with ``step`` directly, for many people at
    once; this wrapper is the same maths for one stream. Owned by one thread.
    """

    def __init__(self, n: int, settings: KalmanSettings = KalmanSettings(),
                 q_scale: np.ndarray | None = None) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n must be a non-negative int, got {n!r}")
        self._n = int(n)
        self._settings = settings
        self._q_scale = None if q_scale is None else np.asarray(q_scale, dtype=float)
        self.state = FilterState.empty(self._n)
        self.last_outcome = np.zeros(self._n, dtype=np.int8)

    @property
    def n(self) -> int:
        return self._n

    @property
    def settings(self) -> KalmanSettings:
        return self._settings

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) metres at each point's last time, NaN for points never measured."""
        return self.state.estimate()[0]

    @property
    def velocities(self) -> np.ndarray:
        """(n, 3) m/s, NaN for points never measured."""
        return self.state.estimate()[1]

    @property
    def covariance(self) -> np.ndarray:
        """(n, 3, 3) packed [pp, pv, vv] covariance of the IMM estimate, per axis."""
        return combine(self.state.x, self.state.P, self.state.mu)[1]

    @property
    def mode_probabilities(self) -> np.ndarray:
        """(n, 3) probability of the fast mode, per axis."""
        return self.state.mu[1].copy()

    @property
    def initialised(self) -> np.ndarray:
        return self.state.initialised

    @property
    def last_time(self) -> np.ndarray:
        return self.state.t.copy()

    def step(self, t: float, z: np.ndarray, conf: np.ndarray,
             r: np.ndarray | None = None) -> np.ndarray:
        """Fold in one measurement set taken at ``t``; returns (n, 3) filtered positions.

        z: (n, 3) metres; conf: (n,), > 0 to use a point; r: (n,) per-axis variance
        (default ``measurement_variance(conf, 1 m)``). Points with conf <= 0 or a
        non-finite z keep their state and time.
        """
        z = np.asarray(z, dtype=float)
        conf = np.asarray(conf, dtype=float)
        if z.shape != (self._n, 3) or conf.shape != (self._n,):
            raise ValueError(f"expected z ({self._n}, 3) and conf ({self._n},), "
                             f"got {z.shape} and {conf.shape}")
        valid = (conf > 0.0) & np.isfinite(conf)
        if r is None:
            r = measurement_variance(np.where(valid, conf, 1.0), 1.0, self._settings)
        r = np.where(valid, r, np.nan)
        self.last_outcome = step(self.state, np.full(self._n, float(t)), z, r, self._settings,
                                 self._q_scale)
        return self.positions

    def predict_positions(self, t: float) -> np.ndarray:
        """(n, 3) metres: each point at ``t`` (never before its last time); no side effect."""
        return self.state.predicted(t)[0]

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Forget the points in ``mask`` ((n,) bool), or all points when None."""
        if mask is None:
            mask = np.ones(self._n, dtype=bool)
        else:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != (self._n,):
                raise ValueError(f"expected mask ({self._n},), got {mask.shape}")
        self.state.assign(FilterState.empty(self._n), mask)
