"""Simulated sensors with known poses, for tests and benchmarks.

Unlike ``stage.body.SensorPose`` (yaw only), a ``SimSensor`` may be tilted
and rolled, has a field of view and a range, and reports its floor plane,
so every calibration method can be checked against ground truth. Errors are
``stage.body.observe_with_errors``' (Kinect-like noise; joints on the far
side of the body inferred and pulled towards the sensor), plus optional
glitches (joints thrown far away) and a clock offset per sensor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..body import observe_with_errors, pose
from ..geometry import invert, matrix, rot_z
from .streams import Stream

Performer = Callable[[float], np.ndarray]


@dataclass(frozen=True)
class SimSensor:
    """A Kinect-like sensor at a known pose. to_stage: (4, 4) sensor -> stage."""

    id: str
    to_stage: np.ndarray
    fov_deg: tuple[float, float] = (70.6, 60.0)   # Kinect v2 depth camera
    range_m: tuple[float, float] = (0.5, 4.5)
    clock_offset_s: float = 0.0                   # its timestamps = true time + offset
    phase_s: float = 0.0                          # when its frames start within a period

    @classmethod
    def looking_at(cls, sensor_id: str, position: tuple[float, float, float],
                   target: tuple[float, float, float], roll_deg: float = 0.0,
                   **kwargs: object) -> "SimSensor":
        pos, tgt = np.asarray(position, float), np.asarray(target, float)
        z = (tgt - pos) / np.linalg.norm(tgt - pos)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        r = np.column_stack([x, y, z]) @ rot_z(np.radians(roll_deg))
        return cls(sensor_id, matrix(r, pos), **kwargs)  # type: ignore[arg-type]

    def observe(self, stage_points: np.ndarray) -> np.ndarray:
        """(..., 3) stage points -> this sensor's camera space."""
        return (stage_points - self.to_stage[:3, 3]) @ self.to_stage[:3, :3]

    def floor_plane(self) -> np.ndarray:
        """The stage floor (y = 0) in this sensor's space: (a, b, c, d), d = height."""
        return np.append(self.to_stage[1, :3], self.to_stage[1, 3])

    def sees(self, truth: np.ndarray) -> bool:
        """Whether the person's torso is inside the field of view and range."""
        c = self.observe(truth[[0, 1, 20]].mean(axis=0))
        if not self.range_m[0] <= c[2] <= self.range_m[1]:
            return False
        return (abs(np.degrees(np.arctan2(c[0], c[2]))) <= self.fov_deg[0] / 2
                and abs(np.degrees(np.arctan2(c[1], c[2]))) <= self.fov_deg[1] / 2)


def relative(reference: SimSensor, sensor: SimSensor) -> np.ndarray:
    """The true calibration: (4, 4) from ``sensor``'s space to ``reference``'s."""
    return invert(reference.to_stage) @ sensor.to_stage


def wander(centre: tuple[float, float] = (0.0, 0.0), radius: tuple[float, float] = (1.2, 0.8),
           period_s: float = 20.0) -> Performer:
    """A dancer walking a figure of eight, arms rising in turn, legs striding."""
    cx, cz = centre
    rx, rz = radius

    def at(t: float) -> np.ndarray:
        w = 2 * np.pi / period_s
        x, z = cx + rx * np.sin(w * t), cz + rz * np.sin(2 * w * t)
        heading = np.arctan2(rx * w * np.cos(w * t), 2 * rz * w * np.cos(2 * w * t))
        left = 0.5 * np.pi * (1 + np.sin(2 * np.pi * t / 6.0))
        right = 0.5 * np.pi * (1 + np.sin(2 * np.pi * t / 6.0 + np.pi))
        return pose(np.array([x, z]), heading, left, right, 0.35 * np.sin(2 * np.pi * t / 1.1))
    return at


def walk_line(start: tuple[float, float], end: tuple[float, float], period_s: float = 24.0,
              ) -> Performer:
    """Walking from ``start`` to ``end`` and back (x, z on the floor), arms moving."""
    a, b = np.asarray(start, float), np.asarray(end, float)
    heading_out = np.arctan2(*(b - a))

    def at(t: float) -> np.ndarray:
        phase = (t / period_s) % 1.0
        s = 2 * phase if phase < 0.5 else 2 - 2 * phase
        heading = heading_out if phase < 0.5 else heading_out + np.pi
        left = 0.5 * np.pi * (1 + np.sin(2 * np.pi * t / 5.0))
        right = 0.5 * np.pi * (1 + np.sin(2 * np.pi * t / 7.0))
        return pose(a + s * (b - a), heading, left, right, 0.35 * np.sin(2 * np.pi * t / 1.1))
    return at


def simulate(sensors: list[SimSensor], performer: Performer, duration_s: float, seed: int = 0,
             fps: float = 30.0, noise_m: float = 0.01, back_bias_m: float = 0.03,
             glitch_p: float = 0.0, floor_noise_deg: float = 0.0,
             require_view: bool = True) -> dict[str, Stream]:
    """Each sensor's stream of one performer for ``duration_s`` seconds.

    Frames come every 1/fps from each sensor's ``phase_s``; their time stamps
    carry the sensor's ``clock_offset_s``. glitch_p: chance per joint per
    frame of a glitch (the joint thrown 0.3-1 m away, still 'tracked').
    floor_noise_deg: error of the reported floor normal.
    """
    rng = np.random.default_rng(seed)
    out = {}
    for sensor in sensors:
        frames = []
        for k in range(int(duration_s * fps)):
            t = sensor.phase_s + k / fps
            truth = performer(t)
            if require_view and not sensor.sees(truth):
                continue
            joints, conf = observe_with_errors(sensor, truth, rng, noise_m, back_bias_m)  # type: ignore[arg-type]
            if glitch_p > 0:
                hit = rng.random(len(joints)) < glitch_p
                if hit.any():
                    direction = rng.normal(size=(int(hit.sum()), 3))
                    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
                    joints[hit] += direction * rng.uniform(0.3, 1.0, (int(hit.sum()), 1))
            frames.append((t + sensor.clock_offset_s, 0, joints, conf))
        plane = sensor.floor_plane()
        if floor_noise_deg > 0:
            axis = rng.normal(size=3)
            tilt = np.radians(floor_noise_deg) * axis / np.linalg.norm(axis)
            plane = plane.copy()
            plane[:3] = plane[:3] + np.cross(tilt, plane[:3])
        out[sensor.id] = Stream.from_frames(sensor.id, frames, [plane])
    return out


def two_sensor_rig(tilt_deg: float = 8.0, roll_deg: float = 0.0) -> list[SimSensor]:
    """The benchmark's pair: two sensors 100 degrees apart around a 3 m x 2 m floor,
    at 0.8 m and 1.5 m, the second tilted down by ``tilt_deg``."""
    a = SimSensor.looking_at("kinect-a", (0.0, 0.8, -3.2), (0.0, 0.8, 0.0))
    angle = np.radians(100.0)
    pos = (3.2 * np.sin(angle), 1.5, -3.2 * np.cos(angle))
    target_y = 1.5 - 3.2 * np.tan(np.radians(tilt_deg))
    b = SimSensor.looking_at("kinect-b", pos, (0.0, target_y, 0.0), roll_deg)
    return [a, b]
