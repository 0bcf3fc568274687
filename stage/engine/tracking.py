"""Per-sensor tracks, fused persons, and the clock-offset estimate of a client.

State only: the engine thread owns every object here.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..joints import N_JOINTS, TORSO, HandState
from .kalman import JointKalman
from ..settings import KalmanSettings


_TORSO_MASK = np.zeros(N_JOINTS, dtype=bool)
_TORSO_MASK[list(TORSO)] = True


class OffsetEstimator:
    """Estimates ``engine_time - client_time`` from (arrival, timetag) pairs.

    Network delay only ever adds to ``arrival - timetag``, so the minimum
    over a sliding window is the offset plus the smallest delay seen — the
    usual one-way estimate when clocks cannot be asked. The window lets a
    client whose clock was reset be followed within ``window_s``.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self._mins: deque[tuple[float, float]] = deque()  # increasing values: monotonic min-queue

    def update(self, arrival: float, timetag: float) -> float:
        value = arrival - timetag
        while self._mins and self._mins[-1][1] >= value:
            self._mins.pop()
        self._mins.append((arrival, value))
        while self._mins[0][0] < arrival - self.window_s:
            self._mins.popleft()
        return self._mins[0][1]

    @property
    def offset(self) -> float | None:
        return self._mins[0][1] if self._mins else None


@dataclass(eq=False)
class Track:
    """One sensor's view of one user (client id, user id 0-5), in stage space."""

    client: str
    user: int
    joints: np.ndarray = field(default_factory=lambda: np.zeros((N_JOINTS, 3)))
    conf: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS))
    t: float = float("-inf")            # capture time of the latest frame (engine clock)
    stamp: float = float("-inf")        # the same on the client's clock (timetag or arrival)
    hands: list[HandState] = field(default_factory=lambda: [HandState.UNKNOWN] * 2)
    person: int | None = None
    far_frames: int = 0                 # consecutive frames beyond release distance

    @property
    def key(self) -> tuple[str, int]:
        return self.client, self.user


@dataclass(eq=False)
class Person:
    """A fused person: the views bound to it and its smoothed skeleton."""

    id: int
    kalman: JointKalman
    created: float
    tracks: set = field(default_factory=set)   # of Track
    joints: np.ndarray = field(default_factory=lambda: np.zeros((N_JOINTS, 3)))
    conf: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros((N_JOINTS, 3)))
    centre: np.ndarray | None = None
    known: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS, dtype=bool))
    t: float = float("-inf")
    hands: list[HandState] = field(default_factory=lambda: [HandState.UNKNOWN] * 2)
    announced: bool = False
    orphan_since: float | None = None       # when its last view went away
    sent_hands: list[HandState | None] = field(default_factory=lambda: [None, None])

    @classmethod
    def new(cls, pid: int, t: float, settings: KalmanSettings) -> "Person":
        return cls(pid, JointKalman(N_JOINTS, settings), t)

    def distance(self, joints: np.ndarray, conf: np.ndarray, t: float) -> float | None:
        """Mean distance (m) from a view's joints to this person predicted at ``t``.

        Compared on the torso joints both have (all shared joints if no torso),
        so a view that sees only part of the body is not judged by a centre
        that jumps with what happens to be occluded.
        """
        shared = (conf > 0) & self.known
        on_torso = shared & _TORSO_MASK
        mask = on_torso if on_torso.any() else shared
        if not mask.any():
            return None
        dt = min(max(t - self.t, 0.0), 0.5)
        predicted = self.joints[mask] + self.velocity[mask] * dt
        return float(np.linalg.norm(joints[mask] - predicted, axis=1).mean())

    def sensors(self) -> tuple[str, ...]:
        return tuple(sorted({tr.client for tr in self.tracks}))
