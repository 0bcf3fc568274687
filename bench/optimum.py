"""The yardstick for calibration benchmarks: a brute-force rigid-with-lag optimum.

Written independently of ``stage.calibration`` (numpy only), so the figures
it gives are an outside reference for what the product finds:

- every lag on a grid (one frame apart over +-``max_lag_s``, then a tenth of
  a frame apart around the three best), the other view read at ``t + lag``
  by linear interpolation between its two frames around that instant;
- for each lag, the rigid transform with the smallest MEDIAN joint residual,
  found by least median of squares: ``hypotheses`` random triples of joint
  pairs, each solved in closed form (Kabsch), the best by its median, then
  concentration steps (refit on the half of the joint pairs nearest to the
  fit, as long as the median drops);
- lags whose overlap covers less than ``min_overlap`` of the shorter view are
  not considered (a few frames at the edge of the window would otherwise fit
  anything).

Frames are (T, J, 3) arrays at ``fps``; a joint at exactly (0, 0, 0) is
missing (the N-UCLA convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Optimum:
    lag_s: float
    matrix: np.ndarray      # (4, 4) other -> ref
    median_m: float         # median joint residual at the optimum
    rms_m: float            # rms of the same residuals (plain, all joint pairs)
    frames: int             # paired frames at that lag
    joints: int             # joint pairs


def pair(ref: np.ndarray, other: np.ndarray, lag_s: float, fps: float = 30.0,
         ) -> tuple[np.ndarray, np.ndarray, int]:
    """Joint pairs (p_other (n, 3), q_ref (n, 3)) at ``lag_s`` and the paired frame count."""
    pos = np.arange(len(ref)) + lag_s * fps       # fractional index into other
    ok = (pos >= -1e-9) & (pos <= len(other) - 1 + 1e-9)
    pos = np.clip(pos, 0, len(other) - 1)
    i0 = np.floor(pos).astype(int)
    frames = np.flatnonzero(ok)
    if not len(frames):
        return np.zeros((0, 3)), np.zeros((0, 3)), 0
    a = (pos[frames] - i0[frames])[:, None, None]
    lo = other[i0[frames]]
    hi = other[np.minimum(i0[frames] + 1, len(other) - 1)]
    o = (1 - a) * lo + a * hi
    r = ref[frames]
    valid = (np.abs(r).sum(-1) > 0) & (np.abs(lo).sum(-1) > 0) & (np.abs(hi).sum(-1) > 0)
    return o[valid], r[valid], len(frames)


def kabsch(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(..., n, 3) -> (..., 4, 4) the least-squares rigid map p -> q."""
    pbar, qbar = p.mean(axis=-2), q.mean(axis=-2)
    c = np.einsum("...ni,...nj->...ij", q - qbar[..., None, :], p - pbar[..., None, :])
    u, _, vt = np.linalg.svd(c)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    r = u @ vt
    m = np.zeros(r.shape[:-2] + (4, 4))
    m[..., :3, :3] = r
    m[..., :3, 3] = qbar - np.einsum("...ij,...j->...i", r, pbar)
    m[..., 3, 3] = 1.0
    return m


def residuals(m: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p @ m[:3, :3].T + m[:3, 3] - q, axis=-1)


def lmeds(p: np.ndarray, q: np.ndarray, hypotheses: int = 400, seed: int = 0,
          ) -> tuple[np.ndarray, float]:
    """The rigid map with the smallest median residual (see the module docstring)."""
    rng = np.random.default_rng(seed)
    n = len(p)
    pick = rng.integers(0, n, size=(hypotheses, 3))
    ms = kabsch(p[pick], q[pick])
    res = np.linalg.norm(np.einsum("kij,nj->kni", ms[:, :3, :3], p) + ms[:, None, :3, 3] - q,
                         axis=-1)
    med = np.median(res, axis=1)
    k = int(np.argmin(med))
    best, best_med = ms[k], float(med[k])
    # also the plain least-squares fit as a starting point
    for m in (best, kabsch(p, q)):
        cur, cur_med = m, float(np.median(residuals(m, p, q)))
        for _ in range(50):
            r = residuals(cur, p, q)
            keep = np.argsort(r)[: n // 2 + 1]
            new = kabsch(p[keep], q[keep])
            new_med = float(np.median(residuals(new, p, q)))
            if new_med >= cur_med - 1e-9:
                break
            cur, cur_med = new, new_med
        if cur_med < best_med:
            best, best_med = cur, cur_med
    return best, best_med


def optimum(ref: np.ndarray, other: np.ndarray, fps: float = 30.0, max_lag_s: float = 1.0,
            min_overlap: float = 0.6, hypotheses: int = 400, seed: int = 0) -> Optimum | None:
    """Brute-force rigid-with-lag optimum of ``other`` onto ``ref`` (see the module docstring)."""
    need = max(3, int(np.ceil(min_overlap * min(len(ref), len(other)))))
    step = 1.0 / fps

    def at(lag: float):
        p, q, frames = pair(ref, other, lag, fps)
        if frames < need or len(p) < 3 * need:
            return None
        m, med = lmeds(p, q, hypotheses, seed)
        return med, m, frames, p, q

    coarse = {}
    for lag in np.arange(-max_lag_s, max_lag_s + step / 2, step):
        found = at(float(lag))
        if found is not None:
            coarse[float(lag)] = found
    if not coarse:
        return None
    best_lags = sorted(coarse, key=lambda lag: coarse[lag][0])[:3]
    fine = dict(coarse)
    for centre in best_lags:
        for lag in np.arange(centre - step, centre + step + step / 20, step / 10):
            lag = float(round(lag, 9))
            if lag not in fine and abs(lag) <= max_lag_s + 1e-9:
                found = at(lag)
                if found is not None:
                    fine[lag] = found
    lag = min(fine, key=lambda k: fine[k][0])
    med, m, frames, p, q = fine[lag]
    r = residuals(m, p, q)
    return Optimum(lag, m, med, float(np.sqrt(np.mean(r * r))), frames, len(p))


def median_residual(m: np.ndarray, ref: np.ndarray, other: np.ndarray, lag_s: float,
                    fps: float = 30.0) -> tuple[float, float, int]:
    """(median, rms, paired frames) of a given transform and lag on the same pairing."""
    p, q, frames = pair(ref, other, lag_s, fps)
    if not len(p):
        return float("nan"), float("nan"), 0
    r = residuals(m, p, q)
    return float(np.median(r)), float(np.sqrt(np.mean(r * r))), frames
