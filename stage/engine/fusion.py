"""Pure fusion maths: combine several sensors' views of one person.

Everything here is a function of numpy arrays in stage space; the engine
decides which views belong together and when.
"""

from __future__ import annotations

import numpy as np

from ..joints import TORSO, HandState


def fuse_joints(positions: np.ndarray, conf: np.ndarray, outlier_m: float = 0.10,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Confidence-weighted average of S views of one skeleton, with outlier rejection.

    positions: (S, J, 3) metres, stage space. conf: (S, J) in [0, 1]; 0 means
    not tracked and never enters the average.

    A view of a joint is an outlier when, with three or more views, its
    distance to the per-axis median is more than ``outlier_m`` beyond the
    median of those distances (the spread). With exactly two views that
    disagree by more than ``2 * outlier_m``, the less confident one is
    dropped (an inferred joint is the usual culprit); if both are equally
    confident neither can be blamed and both are kept.

    Returns (fused (J, 3), weight (J,), used (S, J) bool). ``weight`` is the
    sum of the confidences that entered the average: 0 where no view saw
    the joint, and the measurement "strength" for the Kalman filter.
    """
    positions = np.asarray(positions, dtype=float)
    conf = np.asarray(conf, dtype=float)
    used = conf > 0
    n = used.sum(axis=0)  # (J,)
    if positions.shape[0] >= 2:
        if (n >= 3).any():
            used &= ~_median_outliers(positions, used, n, outlier_m)
        two = n == 2
        if two.any():
            used &= ~_pair_outliers(positions, conf, used, two, outlier_m)
    w = np.where(used, conf, 0.0)
    weight = w.sum(axis=0)
    safe = np.where(weight > 0, weight, 1.0)
    fused = np.einsum("sj,sjk->jk", w, positions) / safe[:, None]
    fused[weight == 0] = 0.0
    return fused, weight, used


def _median_outliers(positions: np.ndarray, used: np.ndarray, n: np.ndarray,
                     outlier_m: float) -> np.ndarray:
    masked = np.where(used[..., None], positions, np.nan)
    median = _nan_median(masked, n)                         # (J, 3)
    dist = np.sqrt(((positions - median[None]) ** 2).sum(axis=2))  # (S, J)
    dist_masked = np.where(used, dist, np.nan)
    spread = _nan_median(dist_masked, n)                    # (J,)
    return used & (n >= 3)[None] & (dist > spread[None] + outlier_m)


def _nan_median(values: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN, given the count ``n`` of non-NaN per column.

    np.nanmedian is an order of magnitude slower on these small arrays.
    """
    ordered = np.sort(values, axis=0)  # NaN sort last
    cols = np.arange(values.shape[1])
    lo = np.maximum((n - 1) // 2, 0)
    hi = np.maximum(n // 2, 0)
    return 0.5 * (ordered[lo, cols] + ordered[hi, cols])


def _pair_outliers(positions: np.ndarray, conf: np.ndarray, used: np.ndarray, two: np.ndarray,
                   outlier_m: float) -> np.ndarray:
    """For joints seen by exactly two views that disagree, drop the less confident view."""
    cols = np.flatnonzero(two)
    first = np.argmax(used[:, cols], axis=0)
    last = used.shape[0] - 1 - np.argmax(used[::-1, cols], axis=0)
    gap = np.sqrt(((positions[first, cols] - positions[last, cols]) ** 2).sum(axis=1))
    cf, cl = conf[first, cols], conf[last, cols]
    disagree = gap > 2 * outlier_m
    drop = np.zeros_like(used)
    lose_first = disagree & (cf < cl)
    lose_last = disagree & (cl < cf)
    drop[first[lose_first], cols[lose_first]] = True
    drop[last[lose_last], cols[lose_last]] = True
    return drop


def vote_hand(states: list[HandState], weights: list[float] | None = None) -> HandState:
    """The hand state seen by most sensors; a tie goes to the higher code.

    Only open, closed and lasso vote. With ``weights`` (e.g. the hand joint's
    confidence per sensor) the vote is weighted. With no voter the result is
    NOT_TRACKED if any sensor said so, else UNKNOWN.
    """
    tally = [0.0] * 5
    for k, state in enumerate(states):
        if state >= HandState.OPEN:
            tally[state] += 1.0 if weights is None else float(weights[k])
    best = max(range(2, 5), key=lambda code: (tally[code], code))
    if tally[best] > 0:
        return HandState(best)
    if HandState.NOT_TRACKED in states:
        return HandState.NOT_TRACKED
    return HandState.UNKNOWN


def torso_centre(joints: np.ndarray, conf: np.ndarray) -> np.ndarray | None:
    """Mean of the tracked torso joints (3,), or of all tracked joints; None if none."""
    mask = conf[list(TORSO)] > 0
    if mask.any():
        return joints[list(TORSO)][mask].mean(axis=0)
    mask = conf > 0
    if mask.any():
        return joints[mask].mean(axis=0)
    return None


def apply_transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 homogeneous transform to (..., 3) points."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]
