"""The live verdict: which sensors disagree with the others, judged relative to the others.

The monitor (``healing``) hands in, every poll, the joint distances of every
two trusted sensors that saw one person (``scoring.distances``, already binned into
weighted histograms: ``scoring.histogram``); this module
keeps the last ``window_s`` of them and decides, per sensor:

- its residual: the weighted median of its distances to the trusted sensors
  that agree with the rest (fitness: ``fitness.fitness_from_median``);
- its LEVEL: the same median over the pairs it is not part of -- how well the
  others agree among themselves right now, with these people, at these
  distances, through this occlusion;
- whether it is an OUTLIER: its fitness is below ``suspect_below`` AND its
  residual is more than ``suspect_ratio`` times the level (or its own
  baseline, whichever is larger: the worst window of the pairs it was
  calibrated on here, if it was). A sensor is
  suspect only when it disagrees with the others while they agree among
  themselves: a crowd far from every sensor, where everybody's joints are
  noisier, raises every residual together and blames nobody. Without a
  level (two sensors, or only pairs with this sensor), the absolute rule
  alone applies and the reference is never the outlier: with two sensors
  that disagree nobody can say which moved, and stage space is the
  reference's.

Suspects are compared (with their last good transform) against the trusted
sensors of the person they see; they fit again when their residual is back
above ``restore_above`` in fitness terms or within ``restore_ratio`` of the
level (or of their own residual while healthy: ``monitor``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .fitness import fitness_from_median
from .scoring import BIN_M, N_BINS, Distances, Histograms, histogram

NAN = float("nan")


def histogram_median(h: np.ndarray) -> float:
    """The weighted median of a ``histogram`` (linear within the bin), NaN if empty."""
    cum = np.cumsum(h)
    total = cum[-1]
    if total <= 0:
        return NAN
    k = int(np.searchsorted(cum, 0.5 * total))
    below = cum[k - 1] if k else 0.0
    frac = (0.5 * total - below) / h[k] if h[k] > 0 else 0.5
    return float((k + frac) * BIN_M)


class PairWindow:
    """Joint distances per sensor pair over the last ``window_s`` seconds of polls."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._polls: deque[tuple[float, dict[tuple[str, str], np.ndarray]]] = deque()

    def add(self, t: float, distances: Distances) -> None:
        self.add_histograms(t, {k: histogram(d, w) for k, (d, w) in distances.items()})

    def add_histograms(self, t: float, histograms: Histograms) -> None:
        """``add``, the distances already binned (``scoring.histogram``)."""
        if histograms:
            self._polls.append((t, histograms))
        while self._polls and self._polls[0][0] <= t - self.window_s:
            self._polls.popleft()

    def forget(self, sensor: str) -> None:
        """Drop every pair with ``sensor`` (its transform changed: old distances mean nothing)."""
        for _, d in self._polls:
            for key in [k for k in d if sensor in k]:
                del d[key]

    def clear(self) -> None:
        self._polls.clear()

    def keys(self) -> set[tuple[str, str]]:
        return {k for _, d in self._polls for k in d}

    def pooled(self, keys) -> np.ndarray:
        """The summed histogram of ``keys`` over the window."""
        total = np.zeros(N_BINS)
        wanted = set(keys)
        for _, d in self._polls:
            for k in wanted & d.keys():
                total += d[k]
        return total

    def median(self, keys) -> float:
        return histogram_median(self.pooled(keys))

    def totals(self) -> dict[tuple[str, str], np.ndarray]:
        """Per pair, its histogram summed over the window."""
        out: dict[tuple[str, str], np.ndarray] = {}
        for _, d in self._polls:
            for k, h in d.items():
                out[k] = out[k] + h if k in out else h.copy()
        return out


class _Pooled:
    """The window's totals of some pairs as rows of one array: the weighted median of any
    set of them, pooled (rows summed in the order given)."""

    def __init__(self, totals: dict, pairs: list) -> None:
        self.row = {k: i for i, k in enumerate(pairs)}
        self.rows = np.array([totals[k] for k in pairs]) if pairs else np.zeros((0, N_BINS))

    def median(self, keys: list) -> float:
        if not keys:
            return NAN
        return histogram_median(self.rows[[self.row[k] for k in keys]].sum(axis=0))


@dataclass
class Verdict:
    """One poll's judgement. Residuals in metres; NaN where there was nothing to compare."""

    residual: dict[str, float] = field(default_factory=dict)
    level: dict[str, float] = field(default_factory=dict)
    fitness: dict[str, float] = field(default_factory=dict)
    outliers: list[str] = field(default_factory=list)
    partners: dict[str, list[str]] = field(default_factory=dict)

    def why(self, sensor: str) -> str:
        """Words for an outlier: its residual against the others' agreement."""
        r, lvl = self.residual.get(sensor, NAN), self.level.get(sensor, NAN)
        partners = ", ".join(self.partners.get(sensor, [])) or "the others"
        text = f"its joints are {r * 100:.0f} cm (median) from {partners}'s"
        if np.isfinite(lvl):
            text += f", while the others agree within {lvl * 100:.0f} cm"
        return text


def judge(trusted: PairWindow, ok: list[str], reference: str | None, suspect_below: float,
          suspect_ratio: float, baselines: dict[str, float | None] | None = None) -> Verdict:
    """Residual, level, fitness and outliers of the trusted sensors ``ok``.

    baselines: the worst a sensor's residual was over any ``window_s`` of the
    pairs it was calibrated on here (m): a sensor calibrated from noisy real
    skeletons whose tracking wanders to 20 cm now and then is not suspect for
    doing it again; it is a second yardstick beside the level (the larger
    counts).
    """
    baselines = baselines or {}
    v = Verdict()
    okset = set(ok)
    totals = trusted.totals()
    pairs = [k for k in totals if k[0] in okset and k[1] in okset]
    pooled = _Pooled(totals, pairs)
    for s in ok:
        mine = [k for k in pairs if s in k]
        if not mine:
            continue
        others = [k for k in pairs if s not in k]
        r = pooled.median(mine)
        lvl = pooled.median(others)
        v.residual[s], v.level[s] = r, lvl
        v.partners[s] = sorted({p for k in mine for p in k if p != s})
        low = fitness_from_median(r) < suspect_below
        base = baselines.get(s)
        base = base if base is not None and np.isfinite(base) else NAN
        if np.isfinite(lvl) or np.isfinite(base):
            far = r > suspect_ratio * max(x for x in (lvl, base) if x == x)  # (nanmax)
        else:
            far = s != reference
        if low and far:
            v.outliers.append(s)
    bad = set(v.outliers)
    for s in v.residual:
        # a sensor's own fitness is judged against the partners that are not outliers
        # (with none, the pairs its residual was the median of)
        mine = [k for k in pairs if s in k and not (set(k) - {s}) & bad] if bad else []
        r = pooled.median(mine) if mine and s not in bad else v.residual[s]
        v.fitness[s] = float(fitness_from_median(r))
        if s not in bad:
            v.residual[s] = r
    return v


def judge_suspect(window: PairWindow, sensor: str, trusted: PairWindow, ok: list[str],
                  outliers: list[str]) -> tuple[float, float]:
    """(residual, level) of a suspect sensor placed with its last good transform."""
    good = [s for s in ok if s not in outliers]
    mine = [(sensor, p) for p in good]
    r = window.median(mine)
    goodset = set(good)
    lvl = trusted.median([k for k in trusted.keys() if k[0] in goodset and k[1] in goodset])
    return r, lvl
