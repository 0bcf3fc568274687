"""The paper's linear-regression calibration (K-Multiscope, section 3.2).

Per paired skeleton k, with the joints centred on each skeleton's centre of
gravity (V: the sensor's, V': the reference's, one joint per column)::

    A_k = V' V^T (V V^T)^-1,   b_k = mean' - A_k mean,   e_k = mean |A_k v + b_k - v'|^2

The estimates are averaged with weights 1 / e_k, A is rescaled so that
det(A) = 1 (the paper's fix for the Kinects' systematic scale bias), joint
pairs further apart than 10 cm after fitting are rejected and the whole
estimate is repeated on what is left. The result is affine, not rigid:
that is the paper's method, and why its fitness wanders (Figure 5).

Our choices where the paper is silent: joints are weighted by the product
of the two confidences inside each per-skeleton fit; b is recomputed over
all pairs after the rescaling (an averaged b would belong to the
un-rescaled A); a skeleton needs 6 joints and a non-degenerate V V^T.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import CalibrationError
from ...geometry import matrix
from ..pairs import PairSet


def fit_regression(pairs: PairSet, reject_m: float = 0.10, rounds: int = 3, min_joints: int = 6,
                   ) -> tuple[np.ndarray, dict[str, Any], np.ndarray]:
    p, q, w0 = pairs.other, pairs.ref, pairs.weight
    w = w0.copy()
    m = np.eye(4)
    used_rounds = 0
    for used_rounds in range(1, rounds + 1):
        a, b_unused, skeletons = _average_affine(p, q, w, min_joints)
        det = float(np.linalg.det(a))
        if det <= 0:
            raise CalibrationError("regression: the averaged matrix flips space (det <= 0); "
                                   "the skeletons do not constrain the rotation")
        a = a / np.cbrt(det)
        total = w.sum()
        b = ((q - p @ a.T) * w[..., None]).sum(axis=(0, 1)) / total
        m = matrix(a, b)
        r = np.linalg.norm(p @ a.T + b - q, axis=-1)
        new_w = np.where(r <= reject_m, w0, 0.0)
        if np.array_equal(new_w > 0, w > 0) or (new_w > 0).sum() < 0.5 * (w0 > 0).sum():
            break  # converged, or rejection would throw away most of the data
        w = new_w
    details = {"rounds": used_rounds, "skeletons": skeletons,
               "kept": float((w > 0).sum() / max((w0 > 0).sum(), 1)),
               "det_before_rescale": det}
    return m, details, w


def _average_affine(p: np.ndarray, q: np.ndarray, w: np.ndarray, min_joints: int,
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-skeleton affine fits, averaged with weights 1/e_k (vectorised over skeletons)."""
    n_joints = (w > 0).sum(axis=1)
    total = w.sum(axis=1)
    ok = n_joints >= min_joints
    if not ok.any():
        raise CalibrationError(f"regression: no paired skeleton has {min_joints} joints in common")
    p, q, w, total = p[ok], q[ok], w[ok], total[ok]
    pbar = np.einsum("nj,njk->nk", w, p) / total[:, None]
    qbar = np.einsum("nj,njk->nk", w, q) / total[:, None]
    pc, qc = p - pbar[:, None], q - qbar[:, None]
    vvt = np.einsum("nj,nja,njb->nab", w, pc, pc)     # V V^T
    vpvt = np.einsum("nj,nja,njb->nab", w, qc, pc)    # V' V^T
    cond = np.linalg.cond(vvt)
    good = np.isfinite(cond) & (cond < 1e8)
    if not good.any():
        raise CalibrationError("regression: every skeleton is degenerate (flat or a point)")
    # A = V'V^T (V V^T)^-1  <=>  (V V^T) A^T = (V'V^T)^T, V V^T symmetric
    a = np.transpose(np.linalg.solve(vvt[good], np.transpose(vpvt[good], (0, 2, 1))), (0, 2, 1))
    b = qbar[good] - np.einsum("nij,nj->ni", a, pbar[good])
    resid = np.einsum("nij,nkj->nki", a, p[good]) + b[:, None] - q[good]
    err = (w[good] * (resid ** 2).sum(axis=2)).sum(axis=1) / total[good]
    inv = 1.0 / np.maximum(err, 1e-10)
    a_avg = np.einsum("n,nij->ij", inv, a) / inv.sum()
    b_avg = inv @ b / inv.sum()
    return a_avg, b_avg, int(good.sum())
