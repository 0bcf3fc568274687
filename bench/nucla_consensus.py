"""A reference for calibrations of real N-UCLA takes: each subject's rig, agreed by its takes.

The brute-force optimum (``optimum.py``) judges a calibration on the take it came from, and a
take that does not determine its rig fools it the same way it fools the product (stop 23: a
rotation tens of degrees wrong can fit a 1-2 s Kinect v1 take about as well as the right one).
This module gives a reference that does not come from the take being judged.

N-UCLA filmed every take of one subject with the three Kinects left where they were: the
pairwise fits of one subject's takes cluster tightly (s01: v1 -> v3 yawed 75-88 degrees with
the translation within ~10 cm on 27 of its 51 takes; s04: 76-92 degrees, the same), while the
rest scatter over tens of degrees, copies aside. So for each subject and pair of views, every
take's fit (the brute-force optimum, written independently of ``stage.calibration``) is a vote,
and the subject's rig is the robust centre of the votes **without the take being judged**
(leave one out): the medoid (the fit with most others within ``AGREE_M``), then the mean of the
fits that agree with it. A calibration is then judged by how far it moves points where people
stand (``POINTS``: a 2 x 1.6 x 2 m box 2-4 m in front of the sensor) from where the reference
puts them, and by the angle between the rotations.

What it does not see: a bias shared by every take of a subject (each view's skeleton sits a
few cm off the body in the same way in every take) is in the reference too. What it is good
for: telling a calibration that is right to within the takes' own scatter from one that is
wrong by tens of centimetres or degrees, which neither the median residual nor the optimum
can on short takes. ``scatter`` says how well the votes agree (the reference's own precision is
about scatter / sqrt(votes)).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np

import optimum
from stage.geometry import nearest_rotation, rotation_angle_deg  # maths, not the calibration

#: where people stand in a sensor's view (its own camera space, metres; z forward)
POINTS = np.array([(x, y, z) for x in (-1.0, 0.0, 1.0) for y in (-0.8, 0.0, 0.8)
                   for z in (2.0, 3.0, 4.0)])
#: two fits agree when they put POINTS within this of each other (rms)
AGREE_M = 0.30
#: a subject's pair needs this many agreeing votes besides the judged take for a reference
MIN_VOTES = 4


def displacement(m1: np.ndarray, m2: np.ndarray, points: np.ndarray = POINTS) -> float:
    """Rms distance (m) between where two transforms of the same space put ``points``."""
    d = (points @ m1[:3, :3].T + m1[:3, 3]) - (points @ m2[:3, :3].T + m2[:3, 3])
    return float(np.sqrt((d * d).sum(axis=1).mean()))


def angle_deg(m1: np.ndarray, m2: np.ndarray) -> float:
    return rotation_angle_deg(m1, m2)


def mean_transform(ms: list[np.ndarray]) -> np.ndarray:
    """The chordal mean of the rotations (nearest rotation to their sum) and the mean translation."""
    out = np.eye(4)
    out[:3, :3] = nearest_rotation(sum(m[:3, :3] for m in ms))
    out[:3, 3] = np.mean([m[:3, 3] for m in ms], axis=0)
    return out


@dataclass
class Reference:
    matrix: np.ndarray   # b's space -> a's
    votes: int           # fits that agree with it (the judged take left out)
    of: int              # fits it was chosen from
    scatter_m: float     # rms displacement of the agreeing fits about it
    scatter_deg: float   # rms angle of the agreeing fits about it


def consensus(fits: dict[str, np.ndarray], leave_out: str | None = None) -> Reference | None:
    """The robust centre of one subject's per-take fits of one pair of views (sample -> 4x4),
    without ``leave_out``'s; None when fewer than ``MIN_VOTES`` fits agree."""
    ms = [m for s, m in sorted(fits.items()) if s != leave_out]
    if len(ms) < MIN_VOTES:
        return None
    d = np.array([[displacement(a, b) for b in ms] for a in ms])
    near = d <= AGREE_M
    k = int(np.lexsort((np.where(near, d, 0).sum(axis=1), -near.sum(axis=1)))[0])
    centre = mean_transform([m for m, ok in zip(ms, near[k]) if ok])
    for _ in range(3):  # re-centre on the fits that agree with the mean
        agree = [m for m in ms if displacement(m, centre) <= AGREE_M]
        if len(agree) < MIN_VOTES:
            return None
        centre = mean_transform(agree)
    scatter_m = float(np.sqrt(np.mean([displacement(m, centre) ** 2 for m in agree])))
    scatter_deg = float(np.sqrt(np.mean([angle_deg(m, centre) ** 2 for m in agree])))
    return Reference(centre, len(agree), len(ms), scatter_m, scatter_deg)


def subject_of(sample: str) -> str:
    return sample.split("_")[1]


def take_fits(found: list[tuple[str, list[str]]], load_view, copied, cache_path: str | None,
              hypotheses: int = 60, say=print) -> dict[tuple[str, int, int], dict[str, np.ndarray]]:
    """Every take's brute-force fit per (subject, view a, view b) -> {sample: b -> a (4x4)}.

    Views that are copies of each other (``copied``) give no vote. Cached in ``cache_path``
    (JSON; deterministic: seeded, numpy only)."""
    cache: dict = {}
    if cache_path and os.path.exists(cache_path):
        with open(cache_path, encoding="utf-8") as f:
            cache = json.load(f)
    out: dict[tuple[str, int, int], dict[str, np.ndarray]] = {}
    dirty = computed = 0
    for n, (sample, paths) in enumerate(found):
        views = None
        for i in range(3):
            for k in range(i + 1, 3):
                key = f"{sample}:{i + 1}:{k + 1}:{hypotheses}"
                if key not in cache:
                    if views is None:
                        views = [load_view(p) for p in paths]
                    if copied(views[i], views[k]) or copied(views[k], views[i]):
                        cache[key] = None
                    else:
                        best = optimum.optimum(views[i], views[k], hypotheses=hypotheses)
                        cache[key] = None if best is None else {
                            "matrix": best.matrix.tolist(), "median_m": best.median_m,
                            "lag_s": best.lag_s}
                    dirty += 1
                    computed += 1
                if cache[key] is not None:
                    out.setdefault((subject_of(sample), i + 1, k + 1), {})[sample] = \
                        np.array(cache[key]["matrix"])
        if cache_path and dirty and (dirty >= 30 or n == len(found) - 1):
            with open(cache_path + ".tmp", "w", encoding="utf-8") as f:
                json.dump(cache, f)
            os.replace(cache_path + ".tmp", cache_path)
            dirty = 0
        if computed and (n + 1) % 20 == 0:
            say(f"  reference fits: {n + 1}/{len(found)} takes")
    return out


__all__ = ["POINTS", "AGREE_M", "MIN_VOTES", "Reference", "consensus", "displacement",
           "angle_deg", "mean_transform", "take_fits", "subject_of"]
