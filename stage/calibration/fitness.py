"""The one fitness formula every method, the monitor, the gates and the plots use.

For a transform ``M`` (sensor -> reference) and N paired joints
``(p_i, q_i)`` with weights ``w_i`` (the product of the two sensors'
confidences, so an inferred joint counts a quarter of a tracked one), the
residuals are ``d_i = |M p_i - q_i|`` and::

    median_m = the weighted median of d_i                    (m)
    fitness  = 1 / (1 + (GAUSS_RMS_PER_MEDIAN * median_m)^2 / SIGMA_M^2)
    rms_m    = sqrt(sum_i w_i d_i^2 / sum_i w_i)              (reported, not judged)

The error scale is the weighted MEDIAN of the joint distances, not their
mean square: real Kinect skeletons have heavy tails (a limb swapped left for
right, a joint guessed 20 cm off, two views that see different sides of the
body), which put the rms of a good fit at 1.5-3.5 times its median, so a
mean-square fitness called good fits of real recordings poor. The median
ignores up to half of the joint pairs being wild, while a fit of two
different people or a moved sensor moves most joints and still scores low.
``GAUSS_RMS_PER_MEDIAN`` (1.1265: the rms / median of the length of a 3-D
isotropic Gaussian error) makes the scale equal to the rms when the errors
are Gaussian, so on clean data fitness is what it always was: 1 for a
perfect match, 0.5 when the joints are 10 cm apart in rms terms (the paper's
outlier distance, section 3.2), 0.92 for 3 cm, towards 0 for a wrong
calibration. The paper computes its GA fitness "via the mean squared error
between the two data sets" without giving the map to (0, 1]; the GA still
searches on that mean square (``Moments``), but every result is judged here.

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
#: rms / median of |e| for a 3-D isotropic Gaussian e (a Maxwell distribution): 1.7321 / 1.5382
GAUSS_RMS_PER_MEDIAN = 1.1265


def fitness_from_mse(mse: np.ndarray | float) -> np.ndarray | float:
    """A mean squared distance (m^2) -> fitness in (0, 1] (the GA's search objective)."""
    out = 1.0 / (1.0 + np.asarray(mse, dtype=float) / SIGMA_M ** 2)
    return out if out.ndim else float(out)


def fitness_from_median(median_m: np.ndarray | float) -> np.ndarray | float:
    """A median joint distance (m) -> fitness in (0, 1] (how every fit is judged)."""
    return fitness_from_mse((GAUSS_RMS_PER_MEDIAN * np.asarray(median_m, dtype=float)) ** 2)


def median_from_fitness(fitness: float) -> float:
    """The median joint distance (m) a fitness stands for (thresholds in words)."""
    return float(np.sqrt((1.0 / fitness - 1.0)) * SIGMA_M / GAUSS_RMS_PER_MEDIAN)


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The weighted median of ``x`` (any shape) with weights ``w`` >= 0; NaN if no weight.

    The smallest x whose cumulative weight reaches half the total (ties
    between two values are averaged, so equal weights give the usual median).
    """
    x, w = np.asarray(x, dtype=float).reshape(-1), np.asarray(w, dtype=float).reshape(-1)
    keep = w > 0
    if not keep.all():
        x, w = x[keep], w[keep]
    if not len(x):
        return float("nan")
    order = np.argsort(x, kind="stable")
    x, cum = x[order], np.cumsum(w[order])
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half - 1e-12 * cum[-1]))
    if abs(cum[k] - half) <= 1e-12 * cum[-1] and k + 1 < len(x):
        return float(0.5 * (x[k] + x[k + 1]))
    return float(x[k])


@dataclass(frozen=True)
class Evaluation:
    mse: float       # m^2, plain weighted mean square (tails included)
    rms_m: float     # sqrt(mse)
    median_m: float  # weighted median joint distance: the robust scale fitness is judged on
    fitness: float   # fitness_from_median(median_m)
    weight: float    # sum of weights that entered


def residuals(m: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """|M p - q| for paired points p, q (..., 3) -> (...) metres."""
    d = p @ m[:3, :3].T + m[:3, 3] - q
    return np.sqrt((d * d).sum(axis=-1))


def evaluate_points(m: np.ndarray, p: np.ndarray, q: np.ndarray, w: np.ndarray) -> Evaluation:
    """Score ``m`` on paired points: p (..., 3) source space, q (..., 3) target, w (...)."""
    w = np.asarray(w, dtype=float)
    total = float(w.sum())
    if total <= 0:
        return Evaluation(float("nan"), float("nan"), float("nan"), float("nan"), 0.0)
    r = np.where(w > 0, residuals(m, p, q), 0.0)
    mse = float((w * r * r).sum() / total)
    med = weighted_median(r, w)
    return Evaluation(mse, float(np.sqrt(mse)), med, float(fitness_from_median(med)), total)


def per_frame_fitness(m: np.ndarray, p: np.ndarray, q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Fitness of ``m`` on each frame separately: p, q (N, J, 3), w (N, J) -> (N,).

    The paper's Figure 5 plots this over time. Frames with no weight get NaN.
    """
    r = residuals(m, p, q)
    return np.array([fitness_from_median(weighted_median(r[k], w[k])) if (w[k] > 0).any()
                     else np.nan for k in range(len(r))])


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
        if not keep.all():   # (a copy only where some point has no weight)
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
