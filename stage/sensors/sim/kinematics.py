"""A procedural 25-joint body: arms by angles or reaching a point, walking legs, crouch, jump.

The one synthetic body of stage: the simulator's performers, the demo and
every test or benchmark that needs a posed skeleton use it
(``standing_pose`` for a simple one).

Body frame: x to the performer's left, y up, z the way they face; metres;
feet on y = 0. Stage space: the body frame turned by ``heading`` about y
(0 faces +z, positive turns to the performer's left, i.e. counter-clockwise
seen from above) and placed at ``position``.

Arm angles (radians): ``elevation`` 0 hanging, pi/2 horizontal, pi overhead;
``azimuth`` 0 out to the side, pi/2 straight ahead (in between: diagonal);
``elbow`` 0 straight, pi/2 forearm at a right angle (bends forwards/up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from ...geometry import rot_x, rot_y
from ...joints import JOINT_INDEX as J
from ...joints import JOINTS

_REST = {
    "SpineBase": (0.0, 0.95, 0.0), "SpineMid": (0.0, 1.20, 0.0), "Neck": (0.0, 1.50, 0.0),
    "Head": (0.0, 1.65, 0.02), "SpineShoulder": (0.0, 1.42, 0.0),
    "ShoulderLeft": (0.18, 1.40, 0.0), "ElbowLeft": (0.22, 1.12, 0.0),
    "WristLeft": (0.24, 0.88, 0.02), "HandLeft": (0.24, 0.80, 0.03),
    "HandTipLeft": (0.24, 0.72, 0.04), "ThumbLeft": (0.21, 0.80, 0.06),
    "HipLeft": (0.09, 0.92, 0.0), "KneeLeft": (0.10, 0.50, 0.02),
    "AnkleLeft": (0.10, 0.08, 0.0), "FootLeft": (0.10, 0.02, 0.10),
}
for _name, (_x, _y, _z) in list(_REST.items()):
    if _name.endswith("Left"):
        _REST[_name[:-4] + "Right"] = (-_x, _y, _z)

#: (25, 3) rest pose of a 1.75 m performer in the body frame, metres: the segment
#: lengths of every simulated body are scaled from it
REST_POSE = np.array([_REST[name] for name in JOINTS])

_UP = np.array([0.0, 1.0, 0.0])
_FWD = np.array([0.0, 0.0, 1.0])
#: stride length of a 1.75 m walker (seed 003, Table 3: stride length ~146 cm)
STRIDE_M = 1.46
#: typical walking speed (seed 003, Table 1: 123 cm/s)
WALK_SPEED = 1.23

_ARM_JOINTS = {s: [J[n + s] for n in ("Elbow", "Wrist", "Hand", "HandTip", "Thumb")]
               for s in ("Left", "Right")}
_LEG_JOINTS = {s: [J[n + s] for n in ("Knee", "Ankle", "Foot")] for s in ("Left", "Right")}
_UPPER = [J[n] for n in ("SpineMid", "Neck", "Head", "SpineShoulder")] + \
    [J[n + s] for s in ("Left", "Right") for n in ("Shoulder", "Elbow", "Wrist", "Hand",
                                                   "HandTip", "Thumb")]
_LOWER = [i for i in range(len(REST_POSE)) if i not in _UPPER]


@dataclass(frozen=True)
class ArmPose:
    elevation: float = 0.0
    azimuth: float = 0.0
    elbow: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([self.elevation, self.azimuth, self.elbow])


@dataclass
class BodyState:
    """Everything that poses the procedural body at one instant."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (x, z) metres, stage
    heading: float = 0.0            # radians
    arms: tuple[ArmPose, ArmPose] = (ArmPose(), ArmPose())  # left, right
    crouch: float = 0.0             # metres the hips are lowered
    lift: float = 0.0               # metres off the floor (jump)
    stride_phase: float = 0.0       # walking cycles done (1 = two steps)
    stride_amp: float = 0.0         # 0 standing, 1 walking at normal speed
    tuck: float = 0.0               # 0-1 knee tuck while airborne


class Proportions:
    """Segment lengths of a performer of ``height`` metres (scaled from the rest pose).

    Everything constant about a body is computed once here: posing it 30
    times a second for every sensor is the simulator's inner loop.
    """

    def __init__(self, height: float) -> None:
        self.height = float(height)
        self.s = s = self.height / 1.75
        self.rest = REST_POSE * s
        r = self.rest
        self.upper_arm = float(np.linalg.norm(r[J["ElbowLeft"]] - r[J["ShoulderLeft"]]))
        self.forearm = float(np.linalg.norm(r[J["WristLeft"]] - r[J["ElbowLeft"]]))
        self.hand = 0.08 * s
        self.thigh = float(np.linalg.norm(r[J["KneeLeft"]] - r[J["HipLeft"]]))
        self.shin = float(np.linalg.norm(r[J["AnkleLeft"]] - r[J["KneeLeft"]]))
        self.foot = {side: r[J["Foot" + side]] - r[J["Ankle" + side]] for side in ("Left", "Right")}
        self.hip_y = float(r[J["HipLeft"], 1])
        self.ankle_y = float(r[J["AnkleLeft"], 1])
        self.pivot = r[J["SpineBase"]].copy()

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Proportions) and other.height == self.height

    def __hash__(self) -> int:
        return hash(self.height)

    def __repr__(self) -> str:
        return f"Proportions(height={self.height})"


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else v


def _bend_dir(d: np.ndarray) -> np.ndarray:
    """The direction an elbow bend moves the forearm: forwards, or up when the arm points forwards."""
    b = _FWD - float(_FWD @ d) * d
    if float(b @ b) < 0.01:
        b = _UP - float(_UP @ d) * d
    return _unit(b)


def arm_direction(elevation: float, azimuth: float, side: str) -> np.ndarray:
    lateral = np.array([1.0 if side == "Left" else -1.0, 0.0, 0.0])
    horizontal = math.cos(azimuth) * lateral + math.sin(azimuth) * _FWD
    return -math.cos(elevation) * _UP + math.sin(elevation) * horizontal


def angles_of(direction: np.ndarray, side: str) -> tuple[float, float]:
    """(elevation, azimuth) of a unit arm direction in the body frame."""
    elevation = math.acos(max(-1.0, min(1.0, -float(direction[1]))))
    lateral = direction[0] if side == "Left" else -direction[0]
    if abs(lateral) + abs(direction[2]) < 1e-6:
        return elevation, 0.0
    return elevation, math.atan2(float(direction[2]), float(lateral))


def reach_angles(target: np.ndarray, shoulder: np.ndarray, props: Proportions, side: str,
                 straight: bool = False) -> ArmPose:
    """Arm angles that put the Hand joint at ``target`` (body frame), or as near as it goes.

    Two-bone inverse kinematics in the plane of the target and the forward
    direction: the elbow bends just enough for the hand to land on the point.
    ``straight``: point the straight arm at the target instead.
    """
    v = np.asarray(target, float) - shoulder
    dist = float(np.linalg.norm(v))
    if dist < 1e-6:
        return ArmPose()
    u = v / dist
    l1, l2 = props.upper_arm, props.forearm + props.hand
    if straight or dist >= l1 + l2 - 1e-6:
        e, a = angles_of(u, side)
        return ArmPose(e, a, 0.0)
    dist = max(dist, abs(l1 - l2) + 0.02)
    alpha = math.acos(max(-1.0, min(1.0, (l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist))))
    inner = math.acos(max(-1.0, min(1.0, (l1 * l1 + l2 * l2 - dist * dist) / (2 * l1 * l2))))
    d = math.cos(alpha) * u - math.sin(alpha) * _bend_dir(u)
    e, a = angles_of(_unit(d), side)
    return ArmPose(e, a, math.pi - inner)


def _leg(joints: np.ndarray, side: str, flex: float, knee: float, props: Proportions) -> None:
    """Pose a leg in place: ``flex`` hip flexion (+ forwards), ``knee`` knee flexion, radians."""
    hip = joints[J["Hip" + side]]
    knee_p = hip + (0.0, -props.thigh * math.cos(flex), props.thigh * math.sin(flex))
    shank = flex - knee
    ankle = knee_p + (0.0, -props.shin * math.cos(shank), props.shin * math.sin(shank))
    joints[J["Knee" + side]] = knee_p
    joints[J["Ankle" + side]] = ankle
    joints[J["Foot" + side]] = ankle + props.foot[side]


def crouch_angles(depth: float, props: Proportions) -> tuple[float, float]:
    """(hip flexion, knee flexion) that shorten the hip-to-ankle distance by ``depth`` metres."""
    if depth <= 0.0:
        return 0.0, 0.0
    thigh, shin = props.thigh, props.shin
    d = max(thigh + shin - depth, 0.35 * (thigh + shin))
    hip = math.acos(max(-1.0, min(1.0, (thigh * thigh + d * d - shin * shin) / (2 * thigh * d))))
    inner = math.acos(max(-1.0, min(1.0, (thigh * thigh + shin * shin - d * d) / (2 * thigh * shin))))
    return hip, math.pi - inner


def upper_frame(state: BodyState, props: Proportions,
                legs: dict[str, tuple[float, float]] | None = None,
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """(rotation, translation, lean) of the upper body: body-frame point p -> stage R @ p + t.

    Needed to turn a stage-space reach target into the arm's own frame.
    """
    legs = _leg_angles(state, props) if legs is None else legs
    hip_flex, _ = crouch_angles(state.crouch, props)
    lean = 0.5 * hip_flex
    pivot = props.pivot
    r_heading = rot_y(state.heading)
    lean_r = rot_x(lean)
    # p_stage = Rh @ (Rl @ (p - pivot) + pivot + [0, y_shift, 0]) + [x, 0, z]
    y_shift = _ground_shift(state, props, legs)
    rotation = r_heading @ lean_r
    translation = r_heading @ (pivot - lean_r @ pivot + np.array([0.0, y_shift, 0.0])) + \
        np.array([state.position[0], 0.0, state.position[1]])
    return rotation, translation, lean


def _leg_angles(state: BodyState, props: Proportions) -> dict[str, tuple[float, float]]:
    hip_c, knee_c = crouch_angles(state.crouch, props)
    phase = 2 * math.pi * state.stride_phase
    amp = state.stride_amp
    swing = 0.35 * amp * math.sin(phase)
    lift = 0.6 * amp
    tuck = 0.8 * state.tuck
    return {"Left": (hip_c + swing + 0.5 * tuck, knee_c + lift * max(0.0, math.cos(phase)) + tuck),
            "Right": (hip_c - swing + 0.5 * tuck, knee_c + lift * max(0.0, -math.cos(phase)) + tuck)}


def _ground_shift(state: BodyState, props: Proportions,
                  legs: dict[str, tuple[float, float]]) -> float:
    """How far the body moves down so the lower ankle stays on the floor, plus the jump lift."""
    lowest = min(props.hip_y - props.thigh * math.cos(flex) - props.shin * math.cos(flex - knee)
                 for flex, knee in legs.values())
    if state.lift > 0:  # airborne: tucked feet do not pull the body down
        lowest = min(lowest, props.ankle_y)
    return props.ankle_y - lowest + state.lift


@lru_cache(maxsize=64)
def proportions(height: float = 1.75) -> Proportions:
    """The (shared, read-only) proportions of a performer ``height`` metres tall."""
    return Proportions(height)


def standing_pose(position: tuple[float, float] | np.ndarray = (0.0, 0.0), heading: float = 0.0,
                  left_arm: float = 0.0, right_arm: float = 0.0, *, height: float = 1.75,
                  stride_phase: float = 0.0, stride_amp: float = 0.0) -> np.ndarray:
    """(25, 3) joints, stage space, metres: an upright performer with straight arms.

    position: (x, z) on the floor, metres. heading: radians (0 faces +z,
    positive turns to the performer's left). left_arm/right_arm: radians the
    straight arm is raised sideways (0 hanging, pi/2 horizontal, pi overhead).
    stride_phase/stride_amp: the legs in a walking stride (phase in cycles,
    1 = two steps; amplitude 0 standing still, 1 a normal walk; hanging arms
    swing with it). The simple posed skeleton for tests and benchmarks; for
    crouching, jumping, reaching or bent elbows pose a ``BodyState`` with
    ``skeleton``.
    """
    x, z = (float(v) for v in position)
    state = BodyState(np.array([x, z]), float(heading),
                      (ArmPose(float(left_arm)), ArmPose(float(right_arm))),
                      stride_phase=float(stride_phase), stride_amp=float(stride_amp))
    return skeleton(state, proportions(float(height)))


def skeleton(state: BodyState, props: Proportions) -> np.ndarray:
    """(25, 3) joint positions in stage space, metres."""
    joints = props.rest.copy()
    for side, arm in zip(("Left", "Right"), state.arms):
        _pose_arm(joints, side, arm, props, state)
    legs = _leg_angles(state, props)
    for side, (flex, knee) in legs.items():
        _leg(joints, side, flex, knee, props)
    rotation, translation, _ = upper_frame(state, props, legs)
    # the legs are not leaned: only joints above the pelvis turn about SpineBase
    out = np.empty_like(joints)
    out[_UPPER] = joints[_UPPER] @ rotation.T + translation
    place = np.array([state.position[0], _ground_shift(state, props, legs), state.position[1]])
    out[_LOWER] = joints[_LOWER] @ rot_y(state.heading).T + place
    return out


def _pose_arm(joints: np.ndarray, side: str, arm: ArmPose, props: Proportions,
              state: BodyState) -> None:
    # plain floats: five small vectors per arm, 30 times a second per sensor per person
    left = side == "Left"
    ce, se = math.cos(arm.elevation), math.sin(arm.elevation)
    ca, sa = math.cos(arm.azimuth), math.sin(arm.azimuth)
    dx, dy, dz = se * ca * (1.0 if left else -1.0), -ce, se * sa
    if state.stride_amp > 0 and arm.elevation < 0.6:
        # arms swing against the legs while walking, less the more the arm is raised
        swing = (-1.0 if left else 1.0) * 0.3 * state.stride_amp * \
            math.sin(2 * math.pi * state.stride_phase)
        a = -swing * (1.0 - arm.elevation / 0.6)
        c, s = math.cos(a), math.sin(a)
        dy, dz = c * dy - s * dz, s * dy + c * dz
    # bend direction: forwards, made perpendicular to the upper arm (up if the arm points ahead)
    bx, by, bz = -dz * dx, -dz * dy, 1.0 - dz * dz
    n2 = bx * bx + by * by + bz * bz
    if n2 < 0.01:
        bx, by, bz = -dy * dx, 1.0 - dy * dy, -dy * dz
        n2 = bx * bx + by * by + bz * bz
    n = math.sqrt(n2) if n2 > 1e-18 else 1.0
    bx, by, bz = bx / n, by / n, bz / n
    ck, sk = math.cos(arm.elbow), math.sin(arm.elbow)
    fx, fy, fz = ck * dx + sk * bx, ck * dy + sk * by, ck * dz + sk * bz
    sx, sy, sz = joints[J["Shoulder" + side]]
    u, fo, h = props.upper_arm, props.forearm, props.hand
    ex, ey, ez = sx + u * dx, sy + u * dy, sz + u * dz
    wx, wy, wz = ex + fo * fx, ey + fo * fy, ez + fo * fz
    hx, hy, hz = wx + h * fx, wy + h * fy, wz + h * fz
    # the thumb sits forward of the palm, a little towards the body's midline
    sign = 1.0 if left else -1.0
    ix, iy, iz = (fy * bz - fz * by) * sign, (fz * bx - fx * bz) * sign, (fx * by - fy * bx) * sign
    tx, ty, tz = bx - 0.3 * ix, by - 0.3 * iy, bz - 0.3 * iz
    tn = math.sqrt(tx * tx + ty * ty + tz * tz) or 1.0
    k1, k2 = 0.02 * props.s, 0.035 * props.s / tn
    joints[_ARM_JOINTS[side]] = ((ex, ey, ez), (wx, wy, wz), (hx, hy, hz),
                                 (hx + h * fx, hy + h * fy, hz + h * fz),
                                 (hx + k1 * fx + k2 * tx, hy + k1 * fy + k2 * ty,
                                  hz + k1 * fz + k2 * tz))
