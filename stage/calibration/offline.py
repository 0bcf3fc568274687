"""Calibrate a whole rig from recorded (or simulated) streams.

Every pair of sensors that saw one person at the same time gives an edge
(time-aligned, paired, calibrated with the chosen method); the graph then
gives each sensor its transform into the reference's space (best path,
composed), and a joint refinement over all overlaps finishes the job.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Callable

import numpy as np

from ..errors import CalibrationError
from .fitness import fitness_from_mse
from .graph import Edge, SensorGraph
from .methods import DEFAULT_PAIRS, calibrate
from .pairs import LagSearch, PairSet, find_lag, pair_streams
from .streams import Stream, find_identical_streams

log = logging.getLogger("stage.calibration")


@dataclass
class SensorCalibration:
    """The outcome for one sensor (``matrix``: its space -> the reference's)."""

    sensor: str
    matrix: np.ndarray | None
    rms_m: float | None = None
    fitness: float | None = None
    pairs: int = 0
    method: str | None = None
    lag_s: float = 0.0
    path: list[str] = field(default_factory=list)
    error: str | None = None
    identical_to: str | None = None

    def as_json(self) -> dict[str, Any]:
        return {"matrix": None if self.matrix is None else
                [[round(float(v), 6) for v in row] for row in self.matrix],
                "rms_m": None if self.rms_m is None else round(self.rms_m, 5),
                "fitness": None if self.fitness is None else round(self.fitness, 4),
                "pairs": self.pairs, "method": self.method, "lag_s": round(self.lag_s, 4),
                "path": self.path, "error": self.error, "identical_to": self.identical_to}


@dataclass
class RigCalibration:
    reference: str
    sensors: dict[str, SensorCalibration]
    graph: SensorGraph
    refinement: dict[str, float] | None
    warnings: list[str]
    pair_sets: dict[tuple[str, str], PairSet] = field(default_factory=dict)
    lags: dict[tuple[str, str], LagSearch] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return all(s.matrix is not None for s in self.sensors.values())


def calibrate_streams(streams: dict[str, Stream], reference: str | None = None,
                      method: str = "rigid", pairs: int | None = None,
                      lag: str | float = "auto", max_lag_s: float = 1.0, min_pairs: int = 30,
                      min_fitness: float = 0.5, refine: bool = True, options: dict[str, Any] | None = None,
                      progress: Callable[[str], None] | None = None) -> RigCalibration:
    """Calibrate every sensor of ``streams`` into ``reference``'s space.

    pairs: paired frames per sensor pair, spread over the recording
    (default 300, 500 for ``trajectory``; 0 = all). lag: "auto" (search
    within ±max_lag_s per pair), or a number of seconds applied to every
    non-reference stream. An overlap whose fit stays below ``min_fitness``
    (joints more than 10 cm apart on average) is not used: the two sensors
    were watching different people, or the method failed on that pair.
    Raises CalibrationError when nothing can be done.
    """
    say = progress or (lambda text: log.info("%s", text))
    options = options or {}
    if not streams:
        raise CalibrationError("the recording holds no skeletons")
    ids = sorted(streams)
    reference = reference or ids[0]
    if reference not in streams:
        raise CalibrationError(f"reference '{reference}' sent no skeletons; sensors: "
                               f"{', '.join(ids)}")
    n_pairs = DEFAULT_PAIRS.get(method, 300) if pairs is None else pairs
    warnings: list[str] = []
    copies: dict[str, str] = {}
    for a, b, count in find_identical_streams({s: streams[s] for s in ids}):
        copy, original = (a, b) if b == reference else (b, a)
        copies[copy] = original
        warnings.append(f"{copy} sent {count} skeletons bit-identical to {original}'s: a copied "
                        f"stream, not a sensor; left out")
    graph = SensorGraph([s for s in ids if s not in copies])
    rig = RigCalibration(reference, {}, graph, None, warnings)
    for a, b in combinations(graph.sensors, 2):
        edge = _edge(streams[a], streams[b], method, n_pairs, lag, max_lag_s, min_pairs,
                     min_fitness, options, rig, say)
        if edge is not None:
            graph.add(edge)
    transforms = graph.compose(reference)
    paths = graph.best_paths(reference)
    if refine and method != "regression" and len(transforms) > 2:
        refined, info = graph.refine(transforms, reference)
        rig.refinement = info
        transforms = refined
        say(f"joint refinement over {len(graph.edges)} overlaps: mean squared disagreement "
            f"{info['before'] * 1e6:.0f} -> {info['after'] * 1e6:.0f} mm^2 ({info['iterations']} iterations)")
    for s in ids:
        if s in copies:
            rig.sensors[s] = SensorCalibration(s, None, error=f"bit-identical to {copies[s]}",
                                               identical_to=copies[s])
        elif s == reference:
            rig.sensors[s] = SensorCalibration(s, np.eye(4), 0.0, 1.0, 0, "reference", 0.0, [s])
        elif s not in transforms:
            rig.sensors[s] = SensorCalibration(
                s, None, error=f"no chain of overlaps to the reference {reference}: it never "
                               f"saw one person at the same time as a connected sensor")
            warnings.append(f"{s} is not connected to the reference {reference} through any "
                            "overlap; walk where it and a calibrated sensor both see you")
        else:
            rig.sensors[s] = _summary(s, transforms, paths[s], graph, method)
    return rig


def _edge(a: Stream, b: Stream, method: str, n_pairs: int, lag: str | float, max_lag_s: float,
          min_pairs: int, min_fitness: float, options: dict[str, Any], rig: RigCalibration,
          say: Callable[[str], None]) -> Edge | None:
    try:
        if lag == "auto":
            search = find_lag(a, b, max_lag_s, min_pairs=min_pairs)
            rig.lags[(a.sensor, b.sensor)] = search
            lag_s = search.lag_s
        else:
            lag_s = float(lag)
        ps = pair_streams(a, b, lag_s)
    except CalibrationError:
        return None  # these two never saw one person together: no edge
    if len(ps) < min_pairs:
        if len(ps):
            say(f"{b.sensor} and {a.sensor}: only {len(ps)} paired frames (need {min_pairs}); "
                "not used")
        return None
    used = ps.evenly(n_pairs)
    rig.pair_sets[(a.sensor, b.sensor)] = used
    try:
        result = calibrate(used, method, **options)
    except CalibrationError as exc:
        rig.warnings.append(f"{b.sensor} -> {a.sensor}: {exc}")
        return None
    text = (f"{b.sensor} -> {a.sensor}: {method}, {len(used)} of {len(ps)} paired frames, lag "
            f"{lag_s:+.3f} s, rms {result.rms_m * 1000:.0f} mm, fitness {result.fitness:.3f}")
    if result.fitness < min_fitness:
        rig.warnings.append(f"{text}: below {min_fitness}, not used (were they watching "
                            "different people at the same time?)")
        return None
    say(text)
    return Edge(a.sensor, b.sensor, result, used)


def _summary(s: str, transforms: dict[str, np.ndarray], path: list[str], graph: SensorGraph,
             method: str) -> SensorCalibration:
    """Score a sensor's final transform over every overlap it has with placed sensors."""
    sse = weight = 0.0
    for e in graph.edges:
        if s in (e.a, e.b) and e.a in transforms and e.b in transforms:
            sse += _affine_sse(e, transforms)
            weight += float(e.pairs.weight.sum())
    mse = sse / weight if weight else float("nan")
    lag = 0.0
    pairs = 0
    for near, far in zip(path, path[1:]):
        found = graph.edge(near, far)
        if found is None:
            continue
        edge, reversed_ = found
        lag += -edge.pairs.lag_s if reversed_ else edge.pairs.lag_s
        pairs = len(edge.pairs)
    return SensorCalibration(s, transforms[s], float(np.sqrt(mse)), float(fitness_from_mse(mse)),
                             pairs, method, lag, path)


def _affine_sse(e: Edge, transforms: dict[str, np.ndarray]) -> float:
    """sum w |Ta p_a - Tb p_b|^2 with the edge's pair weights (works for affine T too)."""
    ta, tb = transforms[e.a], transforms[e.b]
    w = e.pairs.weight
    d = (e.pairs.ref @ ta[:3, :3].T + ta[:3, 3]) - (e.pairs.other @ tb[:3, :3].T + tb[:3, 3])
    return float((w * (d * d).sum(axis=-1)).sum())


__all__ = ["calibrate_streams", "RigCalibration", "SensorCalibration"]
