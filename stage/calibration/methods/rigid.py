"""The closed-form least-squares rigid transform (Kabsch/Umeyama by SVD).

For weighted pairs it is the exact minimiser of the weighted mean squared
error over all rotations and translations, the objective the GA searches
by evolution; so it is the default method and the GA's yardstick.
Outlier joints (a Kinect glitch, a limb snapping to the wrong place) are
handled by iteratively re-weighted least squares with Cauchy weights, or
by RANSAC on minimal triples followed by the same re-weighting; then
concentration steps (as FAST-LTS's C-steps, Rousseeuw and Van Driessen
2006) refit on the better half of the joint pairs as long as that lowers
their weighted median distance, the figure a fit is judged by (``fitness``):
on real N-UCLA pairs they bring the fit from 84 % to 90 % of pairs within
10 % of a brute-force least-median optimum (docs/calibration.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import CalibrationError
from ..fitness import kabsch, weighted_median
from ...geometry import yaw_matrices
from ..pairs import PairSet


def _batched_kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, n, 3) point sets -> K rotations (K, 3, 3) and translations (K, 3)."""
    pbar, qbar = p.mean(axis=1), q.mean(axis=1)
    c = np.einsum("kni,knj->kij", q - qbar[:, None], p - pbar[:, None])
    u, _, vt = np.linalg.svd(c)
    d = np.sign(np.linalg.det(u @ vt))
    d[d == 0] = 1.0
    u[:, :, 2] *= d[:, None]
    r = u @ vt
    return r, qbar - np.einsum("kij,kj->ki", r, pbar)


def fit_rigid(pairs: PairSet, robust: str = "irls", planar: bool = False, iterations: int = 20,
              ransac_iterations: int = 256, inlier_m: float = 0.10, seed: int = 0,
              concentrate: bool = True, starts: int = 4,
              ) -> tuple[np.ndarray, dict[str, Any], np.ndarray]:
    """Weighted rigid fit of ``pairs.other`` onto ``pairs.ref``.

    robust: "none" (plain weighted least squares), "irls" (Cauchy weights
    1 / (1 + (r/c)^2), c = max(2 x median residual, 2 cm), until the
    transform stops moving) or "ransac" (best of ``ransac_iterations``
    random triples by inlier weight within ``inlier_m``, then IRLS on the
    inliers). ``concentrate`` (robust fits): then concentration steps
    (``concentration_steps``), and the same from the ``starts`` best random joint triples
    (``_other_starts``), the lowest weighted median kept. Returns (matrix, details,
    final weights (N, 25)).
    """
    if robust not in ("none", "irls", "ransac"):
        raise CalibrationError(f"robust must be none, irls or ransac, not '{robust}'")
    w0 = pairs.weight
    p, q = pairs.other, pairs.ref
    details: dict[str, Any] = {"robust": robust}
    w = w0.copy()
    if robust == "ransac":
        w = w0 * _ransac_inliers(p, q, w0, ransac_iterations, inlier_m, seed, planar)
        details["ransac_inliers"] = float((w > 0).sum() / max((w0 > 0).sum(), 1))
    m = kabsch(pairs.moments(w), planar)
    if robust == "none":
        return m, details, w
    iterations_done = 0
    for iterations_done in range(1, iterations + 1):
        r = np.linalg.norm(p @ m[:3, :3].T + m[:3, 3] - q, axis=-1)
        c = max(2.0 * float(np.median(r[w > 0])), 0.02)
        robust_w = w * (1.0 / (1.0 + (r / c) ** 2))
        new = kabsch(pairs.moments(robust_w), planar)
        moved = float(np.abs(new - m).max())
        m = new
        if moved < 1e-7:
            break
    details["iterations"] = iterations_done
    details["cauchy_c_m"] = c
    if concentrate:
        m, steps, half = concentration_steps(pairs, m, planar)
        details["concentration_steps"] = steps
        if steps:  # the weights the final transform is the least-squares fit of
            robust_w = half
        if starts > 0:  # other starts: the least-median basin may not be the one IRLS is in
            found = _other_starts(pairs, m, planar, starts, seed)
            if found is not None:
                m, steps, robust_w = found
                details["concentration_steps"] = steps
                details["start"] = "random triple"
    return m, details, robust_w


def _other_starts(pairs: PairSet, m: np.ndarray, planar: bool, starts: int, seed: int,
                  hypotheses: int = 96) -> tuple[np.ndarray, int, np.ndarray] | None:
    """Concentration steps from the ``starts`` best of ``hypotheses`` random joint triples
    (least median of squares, as the benchmarks' brute-force optimum): (matrix, steps,
    weights) of the best if its weighted median is lower than ``m``'s, else None.

    Iteratively re-weighted least squares starts from the plain least-squares fit and
    descends into the nearest basin; on short real takes (1-2 s, heavy tails: a limb
    swapped, a side of the body seen differently) the lowest median is often in another
    one. On N-UCLA a 17-frame pair ended 28 % above the optimum's median from the IRLS
    start; see docs/calibration.md for what this changed."""
    w0, p, q = pairs.weight, pairs.other, pairs.ref
    flat = np.flatnonzero(w0.reshape(-1) > 0)
    if len(flat) < 12:
        return None
    pf, qf, wf = p.reshape(-1, 3)[flat], q.reshape(-1, 3)[flat], w0.reshape(-1)[flat]
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(flat), size=(hypotheses, 3), p=wf / wf.sum())
    ps, qs = pf[pick], qf[pick]
    area = np.linalg.norm(np.cross(ps[:, 1] - ps[:, 0], ps[:, 2] - ps[:, 0]), axis=1)
    keep = area > 0.01   # a triple spanning less than ~10 cm x 10 cm cannot fix a rotation
    if keep.sum() < starts:
        return None
    r, t = _batched_kabsch(ps[keep], qs[keep])
    if planar:
        r = yaw_matrices(np.arctan2(r[:, 0, 2] - r[:, 2, 0], r[:, 0, 0] + r[:, 2, 2]))
        t = qs[keep].mean(axis=1) - np.einsum("kij,kj->ki", r, ps[keep].mean(axis=1))
    # screened by the plain median (cheap), refined by the weighted one
    d = np.linalg.norm(np.einsum("kij,nj->kni", r, pf) + t[:, None] - qf, axis=-1)
    med = np.median(d, axis=1)
    best_med = weighted_median(np.linalg.norm(p @ m[:3, :3].T + m[:3, 3] - q, axis=-1), w0)
    best = None
    for k in np.argsort(med)[:starts]:
        start = np.eye(4)
        start[:3, :3], start[:3, 3] = r[k], t[k]
        # one step is always taken, so the result is the least-squares fit of its weights
        rk = np.linalg.norm(p @ start[:3, :3].T + start[:3, 3] - q, axis=-1)
        half = w0 * (rk <= weighted_median(rk, w0))
        if (half > 0).sum() < 3:
            continue
        mk, steps, used = concentration_steps(pairs, kabsch(pairs.moments(half), planar), planar)
        if not steps:
            used = half
        medk = weighted_median(np.linalg.norm(p @ mk[:3, :3].T + mk[:3, 3] - q, axis=-1), w0)
        if medk < best_med - 1e-6:
            best_med, best = medk, (mk, steps + 1, used)
    return best


def concentration_steps(pairs: PairSet, m: np.ndarray, planar: bool = False, steps: int = 20,
                 ) -> tuple[np.ndarray, int, np.ndarray]:
    """Refit on the joint pairs at or below the weighted median distance, while that median
    drops (each step is a weighted least-squares fit of the better half): (matrix, steps
    taken, the weights (N, 25) the matrix is the weighted least-squares fit of). Cauchy
    weights leave every far pair some pull; this ends on the criterion the fit is judged
    by, from a start near its optimum."""
    w0, p, q = pairs.weight, pairs.other, pairs.ref

    def median(mm: np.ndarray) -> tuple[float, np.ndarray]:
        r = np.linalg.norm(p @ mm[:3, :3].T + mm[:3, 3] - q, axis=-1)
        return weighted_median(r, w0), r

    best, r = median(m)
    done, used = 0, w0
    for done in range(steps):
        half = w0 * (r <= best)
        if (half > 0).sum() < 3:
            break
        new = kabsch(pairs.moments(half), planar)
        med, r_new = median(new)
        if not med < best - 1e-9:
            break
        m, best, r, used = new, med, r_new, half
    else:
        done = steps
    return m, done, used


def _ransac_inliers(p: np.ndarray, q: np.ndarray, w: np.ndarray, iterations: int,
                    inlier_m: float, seed: int, planar: bool) -> np.ndarray:
    """(N, 25) 0/1 mask of the inliers of the best random-triple hypothesis."""
    flat = np.flatnonzero(w.reshape(-1) > 0)
    if len(flat) < 3:
        raise CalibrationError("fewer than 3 joint pairs: nothing to fit")
    pf, qf = p.reshape(-1, 3)[flat], q.reshape(-1, 3)[flat]
    wf = w.reshape(-1)[flat]
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(flat), size=(iterations, 3), p=wf / wf.sum())
    ps, qs = pf[pick], qf[pick]
    # a triple spanning less than ~10 cm x 10 cm cannot fix a rotation
    area = np.linalg.norm(np.cross(ps[:, 1] - ps[:, 0], ps[:, 2] - ps[:, 0]), axis=1)
    keep = area > 0.01
    if not keep.any():
        raise CalibrationError("the joints are (nearly) collinear: rotation is undetermined")
    r, t = _batched_kabsch(ps[keep], qs[keep])
    if planar:  # project each hypothesis on a yaw (the data are level)
        r = yaw_matrices(np.arctan2(r[:, 0, 2] - r[:, 2, 0], r[:, 0, 0] + r[:, 2, 2]))
        t = qs[keep].mean(axis=1) - np.einsum("kij,kj->ki", r, ps[keep].mean(axis=1))
    best_score, best = -1.0, None
    for k in range(len(r)):  # one (n,3) product per hypothesis keeps memory flat
        d = np.linalg.norm(pf @ r[k].T + t[k] - qf, axis=1) <= inlier_m
        score = float(wf[d].sum())
        if score > best_score:
            best_score, best = score, d
    mask = np.zeros(w.size)
    mask[flat[best]] = 1.0
    return mask.reshape(w.shape)
