"""How well a rigid fit is determined by its own pairs: a bootstrap over distinct poses.

A pair set of ten frames of twenty joints is two hundred points in 3-D, and
whether they fix a rotation and a translation is a question the fit itself can
answer: refit on resampled data and look at how far the transform moves.

What is resampled matters. Real skeleton errors are not independent joint by
joint, nor frame by frame: a view that sees a person's back puts the hips and
shoulders a few cm away from one that sees the front, for as long as the person
stands that way; a swapped limb stays swapped while the limbs overlap. Frames of
one pose share their errors, so 300 frames of a person standing still say what
one frame says (a frame bootstrap would call that fit exact, and a closed-form
covariance from the joints' residuals would too). The units resampled are
therefore INDEPENDENT POSES (``pose_units``: frames grouped by the pose they are
within ``POSE_STEP_M`` of, as both sensors see it, on the fit's inlier joints, so
a sensor's glitch makes no new pose): each resample draws
that many poses with replacement, with all their frames, and refits by
concentration steps from the fit (the rigid method's last stage, so each refit
is the same estimator near the same optimum). From ``k`` poses the spread is
scaled by ``sqrt(k / (k - 1))`` (the bootstrap's variance of a mean is (k-1)/k
of the unbiased one), and fewer than ``MIN_UNITS`` poses give no estimate at all:
a spread over one or two independent units says nothing about the next one.

Reported (``Uncertainty``): the rms over resamples of the rotation angle between
each refit and the fit (degrees), and of the displacement each refit gives the
point at the stage's far edge (metres): ``edge_m`` from the sensor towards the
pairs' centre, where the rotation's error is multiplied by the longest lever a
performer can stand at. Both are compared with one tolerance, offline and live
(``coverage.Gates``: ``max_rot_deg``, ``max_far_m``).

The spread is the fit's PRECISION, not its accuracy: an error common to every
pose (a view-dependent bias) moves no resample. On the simulator, whose truth is
known, the true rotation error of 1.5-s fits is 3.5 times the spread (median), so
the spread may only refuse a fit, never vouch for one (docs/calibration.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ..geometry import nearest_rotation, rotation_angle_deg
from .coverage import POSE_STEP_M
from .fitness import weighted_median
from .methods.rigid import concentration_steps
from .pairs import PairSet

#: fewer independent poses than this give no estimate of a fit's spread
MIN_UNITS = 3
#: concentration steps per refit (each resample starts next to the fit's optimum)
STEPS = 10


@dataclass(frozen=True)
class Uncertainty:
    """The spread of a fit over pose-bootstrap resamples (see the module docstring)."""

    rot_deg: float          # rms rotation angle of refit vs fit, degrees (inf: no estimate)
    far_m: float            # rms displacement of the far-edge point, m (inf: no estimate)
    units: int              # distinct poses resampled
    resamples: int

    edge_m: float = 4.5     # where far_m is measured: this far from the sensor

    @property
    def determined(self) -> bool:
        return bool(np.isfinite(self.rot_deg))

    def text(self) -> str:
        if not self.determined:
            return (f"its spread cannot be measured: {self.units} independent pose"
                    f"{'' if self.units == 1 else 's'} (need {MIN_UNITS}; poses both sensors see "
                    "the body move to, 5 cm apart)")
        return (f"+-{self.rot_deg:.2f} deg, +-{self.far_m * 100:.1f} cm at {self.edge_m:g} m "
                f"from the sensor (bootstrap over {self.units} independent poses)")

    def as_json(self) -> dict:
        def r(v, n):
            return None if not np.isfinite(v) else round(float(v), n)
        return {"rot_deg": r(self.rot_deg, 3), "far_m": r(self.far_m, 4),
                "edge_m": self.edge_m, "independent_poses": self.units,
                "resamples": self.resamples}


def pose_units(other: np.ndarray, ref: np.ndarray, weight: np.ndarray,
               matrix: np.ndarray | None = None, step_m: float = POSE_STEP_M) -> np.ndarray:
    """Each frame's pose (n,) int, for frames of both sides (n, J, 3) with weights (n, J):
    greedily, a frame joins the nearest kept pose it is within ``step_m`` of, else starts a
    new one; -1 for a frame with no joint seen. The distance between two frames is the mean
    over the joints of how far each moved, taken in each sensor's own space, the smaller of
    the two (a new pose is one BOTH sensors see), and, given the fit ``matrix`` (other ->
    ref), only over the joints both frames have among the fit's inliers (at or below the
    weighted median joint distance: the half the fit rests on). A limb swapped or a joint
    guessed elsewhere is an outlier of the fit, so it makes no new pose even when both
    sensors err at once (feet together: both swap the legs), while an arm raised where both
    sensors see it does. With the mean over one view's joints, the simulator's realistic
    model turned 20 s of a person standing still into 11 "poses"."""
    seen = weight > 0
    if matrix is not None and seen.any():
        r = np.linalg.norm(other @ matrix[:3, :3].T + matrix[:3, 3] - ref, axis=-1)
        seen = seen & (r <= weighted_median(r, weight))
    kept: list[int] = []
    unit = np.full(len(other), -1)
    for k in range(len(other)):
        if not seen[k].any():
            continue
        if kept:
            both = seen[kept] & seen[k]
            n = both.sum(axis=1)
            dist = np.full(len(kept), np.inf)
            for side in (other, ref):
                d = np.linalg.norm(side[kept] - side[k], axis=-1)
                dist = np.minimum(dist, np.where(n > 0, (d * both).sum(axis=1) /
                                                 np.maximum(n, 1), np.inf))
            near = np.flatnonzero(dist < step_m)
            if len(near):
                unit[k] = int(near[np.argmin(dist[near])])
                continue
        unit[k] = len(kept)
        kept.append(k)
    return unit


def fit_uncertainty(pairs: PairSet, matrix: np.ndarray, edge_m: float = 4.5,
                    resamples: int = 100, seed: int = 0, by: str = "pose",
                    pause: Callable[[], None] | None = None) -> Uncertainty:
    """The spread of the rigid fit ``matrix`` (other -> ref) of ``pairs`` over a bootstrap
    of its distinct poses (module docstring). Deterministic for a seed. ``by="frame"``
    resamples single frames instead (for comparison only: it takes frames of one pose for
    independent evidence). ``pause``, if given, is called after every tenth refit (a live
    worker gives way to the engine there; the result does not depend on it)."""
    p, q, w = pairs.other, pairs.ref, pairs.weight
    # the spread is the rigid estimator's, near this fit: another method's transform (the
    # regression's is affine) is first taken to its nearest rigid one and concentrated
    rigid = np.eye(4)
    rigid[:3, :3], rigid[:3, 3] = nearest_rotation(matrix[:3, :3]), matrix[:3, 3]
    if (w > 0).sum() >= 3:
        rigid = concentration_steps(pairs, rigid, steps=STEPS)[0]
    matrix = rigid
    if by == "frame":
        unit = np.where((w > 0).any(axis=1), np.cumsum((w > 0).any(axis=1)) - 1, -1)
    else:
        unit = pose_units(p, q, w, matrix)
    k = int(unit.max()) + 1 if len(unit) else 0
    if k < MIN_UNITS:
        return Uncertainty(float("inf"), float("inf"), k, 0, edge_m)
    # the far-edge point, in the sensor's space: edge_m from it, towards the pairs' centre
    seen = w > 0
    centre = (p * seen[..., None]).sum(axis=(0, 1)) / max(seen.sum(), 1)
    far = centre / max(float(np.linalg.norm(centre)), 1e-6) * edge_m
    far_fit = matrix[:3, :3] @ far + matrix[:3, 3]
    rng = np.random.default_rng(seed)
    angles, shifts = [], []
    for i in range(resamples):
        if pause is not None and i and i % 10 == 0:
            pause()
        draw = np.bincount(rng.integers(k, size=k), minlength=k)
        mult = np.where(unit >= 0, draw[np.maximum(unit, 0)], 0)
        wb = w * mult[:, None]
        if (wb > 0).sum() < 3:
            continue
        mb = concentration_steps(replace(pairs, weight=wb), matrix, steps=STEPS)[0]
        angles.append(rotation_angle_deg(mb, matrix))
        shifts.append(float(np.linalg.norm(mb[:3, :3] @ far + mb[:3, 3] - far_fit)))
    if not angles:
        return Uncertainty(float("inf"), float("inf"), k, 0, edge_m)
    scale = np.sqrt(k / (k - 1))
    return Uncertainty(float(np.sqrt(np.mean(np.square(angles))) * scale),
                       float(np.sqrt(np.mean(np.square(shifts))) * scale), k, len(angles),
                       edge_m)


__all__ = ["Uncertainty", "fit_uncertainty", "pose_units", "MIN_UNITS"]
