"""What the live calibrator knows about each sensor, and what it reports.

``SensorState`` is one sensor's state (owned by the calibrator, changed
under its lock); ``LiveEvent`` is something the calibrator did. Split from
``healing`` so its parts (``monitor``, ``collector``) share them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .coverage import PoseCounter
from .judge import PairWindow
from .pairs import PairSet

INF = float("inf")


@dataclass(frozen=True)
class LiveEvent:
    """Something the calibrator did, at engine time ``t``."""

    t: float
    sensor: str
    kind: str       # suspect | restored | calibrated | rejected | identical | held | lag
    detail: str
    matrix: np.ndarray | None = None   # sensor -> stage, for calibrated
    fitness: float | None = None


@dataclass
class SensorState:
    sensor: str
    state: str                          # ok | suspect | recalibrating | uncalibrated
    reason: str = ""
    transform: np.ndarray | None = None  # what the engine uses now (None: not fused)
    last_good: np.ndarray | None = None
    fitness: float | None = None
    since: float = -INF
    below_since: float | None = None
    above_since: float | None = None
    pairs: PairSet | None = None
    poses: PoseCounter = field(default_factory=PoseCounter)   # distinct poses in ``pairs``
    poses_count: int = 0                # len(poses) when it last grew ...
    poses_grew: float = INF             # ... and when (engine time)
    needed: int = 0                     # pairs that are enough whatever they cover
    wanted_poses: int = 0               # distinct poses that are enough sooner
    collect_from: float = -INF
    collected_to: float = -INF
    duplicate_of: str | None = None
    requested: bool = False
    busy: bool = False
    epoch: int = 0                      # bumped on every state change (stale decisions lose)
    noted: dict | None = None
    window: PairWindow | None = None    # a suspect's distances with its last good transform
    residual: float | None = None       # m, the robust residual behind ``fitness``
    baseline: float | None = None       # m, its residual when it was calibrated here
    healthy: float | None = None        # m, its residual while it last agreed (running mean)
    lag_s: float = 0.0                  # its clock minus stage time, as the lag search found
    lag_confidence: float | None = None
    lag_searched: float = -INF          # engine time of the last lag search
    lag_settled: bool = False           # a search confirmed the lag in use
    lag_overlap: int = 0                # frames the search that set the lag had
    lag_candidate: float | None = None  # a tracked sensor's lag one sure search proposed (s):
                                        # it moves only when the next search agrees
    lag_quiet: int = 0                  # tracked searches in a row that moved and proposed
                                        # nothing (each doubles the wait for the next)
    loop_s: float | None = None         # the period of a source that loops a take (s)
    loop_folded: bool = False           # its lag was searched on one pass of the take
    last_attempt: str | None = None     # the last calibration attempt's outcome, in words
    lag_last: float | None = None       # the confidence of the last lag search (a sensor to
                                        # calibrate: why it may still wait for a sure lag)

    def reset_pairs(self) -> None:
        self.pairs = None
        self.poses = PoseCounter()
        self.poses_count, self.poses_grew = 0, INF
