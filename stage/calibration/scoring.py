"""Fitness of live sensors: each against what the other trusted sensors say.

Per person (as the engine associated the views), every trusted view is
resampled on a common 30 Hz grid of new instants; each sensor is compared,
joint by joint, with the confidence-weighted average of the *other* views
(leave one out), so one pass per person scores every sensor that sees them.
Sums of weighted squared distances per sensor feed the windowed fitness.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..joints import N_JOINTS
from .live import View, torso_centre
from .pairs import resample


def grid(t0: float, t1: float, fps: float = 30.0) -> np.ndarray:
    """Instants k / fps in (t0, t1]."""
    first, last = int(np.floor(t0 * fps)) + 1, int(np.floor(t1 * fps))
    return np.arange(first, last + 1) / fps


@dataclass
class Sampled:
    """Views of one person on the grid: joints (S, G, 25, 3), conf (S, G, 25)."""

    sensors: list[str]
    joints: np.ndarray
    conf: np.ndarray

    @classmethod
    def of(cls, views: list[View], at: np.ndarray, placed: list[np.ndarray] | None = None,
           ) -> "Sampled":
        js, cs, names = [], [], []
        for k, v in enumerate(views):
            stage = v.stage if placed is None else placed[k]
            rows = np.isfinite(stage).all(axis=(1, 2))
            if not rows.any():
                continue
            j, c, _ = resample(v.t[rows], stage[rows], v.conf[rows], at, max_gap=0.1,
                               max_dt=0.05)
            js.append(j)
            cs.append(c)
            names.append(v.sensor)
        if not js:
            return cls([], np.zeros((0, len(at), N_JOINTS, 3)), np.zeros((0, len(at), N_JOINTS)))
        return cls(names, np.stack(js), np.stack(cs))

    def consensus(self) -> tuple[np.ndarray, np.ndarray]:
        """Everybody's weighted average (G, 25, 3) and its confidence (G, 25), capped at 1."""
        w = self.conf.sum(axis=0)
        tot = (self.conf[..., None] * self.joints).sum(axis=0)
        return tot / np.where(w > 0, w, 1.0)[..., None], np.minimum(w, 1.0)

    def leave_one_out(self) -> dict[str, tuple[float, float]]:
        """sensor -> (sum of w d^2, sum of w) against the other views' average."""
        out: dict[str, tuple[float, float]] = {}
        if len(self.sensors) < 2:
            return out
        w_all = self.conf.sum(axis=0)
        tot = (self.conf[..., None] * self.joints).sum(axis=0)
        for k, sid in enumerate(self.sensors):
            ow = w_all - self.conf[k]
            others = (tot - self.conf[k][..., None] * self.joints[k]) / \
                np.where(ow > 0, ow, 1.0)[..., None]
            pw = np.where(ow > 0, self.conf[k] * np.minimum(ow, 1.0), 0.0)
            d2 = ((self.joints[k] - others) ** 2).sum(axis=-1)
            sse, w = float((pw * d2).sum()), float(pw.sum())
            prev = out.get(sid, (0.0, 0.0))
            out[sid] = (prev[0] + sse, prev[1] + w)
        return out


def errors_against(sampled: Sampled, consensus: tuple[np.ndarray, np.ndarray],
                   ) -> tuple[float, float, float]:
    """(sum w d^2, sum w, median torso distance m) of ONE sampled view against a consensus."""
    joints, conf = sampled.joints[0], sampled.conf[0]
    cj, cc = consensus
    w = conf * cc
    d2 = ((joints - cj) ** 2).sum(axis=-1)
    a, b = torso_centre(joints, conf), torso_centre(cj, cc)
    dist = np.linalg.norm(a - b, axis=-1)
    dist = dist[np.isfinite(dist)]
    return float((w * d2).sum()), float(w.sum()), float(np.median(dist)) if len(dist) else np.inf


def score(views: dict[str, list[View]], states: dict, at: np.ndarray, match_m: float,
          ) -> dict[str, tuple[float, float]]:
    """Per sensor (sum of w d^2, sum of w) on the grid instants ``at``.

    states: sensor -> (state, transform, last good transform, duplicate_of).
    Trusted ("ok") sensors are grouped by the person the engine bound their
    views to and scored leave-one-out; a suspect sensor is scored with its
    last good transform against the person its view matches (nearest torso
    within ``match_m``), which is how a glitch is told from a move.
    """
    ok = {sid for sid, (state, *_rest) in states.items() if state == "ok"}
    persons: dict[int, list[View]] = {}
    for sid in ok:
        for v in views.get(sid, []):
            if v.person is not None and v.t[-1] > at[0] - 0.1:
                persons.setdefault(v.person, []).append(v)
    sums: dict[str, tuple[float, float]] = {}

    def add(sid: str, sse: float, w: float) -> None:
        a, b = sums.get(sid, (0.0, 0.0))
        sums[sid] = (a + sse, b + w)

    consensus_of = []
    for pviews in persons.values():
        sampled = Sampled.of(pviews, at)
        for sid, (sse, w) in sampled.leave_one_out().items():
            add(sid, sse, w)
        if sampled.sensors:
            consensus_of.append(sampled.consensus())
    for sid, (state, _t, last_good, dup) in states.items():
        if state != "suspect" or last_good is None or dup is not None:
            continue
        for v in views.get(sid, []):
            placed = v.raw @ last_good[:3, :3].T + last_good[:3, 3]
            mine = Sampled.of([v], at, [placed])
            if not mine.sensors or not consensus_of:
                continue
            sse, w, dist = min((errors_against(mine, c) for c in consensus_of), key=lambda e: e[2])
            if dist <= match_m:
                add(sid, sse, w)
    return sums
