"""Seed 002's calibration from successive hip-centre positions (3 passes).

The streamer's method: store 500 positions of the hip centre (SpineBase)
seen by both sensors, then

1. yaw: the normalised directions between successive positions, projected
   on the floor plane (x-z here; y is up), give one rotation each between
   the two sensors; accumulated and averaged, they give the yaw;
2. pitch: with the directions rotated by that yaw (we bring the reference's
   into the sensor's yaw-corrected frame, so the pitch is the sensor's own
   tilt about its x axis, R = Ry(yaw) Rx(pitch), the way a Kinect is
   mounted), the y-z projections accumulated the same way give the pitch;
3. translation: the mean difference between the reference's positions and
   the rotated sensor's positions.

Roll is not solved: the author found it made noisy data worse. So the
method is exact only for sensors that differ by yaw, pitch and position.

Where the seed is silent: "successive" positions are taken at least
``min_step_m`` apart along the path (frame-to-frame steps of a walking
person, ~3 cm, are mostly sensor noise); the rotations are accumulated as
sums of the 2-D cross and dot products of the projected unit directions,
so a direction that is nearly perpendicular to the plane counts little.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import CalibrationError
from ...geometry import matrix, rot_x, rot_y
from ..pairs import SPINE_BASE, PairSet


def fit_trajectory(pairs: PairSet, samples: int = 500, min_step_m: float = 0.10,
                   ) -> tuple[np.ndarray, dict[str, Any], None]:
    seen = pairs.weight[:, SPINE_BASE] > 0
    ref = pairs.ref[seen, SPINE_BASE][-samples:]
    other = pairs.other[seen, SPINE_BASE][-samples:]
    if len(ref) < 10:
        raise CalibrationError(f"trajectory: only {len(ref)} hip-centre positions; need a walk "
                               f"({samples} recommended)")
    keep = [0]
    for k in range(1, len(ref)):
        if np.linalg.norm(ref[k] - ref[keep[-1]]) >= min_step_m:
            keep.append(k)
    if len(keep) < 4:
        raise CalibrationError("trajectory: the person hardly moved; walk across the shared "
                               "area while calibrating")
    d_ref = _unit(np.diff(ref[keep], axis=0))
    d_oth = _unit(np.diff(other[keep], axis=0))
    # pass 1, yaw about y: maximise sum b . Ry(a) a on the x-z projections
    cross = d_ref[:, 0] * d_oth[:, 2] - d_ref[:, 2] * d_oth[:, 0]
    dot = d_ref[:, 0] * d_oth[:, 0] + d_ref[:, 2] * d_oth[:, 2]
    yaw = float(np.arctan2(cross.sum(), dot.sum()))
    # pass 2, pitch about the sensor's own x axis: the reference's directions are
    # brought into the sensor's yaw-corrected frame, then compared on y-z projections
    e = d_ref @ rot_y(yaw)  # rows: Ry(yaw)^T d
    cross = e[:, 2] * d_oth[:, 1] - e[:, 1] * d_oth[:, 2]
    dot = e[:, 1] * d_oth[:, 1] + e[:, 2] * d_oth[:, 2]
    pitch = float(np.arctan2(cross.sum(), dot.sum()))
    r = rot_y(yaw) @ rot_x(pitch)
    # pass 3, translation: mean difference of all stored positions
    t = (ref - other @ r.T).mean(axis=0)
    return matrix(r, t), {"yaw_deg": float(np.degrees(yaw)), "pitch_deg": float(np.degrees(pitch)),
                          "positions": len(ref), "directions": len(keep) - 1}, None


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)
