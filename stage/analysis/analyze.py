"""``stage analyze``'s library side: a recording in, gait and body KPIs out, per sensor subset.

    from stage.analysis.analyze import analyze_recording, Subset
    result = analyze_recording("walk.rec", subsets=[Subset("left", ["kinect-l1", "kinect-l2"]),
                                                    Subset("all", None)])
    result.as_json()["subsets"]["all"]["gait"]["step_length"]["left"]["mean"]

Each subset of sensors is integrated seed 003's way (``integrate``) from the
very same recording, then analysed alike: foot placements and gait
parameters (``gait``), seed 004's KPIs (``kpi``). With ground truth (the
simulator's ``--truth`` file, or any ``Trajectory``), the truth is analysed
the same way and every subset's steps are paired with the true ones (same
foot, placed within 0.25 s) for seed 003's agreement statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ..joints import JOINTS
from ..rig import Rig
from .agreement import agreement
from .gait import PARAMETERS, Step, foot_events, match_steps, same_steps, summary, values
from .integrate import SensorFrames, integrate, read_recording_frames
from .kpi import kpis
from .trajectory import Trajectory

_SIDES = ("left", "right", "all")


@dataclass
class Subset:
    """A named choice of sensors (None: every calibrated sensor)."""

    name: str
    sensors: list[str] | None = None


@dataclass
class SubsetResult:
    subset: Subset
    trajectory: Trajectory
    steps: list[Step]
    gait: dict
    kpi: dict
    pairs: list[tuple[Step, Step]] = field(default_factory=list)   # the same steps in both
    placements: int = 0                     # placements paired with true ones (same foot, time)
    agreement: dict = field(default_factory=dict)


@dataclass
class Analysis:
    source: str
    sensors: list[str]
    results: list[SubsetResult]
    truth: SubsetResult | None = None
    drops: dict = field(default_factory=dict)
    truth_shift_s: float | None = None

    def as_json(self) -> dict:
        def result(r: SubsetResult) -> dict:
            out = {"sensors": r.trajectory.meta.get("sensors", r.subset.sensors),
                   "samples": len(r.trajectory), "duration_s": r.trajectory.duration,
                   "gait": _clean(r.gait), "steps": [s.as_json() for s in r.steps],
                   "kpi": _clean(r.kpi),
                   "missing": {JOINTS[j]: round(float(m), 4)
                               for j, m in enumerate(r.trajectory.missing())}}
            if r.agreement:
                out["agreement"] = _clean(r.agreement)
                out["matched_placements"] = r.placements
                out["matched_steps"] = len(r.pairs)
            return out
        out = {"source": self.source, "sensors": self.sensors, "drops": self.drops,
               "subsets": {r.subset.name: result(r) for r in self.results}}
        if self.truth is not None:
            out["truth"] = {"gait": _clean(self.truth.gait),
                            "steps": [s.as_json() for s in self.truth.steps],
                            "shift_s": self.truth_shift_s}
        return out


def _clean(value):
    """JSON-safe: NaN -> None, numpy scalars -> floats, rounded to 6 digits."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return None if not math.isfinite(v) else round(v, 6)
    if isinstance(value, np.integer):
        return int(value)
    return value


def parse_subset(text: str) -> Subset:
    """``[NAME=]ID,ID,...`` or ``all`` -> Subset (the command line's ``--sensors``)."""
    name, _, ids = text.partition("=") if "=" in text else ("", "", text)
    ids = ids.strip()
    if not ids:
        raise ConfigError(f"--sensors '{text}': give sensor ids (a,b,c), NAME=a,b,c or all")
    if ids == "all":
        return Subset(name or "all", None)
    sensors = [s.strip() for s in ids.split(",") if s.strip()]
    return Subset(name or ",".join(sensors), sensors)


def analyse_trajectory(traj: Trajectory, subset: Subset) -> SubsetResult:
    steps = foot_events(traj)
    return SubsetResult(subset, traj, steps, summary(steps), kpis(traj))


def compare(result: SubsetResult, truth: SubsetResult) -> None:
    """Pair ``result``'s steps with the true ones and fill in its agreement statistics."""
    pairs = same_steps(result.steps, truth.steps)
    result.pairs = pairs
    result.placements = len(match_steps(result.steps, truth.steps))
    stats: dict = {}
    for p in PARAMETERS:
        stats[p] = {}
        for side in _SIDES:
            chosen = [(m, t) for m, t in pairs if side == "all" or t.side == side]
            m = np.array([_value(s, p) for s, _ in chosen], float)
            t = np.array([_value(s, p) for _, s in chosen], float)
            stats[p][side] = agreement(m, t)
    stats["speed"] = {"measured": result.gait["speed"], "truth": truth.gait["speed"]}
    result.agreement = stats


def _value(step: Step, parameter: str) -> float:
    v = values([step], parameter)
    return float(v[0]) if len(v) else math.nan


def align_truth(measured: Trajectory, truth: Trajectory) -> float:
    """Seconds to add to the truth's times so its pelvis best matches the measured one.

    A recording made live has its own clock; the truth counts from 0. Every
    shift that overlaps the two (on the measured trajectory's grid) is tried;
    the smallest median pelvis distance wins, and among shifts within 1 cm of
    it the one that compares the most samples (a looping scenario matches
    about as well one loop later, over less of the recording).
    """
    step = 1.0 / measured.rate
    lo, hi = measured.t[0] - truth.t[-1], measured.t[-1] - truth.t[0]
    tp, mp = truth.joints[:, 0], measured.joints[:, 0]
    tried: list[tuple[float, int, float]] = []       # (cost, samples compared, shift)
    for shift in np.arange(lo, hi + step, step):
        idx = np.searchsorted(measured.t, truth.t + shift)
        ok = (idx > 0) & (idx < len(measured.t))
        if ok.sum() < 30:
            continue
        d = np.linalg.norm(mp[idx[ok]] - tp[ok], axis=1)
        d = d[np.isfinite(d)]
        if len(d) >= 30:
            tried.append((float(np.median(d)), len(d), float(shift)))
    if not tried:
        return 0.0
    best = min(c for c, _, _ in tried)
    return max((n, -abs(s), s) for c, n, s in tried if c <= best + 0.01)[2]


def analyze_recording(path: str, subsets: list[Subset] | None = None, rig: Rig | None = None,
                      truth: Trajectory | None = None, *, rate: float = 30.0,
                      keep_inferred: bool = False,
                      frames: dict[str, SensorFrames] | None = None) -> Analysis:
    """Analyse ``path`` once per subset of sensors (default: one subset with every sensor).

    ``rig``: the calibrations (default: the one the recording carries).
    ``truth``: ground truth to compare with (its clock is aligned to the
    recording's when they differ).
    """
    meta: dict = {}
    drops: dict = {}
    if frames is None:
        frames, drops, meta = read_recording_frames(path)
    if rig is None:
        from ..sensors.replay import rig_from_meta
        rig = rig_from_meta(meta)
        if rig is None:
            if len(frames) > 1:
                raise ConfigError(f"{path}: the recording carries no rig and has "
                                  f"{len(frames)} sensors: give --rig (stage calibrate "
                                  f"{path} --rig RIG makes one)")
            rig = Rig(reference=next(iter(frames), None))
    results = []
    for subset in subsets or [Subset("all", None)]:
        traj = integrate(frames, rig, subset.sensors, rate=rate, keep_inferred=keep_inferred,
                         label=subset.name)
        results.append(analyse_trajectory(traj, subset))
    analysis = Analysis(path, sorted(frames), results, drops=drops)
    if truth is not None:
        shift = align_truth(results[0].trajectory, truth)
        shifted = Trajectory(truth.t + shift, truth.joints, None, truth.label or "truth")
        analysis.truth = analyse_trajectory(shifted, Subset("truth", None))
        analysis.truth_shift_s = shift
        for r in results:
            compare(r, analysis.truth)
    return analysis


def truth_trajectory(path: str, performer: str | None = None) -> Trajectory:
    """One performer of a simulator ground-truth file (``stage sim --truth``)."""
    from ..sensors.sim.truth import load_truth
    try:
        truth = load_truth(path)
    except (OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"{path}: not a ground-truth file ({exc})") from None
    names = truth.names
    if performer is None:
        if not names:
            raise ConfigError(f"{path}: the truth has no performers")
        performer = names[0]
    if performer not in names:
        raise ConfigError(f"{path}: no performer '{performer}' (performers: {', '.join(names)})")
    k = names.index(performer)
    return Trajectory(truth.t, truth.joints[:, k].astype(float), None, f"truth ({performer})")
