"""Scripted skeleton streams: fused frames without sensors, for tests and benchmarks.

``ScriptedStage`` turns "person 1 stands here with these joints" into the
``FusedFrame`` objects the engine hands its listeners: velocities by finite
differences, ``new`` and ``lost`` ids, confidences. Times are whatever the
script says (an injected clock), so a test of a trigger is exact and fast.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..frames import Body, FusedFrame
from ..joints import JOINT_INDEX, TORSO, HandState
from ..sensors.sim.kinematics import standing_pose

OPEN = (HandState.OPEN, HandState.OPEN)


def standing(x: float = 0.0, z: float = 0.0, heading: float = 0.0, left_arm: float = 0.0,
             right_arm: float = 0.0, height: float = 1.75) -> np.ndarray:
    """(25, 3) joints of a performer standing at (x, z), stage metres; arms raised sideways
    by ``left_arm``/``right_arm`` radians (the simulator's ``standing_pose``)."""
    return standing_pose((x, z), heading, left_arm, right_arm, height=height)


def with_joint(joints: np.ndarray, name: str, xyz) -> np.ndarray:
    """A copy of ``joints`` with one joint moved to ``xyz`` (metres)."""
    out = joints.copy()
    out[JOINT_INDEX[name]] = xyz
    return out


class ScriptedStage:
    """Feeds a listener (e.g. a PieceRuntime) frames built from scripted joints.

    ``frame(t, {pid: joints})`` or ``{pid: (joints, hands)}`` or
    ``{pid: (joints, hands, conf)}``; people missing from the dict since the
    previous frame are reported lost.
    """

    def __init__(self, listener: Callable[[FusedFrame], None]) -> None:
        self.listener = listener
        self.previous: dict[int, tuple[float, np.ndarray]] = {}
        self.frames = 0

    def frame(self, t: float, people: dict) -> FusedFrame:
        bodies: dict[int, Body] = {}
        new = []
        for pid, spec in people.items():
            if isinstance(spec, tuple):
                joints, hands, *rest = spec
                conf = rest[0] if rest else np.ones(25)
            else:
                joints, hands, conf = spec, OPEN, np.ones(25)
            joints = np.asarray(joints, dtype=float)
            before = self.previous.get(pid)
            if before is None:
                new.append(pid)
                velocity = np.zeros((25, 3))
            else:
                dt = t - before[0]
                velocity = (joints - before[1]) / dt if dt > 0 else np.zeros((25, 3))
            self.previous[pid] = (t, joints)
            position = joints[list(TORSO)].mean(axis=0)
            bodies[pid] = Body(pid, joints, np.asarray(conf, float), velocity, tuple(hands),
                               position, ("scripted",))
        lost = tuple(pid for pid in self.previous if pid not in people)
        for pid in lost:
            del self.previous[pid]
        frame = FusedFrame(t, bodies, tuple(bodies), tuple(new), lost)
        self.frames += 1
        self.listener(frame)
        return frame

    def run(self, t0: float, t1: float, people: Callable[[float], dict], fps: float = 30.0) -> float:
        """Frames at ``fps`` from t0 to t1 (exclusive); ``people(t)`` gives each frame's people."""
        k = 0
        t = t0
        while t < t1 - 1e-9:
            self.frame(t, people(t))
            k += 1
            t = t0 + k / fps
        return t
