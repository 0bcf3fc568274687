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

    x   (2, M, N, 3)  x[0] position (m), x[1] velocity (m/s), per mode, point and axis
    P   (3, M, N, 3)  covariance per mode, point and axis, packed: P[0] var(position),
                      P[1] cov(position, velocity), P[2] var(velocity)
    mu  (M, N, 3)     mode probabilities per point and axis
    t   (N,)          time the row's state refers to, s; NaN = never measured

Component first, so that every operation runs over one contiguous block of
all modes, points and axes; the 2x2 algebra and the two-mode mixing are
written in closed form over all rows at once (no Python loop, no
``np.linalg``, no einsum): a step for six people (150 rows) is a few dozen
numpy operations. The pure functions (``transition``, ``mix``,
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
from dataclasses import dataclass, field

import numpy as np

from ..joints import INFERRED
from ..settings import KalmanSettings
from . import jit
from .imm import _MU_FLOOR, M, fused_update

__all__ = ["KalmanSettings", "FilterState", "JointKalman", "transition", "mix", "predict",
           "update", "gate_distance", "combine", "step", "initial_mu", "measurement_variance"]



def initial_mu(s: KalmanSettings) -> np.ndarray:
    """(M,) mode probabilities of a new point: the chain's stationary distribution."""
    fast = s.quiet_to_fast_per_s / (s.quiet_to_fast_per_s + s.fast_to_quiet_per_s)
    return np.array([1.0 - fast, fast])


def measurement_variance(conf: np.ndarray, distance: np.ndarray | float,
                         s: KalmanSettings) -> np.ndarray:
    """Per-axis variance (m^2) of joints seen with ``conf`` (>0) at ``distance`` m from the sensor.

    The s.d. of a confidence-1 joint is ``sqrt(measurement_noise)`` up to 1 m
    and grows by ``noise_per_m`` per metre beyond; a joint of confidence c
    has c times the inverse variance, and one at or below the inferred level
    (c <= 0.5) also ``(1/c - 1) inferred_sd_m^2``: an inferred joint is the
    sensor's guess, off by up to tens of centimetres, not a noisier
    measurement (with the default 10 cm it weighs about 1/100 of a tracked
    joint near the sensor). A joint above the inferred level is tracked (as
    everywhere in the engine): a client sending continuous confidences (a
    landmark's visibility, 0.9) gets ``sd^2 / c`` only, not a guess's variance
    (which made its 0.9 joints ten times as uncertain as 1.0 ones).
    """
    sd = math.sqrt(s.measurement_noise) + s.noise_per_m * np.maximum(
        np.asarray(distance, dtype=float) - 1.0, 0.0)
    conf = np.asarray(conf, dtype=float)
    guess = np.where(conf <= INFERRED, 1.0 / conf - 1.0, 0.0)
    return sd * sd / conf + guess * s.inferred_sd_m ** 2


def transition(dt: np.ndarray, s: KalmanSettings) -> tuple[np.ndarray, np.ndarray]:
    """(p01, p10), each (N,): the chance of switching quiet -> fast and fast -> quiet
    within ``dt`` (N,) seconds >= 0; the transition matrix is [[1-p01, p01], [p10, 1-p10]]."""
    return -np.expm1(-s.quiet_to_fast_per_s * dt), -np.expm1(-s.fast_to_quiet_per_s * dt)


def _outer(d: np.ndarray) -> np.ndarray:
    """(3, ...) packed outer product of d = (2, ...) [position, velocity] differences."""
    return np.array([d[0] * d[0], d[0] * d[1], d[1] * d[1]])


def mix(x: np.ndarray, P: np.ndarray, mu: np.ndarray, p01: np.ndarray, p10: np.ndarray,
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMM mixing: (x0, P0, cbar), the mixed initial condition of each mode and the
    predicted mode probabilities ``cbar[j] = sum_i T[i, j] mu[i]`` (M, N, 3).

    With two modes the mixture of mode j is ``x_0 + w1j (x_1 - x_0)`` and its
    covariance ``P_0 + w1j (P_1 - P_0) + w1j (1 - w1j) d d^T`` (d = x_1 - x_0),
    where ``w1j = T[1, j] mu[1] / cbar[j]``.
    """
    p01 = p01[:, None]
    p10 = p10[:, None]
    a1 = p10 * mu[1]                        # T10 mu1
    b1 = (1.0 - p10) * mu[1]                # T11 mu1
    cbar = np.array([(1.0 - p01) * mu[0] + a1, p01 * mu[0] + b1])
    w1 = np.array([a1, b1]) / cbar          # (M, N, 3): weight of mode 1 in each mixture
    d = x[:, 1] - x[:, 0]                   # (2, N, 3)
    x0 = x[:, 0, None] + w1 * d[:, None]
    P0 = P[:, 0, None] + w1 * (P[:, 1] - P[:, 0])[:, None] + (w1 * (1.0 - w1)) * _outer(d)[:, None]
    return x0, P0, cbar


def predict(x: np.ndarray, P: np.ndarray, dt: np.ndarray, q: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray]:
    """Propagate by ``dt`` (N,) seconds with acceleration variance ``q`` per mode, (M,) or
    (M, N), (m/s^2)^2: ``x' = F x``, ``P' = F P F^T + Q``. dt = 0 is an exact no-op."""
    q = np.asarray(q, dtype=float)
    q = q[:, None, None] if q.ndim == 1 else q[:, :, None]
    dt = np.asarray(dt, dtype=float)[:, None]
    a, b, c = P
    x_new = np.empty_like(x)
    np.multiply(x[1], dt, out=x_new[0])
    x_new[0] += x[0]
    x_new[1] = x[1]
    qdt2 = q * (dt * dt)                                     # (M, N, 1)
    P_new = np.empty_like(P)
    # pv' = b + dt c + q dt^3 / 2; pp' = a + 2 dt b + dt^2 c + q dt^4 / 4
    #     = a + dt (b + pv') - q dt^4 / 4
    np.add(c, 0.5 * qdt2, out=P_new[1])
    P_new[1] *= dt
    P_new[1] += b
    np.add(b, P_new[1], out=P_new[0])
    P_new[0] *= dt
    P_new[0] += a
    P_new[0] -= (0.25 * qdt2) * (dt * dt)
    np.add(c, qdt2, out=P_new[2])
    return x_new, P_new


def update(x: np.ndarray, P: np.ndarray, cbar: np.ndarray, z: np.ndarray, r: np.ndarray,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correct every mode with position measurements ``z`` (N, 3) of variance ``r`` (N,) m^2,
    and the mode probabilities by each mode's likelihood. Returns (x, P, mu)."""
    a, b, c = P
    r3 = np.asarray(r, dtype=float)[:, None]
    y = z - x[0]                                             # (M, N, 3)
    s = a + r3
    inv = 1.0 / s
    k1 = b * inv
    g = r3 * inv                                             # 1 - k0 without cancellation
    x_new = np.array([x[0] + (a * inv) * y, x[1] + k1 * y])
    # (I - K H) P, filterpy's Joseph form for the optimal gain
    P_new = np.array([a * g, b * g, c - k1 * b])
    # mode probabilities: cbar times each mode's likelihood, normalised; the largest
    # log-likelihood is taken out first so that nothing underflows for big innovations
    log_l = -0.5 * (np.log(s) + y * y * inv)                 # (the 2 pi cancels)
    w = cbar * np.exp(log_l - log_l.max(axis=0))
    # never exactly 0 (as filterpy, whose likelihoods have a floor): a mode that can come
    # back must not be divided by zero when there is no time to switch (dt = 0)
    np.maximum(w, _MU_FLOOR, out=w)
    return x_new, P_new, w / (w[0] + w[1])


def combine(x: np.ndarray, P: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The IMM estimate: (2, N, 3) mean [position, velocity] and (3, N, 3) packed covariance."""
    w1 = mu[1]
    d = x[:, 1] - x[:, 0]
    xm = x[:, 0] + w1 * d
    Pm = P[:, 0] + w1 * (P[:, 1] - P[:, 0]) + (w1 * (1.0 - w1)) * _outer(d)
    return xm, Pm


def gate_distance(xp: np.ndarray, Pp: np.ndarray, cbar: np.ndarray, z: np.ndarray,
                  r: np.ndarray) -> np.ndarray:
    """(N,) squared Mahalanobis distance of ``z`` from the mixture's predicted position
    (the modes' predictions weighted by ``cbar``, their spread included), over 3 axes."""
    w1 = cbar[1]
    p0 = xp[0, 0]
    d = xp[0, 1] - p0
    var = Pp[0, 0] + w1 * (Pp[0, 1] - Pp[0, 0] + (1.0 - w1) * d * d)
    y = z - p0 - w1 * d
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
    #: (block, x, P, mu): ``x``, ``P`` and ``mu`` as views of one (6, M, N, 3) array [x; P; mu]
    #: (what ``step`` leaves), so that the next step reads it without gathering the three;
    #: used only while they are still these very arrays
    block: tuple | None = field(default=None, repr=False, compare=False)
    #: (owner, start, stop, t, held_z, held_t): this state is rows start..stop of ``owner``,
    #: as ``view_rows`` made it (its arrays are these views, while they still are)
    rows_of: tuple | None = field(default=None, repr=False, compare=False)

    @classmethod
    def empty(cls, n: int) -> "FilterState":
        return cls.of_block(np.full((6, M, n, 3), np.nan), np.full(n, np.nan),
                            np.full((n, 3), np.nan), np.full(n, np.nan))

    @classmethod
    def of_block(cls, block: np.ndarray, t: np.ndarray, held_z: np.ndarray,
                 held_t: np.ndarray) -> "FilterState":
        """A state whose x, P and mu are views of ``block`` (6, M, N, 3)."""
        x, P, mu = block[0:2], block[2:5], block[5]
        return cls(x, P, mu, t, held_z, held_t, (block, x, P, mu))

    def stacked(self) -> np.ndarray:
        """(6, M, N, 3) [x; P; mu]: the block itself when x, P and mu still are its views,
        else a new array."""
        b = self.block
        if b is not None and b[1] is self.x and b[2] is self.P and b[3] is self.mu:
            return b[0]
        return np.concatenate((self.x, self.P, self.mu[None]))

    def shallow(self) -> "FilterState":
        """A new state object sharing this one's arrays (``step`` replaces, never writes)."""
        return FilterState(self.x, self.P, self.mu, self.t, self.held_z, self.held_t,
                           self.block)

    @property
    def n(self) -> int:
        return len(self.t)

    def copy(self) -> "FilterState":
        return FilterState.of_block(self.stacked().copy(), self.t.copy(), self.held_z.copy(),
                                    self.held_t.copy())

    @classmethod
    def concat(cls, states: list["FilterState"]) -> "FilterState":
        """One state of all the rows of ``states``, in order (new arrays; with one state, its
        arrays themselves: ``step`` never writes into a state's arrays)."""
        if len(states) == 1:
            return states[0].shallow()
        whole = cls._whole(states)
        if whole is not None:
            return whole.shallow()
        return cls.of_block(np.concatenate([s.stacked() for s in states], axis=2),
                            np.concatenate([s.t for s in states]),
                            np.concatenate([s.held_z for s in states]),
                            np.concatenate([s.held_t for s in states]))

    @staticmethod
    def _whole(states: list["FilterState"]) -> "FilterState | None":
        """The state whose rows ``states`` are, all of them in order, as ``view_rows`` made
        them (so concatenating them would copy it), or None. A fold that takes the same
        persons in the same order as the one before (every datagram of a steady show) then
        starts from the previous fold's arrays instead of copying them: nothing writes
        into a state's arrays (``step`` replaces them)."""
        first = states[0].rows_of
        if first is None:
            return None
        owner, at = first[0], 0
        for s in states:
            r = s.rows_of
            b = s.block
            if (r is None or r[0] is not owner or r[1] != at or b is None or b[1] is not s.x
                    or b[2] is not s.P or b[3] is not s.mu or r[3] is not s.t
                    or r[4] is not s.held_z or r[5] is not s.held_t):
                return None
            at = r[2]
        return owner if at == owner.n else None

    def rows(self, start: int, stop: int) -> "FilterState":
        """Rows start..stop as a new state (copies)."""
        return self.view_rows(start, stop).copy()

    def view_rows(self, start: int, stop: int) -> "FilterState":
        """Rows start..stop as views into this state's arrays (no copy: for a state that
        will not be changed again)."""
        rows = FilterState.of_block(self.stacked()[:, :, start:stop], self.t[start:stop],
                                    self.held_z[start:stop], self.held_t[start:stop])
        rows.rows_of = (self, start, stop, rows.t, rows.held_z, rows.held_t)
        return rows

    def assign(self, other: "FilterState", mask: np.ndarray | None = None) -> None:
        """Take ``other``'s rows (all, or where ``mask`` (N,) is true) in place."""
        if mask is None:
            mask = slice(None)
        self.x[:, :, mask], self.P[:, :, mask] = other.x[:, :, mask], other.P[:, :, mask]
        self.mu[:, mask], self.t[mask] = other.mu[:, mask], other.t[mask]
        self.held_z[mask], self.held_t[mask] = other.held_z[mask], other.held_t[mask]

    @property
    def initialised(self) -> np.ndarray:
        return ~np.isnan(self.t)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) position m, (N, 3) velocity m/s) at each row's own time; NaN if unmeasured."""
        w1 = self.mu[1]
        x = self.x
        return x[0, 0] + w1 * (x[0, 1] - x[0, 0]), x[1, 0] + w1 * (x[1, 1] - x[1, 0])

    def predicted(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity at ``t`` (never extrapolated backwards), NaN if unmeasured."""
        pos, vel = self.estimate()
        dt = np.maximum(np.asarray(t, dtype=float) - self.t, 0.0)
        return pos + dt[:, None] * vel, vel


#: what ``step`` did with each row's measurement
NOT_MEASURED, STARTED, ACCEPTED, DOWNWEIGHTED, REJECTED, RESTARTED = range(6)
#: by outcome: whether the row's measurement went into its filter
USED = np.array([False] * 8)
USED[[STARTED, ACCEPTED, DOWNWEIGHTED, RESTARTED]] = True


def step(state: FilterState, t: np.ndarray, z: np.ndarray, r: np.ndarray,
         s: KalmanSettings, q_scale: np.ndarray | None = None) -> np.ndarray:
    """Fold one measurement per row into ``state``; returns what happened (N,) int8.

    The state's arrays are replaced, never written into: a reference to the old
    arrays (a snapshot for a replay) stays valid without a copy.

    t: (N,) capture time of each row's measurement, s; z: (N, 3) metres; r: (N,) per-axis
    variance, m^2 -- rows with r <= 0, r = inf, NaN or a non-finite z are not measured and
    keep their state exactly. A measurement older than its row's state is applied at the
    row's time (the engine replays out-of-order frames before this happens). ``q_scale``
    (N,): per-row factor on both modes' process noise (default 1).
    """
    if jit.ready():      # (no numpy arithmetic outside its own np.errstate: see _step_compiled)
        return _step(state, t, z, r, s, q_scale)[0]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return _step(state, t, z, r, s, q_scale)[0]


def step_folded(state: FilterState, t: np.ndarray, z: np.ndarray, r: np.ndarray,
                s: KalmanSettings, q_scale: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int]]:
    """``step``, then what a fold records of it: (outcome, position and velocity (N, 3):
    ``state.predicted(t)`` after the step, used (N,) bool: ``USED[outcome]``, (rows
    downweighted, rejected, restarted)). With the compiled step, all but the outcome come
    from the kernel itself where no row was restarted or started (the usual step; the
    same floats)."""
    if jit.ready():      # (no numpy arithmetic outside its own np.errstate: see _step_compiled)
        outcome, predicted, used, counts = _step(state, t, z, r, s, q_scale)
    else:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            outcome, predicted, used, counts = _step(state, t, z, r, s, q_scale)
    if predicted is None:           # (a row restarted from absurd coordinates: inf - inf)
        with np.errstate(invalid="ignore", over="ignore"):
            predicted = state.predicted(t)
    if used is None:
        used = USED[outcome]
        c = np.bincount(outcome, minlength=8)
        counts = (int(c[DOWNWEIGHTED]), int(c[REJECTED]), int(c[RESTARTED]))
    return outcome, predicted[0], predicted[1], used, counts


def step_views(state: FilterState, t: np.ndarray, z: np.ndarray, r: np.ndarray,
               s: KalmanSettings, q_scale: np.ndarray | None = None
               ) -> tuple[list[FilterState], np.ndarray, np.ndarray, np.ndarray,
                          tuple[np.ndarray, np.ndarray] | None]:
    """``step`` of G measurement sets of the same rows in turn: set g at time t[g] (G,) with
    z[g] (N, 3) and r[g] (N,), each from the state the one before left. Returns (the G
    states after each set, new objects; outcome (G, N); used (G, N): ``USED[outcome]``;
    counts (G, 4): rows to restart, to start, downweighted, rejected and held; the last
    state's ``predicted(t[-1])`` as the kernel computed it, or None). ``state`` is not
    changed. With the kernels, one compiled call for the sets (``jit.step_views``)
    instead of a ``step`` each: a replay with sensors in step folds a person's views of an
    instant again, several times a datagram; else ``step`` for each set."""
    G = len(t)
    if np.shape(z) != (G, state.n, 3) or np.shape(r) != (G, state.n):
        raise ValueError(f"step_views: {G} sets of {state.n} rows, got z {np.shape(z)} and "
                         f"r {np.shape(r)}")
    if not jit.ready():
        states, outcomes = [], []
        for g in range(G):
            state = state.shallow()
            outcomes.append(step(state, np.full(state.n, t[g]), z[g], r[g], s, q_scale))
            states.append(state)
        outcome = np.array(outcomes, dtype=np.int8).reshape(G, -1)
        counts = np.array([[np.count_nonzero(o == RESTARTED), np.count_nonzero(o == STARTED),
                            np.count_nonzero(o == DOWNWEIGHTED),
                            np.count_nonzero(o == REJECTED)] for o in outcome])
        return states, outcome, USED[outcome], counts, None
    t = np.ascontiguousarray(t, dtype=float)
    z = np.ascontiguousarray(z, dtype=float)
    r = np.ascontiguousarray(r, dtype=float)
    into = jit.Views(G, state.n)
    states: list[FilterState] = []
    start = 0
    while start < G:
        stop = jit.step_views(state.stacked(), state.t, state.held_z, state.held_t, t, z, r, s,
                              q_scale, into, start)
        for g in range(start, min(stop + 1, G)):
            states.append(FilterState.of_block(into.block[g], into.t[g], into.held_z[g],
                                               into.held_t[g]))
        if stop < G:          # rows to restart or start after set ``stop``: as ``step``
            state = states[-1]
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                _fix_rows(state, into.outcome[stop], np.full(state.n, t[stop]), z[stop],
                          r[stop], s, into.counts[stop, 0], into.counts[stop, 1])
            into.used[stop] = USED[into.outcome[stop]]
        start = stop + 1
    # (the kernel's position and velocity of a set are ``predicted`` of its state unless rows
    # were restarted or started after it)
    last = None if into.counts[-1, 0] or into.counts[-1, 1] else (into.pos[-1], into.vel[-1])
    return states, into.outcome, into.used, into.counts, last


def _step(state: FilterState, t: np.ndarray, z: np.ndarray, r: np.ndarray,
          s: KalmanSettings, q_scale: np.ndarray | None
          ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None, np.ndarray | None,
                     tuple[int, int, int] | None]:
    """``step``, inside one ``np.errstate`` (entering one costs as much as a few array
    operations of a step); with the compiled step, also ``state.predicted(t)``, the rows
    used and the counts (``step_folded``) when no row was restarted or started (else None,
    None, None)."""
    n = state.n
    z = np.asarray(z, dtype=float)
    r = np.asarray(r, dtype=float)
    t = np.asarray(t, dtype=float)
    if t.shape != (n,):
        t = np.broadcast_to(t, (n,))
    if jit.ready():
        return _step_compiled(state, t, z, r, s, q_scale)
    # r <= 0, r = inf, NaN anywhere: not measured (0 * inf and 0 * NaN are NaN)
    valid = np.isfinite(z[:, 0] + z[:, 1] + z[:, 2] + t + 0.0 * r) & (r > 0)
    init = state.t == state.t                                # not NaN: has a state
    upd = valid & init
    # (np.count_nonzero, not .any() / .all(): a numpy reduction costs several elementwise
    # operations; the step is made of small operations, so their count is its cost; the
    # usual step -- every row measured, known and accepted -- skips the masks it needs not)
    n_upd = np.count_nonzero(upd)
    fresh = valid & ~init if n_upd < np.count_nonzero(valid) else None
    outcome = None
    if n_upd:
        # every row is computed (rows without a measurement, or without a state, give NaN
        # or junk) and only the measured ones are kept: one pass of whole-array operations
        # is cheaper than gathering and scattering the rows
        S = state.stacked()
        dt = np.maximum(t - state.t, 0.0)
        if n_upd < n:
            dt = np.where(upd, dt, 0.0)
        gate2 = s.gate_sigma ** 2
        new, d2 = fused_update(S, dt, z, r, s, q_scale, gate2)
        use = d2 <= s.reject_sigma ** 2
        outcome = np.add(d2 > gate2, ACCEPTED, dtype=np.int8)   # DOWNWEIGHTED = ACCEPTED + 1
        if n_upd < n:
            use &= upd
            outcome[~upd] = NOT_MEASURED
        if np.count_nonzero(use) == n:
            keep = FilterState.of_block(new, np.maximum(t, state.t), state.held_z,
                                        np.full(n, np.nan))
        else:
            keep = FilterState.of_block(np.where(use[:, None], new, S),
                                        np.where(use, np.maximum(t, state.t), state.t),
                                        state.held_z, np.where(use, np.nan, state.held_t))
        state.x, state.P, state.mu, state.t, state.held_t, state.block = (
            keep.x, keep.P, keep.mu, keep.t, keep.held_t, keep.block)
        bad = np.flatnonzero(upd & ~use) if np.count_nonzero(use) < n_upd else ()
        if len(bad):
            again = bad[~np.isnan(state.held_t[bad])]
            first = bad[np.isnan(state.held_t[bad])]
            outcome[bad] = REJECTED
            state.held_z = state.held_z.copy()
            state.held_z[first], state.held_t[first] = z[first], t[first]
            if len(again):
                _restart(state, again, z[again], t[again], r[again], s)
                outcome[again] = RESTARTED
    if outcome is None:
        outcome = np.zeros(n, dtype=np.int8)
    if fresh is not None and np.count_nonzero(fresh):
        _start(state, np.flatnonzero(fresh), z[fresh], t[fresh], r[fresh], s)
        outcome[fresh] = STARTED
    return outcome, None, None, None


def _step_compiled(state: FilterState, t: np.ndarray, z: np.ndarray, r: np.ndarray,
                   s: KalmanSettings, q_scale: np.ndarray | None
                   ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None, np.ndarray | None,
                              tuple[int, int, int] | None]:
    """``_step`` with its usual path in one compiled loop (``jit.step_rows``): the same
    outcome and state; rejected, restarted and new rows as there. Also the kernel's
    ``state.predicted(t)``, its rows used and its counts, unless a row was restarted or
    started after it (None, None, None).

    Called without ``np.errstate`` (entering one costs as much as a few array operations,
    2 % of the engine at 6x6): the kernel raises no floating-point warning, and the numpy
    arithmetic for rows restarted or started runs in its own."""
    t, z, r = np.ascontiguousarray(t), np.ascontiguousarray(z), np.ascontiguousarray(r)
    block, new_t, held_z, held_t, outcome, used, counts, pos, vel = jit.step_rows(
        state.stacked(), state.t, state.held_z, state.held_t, t, z, r, s, q_scale)
    keep = FilterState.of_block(block, new_t, held_z, held_t)
    state.x, state.P, state.mu, state.t, state.held_z, state.held_t, state.block = (
        keep.x, keep.P, keep.mu, keep.t, keep.held_z, keep.held_t, keep.block)
    # a row held (rejected once, by the kernel) keeps its x, P, mu and t
    if counts[0] or counts[1]:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            _fix_rows(state, outcome, t, z, r, s, counts[0], counts[1])
        return outcome, None, None, None
    return outcome, (pos, vel), used, (int(counts[2]), int(counts[3]), 0)


def _fix_rows(state: FilterState, outcome: np.ndarray, t: np.ndarray, z: np.ndarray,
              r: np.ndarray, s: KalmanSettings, n_again: int, n_fresh: int) -> None:
    """After the compiled step: rows it marked RESTARTED (rejected twice in a row; it kept
    their state and held measurement) restarted, new rows started."""
    if n_again:
        again = np.flatnonzero(outcome == RESTARTED)
        _restart(state, again, z[again], t[again], r[again], s)
    if n_fresh:
        fresh = np.flatnonzero(outcome == STARTED)
        _start(state, fresh, z[fresh], t[fresh], r[fresh], s)


def _start(state: FilterState, rows: np.ndarray, z: np.ndarray, t: np.ndarray, r: np.ndarray,
           s: KalmanSettings, v: np.ndarray | None = None, dt: np.ndarray | None = None) -> None:
    """New points: at ``z`` (k, 3), position variance ``r`` (k,), at rest with velocity variance
    from the settings -- or, with ``v`` (k, 3) and ``dt`` (k,), a two-point start (velocity
    from two measurements ``dt`` apart, covariance [[r, r/dt], [r/dt, 2r/dt^2]])."""
    k = len(rows)
    x = np.zeros((2, M, k, 3))
    x[0] = z[None]
    P = np.zeros((3, M, k, 3))
    P[0] = r[None, :, None]
    if v is None:
        P[2] = s.initial_velocity_var
        mu = np.broadcast_to(initial_mu(s)[:, None, None], (M, k, 3))
    else:
        x[1] = v[None]
        P[1] = (r / dt)[None, :, None]
        P[2] = (2.0 * r / (dt * dt))[None, :, None]
        mu = np.broadcast_to(np.array([_MU_FLOOR, 1.0])[:, None, None], (M, k, 3))
    # copies first: the arrays may be shared with a snapshot (see ``step``)
    new = FilterState.of_block(state.stacked().copy(), state.t.copy(), state.held_z,
                               state.held_t.copy())
    new.x[:, :, rows], new.P[:, :, rows], new.mu[:, rows] = x, P, mu
    new.t[rows] = t
    new.held_t[rows] = np.nan
    state.x, state.P, state.mu, state.t, state.held_t, state.block = (
        new.x, new.P, new.mu, new.t, new.held_t, new.block)


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
        """(n, 3, 3): per point and axis, the IMM estimate's packed covariance [pp, pv, vv]."""
        return np.moveaxis(combine(self.state.x, self.state.P, self.state.mu)[1], 0, -1)

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
