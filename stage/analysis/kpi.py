"""Seed 004's body KPIs over a recording: amplitudes, speeds, angles, working envelope, fatigue.

Seed 004 lists, for a training session: "evolution of joint movement
amplitudes and velocities, position of joints, angles at joints, functional
working envelope (FWE), velocity of joints, rate of fatigue"; "the rate of
fatigue is calculated as the average difference in the joint movement
velocity in the first versus the last half of a training session", and "FWE
defines the volume generated using all possible points touched by a
considered body limb". Choices made here:

* amplitudes are measured in the body's own frame (origin SpineBase, x to
  the body's left, z the way it faces, y up), so walking across the room
  does not count as arm movement: per joint, the 5-95 percentile range
  along each body axis (metres) and their Euclidean norm;
* speeds are in stage space (what an audience sees move): mean and 95th
  percentile per joint (m/s);
* angles: the joint angles of ``features`` (degrees): mean, min, max and
  range (5-95 percentile);
* the working envelope of a limb end (hands, feet) is the volume of the
  convex hull of its body-frame positions (cubic metres, Qhull through
  scipy, which filterpy already requires);
* fatigue per joint: mean speed in the second half minus the first (m/s)
  and as a percentage of the first; negative means slowing down.
"""

from __future__ import annotations

import math

import numpy as np

from ..joints import JOINT_INDEX as J
from ..joints import JOINTS
from .features import ANGLES, facing, joint_angle
from .trajectory import Trajectory

LIMB_ENDS = ("HandLeft", "HandRight", "FootLeft", "FootRight")


def body_frame(joints: np.ndarray) -> np.ndarray:
    """(N, 25, 3) joints in each frame's body frame (x left, y up, z facing; origin SpineBase)."""
    f = facing(joints)                                   # (N, 3)
    f = _hold(f)
    left = np.stack([f[:, 2], np.zeros(len(f)), -f[:, 0]], axis=1)
    rel = joints - joints[:, J["SpineBase"]][:, None, :]
    return np.stack([np.einsum("njk,nk->nj", rel, left), rel[..., 1],
                     np.einsum("njk,nk->nj", rel, f)], axis=-1)


def _hold(f: np.ndarray) -> np.ndarray:
    """Facing directions with missing ones taken from the nearest known (or +z)."""
    ok = np.isfinite(f).all(axis=1)
    if not ok.any():
        return np.tile([0.0, 0.0, 1.0], (len(f), 1))
    idx = np.flatnonzero(ok)
    nearest = idx[np.clip(np.searchsorted(idx, np.arange(len(f))), 0, len(idx) - 1)]
    return f[nearest]


def hull_volume(points: np.ndarray) -> float:
    """Volume (m^3) of the convex hull of (M, 3) points; 0 when they span no volume."""
    p = points[np.isfinite(points).all(axis=1)]
    if len(p) < 4:
        return 0.0
    from scipy.spatial import ConvexHull, QhullError
    try:
        return float(ConvexHull(p).volume)
    except (QhullError, ValueError):
        return 0.0


def kpis(traj: Trajectory) -> dict:
    """Seed 004's KPIs of a trajectory (see the module notes for the definitions)."""
    t, joints = traj.t, traj.joints
    out: dict = {"duration_s": traj.duration, "samples": len(traj)}
    if len(traj) < 3:
        return out
    local = body_frame(joints)
    vel = np.gradient(joints, t, axis=0)
    speed = np.linalg.norm(vel, axis=-1)                 # (N, 25)
    half = t[0] + 0.5 * (t[-1] - t[0])
    first, second = t <= half, t > half
    per_joint = {}
    for j, name in enumerate(JOINTS):
        pos = local[:, j]
        ok = np.isfinite(pos).all(axis=1)
        s = speed[:, j]
        sok = np.isfinite(s)
        if ok.sum() < 3 or sok.sum() < 3:
            continue
        lo, hi = np.percentile(pos[ok], [5, 95], axis=0)
        rng = hi - lo
        a = float(np.nanmean(s[first])) if (first & sok).any() else math.nan
        b = float(np.nanmean(s[second])) if (second & sok).any() else math.nan
        per_joint[name] = {
            "amplitude_m": float(np.linalg.norm(rng)),
            "amplitude_lateral_m": float(rng[0]), "amplitude_vertical_m": float(rng[1]),
            "amplitude_forward_m": float(rng[2]),
            "speed_mean": float(np.nanmean(s)), "speed_p95": float(np.nanpercentile(s, 95)),
            "fatigue_delta": b - a,
            "fatigue_percent": 100.0 * (b - a) / a if a and math.isfinite(a) else math.nan}
    out["joints"] = per_joint
    angles = {}
    for name in ANGLES:
        v = joint_angle(joints, name)
        v = v[np.isfinite(v)]
        if len(v) < 3:
            continue
        lo, hi = np.percentile(v, [5, 95])
        angles[name] = {"mean": float(v.mean()), "min": float(v.min()), "max": float(v.max()),
                        "range": float(hi - lo)}
    out["angles"] = angles
    out["envelope_m3"] = {name: hull_volume(local[:, J[name]]) for name in LIMB_ENDS}
    hands = [per_joint[n] for n in ("HandLeft", "HandRight") if n in per_joint]
    if hands:
        out["hand_speed_mean"] = float(np.mean([h["speed_mean"] for h in hands]))
    moving = [p["fatigue_percent"] for p in per_joint.values()
              if math.isfinite(p["fatigue_percent"])]
    out["fatigue_percent_median"] = float(np.median(moving)) if moving else math.nan
    return out
