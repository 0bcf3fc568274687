"""Calibration methods: each turns a ``PairSet`` into a 4x4 transform.

Every method maps the ``other`` side onto the ``ref`` side and is judged the
same way (``fitness.evaluate_points`` over all joint pairs, confidence
weighted: fitness from the median joint distance), so their figures compare
directly:

- ``rigid``      closed-form least squares (Kabsch/Umeyama, SVD), weighted,
                 robust re-weighting (default) or RANSAC; the optimum.
- ``regression`` the paper's per-skeleton affine regression (section 3.2).
- ``ga``         the paper's genetic algorithm, 2-D: yaw + floor translation.
- ``ga3d``       the same with three angles and a 3-D translation.
- ``trajectory`` seed 002: yaw, then pitch, from hip-centre trajectories.
- ``floor``      seed 004: level with the floor planes, then 2-D fit.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ...errors import CalibrationError
from ..fitness import evaluate_points
from ..pairs import PairSet
from .floor import fit_floor
from .ga import fit_ga, fit_ga3d
from .regression import fit_regression
from .rigid import fit_rigid
from .trajectory import fit_trajectory


@dataclass
class CalibrationResult:
    """A transform from the sensor's space to the reference's, and how good it is."""

    matrix: np.ndarray        # (4, 4) other -> ref
    rms_m: float              # RMS joint distance after the transform, m (all pairs, weighted,
                              # tails included: what a least-squares method minimises)
    fitness: float            # from median_m (fitness.fitness_from_median), in (0, 1]
    method: str
    pairs: int                # paired frames used
    seconds: float = 0.0      # time the method took
    lag_s: float = 0.0
    details: dict[str, Any] = field(default_factory=dict)
    weight: np.ndarray | None = None  # (N, 25) weights the method ended with (robust ones)
    median_m: float = float("nan")    # weighted median joint distance, m: the robust residual


Method = Callable[..., tuple[np.ndarray, dict[str, Any], "np.ndarray | None"]]

METHODS: dict[str, Method] = {
    "rigid": fit_rigid,
    "regression": fit_regression,
    "ga": fit_ga,
    "ga3d": fit_ga3d,
    "trajectory": fit_trajectory,
    "floor": fit_floor,
}

#: Paired frames each method wants by default (seed 002 stores 500 hip positions).
DEFAULT_PAIRS: dict[str, int] = {"trajectory": 500}


def calibrate(pairs: PairSet, method: str = "rigid", **options: Any) -> CalibrationResult:
    """Run one method on a pair set; CalibrationError with a readable reason on failure."""
    fn = METHODS.get(method)
    if fn is None:
        raise CalibrationError(f"unknown method '{method}'; choose from {', '.join(METHODS)}")
    if len(pairs) < 3:
        raise CalibrationError(f"{pairs.other_id} -> {pairs.ref_id}: only {len(pairs)} paired "
                               "frames; need at least 3 (300 recommended)")
    start = time.perf_counter()
    m, details, weight = fn(pairs, **options)
    seconds = time.perf_counter() - start
    if not np.isfinite(m).all():
        raise CalibrationError(f"{method} produced no finite transform")
    ev = evaluate_points(m, pairs.other, pairs.ref, pairs.weight)
    return CalibrationResult(m, ev.rms_m, ev.fitness, method, len(pairs), seconds, pairs.lag_s,
                             details, weight, ev.median_m)


__all__ = ["CalibrationResult", "METHODS", "DEFAULT_PAIRS", "calibrate"]
