"""A procedural 25-joint body and the geometry of a Kinect-style sensor looking at it.

Used by the built-in demo and by tests that need ground truth. Body frame:
x to the performer's left, y up, z the way they face; metres; feet on y = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .joints import JOINT_INDEX, N_JOINTS, HandState

from .geometry import rot_x as _rot_x
from .geometry import rot_y
from .geometry import rot_z as _rot_z
from .sensors.sim.kinematics import REST_POSE

_ARM = {side: [JOINT_INDEX[n + side] for n in ("Elbow", "Wrist", "Hand", "HandTip", "Thumb")]
        for side in ("Left", "Right")}
_LEG = {side: [JOINT_INDEX[n + side] for n in ("Knee", "Ankle", "Foot")]
        for side in ("Left", "Right")}


def pose(position: np.ndarray, heading: float, left_arm: float = 0.0, right_arm: float = 0.0,
         stride: float = 0.0, height: float = 1.75) -> np.ndarray:
    """A posed skeleton in stage space, (25, 3) metres.

    position: (x, z) on the floor or (x, y, z). heading: yaw in radians (0 faces
    +z). left_arm/right_arm: abduction in radians (0 hanging, pi/2 horizontal,
    pi overhead). stride: leg swing in radians (+ left leg forward).
    """
    joints = REST_POSE * (height / 1.75)
    for side, angle, sign in (("Left", left_arm, 1.0), ("Right", right_arm, -1.0)):
        pivot = joints[JOINT_INDEX["Shoulder" + side]]
        r = _rot_z(sign * angle)
        joints[_ARM[side]] = (joints[_ARM[side]] - pivot) @ r.T + pivot
    for side, angle in (("Left", stride), ("Right", -stride)):
        pivot = joints[JOINT_INDEX["Hip" + side]]
        r = _rot_x(-angle)
        joints[_LEG[side]] = (joints[_LEG[side]] - pivot) @ r.T + pivot
    p = np.asarray(position, dtype=float)
    offset = np.array([p[0], 0.0, p[1]]) if p.shape == (2,) else p
    return joints @ rot_y(heading).T + offset


@dataclass(frozen=True)
class SensorPose:
    """Where a sensor stands in stage space and the matrix of its camera space.

    Camera space is Kinect-like: z out of the lens, y up, x = y cross z.
    """

    position: np.ndarray   # (3,) metres
    yaw: float             # radians; 0 looks along +z

    @classmethod
    def looking_at(cls, position: np.ndarray, target: np.ndarray) -> "SensorPose":
        d = np.asarray(target, float) - np.asarray(position, float)
        return cls(np.asarray(position, float), float(np.arctan2(d[0], d[2])))

    @property
    def to_stage(self) -> np.ndarray:
        """4x4: sensor camera space -> stage space."""
        m = np.eye(4)
        m[:3, :3] = rot_y(self.yaw)
        m[:3, 3] = self.position
        return m

    def observe(self, stage_points: np.ndarray) -> np.ndarray:
        """(..., 3) stage points -> the same points in this sensor's camera space."""
        return (stage_points - self.position) @ rot_y(self.yaw)


def ring_of_sensors(n: int = 3, radius: float = 2.5, height: float = 0.8,
                    centre: tuple[float, float] = (0.0, 0.0)) -> list[SensorPose]:
    """``n`` sensors evenly around a circle, all looking at its centre (seed 004's rig)."""
    target = np.array([centre[0], height, centre[1]])
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        position = np.array([centre[0] - radius * np.sin(a), height, centre[1] - radius * np.cos(a)])
        out.append(SensorPose.looking_at(position, target))
    return out


def observe_with_errors(sensor: SensorPose, truth: np.ndarray, rng: np.random.Generator,
                        noise_m: float = 0.01, back_bias_m: float = 0.03,
                        ) -> tuple[np.ndarray, np.ndarray]:
    """What a Kinect-style sensor reports for a true skeleton: (joints (25,3), conf (25,)).

    Gaussian noise of ``noise_m`` per axis; joints on the far side of the body
    from the sensor are "inferred" (confidence 0.5) and pulled towards the
    sensor by ``back_bias_m``, as depth sensors see only the near surface.
    """
    seen = sensor.observe(truth)
    centre_depth = seen[list((JOINT_INDEX["SpineBase"], JOINT_INDEX["SpineMid"]))][:, 2].mean()
    behind = seen[:, 2] > centre_depth + 0.08
    conf = np.where(behind, 0.5, 1.0)
    direction = seen / np.linalg.norm(seen, axis=1, keepdims=True)
    seen = seen - behind[:, None] * back_bias_m * direction
    seen = seen + rng.normal(0.0, noise_m, size=seen.shape)
    return seen, conf


def misread_hand(state: HandState, rng: np.random.Generator, p: float) -> HandState:
    if rng.random() >= p:
        return state
    others = [s for s in (HandState.OPEN, HandState.CLOSED, HandState.LASSO) if s != state]
    return others[int(rng.integers(len(others)))]


__all__ = ["REST_POSE", "N_JOINTS", "pose", "rot_y", "SensorPose", "ring_of_sensors",
           "observe_with_errors", "misread_hand"]
