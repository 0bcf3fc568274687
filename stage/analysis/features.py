"""Body features: joint angles, distances, height, lean, centre of mass, speeds, motion.

Pure functions over one skeleton (``joints``: (25, 3) metres, stage space,
y up; or (N, 25, 3) for N frames, NaN where a joint is missing), and
``FeatureTracker``, which follows one body frame by frame for the features
that need time (joint speed and acceleration, centre-of-mass speed, quantity
of motion over a window). Pieces use ``angle_at``; views, reports and the
command line use the rest.

Joint angles are the angle between the two segments that meet at the joint,
each taken from the joint outwards, in degrees (seed 004: the angle "is
calculated as the scalar product between the segments (links) that connect
at a given joint"). At the shoulder and the hip the second segment is the
trunk (SpineShoulder to SpineBase), so the readings are the usual ones:

========  =================================  ==================================
joint     segments                           reads
========  =================================  ==================================
elbow     elbow->shoulder, elbow->wrist      180 straight arm, 90 forearm square
knee      knee->hip, knee->ankle             180 straight leg
shoulder  shoulder->elbow, trunk downwards   0 arm hanging, 90 level, 180 overhead
hip       hip->knee, trunk upwards           180 standing, about 90 sitting
========  =================================  ==================================
"""

from __future__ import annotations

import math
import warnings
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..joints import JOINT_INDEX as J
from ..joints import N_JOINTS

#: joint name -> the two segments whose angle is read there, each (from joint, to joint)
ANGLES: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {}
for _side in ("Left", "Right"):
    _down = (J["SpineShoulder"], J["SpineBase"])
    ANGLES["Elbow" + _side] = ((J["Elbow" + _side], J["Shoulder" + _side]),
                               (J["Elbow" + _side], J["Wrist" + _side]))
    ANGLES["Knee" + _side] = ((J["Knee" + _side], J["Hip" + _side]),
                              (J["Knee" + _side], J["Ankle" + _side]))
    ANGLES["Shoulder" + _side] = ((J["Shoulder" + _side], J["Elbow" + _side]), _down)
    ANGLES["Hip" + _side] = ((J["Hip" + _side], J["Knee" + _side]), _down[::-1])
#: joint index -> its angle's segments, for callers that hold indices (pieces)
ANGLE_BY_INDEX: dict[int, tuple[tuple[int, int], tuple[int, int]]] = {
    J[name]: segs for name, segs in ANGLES.items()}
#: the joints a segment of each angle needs
ANGLE_JOINTS: dict[int, tuple[int, ...]] = {
    j: tuple(sorted({*a, *b})) for j, (a, b) in ANGLE_BY_INDEX.items()}

# Segment masses (fraction of body mass) and centre positions (fraction from the
# proximal end) after Winter's anthropometric table (D. A. Winter, Biomechanics and
# Motor Control of Human Movement, table 4.1, from Dempster's cadaver data).
_SEGMENTS: list[tuple[float, int, int, float]] = [
    (0.081, J["Neck"], J["Head"], 1.0),                 # head and neck: at the head joint
    (0.497, J["SpineShoulder"], J["SpineBase"], 0.5),   # trunk (thorax + abdomen + pelvis)
]
for _side in ("Left", "Right"):
    _SEGMENTS += [
        (0.028, J["Shoulder" + _side], J["Elbow" + _side], 0.436),   # upper arm
        (0.016, J["Elbow" + _side], J["Wrist" + _side], 0.430),      # forearm
        (0.006, J["Wrist" + _side], J["Hand" + _side], 0.506),       # hand
        (0.100, J["Hip" + _side], J["Knee" + _side], 0.433),         # thigh
        (0.0465, J["Knee" + _side], J["Ankle" + _side], 0.433),      # shank
        (0.0145, J["Ankle" + _side], J["Foot" + _side], 0.50),       # foot
    ]
_MASS = np.array([s[0] for s in _SEGMENTS])
_PROX = np.array([s[1] for s in _SEGMENTS])
_DIST = np.array([s[2] for s in _SEGMENTS])
_FRAC = np.array([s[3] for s in _SEGMENTS])
_FEET = [J[n] for n in ("AnkleLeft", "AnkleRight", "FootLeft", "FootRight")]
_TORSO = [J["SpineBase"], J["SpineShoulder"]]


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors ``a`` and ``b`` (..., 3), degrees; NaN where either is zero/NaN.

    atan2 of the cross and dot products: exact near 0 and 180 degrees, where arccos is not.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.einsum("...k,...k->...", a, b)
    with np.errstate(invalid="ignore"):
        return np.where((na > 1e-9) & (nb > 1e-9), np.degrees(np.arctan2(cross, dot)), np.nan)


def joint_angle(joints: np.ndarray, name: str) -> np.ndarray:
    """The angle at joint ``name`` (a key of ``ANGLES``), degrees: () for one skeleton, (N,)."""
    if name not in ANGLES:
        raise KeyError(f"no angle is defined at '{name}' (angles: {', '.join(ANGLES)})")
    (a0, a1), (b0, b1) = ANGLES[name]
    joints = np.asarray(joints, float)
    return angle_between(joints[..., a1, :] - joints[..., a0, :],
                         joints[..., b1, :] - joints[..., b0, :])


def joint_angles(joints: np.ndarray) -> dict[str, np.ndarray]:
    """Every angle of ``ANGLES`` for one skeleton (floats) or N frames ((N,) arrays), degrees."""
    return {name: joint_angle(joints, name) for name in ANGLES}


def angle_at(points: dict[int, tuple[float, float, float] | None], joint: int) -> float | None:
    """The angle at ``joint`` (an index of ``ANGLE_BY_INDEX``) from a few known points.

    ``points``: joint index -> (x, y, z) or None when unseen. None when a
    joint the angle needs is unseen (a piece then holds its last value).
    """
    (a0, a1), (b0, b1) = ANGLE_BY_INDEX[joint]
    p = [points.get(k) for k in (a0, a1, b0, b1)]
    if any(q is None for q in p):
        return None
    ux, uy, uz = p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]
    vx, vy, vz = p[3][0] - p[2][0], p[3][1] - p[2][1], p[3][2] - p[2][2]
    if ux * ux + uy * uy + uz * uz < 1e-18 or vx * vx + vy * vy + vz * vz < 1e-18:
        return None
    cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    return math.degrees(math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz),
                                   ux * vx + uy * vy + uz * vz))


def distance(joints: np.ndarray, a: str, b: str) -> np.ndarray:
    """Distance between joints ``a`` and ``b`` (names), metres: () or (N,)."""
    joints = np.asarray(joints, float)
    return np.linalg.norm(joints[..., J[a], :] - joints[..., J[b], :], axis=-1)


def hand_distances(joints: np.ndarray) -> dict[str, np.ndarray]:
    """hand_to_hand, hand_left_to_head, hand_right_to_head (metres)."""
    return {"hand_to_hand": distance(joints, "HandLeft", "HandRight"),
            "hand_left_to_head": distance(joints, "HandLeft", "Head"),
            "hand_right_to_head": distance(joints, "HandRight", "Head")}


def body_height(joints: np.ndarray) -> np.ndarray:
    """How tall the body is now: the head above the lower foot (metres; lower when crouching).

    The Head joint is the middle of the head, so a standing 1.75 m person
    reads about 1.6 m.
    """
    joints = np.asarray(joints, float)
    feet = joints[..., _FEET, 1]
    with np.errstate(all="ignore"):
        low = np.nanmin(np.where(np.isnan(feet), np.inf, feet), axis=-1)
    low = np.where(np.isfinite(low), low, np.nan)
    return joints[..., J["Head"], 1] - low


def facing(joints: np.ndarray) -> np.ndarray:
    """Unit horizontal facing direction (..., 3): the left-hip direction turned a quarter right."""
    joints = np.asarray(joints, float)
    left = (joints[..., J["HipLeft"], :] - joints[..., J["HipRight"], :]
            + joints[..., J["ShoulderLeft"], :] - joints[..., J["ShoulderRight"], :])
    f = np.stack([-left[..., 2], np.zeros(left.shape[:-1]), left[..., 0]], axis=-1)
    n = np.linalg.norm(f, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 1e-9, f / n, np.nan)


def lean(joints: np.ndarray) -> dict[str, np.ndarray]:
    """Trunk lean (SpineBase to SpineShoulder) from vertical, degrees.

    ``lean``: total tilt (0 upright); ``lean_forward``: towards the facing
    direction (negative: backwards); ``lean_side``: towards the body's left
    (negative: right).
    """
    joints = np.asarray(joints, float)
    trunk = joints[..., J["SpineShoulder"], :] - joints[..., J["SpineBase"], :]
    f = facing(joints)
    left = np.stack([f[..., 2], np.zeros(f.shape[:-1]), -f[..., 0]], axis=-1)
    up = trunk[..., 1]
    return {"lean": angle_between(trunk, np.broadcast_to([0.0, 1.0, 0.0], trunk.shape)),
            "lean_forward": np.degrees(np.arctan2(np.einsum("...k,...k->...", trunk, f), up)),
            "lean_side": np.degrees(np.arctan2(np.einsum("...k,...k->...", trunk, left), up))}


def centre_of_mass(joints: np.ndarray) -> np.ndarray:
    """Whole-body centre of mass (..., 3), metres, from 14 segments (Winter's table).

    Segments with a missing end are left out and the rest re-weighted.
    """
    joints = np.asarray(joints, float)
    prox, dist = joints[..., _PROX, :], joints[..., _DIST, :]
    centres = prox + _FRAC[:, None] * (dist - prox)
    ok = np.isfinite(centres).all(axis=-1)
    w = np.where(ok, _MASS, 0.0)
    total = w.sum(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.einsum("...s,...sk->...k", w, np.nan_to_num(centres)) / \
            np.where(total > 0, total, np.nan)


def snapshot(joints: np.ndarray) -> dict[str, float]:
    """The instantaneous features of one skeleton as a flat dict of floats (NaN unknown)."""
    out: dict[str, float] = {f"angle_{k}": float(v) for k, v in joint_angles(joints).items()}
    out.update({k: float(v) for k, v in hand_distances(joints).items()})
    out["height"] = float(body_height(joints))
    out.update({k: float(v) for k, v in lean(joints).items()})
    com = centre_of_mass(joints)
    out.update(com_x=float(com[0]), com_y=float(com[1]), com_z=float(com[2]))
    return out


@dataclass
class Features:
    """One body's features at time ``t`` (see ``FeatureTracker.update``)."""

    t: float
    values: dict[str, float]               # snapshot() + speeds, CoM speed, quantity of motion
    speed: np.ndarray                      # (25,) m/s per joint (NaN unknown)
    acceleration: np.ndarray               # (25,) m/s^2 per joint (NaN unknown)

    def __getitem__(self, key: str) -> float:
        return self.values[key]


class FeatureTracker:
    """Follows one body frame by frame: the features that need time.

    ``update(t, joints, conf)`` with stage-space joints (25, 3) and their
    confidences (joints below ``min_conf`` count as unseen). Speeds are
    backward differences of positions; a frame closer than ``min_dt`` seconds
    to the last one used only refreshes the instantaneous features (so a
    fused stream at uneven intervals does not make speeds jump).
    Acceleration is the change of velocity between successive speeds;
    quantity of motion is the mean joint speed over the last ``window``
    seconds (m/s: 0 for a still body).
    """

    def __init__(self, window: float = 1.0, min_conf: float = 0.5,
                 min_dt: float = 1.0 / 40.0) -> None:
        self.window, self.min_conf, self.min_dt = window, min_conf, min_dt
        self._t: float | None = None
        self._joints: np.ndarray | None = None
        self._vel: np.ndarray | None = None
        self._com: np.ndarray | None = None
        self._motion: deque[tuple[float, float]] = deque()
        self._timed = {"com_speed": math.nan, "com_speed_horizontal": math.nan,
                       "quantity_of_motion": math.nan}
        self._speed = np.full(N_JOINTS, np.nan)
        self._accel = np.full(N_JOINTS, np.nan)

    def update(self, t: float, joints: np.ndarray, conf: np.ndarray | None = None) -> Features:
        joints = np.array(joints, dtype=float)
        if conf is not None:
            joints[np.asarray(conf) < self.min_conf] = np.nan
        values = snapshot(joints)
        if self._t is not None and t - self._t < self.min_dt:
            return Features(t, {**values, **self._timed}, self._speed, self._accel)
        com = np.array([values["com_x"], values["com_y"], values["com_z"]])
        speed = np.full(N_JOINTS, np.nan)
        accel = np.full(N_JOINTS, np.nan)
        timed = {"com_speed": math.nan, "com_speed_horizontal": math.nan}
        if self._t is not None and self._joints is not None:
            dt = t - self._t
            vel = (joints - self._joints) / dt
            speed = np.linalg.norm(vel, axis=1)
            if self._vel is not None:
                accel = np.linalg.norm(vel - self._vel, axis=1) / dt
            self._vel = vel
            if self._com is not None:
                dc = (com - self._com) / dt
                timed = {"com_speed": float(np.linalg.norm(dc)),
                         "com_speed_horizontal": float(math.hypot(dc[0], dc[2]))}
            seen = np.isfinite(speed)
            if seen.any():
                self._motion.append((t, float(speed[seen].mean())))
        self._t, self._joints, self._com = t, joints, com
        while self._motion and self._motion[0][0] <= t - self.window:
            self._motion.popleft()
        timed["quantity_of_motion"] = (float(np.mean([m for _, m in self._motion]))
                                       if self._motion else math.nan)
        self._timed, self._speed, self._accel = timed, speed, accel
        return Features(t, {**values, **timed}, speed, accel)


def series(t: np.ndarray, joints: np.ndarray, window: float = 1.0) -> dict[str, np.ndarray]:
    """Features of a whole trajectory: (N,) arrays, plus joint speeds (N, 25) m/s.

    ``t`` (N,) seconds; ``joints`` (N, 25, 3) metres with NaN where missing.
    Speeds are central differences; quantity of motion is the mean joint speed
    over the ``window`` seconds up to each sample (as ``FeatureTracker``).
    """
    out: dict[str, np.ndarray] = {f"angle_{k}": v for k, v in joint_angles(joints).items()}
    out.update(hand_distances(joints))
    out["height"] = body_height(joints)
    out.update(lean(joints))
    com = centre_of_mass(joints)
    if len(t) >= 3:
        vel = np.gradient(joints, t, axis=0)
        dcom = np.gradient(com, t, axis=0)
    else:
        vel, dcom = np.full_like(joints, np.nan), np.full_like(com, np.nan)
    out["speed"] = np.linalg.norm(vel, axis=-1)
    out["com_speed"] = np.linalg.norm(dcom, axis=-1)
    out["com_speed_horizontal"] = np.hypot(dcom[:, 0], dcom[:, 2])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # a frame with no joint seen
        mean = np.nanmean(out["speed"], axis=1)
    ok = np.isfinite(mean)
    total = np.concatenate([[0.0], np.cumsum(np.where(ok, mean, 0.0))])
    count = np.concatenate([[0], np.cumsum(ok)])
    start = np.searchsorted(t, t - window, side="right")     # samples in (t - window, t]
    n = count[1:] - count[start]
    with np.errstate(invalid="ignore", divide="ignore"):
        out["quantity_of_motion"] = np.where(n > 0, (total[1:] - total[start]) / n, np.nan)
    return out
