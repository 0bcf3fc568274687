"""Calibrate a whole rig from recorded (or simulated) streams.

Every pair of sensors that saw one person at the same time gives an edge
(time-aligned, paired, calibrated with the chosen method); the graph then
gives each sensor its transform into the reference's space (best path,
composed), and a joint refinement over all overlaps finishes the job.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from itertools import combinations
from typing import Any, Callable

import numpy as np

from ..errors import CalibrationError
from ..geometry import rotation_angle_deg, transform_error
from .coverage import Gates, count_poses
from .fitness import fitness_from_median, weighted_median
from .graph import Edge, SensorGraph
from .methods import DEFAULT_PAIRS, calibrate
from .pairs import LagSearch, PairSet, find_lag, pair_streams
from .streams import Stream, find_identical_streams
from .uncertainty import Uncertainty, fit_uncertainty

log = logging.getLogger("stage.calibration")


@dataclass
class SensorCalibration:
    """The outcome for one sensor (``matrix``: its space -> the reference's).

    ``median_m`` (the judged, robust figure) and ``rms_m`` (plain, tails
    included) are the joint distances between this sensor and every placed
    sensor it overlaps, with the final transforms; ``lag_s`` is the lag the
    search found, summed along ``path``; ``method`` names what produced the
    matrix, with ", refined" when the joint refinement changed it.
    """

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
    median_m: float | None = None
    refined: dict[str, float] | None = None   # what refinement changed: rot_deg, trans_mm
    uncertainty: dict[str, Any] | None = None  # the spread of the overlaps along its path

    def as_json(self) -> dict[str, Any]:
        return {"matrix": None if self.matrix is None else
                [[round(float(v), 6) for v in row] for row in self.matrix],
                "median_m": None if self.median_m is None else round(self.median_m, 5),
                "rms_m": None if self.rms_m is None else round(self.rms_m, 5),
                "fitness": None if self.fitness is None else round(self.fitness, 4),
                "pairs": self.pairs, "method": self.method, "lag_s": round(self.lag_s, 4),
                "path": self.path, "refined": self.refined, "uncertainty": self.uncertainty,
                "error": self.error, "identical_to": self.identical_to}


@dataclass
class Overlap:
    """What happened to one pair of sensors (used as an edge, or why not)."""

    a: str
    b: str
    paired: int = 0                 # paired frames at the lag used
    poses: int = 0                  # distinct poses among them
    spread_m: float = 0.0           # rms spread of the torso over those poses
    lag_s: float | None = None      # b's clock minus a's
    lag_confidence: float | None = None
    median_m: float | None = None
    rms_m: float | None = None
    fitness: float | None = None
    used: bool = False
    reason: str | None = None       # why not used
    matrix: np.ndarray | None = None  # the pairwise fit, b's space -> a's
    uncertainty: Uncertainty | None = None  # the fit's spread over its independent poses

    def as_json(self) -> dict[str, Any]:
        def r(v, n=5):
            return None if v is None else round(float(v), n)
        return {"a": self.a, "b": self.b, "paired": self.paired, "poses": self.poses,
                "spread_m": r(self.spread_m, 3), "lag_s": r(self.lag_s, 4),
                "lag_confidence": r(self.lag_confidence, 3), "median_m": r(self.median_m),
                "rms_m": r(self.rms_m), "fitness": r(self.fitness, 4), "used": self.used,
                "reason": self.reason, "uncertainty": None if self.uncertainty is None
                else self.uncertainty.as_json(), "matrix": None if self.matrix is None else
                [[round(float(v), 6) for v in row] for row in self.matrix]}


@dataclass
class RigCalibration:
    reference: str
    sensors: dict[str, SensorCalibration]
    graph: SensorGraph
    refinement: dict[str, float] | None
    warnings: list[str]
    pair_sets: dict[tuple[str, str], PairSet] = field(default_factory=dict)
    lags: dict[tuple[str, str], LagSearch] = field(default_factory=dict)
    overlaps: list[Overlap] = field(default_factory=list)
    loops: list[dict[str, Any]] = field(default_factory=list)  # every triangle of fits

    @property
    def complete(self) -> bool:
        return all(s.matrix is not None for s in self.sensors.values())


def calibrate_streams(streams: dict[str, Stream], reference: str | None = None,
                      method: str = "rigid", pairs: int | None = None,
                      lag: str | float = "auto", max_lag_s: float = 1.0,
                      min_pairs: int | None = None, min_fitness: float | None = None,
                      refine: bool = True, options: dict[str, Any] | None = None,
                      progress: Callable[[str], None] | None = None,
                      gates: Gates | None = None) -> RigCalibration:
    """Calibrate every sensor of ``streams`` into ``reference``'s space.

    pairs: paired frames per sensor pair, spread over the recording
    (default 300, 500 for ``trajectory``; 0 = all). lag: "auto" (search
    within ±max_lag_s per pair), or a number of seconds applied to every
    non-reference stream. An overlap is used only when it passes ``gates``
    (``coverage.Gates``; ``min_pairs``/``min_fitness`` override its fields):
    enough paired frames and distinct poses, and a fit whose fitness
    (from the median joint distance) is at least ``min_fitness``, since two
    sensors watching different people at the same time would otherwise be
    "calibrated" to nonsense. Raises CalibrationError when nothing can be done.
    """
    say = progress or (lambda text: log.info("%s", text))
    options = options or {}
    gates = gates or Gates()
    if min_pairs is not None:
        gates = replace(gates, min_pairs=min_pairs)
    if min_fitness is not None:
        gates = replace(gates, min_fitness=min_fitness)
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
        edge = _edge(streams[a], streams[b], method, n_pairs, lag, max_lag_s, gates, options,
                     rig, say)
        if edge is not None:
            graph.add(edge)
    _check_loops(graph, rig, gates, say)
    transforms, composed, paths = _place(graph, reference, streams, n_pairs,
                                         refine and method != "regression", rig, say)
    for s in ids:
        if s in copies:
            rig.sensors[s] = SensorCalibration(s, None, error=f"bit-identical to {copies[s]}: "
                                               "a copied stream", identical_to=copies[s])
        elif s == reference:
            rig.sensors[s] = SensorCalibration(s, np.eye(4), 0.0, 1.0, 0, "reference", 0.0, [s],
                                               median_m=0.0)
        elif s not in transforms:
            why = _why_unconnected(s, rig, set(transforms))
            if why is None:  # it truly never overlapped a placed sensor
                rig.sensors[s] = SensorCalibration(
                    s, None, error=f"no chain of overlaps to the reference {reference}: it never "
                                   "saw one person at the same time as a connected sensor")
                warnings.append(f"{s} is not connected to the reference {reference} through any "
                                "overlap; walk where it and a calibrated sensor both see you")
            else:
                rig.sensors[s] = SensorCalibration(
                    s, None, error=f"no usable overlap links it to the reference {reference}: "
                                   f"{why}")
                warnings.append(f"{s} is not calibrated: {why}")
        else:
            rig.sensors[s] = _summary(s, transforms, composed[s], paths[s], graph, method,
                                      rig.overlaps)
    return rig


def _place(graph: SensorGraph, reference: str, streams: dict[str, Stream], n_pairs: int,
           refine: bool, rig: RigCalibration, say: Callable[[str], None],
           ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, list[str]]]:
    """Each sensor's final transform: (transforms, composed chains, paths).

    Without ``refine``: the chains along the best paths. With it, where the overlaps form
    loops, the candidates are every spanning tree of the overlaps (``SensorGraph.trees``),
    each composed and each jointly refined (``SensorGraph.refine``), and the one kept is
    the one that leaves the fewest overlaps more than ``KEEP_RATIO`` away from their own
    fits, then whose WORST overlap is closest to its own fit: the ratio of its median
    joint distance under the rig (at the lags the rig implies) to the pairwise fit's. Real takes' overlaps contradict each other (three views of one short take do
    not close a loop), and a rig judged by the mean disagreement over its overlaps moved
    the pair it composed 10-40 % away from its own optimum; judged per overlap, no pair
    is given up for the others."""
    best = graph.best_paths(reference)
    composed = graph.compose(reference, best)
    if not refine or len(composed) <= 2:
        return composed, composed, best
    cache: dict = {}
    candidates = []
    for paths in graph.trees(reference):
        chain = graph.compose(reference, paths)
        lags = {s: graph.path_lag(p) for s, p in paths.items()}
        refined, info = graph.refine(chain, reference)
        for name, t in (("composed", chain), ("refined", refined)):
            ratios = _overlap_ratios(graph, t, lags, streams, n_pairs, cache)
            score = ((sum(r > KEEP_RATIO for r in ratios), max(ratios),
                      float(np.mean(np.log(ratios)))) if ratios else (0, 0.0, 0.0))
            candidates.append((score, paths == best, name, paths, chain, t, info))
    # the best paths' plain chains win ties (the order before was: best paths, then refined)
    candidates.sort(key=lambda c: (c[0], not c[1], c[2] != "composed"))
    score, _, name, paths, chain, transforms, info = candidates[0]
    base = next(c for c in candidates if c[1] and c[2] == "composed")
    info = dict(info)
    info["kept"] = name == "refined"
    info["tree_changed"] = paths != best
    info["robust_before"] = graph.robust_disagreement(composed)
    info["robust_after"] = graph.robust_disagreement(transforms)
    info["before"], info["after"] = graph.objective(composed), graph.objective(transforms)
    info["worst_ratio_before"], info["worst_ratio_after"] = base[0][1], score[1]
    info["overlaps_off_before"], info["overlaps_off_after"] = base[0][0], score[0]
    rig.refinement = info
    say(f"joint refinement over {len(graph.edges)} overlaps: rms disagreement of every joint "
        f"pair of every overlap {np.sqrt(info['before']) * 1000:.1f} -> "
        f"{np.sqrt(info['after']) * 1000:.1f} mm, mean median per overlap "
        f"{info['robust_before'] * 1000:.1f} -> {info['robust_after'] * 1000:.1f} mm, worst "
        f"overlap against its own fit x{base[0][1]:.2f} -> x{score[1]:.2f} ({score[0]} of "
        f"{len(graph.edges)} more than x{KEEP_RATIO:g}): "
        f"{'kept' if info['kept'] else 'not kept'}"
        + ("" if paths == best else f" (chains through {_tree_text(paths)})"))
    return transforms, chain, paths


#: an overlap whose median under the rig is within this of its own fit's is kept as it is
KEEP_RATIO = 1.1


def _check_loops(graph: SensorGraph, rig: RigCalibration, gates: Gates,
                 say: Callable[[str], None]) -> None:
    """Three sensors that overlap pairwise must agree: their three pairwise fits, composed
    round the triangle, must come back to no turn within ``gates.max_loop_deg``. Where they
    do not, at least one fit is wrong, and the one with the largest median joint distance
    is taken out of the rig (if it was used) with the loop's figures as its reason.

    Why: on real short takes a fit can be tens of degrees wrong while its median residual,
    its ratio to a brute-force optimum and its bootstrap spread all look fine (a Kinect v1
    tracks a person seen from behind as if facing it; a few poses in place fit a wrong turn
    about as well as the right one). Judged against each N-UCLA subject's own rig (agreed
    by its other takes, bench/bench_calibration_consensus.py), no development triple whose
    three fits were all right had a loop over 10 degrees, and of the 24 open loops with a
    wrong fit the largest median named a wrong one 23 times (never a right one). Every
    triangle is recorded in ``rig.loops`` (its turn, and how far it moves a point
    ``gates.edge_m`` from the first sensor), judged or not. Fits refused for other reasons
    take part (they are evidence too) but only a used one is taken out."""
    fitted = {(o.a, o.b): o for o in rig.overlaps if o.matrix is not None}
    for a, b, c in combinations(sorted(graph.sensors), 3):
        abc = [fitted.get(k) for k in ((a, b), (b, c), (a, c))]
        if any(o is None for o in abc):
            continue
        ab, bc, ac = abc
        try:
            loop = ab.matrix @ bc.matrix @ np.linalg.inv(ac.matrix)   # a's space -> a's
        except np.linalg.LinAlgError:
            continue  # a degenerate affine fit (regression): nothing to compose
        if not np.isfinite(loop).all():
            continue
        turn = rotation_angle_deg(loop, np.eye(4))
        far = float(np.linalg.norm(loop[:3, :3] @ [0.0, 0.0, gates.edge_m] + loop[:3, 3]
                                   - [0.0, 0.0, gates.edge_m]))
        worst = max(abc, key=lambda o: o.median_m if o.median_m is not None else np.inf)
        record = {"sensors": [a, b, c], "rot_deg": round(turn, 3), "far_m": round(far, 4),
                  "open": bool(gates.max_loop_deg > 0 and turn > gates.max_loop_deg),
                  "dropped": None}
        rig.loops.append(record)
        if not record["open"] or not worst.used:
            continue
        graph.edges = [e for e in graph.edges if {e.a, e.b} != {worst.a, worst.b}]
        worst.used = False
        record["dropped"] = [worst.a, worst.b]
        worst.reason = (f"the three fits of {a}, {b} and {c} do not agree: composed round the "
                        f"triangle they turn {turn:.1f} degrees (tolerance "
                        f"{gates.max_loop_deg:g}) and move a point {gates.edge_m:g} m from "
                        f"{a} by {far * 100:.0f} cm; of the three this fit has the largest "
                        f"median joint distance ({worst.median_m * 100:.1f} cm), so it is not "
                        "used")
        rig.warnings.append(f"{worst.b} -> {worst.a}: {worst.reason}")
        say(f"{worst.b} and {worst.a}: {worst.reason}")


def _tree_text(paths: dict[str, list[str]]) -> str:
    return ", ".join("-".join(p) for s, p in sorted(paths.items()) if len(p) > 1)


def _overlap_ratios(graph: SensorGraph, t: dict[str, np.ndarray], lags: dict[str, float],
                    streams: dict[str, Stream], n_pairs: int, cache: dict) -> list[float]:
    """Per used overlap: its median joint distance under transforms ``t``, paired at the
    lag the rig implies (``lags``: each sensor's lag against the reference), over the
    median of its own pairwise fit."""
    out = []
    for e in graph.edges:
        if e.a not in t or e.b not in t:
            continue
        lag = lags[e.b] - lags[e.a]
        ps: PairSet | None = e.pairs
        if abs(lag - e.pairs.lag_s) > 1e-6:
            key = (e.a, e.b, round(lag, 5))
            if key not in cache:
                try:
                    cache[key] = pair_streams(streams[e.a], streams[e.b], lag).evenly(n_pairs)
                except CalibrationError:
                    cache[key] = None
            ps = cache[key]
        if ps is None or not len(ps):
            out.append(float("inf"))
            continue
        ta, tb = t[e.a], t[e.b]
        d = np.linalg.norm((ps.ref @ ta[:3, :3].T + ta[:3, 3])
                           - (ps.other @ tb[:3, :3].T + tb[:3, 3]), axis=-1).reshape(-1)
        own = e.result.median_m if np.isfinite(e.result.median_m) else float("nan")
        out.append(weighted_median(d, ps.weight.reshape(-1)) / max(own, 1e-3))
    return out


def _why_unconnected(s: str, rig: RigCalibration, placed: set[str]) -> str | None:
    """The real causes: each of ``s``'s overlaps with a placed sensor that paired frames,
    and why it was not used; None when it never paired a frame with one (no overlap)."""
    reasons = [f"with {o.b if o.a == s else o.a}: {o.reason}" for o in rig.overlaps
               if s in (o.a, o.b) and not o.used and o.paired
               and (o.b if o.a == s else o.a) in placed]
    return "; ".join(reasons) if reasons else None


def _edge(a: Stream, b: Stream, method: str, n_pairs: int, lag: str | float, max_lag_s: float,
          gates: Gates, options: dict[str, Any], rig: RigCalibration,
          say: Callable[[str], None]) -> Edge | None:
    o = Overlap(a.sensor, b.sensor)
    rig.overlaps.append(o)
    try:
        if lag == "auto":
            search = find_lag(a, b, max_lag_s, min_pairs=gates.min_pairs)
            rig.lags[(a.sensor, b.sensor)] = search
            lag_s, o.lag_confidence = search.lag_s, search.confidence
        else:
            lag_s = float(lag)
        o.lag_s = lag_s
        ps = pair_streams(a, b, lag_s)
    except CalibrationError as exc:
        o.reason = str(exc)  # these two never saw one person together: no edge
        return None
    o.paired = len(ps)
    o.poses, o.spread_m = count_poses(ps.other, ps.weight)
    o.reason = gates.too_little(o.paired, o.poses)
    if o.reason is not None:
        if o.paired >= gates.min_pairs and gates.judges_uncertainty:
            o.reason += _spread_note(ps.evenly(n_pairs), method, options, gates, o)
        if o.paired:
            say(f"{b.sensor} and {a.sensor}: {o.reason}; not used")
        return None
    used = ps.evenly(n_pairs)
    try:
        result = calibrate(used, method, **options)
    except CalibrationError as exc:
        o.reason = str(exc)
        rig.warnings.append(f"{b.sensor} -> {a.sensor}: {exc}")
        return None
    if lag == "auto" and method == "rigid" and len(ps) <= SHORT_OVERLAP:
        lag_s, ps, used, result = _refine_lag(a, b, lag_s, ps, used, result, n_pairs,
                                              gates, options)
        o.lag_s, o.paired = lag_s, len(ps)
        o.poses, o.spread_m = count_poses(ps.other, ps.weight)
    rig.pair_sets[(a.sensor, b.sensor)] = used
    o.median_m, o.rms_m, o.fitness = result.median_m, result.rms_m, result.fitness
    o.matrix = result.matrix
    text = (f"{b.sensor} -> {a.sensor}: {method}, {len(used)} of {len(ps)} paired frames "
            f"({o.poses} distinct poses), lag {lag_s:+.3f} s, median joint distance "
            f"{result.median_m * 1000:.0f} mm (rms {result.rms_m * 1000:.0f} mm), fitness "
            f"{result.fitness:.3f}")
    o.uncertainty = fit_uncertainty(used, result.matrix, gates.edge_m)
    o.reason = gates.too_poor(result.fitness, result.median_m, o.lag_confidence)
    if o.reason is not None:
        rig.warnings.append(f"{text}: {o.reason}; not used (were they watching different "
                            "people at the same time?)")
        return None
    o.reason = gates.too_uncertain(o.uncertainty)
    if o.reason is not None:
        rig.warnings.append(f"{text}: {o.reason}; not used (a longer take, or one where the "
                            "person moves about more, would determine it)")
        return None
    o.used = True
    say(f"{text}, spread {o.uncertainty.text()}")
    if gates.is_poor(result.fitness):
        rig.warnings.append(f"{b.sensor} -> {a.sensor}: a poor fit (median joint distance "
                            f"{result.median_m * 100:.1f} cm), used because the lag search "
                            f"found its timing clear (confidence {o.lag_confidence:.2f}); a "
                            "longer take with more movement would calibrate better")
    return Edge(a.sensor, b.sensor, result, used)


def _spread_note(used: PairSet, method: str, options: dict[str, Any], gates: Gates,
                 o: Overlap) -> str:
    """For an overlap refused for its poses: what its fit's spread would have been (so the
    refusal says how undetermined the fit is, not only that a count fell short)."""
    try:
        result = calibrate(used, method, **options)
    except CalibrationError:
        return ""
    o.uncertainty = fit_uncertainty(used, result.matrix, gates.edge_m)
    o.median_m, o.rms_m, o.fitness = result.median_m, result.rms_m, result.fitness
    return (f" (a fit on them: median joint distance {result.median_m * 100:.1f} cm, "
            f"{o.uncertainty.text()}; tolerance {gates.tolerance_text()})")


#: overlaps of at most this many paired frames get their lag refined with the fit itself
SHORT_OVERLAP = 120


def _refine_lag(a: Stream, b: Stream, lag_s: float, ps: PairSet, used: PairSet,
                result, n_pairs: int, gates: Gates, options: dict[str, Any]):
    """The lag and the fit refined together on a short overlap: the fit (concentration
    steps, one start) redone at lags a quarter of a frame apart within a frame of the
    searched one; the best lag's fit, redone with every start, replaces ``result`` if its
    median joint distance is lower. The search scores each lag with a quicker fit (least
    squares and two re-weightings), which on 1-2 s takes can rank lags a frame or two away
    from the ones the final fit does best at; the final fit is what the overlap is judged
    by. (Every start at every lag: the same accuracy on N-UCLA, twice the time.) Long
    overlaps keep the search's lag: their lag is sharp and this would cost seconds.
    Returns (lag, pairs, pairs used, result)."""
    step = b.frame_interval() / 4.0
    quick = {**options, "starts": 0}  # the scan: one start each; the winner refitted in full
    try:
        base = calibrate(used, "rigid", **quick).median_m
    except CalibrationError:
        return lag_s, ps, used, result
    scan = (base, lag_s, ps, used)
    for k in (-4, -3, -2, -1, 1, 2, 3, 4):
        lag = lag_s + k * step
        try:
            ps_k = pair_streams(a, b, lag)
        except CalibrationError:
            continue
        if len(ps_k) < max(gates.min_pairs, 0.6 * len(ps)):
            continue  # a few frames at the edge fit anything
        used_k = ps_k.evenly(n_pairs)
        try:
            med_k = calibrate(used_k, "rigid", **quick).median_m
        except CalibrationError:
            continue
        if med_k < scan[0] - 1e-6:
            scan = (med_k, lag, ps_k, used_k)
    if scan[1] == lag_s:
        return lag_s, ps, used, result
    full = calibrate(scan[3], "rigid", **options)
    if full.median_m < result.median_m - 1e-6:
        return scan[1], scan[2], scan[3], full
    return lag_s, ps, used, result


def _path_uncertainty(path: list[str], overlaps: list[Overlap]) -> dict[str, Any] | None:
    """The spread of a sensor's chain: its overlaps' spreads added in quadrature (as if
    independent; each overlap's far-edge point is its own sensor's), with the overlaps."""
    found = []
    for near, far in zip(path, path[1:]):
        o = next((o for o in overlaps if {o.a, o.b} == {near, far}), None)
        if o is None or o.uncertainty is None:
            return None
        found.append(o.uncertainty)
    if not found:
        return None
    rot = float(np.sqrt(sum(u.rot_deg ** 2 for u in found)))
    far_m = float(np.sqrt(sum(u.far_m ** 2 for u in found)))
    return {"rot_deg": round(rot, 3) if np.isfinite(rot) else None,
            "far_m": round(far_m, 4) if np.isfinite(far_m) else None,
            "edge_m": found[0].edge_m, "overlaps": len(found)}


def _summary(s: str, transforms: dict[str, np.ndarray], composed: np.ndarray, path: list[str],
             graph: SensorGraph, method: str, overlaps: list[Overlap]) -> SensorCalibration:
    """Score a sensor's final transform over every overlap it has with placed sensors."""
    ds, ws = [], []
    for e in graph.edges:
        if s in (e.a, e.b) and e.a in transforms and e.b in transforms:
            d, w = _distances(e, transforms)
            ds.append(d)
            ws.append(w)
    d, w = (np.concatenate(ds), np.concatenate(ws)) if ds else (np.zeros(0), np.zeros(0))
    median = weighted_median(d, w)
    rms = float(np.sqrt((w * d * d).sum() / w.sum())) if w.sum() > 0 else float("nan")
    lag = graph.path_lag(path)
    pairs = 0
    for near, far in zip(path, path[1:]):
        found = graph.edge(near, far)
        if found is not None:
            pairs = len(found[0].pairs)
    change = transform_error(transforms[s], composed)
    refined = None
    if change["rot_deg"] > 0.01 or change["trans_mm"] > 0.1:
        refined = {"rot_deg": round(change["rot_deg"], 3),
                   "trans_mm": round(change["trans_mm"], 1)}
    name = method if refined is None else f"{method}, refined"
    return SensorCalibration(s, transforms[s], rms, float(fitness_from_median(median)), pairs,
                             name, lag, path, median_m=median, refined=refined,
                             uncertainty=_path_uncertainty(path, overlaps))


def _distances(e: Edge, transforms: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """|Ta p_a - Tb p_b| (flat) and the edge's pair weights (works for affine T too)."""
    ta, tb = transforms[e.a], transforms[e.b]
    w = e.pairs.weight.reshape(-1)
    d = (e.pairs.ref @ ta[:3, :3].T + ta[:3, 3]) - (e.pairs.other @ tb[:3, :3].T + tb[:3, 3])
    return np.sqrt((d * d).sum(axis=-1)).reshape(-1), w


__all__ = ["calibrate_streams", "RigCalibration", "SensorCalibration", "Overlap"]
