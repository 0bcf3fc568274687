"""The one fitness formula every method, the monitor and the plots use.

For a transform ``M`` (sensor -> reference) and N paired joints
``(p_i, q_i)`` with weights ``w_i`` (the product of the two sensors'
confidences, so an inferred joint counts a quarter of a tracked one)::

    mse     = sum_i w_i |M p_i - q_i|^2 / sum_i w_i          (m^2)
    rms_m   = sqrt(mse)
    fitness = 1 / (1 + mse / SIGMA_M^2),   SIGMA_M = 0.10 m

so fitness is 1 for a perfect match, 0.5 when the joints are on average
10 cm apart (the paper's outlier distance, section 3.2), 0.92 for the 3 cm
two healthy Kinects typically disagree by, and tends to 0 for a wrong
calibration. The paper computes its GA fitness "via the mean squared error
between the two data sets" without giving the map to (0, 1]; this is ours.

``Moments`` holds weighted sufficient statistics of a pair set, so the
squared error of any affine map is exact in O(1) instead of O(N): the GA
scores a 200-strong population 250 times from them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import matrix, rot_y

#: Scale of the fitness map, metres (see module docstring).
SIGMA_M = 0.10


def fitness_from_mse(mse: np.ndarray | float) -> np.ndarray | float:
    """Mean squared distance (m^2) -> fitness in (0, 1]."""
    out = 1.0 / (1.0 + np.asarray(mse, dtype=float) / SIGMA_M ** 2)
    return out if out.ndim else float(out)


def mse_from_fitness(fitness: float) -> float:
    return (1.0 / fitness - 1.0) * SIGMA_M ** 2


@dataclass(frozen=True)
class Evaluation:
    mse: float       # m^2
    rms_m: float
    fitness: float
    weight: float    # sum of weights that entered


def evaluate_points(m: np.ndarray, p: np.ndarray, q: np.ndarray, w: np.ndarray) -> Evaluation:
    """Score ``m`` on paired points: p (..., 3) source space, q (..., 3) target, w (...)."""
    w = np.asarray(w, dtype=float)
    total = float(w.sum())
    if total <= 0:
        return Evaluation(float("nan"), float("nan"), float("nan"), 0.0)
    d = p @ m[:3, :3].T + m[:3, 3] - q
    sq = np.where(w > 0, (d * d).sum(axis=-1), 0.0)
    mse = float((w * sq).sum() / total)
    return Evaluation(mse, float(np.sqrt(mse)), float(fitness_from_mse(mse)), total)


def per_frame_fitness(m: np.ndarray, p: np.ndarray, q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Fitness of ``m`` on each frame separately: p, q (N, J, 3), w (N, J) -> (N,).

    The paper's Figure 5 plots this over time. Frames with no weight get NaN.
    """
    d = p @ m[:3, :3].T + m[:3, 3] - q
    sq = np.where(w > 0, (d * d).sum(axis=-1), 0.0)
    total = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mse = (w * sq).sum(axis=1) / total
    return np.where(total > 0, 1.0 / (1.0 + mse / SIGMA_M ** 2), np.nan)


@dataclass(frozen=True)
class Moments:
    """Weighted sufficient statistics of paired points (source p, target q).

    With centroids pbar, qbar and centred points, for any 3x3 ``A`` and
    translation ``t`` the weighted sum of squared errors is::

        sse = tr(A P A^T) + Sqq - 2 tr(A C^T) + W |A pbar + t - qbar|^2

    with P = sum w p~ p~^T, C = sum w q~ p~^T, Sqq = sum w |q~|^2.
    Centring first keeps the cancellation harmless in float64.
    """

    W: float
    pbar: np.ndarray   # (3,)
    qbar: np.ndarray   # (3,)
    P: np.ndarray      # (3, 3)
    C: np.ndarray      # (3, 3)
    Sqq: float

    @classmethod
    def of(cls, p: np.ndarray, q: np.ndarray, w: np.ndarray) -> "Moments":
        p = np.asarray(p, dtype=float).reshape(-1, 3)
        q = np.asarray(q, dtype=float).reshape(-1, 3)
        w = np.asarray(w, dtype=float).reshape(-1)
        keep = w > 0
        p, q, w = p[keep], q[keep], w[keep]
        total = float(w.sum())
        if total <= 0:
            raise ValueError("no weighted points")
        pbar = w @ p / total
        qbar = w @ q / total
        pc, qc = p - pbar, q - qbar
        return cls(total, pbar, qbar, (pc * w[:, None]).T @ pc, (qc * w[:, None]).T @ pc,
                   float(w @ (qc * qc).sum(axis=1)))

    def sse(self, a: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Weighted sum of squared errors of ``a`` (..., 3, 3), ``t`` (..., 3), vectorised."""
        quad = np.einsum("...ij,jk,...ik->...", a, self.P, a)
        cross = np.einsum("...ij,ij->...", a, self.C)
        u = np.einsum("...ij,j->...i", a, self.pbar) + t - self.qbar
        return quad + self.Sqq - 2.0 * cross + self.W * (u * u).sum(axis=-1)

    def mse(self, a: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.maximum(self.sse(a, t), 0.0) / self.W

    def mse_of(self, m: np.ndarray) -> float:
        return float(self.mse(m[:3, :3], m[:3, 3]))


def kabsch(m: Moments, planar: bool = False) -> np.ndarray:
    """The rigid 4x4 minimising the weighted squared error of the moments' pairs.

    planar: rotation about y only (sensors already level); the vertical
    offset is still solved.
    """
    if planar:
        r = rot_y(np.arctan2(m.C[0, 2] - m.C[2, 0], m.C[0, 0] + m.C[2, 2]))
    else:
        u, _, vt = np.linalg.svd(m.C)
        d = 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0  # a reflection is never a sensor pose
        r = u @ np.diag([1.0, 1.0, d]) @ vt
    return matrix(r, m.qbar - r @ m.pbar)
