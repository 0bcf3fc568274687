"""How much a set of pairs says: distinct poses and the space they cover, and the gates.

A fixed number of paired frames is the wrong yardstick: 300 frames of a
person standing still are one pose said 300 times (and its errors with it),
while a person walking 3 m in 2 s shows the sensors 60 different skeletons
in 60 different places. So a pair set is judged by

- its DISTINCT POSES: frames kept greedily, each at least ``pose_step_m``
  (mean over the joints both frames have) from every pose kept before, in
  the sensor's own space, so a new place or a new posture counts and noise
  does not;
- the SPREAD of the torso over those poses (metres, rms about their
  centre), reported so a user can see how much of the space was covered.

``Gates`` are the defaults both the offline and the live calibrations use:
at least ``min_pairs`` paired frames, ``min_poses`` distinct poses, and a
good fit, or a poor one whose timing the lag search found unambiguous
(fitness from the median joint distance, see ``fitness``); each refusal
names its cause with the counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..joints import TORSO
from .fitness import median_from_fitness

#: two frames whose joints are this far apart on average (m) are two poses
POSE_STEP_M = 0.05


class PoseCounter:
    """Distinct poses among frames added so far (incremental; see the module docstring)."""

    def __init__(self, step_m: float = POSE_STEP_M, cap: int = 400) -> None:
        self.step_m, self.cap = step_m, cap
        self._joints: list[np.ndarray] = []
        self._seen: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._joints)

    def add(self, joints: np.ndarray, weight: np.ndarray) -> int:
        """Frames (n, J, 3) with weights (n, J) (0: not seen); returns the poses counted."""
        for k in range(len(joints)):
            if len(self._joints) >= self.cap:
                break
            seen = weight[k] > 0
            if not seen.any():
                continue
            if self._joints:
                kept, kseen = np.stack(self._joints), np.stack(self._seen)
                both = kseen & seen
                d = np.linalg.norm(kept - joints[k], axis=-1)
                n = both.sum(axis=1)
                mean = np.where(n > 0, (d * both).sum(axis=1) / np.maximum(n, 1), np.inf)
                if (mean < self.step_m).any():
                    continue
            self._joints.append(joints[k])
            self._seen.append(seen)
        return len(self._joints)

    def spread_m(self) -> float:
        """RMS distance (m) of the kept poses' torso centres from their mean."""
        if not self._joints:
            return 0.0
        j, s = np.stack(self._joints), np.stack(self._seen)
        t = list(TORSO)
        n = s[:, t].sum(axis=1)
        ok = n > 0
        if not ok.any():
            return 0.0
        c = (j[:, t] * s[:, t, None]).sum(axis=1)[ok] / n[ok, None]
        return float(np.sqrt(((c - c.mean(axis=0)) ** 2).sum(axis=1).mean()))


def count_poses(joints: np.ndarray, weight: np.ndarray, step_m: float = POSE_STEP_M,
                ) -> tuple[int, float]:
    """(distinct poses, torso spread m) of frames (n, J, 3) with weights (n, J)."""
    counter = PoseCounter(step_m)
    counter.add(joints, weight)
    return len(counter), counter.spread_m()


@dataclass(frozen=True)
class Gates:
    """What a pair set and its fit need before a calibration is used (documented defaults).

    Two tiers of fit: GOOD (fitness ``min_fitness`` or better) is used as it
    is; POOR (down to ``poor_fitness``) only when the lag search found the
    two streams' timing unambiguous (confidence ``min_lag_confidence`` or
    more: one clear minimum, so the two sensors really watched the same
    motion at the same time). Real short takes fit at 5-25 cm (median) even
    at their brute-force optimum, so a single good/bad line either refused
    most of them or let anything through; two sensors watching different
    people at the same time fit at 70 cm or more and their timing is flat.
    """

    min_pairs: int = 10           # paired frames: a third of a second at 30 Hz
    min_poses: int = 5            # distinct poses (POSE_STEP_M apart)
    min_fitness: float = 0.5      # good: a median joint distance of 8.9 cm or less
    poor_fitness: float = 0.1     # poor but usable: 26.6 cm or less, with clear timing
    min_lag_confidence: float = 0.15
    # how well the pairs must determine the fit (``uncertainty``: the spread of the fit over
    # a bootstrap of its independent poses); 0 switches a tolerance off
    max_rot_deg: float = 2.0      # rms rotation spread, degrees
    max_far_m: float = 0.05       # rms spread of a point ``edge_m`` from the sensor
    edge_m: float = 4.5           # the stage's far edge: a Kinect's tracking range
    # three sensors that overlap pairwise: their three fits must compose to within this of no
    # turn at all (degrees; 0: not judged); see offline._check_loops
    max_loop_deg: float = 10.0

    def too_little(self, pairs: int, poses: int) -> str | None:
        """Why these pairs are not enough, or None."""
        if pairs < self.min_pairs:
            return f"only {pairs} paired frames (need {self.min_pairs})"
        if poses < self.min_poses:
            return (f"too few distinct poses: {poses} in {pairs} paired frames (need "
                    f"{self.min_poses}; the person hardly moved)")
        return None

    def too_poor(self, fitness: float, median_m: float,
                 lag_confidence: float | None = None) -> str | None:
        """Why a fit is not good enough, or None (see the class docstring)."""
        if fitness >= self.min_fitness:
            return None
        good = median_from_fitness(self.min_fitness) * 100
        if not fitness >= self.poor_fitness:
            return (f"fit too poor: median joint distance {median_m * 100:.1f} cm (fitness "
                    f"{fitness:.2f} < {self.poor_fitness:g}, i.e. more than "
                    f"{median_from_fitness(self.poor_fitness) * 100:.1f} cm: not the same "
                    "person seen twice)")
        if lag_confidence is None or lag_confidence < self.min_lag_confidence:
            timing = ("no lag search" if lag_confidence is None
                      else f"lag search confidence {lag_confidence:.2f} < "
                           f"{self.min_lag_confidence:g}")
            return (f"fit too poor: median joint distance {median_m * 100:.1f} cm (fitness "
                    f"{fitness:.2f} < {self.min_fitness:g}, more than {good:.1f} cm) and the "
                    f"timing does not confirm it ({timing})")
        return None

    @property
    def judges_uncertainty(self) -> bool:
        return self.max_rot_deg > 0 or self.max_far_m > 0

    def tolerance_text(self) -> str:
        parts = []
        if self.max_rot_deg > 0:
            parts.append(f"{self.max_rot_deg:g} deg")
        if self.max_far_m > 0:
            parts.append(f"{self.max_far_m * 100:g} cm at {self.edge_m:g} m from the sensor")
        return ", ".join(parts) or "none"

    def too_uncertain(self, spread) -> str | None:
        """Why a fit is not determined well enough by its pairs, or None. ``spread``: an
        ``uncertainty.Uncertainty`` (rot_deg, far_m: inf when it cannot be measured)."""
        if not self.judges_uncertainty:
            return None
        over = ((self.max_rot_deg > 0 and not spread.rot_deg <= self.max_rot_deg)
                or (self.max_far_m > 0 and not spread.far_m <= self.max_far_m))
        if not over:
            return None
        return (f"fit undetermined: {spread.text()}; tolerance {self.tolerance_text()}")

    def is_poor(self, fitness: float) -> bool:
        return fitness < self.min_fitness
