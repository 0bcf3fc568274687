"""A body's joints over time, with missing values: what every analysis reads.

A ``Trajectory`` comes from a recording (``integrate``: seed 003's
resampled average over sensors), from fused frames (the engine's output),
or from ground truth (the simulator's, a BVH take). Missing joints are NaN;
the gap filling and smoothing here never invent data across long gaps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from ..frames import FusedFrame
from ..joints import N_JOINTS


@dataclass
class Trajectory:
    """One body over time.

    t: (N,) seconds, ascending. joints: (N, 25, 3) metres, stage space (y up),
    NaN where missing. count: (N, 25) how many sensors were averaged into each
    joint (0 where missing), or None when not known (truth, fused frames).
    """

    t: np.ndarray
    joints: np.ndarray
    count: np.ndarray | None = None
    label: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float)
        self.joints = np.asarray(self.joints, dtype=float)
        if self.joints.shape != (len(self.t), N_JOINTS, 3):
            raise ValueError(f"joints must be ({len(self.t)}, {N_JOINTS}, 3), "
                             f"got {self.joints.shape}")

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) > 1 else 0.0

    @property
    def rate(self) -> float:
        """Samples per second (median spacing); 30 when there are fewer than two samples."""
        if len(self.t) < 2:
            return 30.0
        return float(1.0 / np.median(np.diff(self.t)))

    def missing(self) -> np.ndarray:
        """(25,) fraction of samples in which each joint is missing."""
        if not len(self.t):
            return np.ones(N_JOINTS)
        return np.isnan(self.joints[..., 0]).mean(axis=0)

    def between(self, t0: float, t1: float) -> "Trajectory":
        keep = (self.t >= t0) & (self.t <= t1)
        return Trajectory(self.t[keep], self.joints[keep],
                          None if self.count is None else self.count[keep], self.label,
                          dict(self.meta))

    def filled(self, max_gap_s: float = 0.25) -> "Trajectory":
        """Gaps of at most ``max_gap_s`` seconds bridged by linear interpolation, per joint."""
        out = self.joints.copy()
        for j in range(N_JOINTS):
            out[:, j] = _fill(self.t, self.joints[:, j], max_gap_s)
        return Trajectory(self.t, out, self.count, self.label, dict(self.meta))

    def smoothed(self, sigma_s: float = 0.05) -> "Trajectory":
        """A zero-phase Gaussian low-pass (s.d. ``sigma_s`` seconds) within each unbroken run.

        Seed 003 filters the joint trajectories in time before extracting gait
        parameters; zero phase keeps foot events where they were.
        """
        if sigma_s <= 0 or len(self.t) < 3:
            return self
        flat = smooth(self.joints.reshape(len(self.t), -1), sigma_s * self.rate)
        return Trajectory(self.t, flat.reshape(self.joints.shape), self.count, self.label,
                          dict(self.meta))

    def resampled(self, rate: float = 30.0, max_gap_s: float = 0.1) -> "Trajectory":
        """Linear interpolation onto a ``rate`` Hz grid; samples across longer gaps stay missing."""
        if len(self.t) < 2:
            return self
        grid = np.arange(self.t[0], self.t[-1] + 1e-9, 1.0 / rate)
        out = np.full((len(grid), N_JOINTS, 3), np.nan)
        i = np.clip(np.searchsorted(self.t, grid, side="right") - 1, 0, len(self.t) - 2)
        t0, t1 = self.t[i], self.t[i + 1]
        u = np.clip((grid - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)[:, None, None]
        value = self.joints[i] * (1.0 - u) + self.joints[i + 1] * u
        close = (t1 - t0 <= max_gap_s + 1e-9)[:, None, None] | (u == 0.0) | (u == 1.0)
        out[:] = np.where(close, value, np.nan)
        return Trajectory(grid, out, None, self.label, dict(self.meta))

    @classmethod
    def from_frames(cls, frames: Iterable[FusedFrame], person: int | None = None,
                    min_conf: float = 0.5, label: str = "") -> "Trajectory":
        """One person of a stream of fused frames (default: the first one seen).

        Joints below ``min_conf`` are missing, as are frames without the person.
        """
        t: list[float] = []
        rows: list[np.ndarray] = []
        for frame in frames:
            if person is None and frame.bodies:
                person = min(frame.bodies)
            body = frame.bodies.get(person) if person is not None else None
            if body is None:
                continue
            j = np.array(body.joints, dtype=float)
            j[np.asarray(body.conf) < min_conf] = np.nan
            t.append(frame.t)
            rows.append(j)
        joints = np.stack(rows) if rows else np.zeros((0, N_JOINTS, 3))
        return cls(np.array(t), joints, None, label or f"person {person}")


def smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Each column of (N, k) low-passed by a Gaussian of s.d. ``sigma`` samples, zero phase.

    Missing samples (NaN) stay missing and do not pull their neighbours: the
    kernel is renormalised over the samples present.
    """
    half = max(1, int(np.ceil(3 * sigma)))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    out = np.full_like(x, np.nan, dtype=float)
    for c in range(x.shape[1]):
        ok = np.isfinite(x[:, c])
        if not ok.any():
            continue
        # "full" then the centre: "same" would return the kernel's length for a short series
        n = len(ok)
        num = np.convolve(np.where(ok, x[:, c], 0.0), kernel)[half:half + n]
        den = np.convolve(ok.astype(float), kernel)[half:half + n]
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, c] = np.where(ok, num / den, np.nan)
    return out


def fill(t: np.ndarray, x: np.ndarray, max_gap_s: float) -> np.ndarray:
    """(N, 3) with NaN runs no longer than ``max_gap_s`` (between two known samples) filled."""
    return _fill(t, x, max_gap_s)


def _fill(t: np.ndarray, x: np.ndarray, max_gap_s: float) -> np.ndarray:
    """(N, 3) with NaN runs no longer than ``max_gap_s`` (between two known samples) filled."""
    ok = np.isfinite(x).all(axis=1)
    if ok.all() or ok.sum() < 2:
        return x
    out = x.copy()
    idx = np.flatnonzero(ok)
    gaps = np.flatnonzero(np.diff(idx) > 1)
    for g in gaps:
        a, b = idx[g], idx[g + 1]
        if t[b] - t[a] <= max_gap_s + 1e-9:
            u = ((t[a + 1:b] - t[a]) / (t[b] - t[a]))[:, None]
            out[a + 1:b] = x[a] * (1.0 - u) + x[b] * u
    return out
