"""The smoothing filters users would otherwise pick, as benchmark anchors.

Written here from their published descriptions, batched over points (rows)
with a Python loop over frames only:

- ``HoltFilter``: the Kinect for Windows SDK 1.x skeleton smoothing filter,
  Holt's double exponential smoothing with a jitter radius and a maximum
  deviation clamp. Source: M. Azimi, "Skeletal Joint Smoothing White Paper",
  Microsoft Developer Network (Kinect for Windows SDK 1.x documentation),
  2012, and the SDK's ``NUI_TRANSFORM_SMOOTH_PARAMETERS`` (smoothing,
  correction, prediction, jitter radius, max deviation radius; documented
  defaults 0.5, 0.5, 0.5, 0.05 m, 0.04 m). Per frame, for each joint: if the
  raw position is within the jitter radius of the last filtered one it is
  pulled towards it in proportion to its distance; then
  ``filtered = (1 - smoothing) * raw' + smoothing * (filtered + trend)``,
  ``trend = correction * (filtered - previous) + (1 - correction) * trend``;
  the output is ``filtered + prediction * trend``, clamped to within the max
  deviation radius of the raw position. The first frame is passed through; the
  second averages the two raw positions.
- ``OneEuroFilter``: G. Casiez, N. Roussel, D. Vogel, "1 Euro Filter: A Simple
  Speed-based Low-pass Filter for Noisy Input in Interactive Systems", CHI
  2012. A first-order low-pass whose cutoff grows with speed:
  ``cutoff = min_cutoff + beta * |dx/dt|`` (the derivative itself low-passed at
  ``d_cutoff``), ``alpha = 1 / (1 + tau / dt)``, ``tau = 1 / (2 pi cutoff)``.
  Applied to each coordinate on its own, as the paper's reference code does.
"""

from __future__ import annotations

import math

import numpy as np


class HoltFilter:
    """Kinect SDK 1.x joint smoothing for (N, 3) points; frames at the sensor's own rate."""

    DEFAULTS = dict(smoothing=0.5, correction=0.5, prediction=0.5, jitter_radius=0.05,
                    max_deviation_radius=0.04)

    def __init__(self, smoothing: float = 0.5, correction: float = 0.5, prediction: float = 0.5,
                 jitter_radius: float = 0.05, max_deviation_radius: float = 0.04) -> None:
        self.smoothing, self.correction, self.prediction = smoothing, correction, prediction
        self.jitter, self.max_dev = jitter_radius, max_deviation_radius
        self.frames = 0
        self.raw = self.filtered = self.trend = None

    def step(self, x: np.ndarray) -> np.ndarray:
        """x (N, 3) raw positions -> (N, 3) smoothed output."""
        if self.frames == 0:
            filtered, trend = x.copy(), np.zeros_like(x)
        elif self.frames == 1:
            filtered = 0.5 * (x + self.raw)
            trend = self.correction * (filtered - self.filtered) + (1 - self.correction) * self.trend
        else:
            d = np.linalg.norm(x - self.filtered, axis=1, keepdims=True)
            w = np.where(d <= self.jitter, d / self.jitter, 1.0)
            filtered = w * x + (1 - w) * self.filtered
            filtered = (1 - self.smoothing) * filtered + self.smoothing * (self.filtered + self.trend)
            trend = self.correction * (filtered - self.filtered) + (1 - self.correction) * self.trend
        out = filtered + self.prediction * trend
        d = np.linalg.norm(out - x, axis=1, keepdims=True)
        lam = np.where(d > self.max_dev, self.max_dev / np.maximum(d, 1e-12), 1.0)
        out = lam * out + (1 - lam) * x
        self.raw, self.filtered, self.trend = x, filtered, trend
        self.frames += 1
        return out


class OneEuroFilter:
    """The 1 Euro filter for (N, 3) points, per coordinate."""

    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0) -> None:
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff, beta, d_cutoff
        self.t = None
        self.x = self.dx = None

    @staticmethod
    def _alpha(cutoff, dt: float):
        tau = 1.0 / (2.0 * math.pi * cutoff)
        return 1.0 / (1.0 + tau / dt)

    def step(self, t: float, x: np.ndarray) -> np.ndarray:
        if self.t is None:
            self.t, self.x, self.dx = t, x.copy(), np.zeros_like(x)
            return self.x.copy()
        dt = max(t - self.t, 1e-6)
        dx = (x - self.x) / dt
        a_d = self._alpha(self.d_cutoff, dt)
        self.dx = a_d * dx + (1 - a_d) * self.dx
        a = self._alpha(self.min_cutoff + self.beta * np.abs(self.dx), dt)
        self.x = a * x + (1 - a) * self.x
        self.t = t
        return self.x.copy()
