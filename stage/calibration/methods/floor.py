"""Seed 004's calibration: level each sensor with its floor plane, then 2-D.

1. Each sensor's space is rotated so the floor plane it reports becomes
   y = 0 (normal onto +y, lifted by the plane's d: the sensor height).
   The plane comes with our ``/floorPlane clientID a b c d`` extension
   (Kinect's FloorClipPlane; docs/osc-api.md).
2. With both sensors level, one rotation about y and a translation along
   the floor remain. The seed takes them from two and one chosen joints;
   here they are the weighted least-squares optimum over all joint pairs
   (a 2-D Kabsch), with one round of rejecting pairs more than 10 cm apart.
   The vertical offset stays 0: both floors are at y = 0 (the seed's
   assumption, and what makes the method immune to height bias).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import CalibrationError
from ..fitness import Moments, kabsch
from ...geometry import apply, invert, level_matrix, matrix
from ..pairs import PairSet


def fit_floor(pairs: PairSet, reject_m: float = 0.10,
              ) -> tuple[np.ndarray, dict[str, Any], np.ndarray]:
    if pairs.floor_ref is None or pairs.floor_other is None:
        missing = [sid for sid, f in ((pairs.ref_id, pairs.floor_ref),
                                      (pairs.other_id, pairs.floor_other)) if f is None]
        raise CalibrationError(f"floor: no /floorPlane from {' and '.join(missing)}; the floor "
                               "method needs both sensors' floor planes")
    lr, lo = level_matrix(pairs.floor_ref), level_matrix(pairs.floor_other)
    p, q = apply(lo, pairs.other), apply(lr, pairs.ref)
    w = pairs.weight
    m2 = _planar(p, q, w)
    r = np.linalg.norm(apply(m2, p) - q, axis=-1)
    kept = np.where(r <= reject_m, w, 0.0)
    if (kept > 0).sum() >= 0.5 * (w > 0).sum():
        m2 = _planar(p, q, kept)
        w = kept
    m = invert(lr) @ m2 @ lo
    tilt = [float(np.degrees(np.arccos(np.clip(abs(f[1]) / np.linalg.norm(f[:3]), 0, 1))))
            for f in (pairs.floor_ref, pairs.floor_other)]
    return m, {"tilt_ref_deg": tilt[0], "tilt_other_deg": tilt[1],
               "height_ref_m": float(pairs.floor_ref[3]),
               "height_other_m": float(pairs.floor_other[3])}, w


def _planar(p: np.ndarray, q: np.ndarray, w: np.ndarray) -> np.ndarray:
    if not (w > 0).any():
        raise CalibrationError("floor: no joint pairs to fit")
    m = kabsch(Moments.of(p, q, w), planar=True)
    return matrix(m[:3, :3], m[:3, 3] * np.array([1.0, 0.0, 1.0]))
