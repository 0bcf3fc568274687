"""A walk whose gait is set: planted feet at a chosen step length, width and cadence.

The procedural body of ``kinematics`` slides its feet (its legs swing about
the hips while the pelvis glides), which is fine for a dance but gives no
gait to measure. ``GaitClip`` is a straight walk in which each foot stays
on the floor where it was put down until it swings to its next placement,
so step length, step width and step time are known exactly: the ground
truth for gait analysis (``stage.analysis``), as a simulator clip.

Clip space (the ``Clip`` protocol of ``performer``): metres, y up, feet on
y = 0, the walker starts with both feet beside the origin and walks along
+z (heading 0, the left foot on +x).

The gait cycle follows the usual proportions of normal walking: each foot
swings for 40 % of the cycle (0.8 step times) and both feet are on the
floor for 0.2 step times after each placement. The first step starts from
standing and is ``first_step`` long (default half a step: the first step
of a walk is shorter, seed 003, Figure 6), so the first stride of the other
foot is short too; after the last step the trailing foot closes beside the
leading one (a closing step never passes the other foot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...joints import JOINT_INDEX as J
from ...joints import N_JOINTS
from .kinematics import Proportions, proportions

#: fraction of a step time one foot swings (40 % of the gait cycle = 0.8 step times)
SWING = 0.8
_SIDES = ("Left", "Right")
_ARM = {s: [J[n + s] for n in ("Elbow", "Wrist", "Hand", "HandTip", "Thumb")] for s in _SIDES}
_LEGS = [J[n + s] for s in _SIDES for n in ("Hip", "Knee", "Ankle", "Foot")]


def _min_jerk(u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


@dataclass(frozen=True)
class Placement:
    """A foot put down: time (s, clip time), which foot, where (x, z metres, clip space)."""

    t: float
    side: str
    x: float
    z: float


class GaitClip:
    """A straight walk with set step length (m), step width (m) and cadence (steps/min).

    ``steps``: how many steps (placements), the first one ``first_step`` m
    long (default half a step); ``lead``: the foot that starts ("left" or
    "right"); ``lift``: how high the ankle rises in mid-swing (m);
    ``stand``: seconds standing before the first foot lifts and after the
    closing step. The step width is the lateral distance between the ankles.
    """

    def __init__(self, steps: int, step_length: float = 0.70, step_width: float = 0.12,
                 cadence: float = 110.0, *, first_step: float | None = None, lead: str = "left",
                 lift: float = 0.08, stand: float = 0.5, height: float = 1.75,
                 props: Proportions | None = None) -> None:
        if steps < 1 or step_length <= 0 or step_width < 0 or cadence <= 0:
            raise ValueError("a gait needs steps >= 1, step_length > 0, step_width >= 0, "
                             "cadence > 0")
        if lead not in ("left", "right"):
            raise ValueError("lead must be 'left' or 'right'")
        self.steps, self.step_length, self.step_width = int(steps), float(step_length), \
            float(step_width)
        self.cadence = float(cadence)
        self.step_time = 60.0 / self.cadence
        self.first_step = 0.5 * self.step_length if first_step is None else float(first_step)
        self.lead = lead.capitalize()
        self.lift, self.stand = float(lift), float(stand)
        self.props = props or proportions(float(height))
        T = self.step_time
        other = "Right" if self.lead == "Left" else "Left"
        half = 0.5 * self.step_width
        lateral = {"Left": half, "Right": -half}
        # each foot's keyframes: (time it lifts, time it lands, from z, to z)
        self.placements: list[Placement] = []
        self._swings: dict[str, list[tuple[float, float, float, float]]] = {"Left": [], "Right": []}
        z = {"Left": 0.0, "Right": 0.0}
        for k in range(1, self.steps + 1):
            side = self.lead if k % 2 else other
            land = self.stand + SWING * T + (k - 1) * T
            goal = self.first_step if k == 1 else z["Left" if side == "Right" else "Right"] + \
                self.step_length
            self._swings[side].append((land - SWING * T, land, z[side], goal))
            z[side] = goal
            self.placements.append(Placement(land, side, lateral[side], goal))
        last = self.placements[-1]
        trailing = "Right" if last.side == "Left" else "Left"
        close = last.t + T
        self._swings[trailing].append((close - SWING * T, close, z[trailing], last.z))
        self.duration = close + self.stand
        self._lateral = lateral
        # pelvis along the walk: midway between the feet at each placement, eased at both ends
        knots_t = [self.stand] + [p.t for p in self.placements] + [close]
        feet = {"Left": 0.0, "Right": 0.0}
        knots_z = [0.0]
        for p in self.placements:
            feet[p.side] = p.z
            knots_z.append(0.5 * (feet["Left"] + feet["Right"]))
        knots_z.append(last.z)
        self._knots_t, self._knots_z = np.array(knots_t), np.array(knots_z)

    # ------------------------------------------------------------ truth
    def truth(self) -> dict[str, float]:
        """The walk's set parameters: step length/width (m), step time (s), cadence, speed."""
        return {"step_length": self.step_length, "step_width": self.step_width,
                "step_time": self.step_time, "cadence": self.cadence,
                "stride_length": 2.0 * self.step_length,
                "speed": self.step_length / self.step_time, "first_step": self.first_step}

    # ------------------------------------------------------------ the Clip protocol
    def root(self, t: float) -> np.ndarray:
        return np.array([self._sway(t), self._pelvis_z(t)])

    def heading(self, t: float) -> float:
        return 0.0

    def conf(self) -> np.ndarray:
        return np.ones(N_JOINTS)

    def joints(self, t: float) -> np.ndarray:
        """(25, 3) joint positions at clip time ``t`` (s), metres, clip space."""
        p = self.props
        ankles = {side: self._ankle(side, t) for side in _SIDES}
        pelvis_xz = self.root(t)
        hip_off = {side: p.rest[J["Hip" + side]] - p.pivot for side in _SIDES}
        # the pelvis drops just enough for the legs to reach the feet on or ahead of it; a
        # foot behind it rises on its toes instead (heel off), staying where it was put down
        reach = 0.995 * (p.thigh + p.shin)
        y = p.pivot[1]
        flat = {}
        for side in _SIDES:
            a = ankles[side]
            hx = pelvis_xz[0] + hip_off[side][0]
            hz = pelvis_xz[1] + hip_off[side][2]
            flat[side] = min(math.hypot(a[0] - hx, a[2] - hz), reach)
            if a[2] >= hz:
                y = min(y, a[1] + math.sqrt(reach * reach - flat[side] ** 2) - hip_off[side][1])
        pelvis = np.array([pelvis_xz[0], y, pelvis_xz[1]])
        out = p.rest - p.pivot + pelvis          # upper body upright, carried by the pelvis
        for side in _SIDES:
            hip = out[J["Hip" + side]]
            ankle = ankles[side]
            ankle[1] = max(ankle[1], hip[1] - math.sqrt(reach * reach - flat[side] ** 2))
            out[J["Knee" + side]] = _knee(hip, ankle, p.thigh, p.shin)
            out[J["Ankle" + side]] = ankle
            out[J["Foot" + side]] = ankle + p.foot[side]
        for side in _SIDES:
            self._swing_arm(out, side, ankles)
        return out

    # ------------------------------------------------------------ parts
    def _ankle(self, side: str, t: float) -> np.ndarray:
        z, height = 0.0, 0.0
        for t0, t1, z0, z1 in self._swings[side]:
            if t < t0:
                break
            if t >= t1:
                z = z1
                continue
            u = (t - t0) / (t1 - t0)
            z = z0 + (z1 - z0) * _min_jerk(u)
            height = self.lift * math.sin(math.pi * u)
            break
        return np.array([self._lateral[side], self.props.ankle_y + height, z])

    def _pelvis_z(self, t: float) -> float:
        kt, kz = self._knots_t, self._knots_z
        if t <= kt[0]:
            return float(kz[0])
        if t >= kt[-1]:
            return float(kz[-1])
        i = int(np.searchsorted(kt, t, side="right")) - 1
        u = (t - kt[i]) / (kt[i + 1] - kt[i])
        if i == 0 or i == len(kt) - 2:  # start and stop eased, the rest at walking speed
            u = u * u * (3.0 - 2.0 * u)
        return float(kz[i] + (kz[i + 1] - kz[i]) * u)

    def _sway(self, t: float) -> float:
        """The pelvis moves 1.5 cm over the foot it stands on (towards +x over the left)."""
        first, last = self.placements[0].t, self.placements[-1].t
        if t <= first - SWING * self.step_time or t >= last + self.step_time:
            return 0.0
        sign = 1.0 if self.lead == "Left" else -1.0
        phase = math.pi * (t - first - 0.6 * self.step_time) / self.step_time
        ramp = min(1.0, (t - first + SWING * self.step_time) / self.step_time,
                   (last + self.step_time - t) / self.step_time)
        return 0.015 * sign * math.cos(phase) * max(ramp, 0.0)

    def _swing_arm(self, out: np.ndarray, side: str, ankles: dict[str, np.ndarray]) -> None:
        """Arms swing against the legs: forwards while the other foot is ahead."""
        other = "Right" if side == "Left" else "Left"
        ahead = (ankles[other][2] - ankles[side][2]) / max(self.step_length, 1e-6)
        angle = 0.35 * max(-1.0, min(1.0, ahead))
        c, s = math.cos(angle), math.sin(angle)
        shoulder = out[J["Shoulder" + side]].copy()
        rel = out[_ARM[side]] - shoulder
        # about the body's x axis: a hanging arm's hand moves towards +z for angle > 0
        y, z = rel[:, 1].copy(), rel[:, 2].copy()
        rel[:, 1], rel[:, 2] = c * y + s * z, c * z - s * y
        out[_ARM[side]] = shoulder + rel


def _knee(hip: np.ndarray, ankle: np.ndarray, thigh: float, shin: float) -> np.ndarray:
    """Two-bone inverse kinematics: the knee bends forwards (+z) in the leg's plane."""
    d = ankle - hip
    dist = float(np.linalg.norm(d))
    if dist < 1e-9:
        return hip + np.array([0.0, -thigh, 0.0])
    u = d / dist
    dist = min(dist, thigh + shin - 1e-9)
    cos_a = (thigh * thigh + dist * dist - shin * shin) / (2.0 * thigh * dist)
    alpha = math.acos(max(-1.0, min(1.0, cos_a)))
    fwd = np.array([0.0, 0.0, 1.0]) - u[2] * u
    n = float(np.linalg.norm(fwd))
    fwd = fwd / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])
    return hip + thigh * (math.cos(alpha) * u + math.sin(alpha) * fwd)
