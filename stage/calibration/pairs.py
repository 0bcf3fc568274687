"""Pairs of skeletons seen at the same moment by two sensors, and time alignment.

A ``PairSet`` holds N paired frames: the reference side ``ref`` (the space
we calibrate into: the reference sensor's, or stage space when live) and
the sensor's own side ``other``. Joint pairs count only where both sensors
tracked the joint; their weight is the product of the two confidences.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ..errors import CalibrationError
from ..joints import JOINT_INDEX, N_JOINTS
from .fitness import GAUSS_RMS_PER_MEDIAN, Moments, kabsch, residuals, weighted_median
from .streams import Stream

SPINE_BASE = JOINT_INDEX["SpineBase"]


@dataclass
class PairSet:
    """N paired frames. ref, other: (N, 25, 3) metres; weight: (N, 25); t: (N,) s."""

    ref_id: str
    other_id: str
    ref: np.ndarray
    other: np.ndarray
    weight: np.ndarray
    t: np.ndarray
    floor_ref: np.ndarray | None = None     # (4,) plane in the ref side's space
    floor_other: np.ndarray | None = None   # (4,) plane in the other side's space
    lag_s: float = 0.0                      # other's clock minus ref's clock

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def empty(cls, ref_id: str, other_id: str) -> "PairSet":
        return cls(ref_id, other_id, np.zeros((0, N_JOINTS, 3)), np.zeros((0, N_JOINTS, 3)),
                   np.zeros((0, N_JOINTS)), np.zeros(0))

    def subset(self, index: np.ndarray | slice) -> "PairSet":
        return replace(self, ref=self.ref[index], other=self.other[index],
                       weight=self.weight[index], t=self.t[index])

    def with_weight(self, weight: np.ndarray) -> "PairSet":
        return replace(self, weight=np.asarray(weight, dtype=float))

    def concat(self, more: "PairSet") -> "PairSet":
        return replace(self, ref=np.concatenate([self.ref, more.ref]),
                       other=np.concatenate([self.other, more.other]),
                       weight=np.concatenate([self.weight, more.weight]),
                       t=np.concatenate([self.t, more.t]))

    def moments(self, weight: np.ndarray | None = None) -> Moments:
        """Weighted statistics of (other -> ref) joint pairs; CalibrationError if empty."""
        w = self.weight if weight is None else weight
        if not (w > 0).any():
            raise CalibrationError(f"no joint seen by both {self.ref_id} and {self.other_id}")
        return Moments.of(self.other, self.ref, w)

    def evenly(self, n: int) -> "PairSet":
        """At most ``n`` pairs spread evenly over the set (all when n <= 0)."""
        if n <= 0 or len(self) <= n:
            return self
        return self.subset(np.unique(np.linspace(0, len(self) - 1, n).round().astype(int)))


def pair_streams(ref: Stream, other: Stream, lag_s: float = 0.0, max_dt: float = 0.02,
                 max_gap: float = 0.1, interpolate: bool = True, min_joints: int = 8,
                 single_window_s: float = 0.5) -> PairSet:
    """Pair each usable frame of ``ref`` with ``other`` at the same instant.

    ``other`` is read at ``t + lag_s`` (its clock runs ``lag_s`` ahead).
    Usable frames: no NaN, and exactly one user visible to that sensor
    within ``single_window_s`` (so both sensors surely see the same person).
    With ``interpolate``, the other sensor's skeleton is linearly
    interpolated between its two frames around that instant when they are
    at most ``max_gap`` apart (removes up to half a frame of motion error);
    otherwise, or when no such bracket exists, the nearest frame within
    ``max_dt`` is used. A pair needs ``min_joints`` joints tracked by both.
    """
    rmask = ref.finite() & ref.single_user(single_window_s)
    omask = other.finite() & other.single_user(single_window_s)
    if not rmask.any() or not omask.any():
        return _empty(ref, other, lag_s)
    r, o = ref.subset(rmask), other.subset(omask)
    joints, conf, valid = resample(o.t - lag_s, o.joints, o.conf, r.t, max_gap, max_dt,
                                   o.user if interpolate else None, interpolate)
    weight = np.where(valid[:, None], r.conf * conf, 0.0)
    valid &= (weight > 0).sum(axis=1) >= min_joints
    return PairSet(ref.sensor, other.sensor, r.joints[valid], joints[valid], weight[valid],
                   r.t[valid], ref.floor, other.floor, lag_s)


def resample(times: np.ndarray, joints: np.ndarray, conf: np.ndarray, at: np.ndarray,
                max_gap: float = 0.1, max_dt: float = 0.02, user: np.ndarray | None = None,
                linear: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A skeleton stream read at other instants.

    times (n,) ascending; joints (n, J, 3); conf (n, J); at (m,). Between two
    frames at most ``max_gap`` apart (and of the same ``user``, if given) the
    joints are interpolated linearly, a joint counting only if tracked in both
    (confidence: the smaller); elsewhere the nearest frame within ``max_dt``
    is used. Returns (joints (m, J, 3), conf (m, J), valid (m,) bool); rows
    that are not valid hold zeros.
    """
    n, m = len(times), len(at)
    if n == 0 or m == 0:
        return np.zeros((m,) + joints.shape[1:]), np.zeros((m,) + conf.shape[1:]), \
            np.zeros(m, dtype=bool)
    idx = np.searchsorted(times, at)
    i0 = np.maximum(idx - 1, 0)   # (np.clip costs several times more on small arrays)
    i1 = np.minimum(idx, n - 1)
    return read_between(times, joints, conf, at, idx, n, i0, i1, max_gap, max_dt, user, linear)


def read_between(times: np.ndarray, joints: np.ndarray, conf: np.ndarray, at: np.ndarray,
                 idx: np.ndarray, n, i0: np.ndarray, i1: np.ndarray, max_gap: float,
                 max_dt: float, user: np.ndarray | None = None, linear: bool = True,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``resample``'s reading once the neighbours are found, for instants ``at`` of any
    shape S: ``idx`` (S) each instant's insertion point in its own stream of ``n`` frames
    (``n`` broadcast against S), ``i0``/``i1`` (S) the frames before and after it as rows
    of ``times``/``joints``/``conf`` (several streams may be laid end to end). Returns
    (joints S+(J, 3), conf S+(J,), valid S)."""
    out_j = np.zeros(idx.shape + joints.shape[1:])
    out_c = np.zeros(idx.shape + conf.shape[1:])
    valid = np.zeros(idx.shape, dtype=bool)
    if linear:
        span = times[i1] - times[i0]
        ok = (idx > 0) & (idx < n) & (span > 0) & (span <= max_gap)
        if user is not None:
            ok &= user[i0] == user[i1]
        if ok.any():
            a = ((at[ok] - times[i0[ok]]) / span[ok])[:, None, None]
            out_j[ok] = (1 - a) * joints[i0[ok]] + a * joints[i1[ok]]
            c0, c1 = conf[i0[ok]], conf[i1[ok]]
            out_c[ok] = np.where((c0 > 0) & (c1 > 0), np.minimum(c0, c1), 0.0)
            valid |= ok
        if valid.all():
            return out_j, out_c, valid
    d0 = np.where(idx > 0, np.abs(at - times[i0]), np.inf)
    d1 = np.where(idx < n, np.abs(times[i1] - at), np.inf)
    near = np.where(d0 <= d1, i0, i1)
    nearest = ~valid & (np.minimum(d0, d1) <= max_dt)
    out_j[nearest] = joints[near[nearest]]
    out_c[nearest] = conf[near[nearest]]
    valid |= nearest
    return out_j, out_c, valid


def _empty(ref: Stream, other: Stream, lag_s: float) -> PairSet:
    out = PairSet.empty(ref.sensor, other.sensor)
    out.floor_ref, out.floor_other, out.lag_s = ref.floor, other.floor, lag_s
    return out


#: streams shorter than this (frames) are searched unsmoothed (see find_lag)
SMOOTH_FROM_FRAMES = 100
#: the finest coarse step of a lag search (s): 250 Hz, finer than any skeleton sensor
MIN_LAG_STEP_S = 0.004


@dataclass(frozen=True)
class LagSearch:
    lag_s: float
    lags: np.ndarray      # every lag tried, s
    residual: np.ndarray  # robust residual (median joint distance, m) of the best rigid fit at
                          # each lag; NaN where the lag paired too few frames to be judged
    pairs: int            # pairs at the chosen lag
    confidence: float = 0.0   # 1 - best / median over the lags judged: 0 = every lag alike
                              # (nobody moved: the lag does not matter), near 1 = one sharp fit
    overlap: int = 0          # the most frames any lag paired (the eligibility yardstick)

    @property
    def mse(self) -> np.ndarray:
        """The residuals as the mean square a Gaussian error with that median has (m^2)."""
        return (GAUSS_RMS_PER_MEDIAN * self.residual) ** 2


def robust_residual(ps: PairSet, rounds: int = 2) -> float:
    """Median joint distance (m) of a quick robust rigid fit: least squares, then ``rounds``
    of Cauchy re-weighting (the same weights ``methods.rigid`` uses)."""
    # on the weighted joint pairs only, taken out once: the same floats as on all of them
    # (every step below leaves out the pairs without weight, and a re-weighting keeps the
    # weight of every pair that has one), without copying them out again at each step
    keep = ps.weight > 0
    if not keep.any():
        ps.moments()                    # its CalibrationError, naming the sensors
    p, q, w = ps.other[keep], ps.ref[keep], ps.weight[keep]
    m = kabsch(Moments.of(p, q, w))
    for _ in range(rounds):
        r = residuals(m, p, q)
        c = max(2.0 * weighted_median(r, w), 0.02)
        m = kabsch(Moments.of(p, q, w / (1.0 + (r / c) ** 2)))
    return weighted_median(residuals(m, p, q), w)


def find_lag(ref: Stream, other: Stream, max_lag_s: float = 1.0, step_s: float | None = None,
             fine_steps: int = 10, max_frames: int = 400, min_pairs: int = 10,
             min_overlap: float = 0.6, prefer_zero: float = 0.02, smooth_frames: int = 5,
             single_window_s: float = 0.5, pause: Callable[[], None] | None = None
             ) -> LagSearch:
    """The clock offset of ``other`` against ``ref`` with the best robust fit.

    For each candidate lag in [-max_lag_s, max_lag_s], one frame apart, the
    streams are paired (interpolated) and a robust rigid fit scored by its
    MEDIAN joint distance, so the score is per joint pair, whatever the
    overlap. A lag counts only when it pairs at least ``min_pairs`` frames
    and ``min_overlap`` of the most any lag paired: at the edge of the window
    only a few frames overlap, and a few frames fit almost anything, which
    let 5-frame overlaps win on short takes. Around the best lag the search
    goes ``fine_steps`` times finer, and a parabola through the finest
    scores gives the sub-frame lag. Both streams are first smoothed over
    ``smooth_frames`` frames (see ``Stream.smoothed``), unless one has fewer
    than ``SMOOTH_FROM_FRAMES`` usable frames. A person standing still makes every lag look alike, so zero is kept unless another lag is
    better by more than ``prefer_zero`` (2 %). ``max_frames`` reference
    frames, spread over the stream, keep the search fast. ``single_window_s``: as
    ``pair_streams``'s (0: the caller kept only frames with one person in view; its user
    ids then only cut runs). ``pause``, if given, is called after each lag is paired and
    after each is scored (a live worker gives way to the engine there; the result does not
    depend on it).
    """
    usable = np.flatnonzero(ref.finite() & ref.single_user(single_window_s))
    if len(usable) > max_frames:
        usable = usable[np.linspace(0, len(usable) - 1, max_frames).round().astype(int)]
    # (a floor: near-duplicate frames 1 ms apart once made this 1 ms, thousands of lags)
    step = max(step_s or other.frame_interval(), MIN_LAG_STEP_S)
    # both streams smoothed alike: see Stream.smoothed for why; not short takes, whose few
    # frames the smoothing would blur into each other (measured on N-UCLA: 42 of 50 pairs
    # within a frame of the brute-force lag unsmoothed, 39 smoothed)
    if min(len(usable), len(other)) < SMOOTH_FROM_FRAMES:
        smooth_frames = 1
    r = ref.smoothed(smooth_frames).subset(usable)
    other = other.smoothed(smooth_frames)
    paired: dict[float, PairSet] = {}

    def pairs_at(lag: float) -> PairSet:
        lag = float(round(lag, 9))
        if lag not in paired:
            paired[lag] = pair_streams(r, other, lag, single_window_s=single_window_s)
            if pause is not None:
                pause()
        return paired[lag]

    coarse = np.arange(-max_lag_s, max_lag_s + step / 2, step)
    counts = np.array([len(pairs_at(lag)) for lag in coarse])
    overlap = int(counts.max()) if len(counts) else 0
    need = max(3, min(min_pairs, overlap), int(np.ceil(min_overlap * overlap)))
    if overlap < 3:
        raise CalibrationError(f"{ref.sensor} and {other.sensor} never saw one person at "
                               f"the same time (within ±{max_lag_s:g} s)")
    scores: dict[float, float] = {}

    def score(lag: float) -> float:
        lag = float(round(lag, 9))
        if lag not in scores:
            ps = pairs_at(lag)
            scores[lag] = robust_residual(ps) if len(ps) >= need else float("nan")
            if pause is not None:
                pause()
        return scores[lag]

    errs = np.array([score(lag) for lag in coarse])
    judged = errs[np.isfinite(errs)]
    best = float(round(coarse[np.nanargmin(errs)], 9))
    fine = step / fine_steps
    for lag in best + fine * np.arange(-fine_steps, fine_steps + 1):
        if abs(lag) <= max_lag_s + 1e-9:
            score(lag)
    lags = np.array(sorted(scores))
    res = np.array([scores[lag] for lag in lags])
    k = int(np.nanargmin(res))
    lag = float(lags[k])
    near = np.isfinite(res) & (np.abs(lags - lag) <= 0.5 * step + 1e-9)
    if near.sum() >= 3:  # sub-frame: the vertex of a parabola through the finest scores
        a, b, _ = np.polyfit(lags[near] - lag, res[near], 2)
        if a > 0:
            vertex = float(np.clip(-b / (2 * a), -0.5 * step, 0.5 * step))
            if abs(lag + vertex) <= max_lag_s and score(lag + vertex) <= res[k]:
                lag = float(round(lag + vertex, 9))
    zero = score(0.0) if abs(lag) > 0 else scores[lag]
    if np.isfinite(zero) and zero <= (1.0 + prefer_zero) * scores[lag]:
        lag = 0.0
    confidence = float(max(0.0, 1.0 - scores[lag] / np.median(judged))) if len(judged) else 0.0
    lags = np.array(sorted(scores))
    return LagSearch(lag, lags, np.array([scores[x] for x in lags]), len(pairs_at(lag)),
                     confidence, overlap)
