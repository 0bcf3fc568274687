"""Fusion judged on real sensors: each N-UCLA view held out in turn, the other two fused.

bench_fusion.py measures the fused error against the truth the simulator knows; the
simulator's Kinects are our own model, and on N-UCLA's real Kinect v1 views of one person the
fusion's instant check leaves about one joint in eight out (stop 43), because calibrated real
views disagree by ~10 cm. Whether that helps or hurts cannot be read from the simulator.
Real takes have no truth, but three sensors filmed each one at once: fuse two views and
compare the stream of fused skeletons with the third view, which the fusion never saw. The
held-out view's own noise and its body-fit offset add the same to every method compared, so
the ranking of methods is that of their errors (their absolute values are not errors).

For each clean development take (``nucla.triples``: never s02/s03/s08/s09; takes with copied
views skipped):
- v02 and v03 are put into v01's space (stage space) by their per-take brute-force fits
  (``nucla_consensus.take_fits``, cached in ``--fits``) and shifted by the fit's lag. A take is
  used only where both fits agree with the rig the subject's OTHER takes agree on (the
  consensus within ``AGREE_M``): a wrong calibration would judge the calibration, not the
  fusion;
- for each held-out view h, the other two views go through an engine as timetagged sensor
  datagrams (one per frame, in capture order, arrival = capture time) and every fused body
  the engine holds after a datagram is recorded at its capture time;
- each held-out frame's joints are compared with each method's estimate at that frame's time
  (linear between the two samples around it, none further than ``MAX_GAP_S`` apart), over the
  joints every method has there.

Methods, in the same run: the engine with the default rig, with other
``fusion.view_offset_s`` (``--offset``; 0 turns the view offsets off) and
``fusion.view_bias_m`` (``--bias``), with any fusion or smoothing keys changed
(``--variant``), and with smoothing off; and the references a user could have without us:
each input view alone (raw), the plain mean of the two input views (raw, the second
interpolated to the first's times: it looks up to a frame ahead) and the live mean (after
each frame, the mean of each view's latest frame: what a live fuser without a filter gives,
using nothing captured later, as the engine). Each stream's jitter is printed too (each
sample's distance from the line between its neighbours), and every method's error split by
how far apart the two input views put the joint. ``--three`` also fuses all three views and
measures how each method stays with two views that agree where the third is far off.
``--subjects`` splits the development subjects (tune on some, check on the others).

    python bench/fusion_real.py bench/data/nucla --fits bench/data/nucla_fits.json
    python bench/fusion_real.py bench/data/nucla --fits F --subjects s01,s04,s05 --bias 0.02,0.05,0.1

docs/datasets.md says how to fetch the files into bench/data/nucla (never committed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time

import numpy as np

import nucla
import nucla_consensus as nc
from bench_calibration_real import copied, load_view

from stage.clock import ManualClock
from stage.engine.engine import Engine
from stage.joints import JOINT_INDEX
from stage.rig import Rig, set_calibration
from stage.sensors.importers.nucla import to_kinect2
from stage.sensors.protocol import encode_bundle, encode_client_joints
from stage.testing.native_shadow import Recorder

EPOCH = 1.7e9
FPS = 30.0
#: every take starts this far into the engine's clock (fit lags are within +-1 s)
BASE_S = 5.0
#: an estimate is interpolated between two samples at most this far apart
MAX_GAP_S = 0.1
SENSORS = ("nucla-v1", "nucla-v2", "nucla-v3")
#: the take_fits' hypotheses (``nucla_consensus.take_fits``'s default; its cache key)
HYPOTHESES = 60

GROUPS = {
    "trunk": ("SpineBase", "SpineMid", "SpineShoulder", "Head", "ShoulderLeft",
              "ShoulderRight", "HipLeft", "HipRight"),
    "limbs": ("ElbowLeft", "ElbowRight", "KneeLeft", "KneeRight"),
    "extremities": ("WristLeft", "WristRight", "HandLeft", "HandRight", "AnkleLeft",
                    "AnkleRight", "FootLeft", "FootRight"),
}
#: the bands of the two input views' disagreement on a joint the report splits by, mm
APART_MM = (0, 50, 100, 200, 400, float("inf"))
#: ``--three``: two views this close on a joint agree (m)...
PAIR_M = 0.10
#: ...and a third this far from their mean is the odd one (m)
ODD_M = 0.30
#: the raw input views' names in ``judge`` (``_generic``)
RAW_A, RAW_B = "raw input view A alone", "raw input view B alone"
GROUP_OF = {JOINT_INDEX[n]: g for g, names in GROUPS.items() for n in names}


def stage_view(skel: np.ndarray, matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 25, 3) stage-space joints and (T, 25) presence of a view's Kinect v1 frames."""
    joints = np.zeros((len(skel), 25, 3))
    present = np.zeros((len(skel), 25), dtype=bool)
    for j, frame in enumerate(skel):
        p, conf = to_kinect2(frame)
        joints[j] = p @ matrix[:3, :3].T + matrix[:3, 3]
        present[j] = conf > 0
    return joints, present


def interpolate(times: np.ndarray, joints: np.ndarray, ok: np.ndarray, at: float
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """A series' (25, 3) joints and (25,) availability at ``at`` (None: no bracketing pair)."""
    k = int(np.searchsorted(times, at, side="right"))
    if k == 0 or k == len(times):
        if k == len(times) and len(times) and times[-1] == at:
            return joints[-1], ok[-1]
        return None
    t0, t1 = times[k - 1], times[k]
    if t1 - t0 > MAX_GAP_S:
        return None
    w = 0.0 if t1 == t0 else (at - t0) / (t1 - t0)
    return (1 - w) * joints[k - 1] + w * joints[k], ok[k - 1] & ok[k]


def fused_series(rig: Rig, inputs: list[tuple[int, np.ndarray, float]], matrices: list
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Two input views through one engine: (times, joints, reported) of every fused body
    after each datagram, and how many persons the engine found."""
    engine = Engine(rig, ManualClock(0.0), Recorder())
    for s, _, _ in inputs:
        if s != 0:
            set_calibration(engine.rig, SENSORS[s], matrices[s], "bench")
        engine.set_calibration(SENSORS[s], matrices[s])
    items = []
    for s, skel, lag in inputs:
        for j, frame in enumerate(skel):
            joints, conf = to_kinect2(frame)
            if conf.any():
                items.append((BASE_S + j / FPS - lag, s, joints, conf))
    items.sort(key=lambda i: (i[0], i[1]))
    times, series, reported, last_tick, seen = [], [], [], 0.0, set()
    for t, s, joints, conf in items:
        engine.clock.set(t)
        data = encode_bundle([encode_client_joints(SENSORS[s], 0, joints, conf)], EPOCH + t)
        engine.handle_datagram(data, ("127.0.0.1", 7000 + s), arrival=t)
        if t - last_tick >= 0.02:
            engine.tick(t)
            last_tick = t
        bodies = engine.bodies()
        seen.update(bodies)
        if len(bodies) == 1:
            body = next(iter(bodies.values()))
            if not times or body.t > times[-1]:
                times.append(body.t)
                series.append(body.joints.copy())
                reported.append(body.conf > 0)
    return np.array(times), np.array(series), np.array(reported), len(seen)


def zigzag(times: np.ndarray, joints: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """A series' jitter: each sample's distance (m) from the line between the samples before
    and after it (joints reported at all three, neighbours within ``MAX_GAP_S``). Noise of
    s.d. s gives about 1.2 s at any rate; a smooth move gives almost nothing at 30 Hz, so a
    stream that swings between two views' positions shows as a large figure."""
    if len(times) < 3:
        return np.zeros(0)
    t0, t1, t2 = times[:-2], times[1:-1], times[2:]
    near = (t2 - t0 <= MAX_GAP_S) & (t2 > t0)
    w = np.where(near, (t1 - t0) / np.where(t2 > t0, t2 - t0, 1.0), 0.0)
    line = (1 - w)[:, None, None] * joints[:-2] + w[:, None, None] * joints[2:]
    d = np.linalg.norm(joints[1:-1] - line, axis=2)
    have = ok[:-2] & ok[1:-1] & ok[2:] & near[:, None]
    return d[have]


def raw_series(skel: np.ndarray, lag: float, matrix: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    joints, present = stage_view(skel, matrix)
    return BASE_S + np.arange(len(skel)) / FPS - lag, joints, present


def judge(take: dict, h: int, methods: dict) -> dict[str, list]:
    """Per method, the distances (m) of its estimates to held-out view ``h``'s joints, over
    the frames and joints every method has; each joint's group; and how far apart (m) the two
    raw input views put it there (``_apart``)."""
    skel, lag = take["views"][h], take["lags"][h]
    times, joints, present = raw_series(skel, lag, take["matrices"][h])
    out: dict[str, list] = {name: [] for name in methods}
    out["_group"] = []
    out["_apart"] = []
    for k, at in enumerate(times):
        est = {}
        for name, (ts, js, ok) in methods.items():
            got = interpolate(ts, js, ok, at) if len(ts) else None
            if got is None:
                break
            est[name] = got
        else:
            common = present[k].copy()
            for _, ok in est.values():
                common &= ok
            idx = np.flatnonzero(common)
            if not len(idx):
                continue
            for name, (js, _) in est.items():
                out[name].extend(np.linalg.norm(js[idx] - joints[k][idx], axis=1))
            out["_group"].extend(GROUP_OF.get(int(i), "other") for i in idx)
            a, b = est[RAW_A][0], est[RAW_B][0]
            out["_apart"].extend(np.linalg.norm(a[idx] - b[idx], axis=1))
    return out


def load_takes(folder: str, fits_path: str, subjects: set[str] | None, every: int,
               limit: int) -> tuple[list[dict], dict]:
    found = nucla.triples(folder)               # development subjects only, by file name
    if subjects:
        found = [(s, p) for s, p in found if nc.subject_of(s) in subjects]
    fits = nc.take_fits(found, load_view, copied, fits_path, hypotheses=HYPOTHESES)
    with open(fits_path, encoding="utf-8") as f:
        cache = json.load(f)
    counts = {"triples": len(found), "copied": 0, "no fit": 0, "off the rig": 0}
    takes = []
    for sample, paths in found[::every]:
        views = [load_view(p) for p in paths]
        if any(copied(a, b) for k, a in enumerate(views) for b in views[k + 1:]):
            counts["copied"] += 1
            continue
        matrices, lags, ok = [np.eye(4)], [0.0], True
        for k in (2, 3):
            hit = cache.get(f"{sample}:1:{k}:{HYPOTHESES}")
            if hit is None:
                counts["no fit"] += 1
                ok = False
                break
            m = np.array(hit["matrix"])
            ref = nc.consensus(fits.get((nc.subject_of(sample), 1, k), {}), leave_out=sample)
            if ref is None or nc.displacement(m, ref.matrix) > nc.AGREE_M:
                counts["off the rig"] += 1
                ok = False
                break
            matrices.append(m)
            lags.append(hit["lag_s"])
        if ok:
            takes.append({"sample": sample, "views": views, "matrices": matrices, "lags": lags})
        if limit and len(takes) >= limit:
            break
    counts["used"] = len(takes)
    return takes, counts


def rig_with(changes: dict, smoothing: bool = True) -> Rig:
    """The default rig with ``fusion`` or ``smoothing`` keys changed (a fresh one: engines
    write into it)."""
    rig = Rig(reference=SENSORS[0], views=[("127.0.0.1", 9)])
    fusion = {k: v for k, v in changes.items() if hasattr(rig.fusion, k)}
    rig.fusion = dataclasses.replace(rig.fusion, **fusion)
    rig.smoothing = dataclasses.replace(
        rig.smoothing, **{k: v for k, v in changes.items() if k not in fusion})
    rig.smoothing_enabled = smoothing
    return rig


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="the N-UCLA all_sqe files (docs/datasets.md)")
    parser.add_argument("--fits", default=None,
                        help="cache of the per-take fits (JSON; ~1.5 s a pair to compute; "
                             "default: nucla_fits.json beside the folder)")
    parser.add_argument("--subjects", default="",
                        help="comma-separated development subjects (default: all six)")
    parser.add_argument("--bias", default="0.1",
                        help="fusion.view_bias_m values besides the default (comma-separated)")
    parser.add_argument("--offset", default="0,0.25,1",
                        help="fusion.view_offset_s values besides the default (0: off)")
    parser.add_argument("--variant", action="append", default=[],
                        help="an engine with numeric fusion or smoothing keys changed: "
                             "KEY=VALUE[,...] (repeatable)")
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--limit", type=int, default=0)
    parser.add_argument("--three", action="store_true",
                        help="also fuse all three views and measure how each method stays "
                             "with two views that agree where the third is far off")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    subjects = {s.strip() for s in args.subjects.split(",") if s.strip()} or None
    if subjects and not subjects <= set(nucla.DEVELOPMENT):
        print(f"--subjects must be among the development subjects {nucla.DEVELOPMENT}",
              file=sys.stderr)
        return 2
    started = time.perf_counter()
    # (the fits' lags are read from the cache: there is always one)
    fits = args.fits or os.path.join(os.path.dirname(os.path.abspath(args.folder)),
                                     "nucla_fits.json")
    takes, counts = load_takes(args.folder, fits, subjects, args.every, args.limit)
    if not takes:
        print(f"no usable takes in {args.folder} ({counts}): see docs/datasets.md",
              file=sys.stderr)
        return 2
    default = Rig().fusion
    # name -> (fusion keys changed, smoothing); a fresh rig for every run
    engines = {f"engine (default: view_offset_s {default.view_offset_s:g}, view_bias_m "
               f"{default.view_bias_m:g})": ({}, True)}
    for key, values in (("view_offset_s", args.offset), ("view_bias_m", args.bias)):
        for v in (float(x) for x in values.split(",") if x.strip()):
            if v != getattr(default, key):
                engines[f"engine, {key} {v:g}"] = ({key: v}, True)
    for variant in args.variant:
        changes = {}
        for pair in variant.split(","):
            key, _, value = pair.partition("=")
            changes[key.strip()] = float(value)
        engines[f"engine, {variant}"] = (changes, True)
    engines["engine, smoothing off"] = ({}, False)
    print(f"N-UCLA development subjects {sorted(subjects) if subjects else 'all'}: "
          f"{counts['triples']} triples, {counts['copied']} with copied views, "
          f"{counts['no fit']} without a fit, {counts['off the rig']} fitted off the subject's "
          f"rig; {counts['used']} takes used, each view held out in turn", flush=True)
    dist: dict[str, list] = {}
    jitter: dict[str, list] = {}
    groups: list[str] = []
    apart: list[float] = []
    persons_extra: dict[str, int] = {}
    for take in takes:
        for h in range(3):
            inputs = [(s, take["views"][s], take["lags"][s]) for s in range(3) if s != h]
            methods = {}
            for name, (fusion, smoothing) in engines.items():
                ts, js, ok, persons = fused_series(rig_with(fusion, smoothing), inputs,
                                                   take["matrices"])
                if persons > 1:
                    persons_extra[name] = persons_extra.get(name, 0) + 1
                methods[name] = (ts, js, ok)
            for s, skel, lag in inputs:
                methods[f"raw view v0{s + 1} alone"] = raw_series(skel, lag, take["matrices"][s])
            (ta, ja, pa), (tb, jb, pb) = (raw_series(skel, lag, take["matrices"][s])
                                          for s, skel, lag in inputs)
            methods["raw mean of the two"] = _mean_series(ta, ja, pa, tb, jb, pb)
            methods["live mean of the two"] = _live_mean_series(ta, ja, pa, tb, jb, pb)
            methods = {_generic(n, inputs): m for n, m in methods.items()}
            for name, series in methods.items():
                jitter.setdefault(name, []).extend(zigzag(*series))
            got = judge(take, h, methods)
            for name, d in got.items():
                if name == "_group":
                    groups.extend(d)
                elif name == "_apart":
                    apart.extend(d)
                else:
                    dist.setdefault(name, []).extend(d)
    if args.three:
        three_views(takes, engines)
    report(dist, jitter, groups, apart, persons_extra, time.perf_counter() - started)
    return 0


def _generic(name: str, inputs: list) -> str:
    """A raw single view named by its place among the inputs (first / second)."""
    for rank, (s, _, _) in enumerate(inputs):
        if name == f"raw view v0{s + 1} alone":
            return f"raw input view {'AB'[rank]} alone"
    return name


def _mean_series(ta, ja, pa, tb, jb, pb):
    """The plain mean of two raw series at the first's times (where both have a joint)."""
    times, joints, ok = [], [], []
    for k, at in enumerate(ta):
        got = interpolate(tb, jb, pb, at)
        if got is None:
            continue
        j, p = got
        both = pa[k] & p
        joints.append(np.where(both[:, None], (ja[k] + j) / 2, 0.0))
        ok.append(both)
        times.append(at)
    return np.array(times), np.array(joints).reshape(-1, 25, 3), np.array(ok).reshape(-1, 25)


def _live_mean_series(*series):
    """The plain mean a live fuser without a filter gives: after each frame of any view,
    the mean of each view's latest frame (where every view has the joint); ``series`` is
    (times, joints, present) of each view, flattened. Unlike ``_mean_series``, which
    interpolates the second view to the first's times and so looks up to a frame ahead, it
    uses no frame captured after its time, as the engine."""
    views = [series[k:k + 3] for k in range(0, len(series), 3)]
    events = sorted((t, v, k) for v, (ts, _, _) in enumerate(views) for k, t in enumerate(ts))
    last: list[int | None] = [None] * len(views)
    times, joints, ok = [], [], []
    for at, v, k in events:
        last[v] = k
        if any(i is None for i in last):
            continue
        every = np.logical_and.reduce([p[i] for (_, _, p), i in zip(views, last)])
        mean = sum(j[i] for (_, j, _), i in zip(views, last)) / len(views)
        mean = np.where(every[:, None], mean, 0.0)
        if times and times[-1] == at:           # frames of one instant: one sample
            joints[-1], ok[-1] = mean, every
            continue
        times.append(at)
        joints.append(mean)
        ok.append(every)
    return np.array(times), np.array(joints).reshape(-1, 25, 3), np.array(ok).reshape(-1, 25)


def three_views(takes: list[dict], engines: dict) -> None:
    """All three views fused; where two views agree on a joint (within ``PAIR_M``) and the
    third is far from them (beyond ``ODD_M``), how close each method stays to the pair.
    There is no truth here either, but a view two others contradict is most likely the wrong
    one (a limb it fitted wrongly): this is what the gate's choice is for, and what the
    held-out runs, which leave two views, cannot show."""
    dist: dict[str, list] = {}
    for take in takes:
        inputs = [(s, take["views"][s], take["lags"][s]) for s in range(3)]
        raws = [raw_series(skel, lag, take["matrices"][s]) for s, skel, lag in inputs]
        methods = {name: fused_series(rig_with(fusion, smoothing), inputs, take["matrices"])[:3]
                   for name, (fusion, smoothing) in engines.items()}
        methods["live mean of the three"] = _live_mean_series(*[x for r in raws for x in r])
        for at in raws[0][0]:
            views = [interpolate(*r, at) for r in raws]
            est = {name: interpolate(*m, at) if len(m[0]) else None for name, m in methods.items()}
            if any(v is None for v in views) or any(e is None for e in est.values()):
                continue
            common = np.logical_and.reduce([v[1] for v in views] + [e[1] for e in est.values()])
            for j in np.flatnonzero(common):
                p = [v[0][j] for v in views]
                for a, b, c in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
                    pair = (p[a] + p[b]) / 2
                    if (np.linalg.norm(p[a] - p[b]) <= PAIR_M
                            and np.linalg.norm(p[c] - pair) > ODD_M):
                        for name, (js, _) in est.items():
                            dist.setdefault(name, []).append(np.linalg.norm(js[j] - pair))
                        dist.setdefault("the odd view", []).append(np.linalg.norm(p[c] - pair))
                        break
    n = len(dist.get("the odd view", []))
    print(f"\nall three views fused: {n} joints where two views agree within {PAIR_M * 100:g} cm "
          f"and the third is over {ODD_M * 100:g} cm from them; each method's distance to the "
          f"pair's mean, mm")
    print(f"{'method':44} {'rms':>6} {'p50':>6} {'p90':>6} {'nearer the odd view':>20}")
    odd = np.array(dist.get("the odd view", [])) * 1000
    for name, d in dist.items():
        d = np.array(d) * 1000
        print(f"{name:44} {np.sqrt(np.mean(d * d)):6.1f} {np.percentile(d, 50):6.1f} "
              f"{np.percentile(d, 90):6.1f} {100 * np.mean(d > odd / 2):19.0f}%")


def report(dist: dict[str, list], jitter: dict[str, list], groups: list[str], apart: list,
           persons_extra: dict[str, int], seconds: float) -> None:
    g = np.array(groups)
    n = len(g)
    print(f"\n{n} held-out joints compared (every method has each of them); distance to the "
          f"held-out view, mm (the held-out view's own noise and fit are in every row)")
    print(f"{'method':44} {'rms':>6} {'p50':>6} {'p90':>6} | "
          + " ".join(f"{k + ' rms':>15}" for k in GROUPS))
    for name, d in dist.items():
        d = np.array(d) * 1000
        row = f"{name:44} {np.sqrt(np.mean(d * d)):6.1f} {np.percentile(d, 50):6.1f} " \
              f"{np.percentile(d, 90):6.1f} | "
        row += " ".join(f"{np.sqrt(np.mean(d[g == k] ** 2)):15.1f}" for k in GROUPS)
        print(row)
    a = np.array(apart) * 1000
    print("\nby how far apart the two input views put the joint (mm): share of the joints, "
          "then each method's rms")
    bands = [(lo, hi) for lo, hi in zip(APART_MM[:-1], APART_MM[1:])]
    print(f"{'views apart':44} " + " ".join(f"{f'{lo:g}-{hi:g}':>9}" for lo, hi in bands))
    masks = [(a >= lo) & (a < hi) for lo, hi in bands]
    print(f"{'share of the joints':44} " + " ".join(f"{100 * m.mean():8.0f}%" for m in masks))
    for name, d in dist.items():
        d = np.array(d) * 1000
        print(f"{name:44} " + " ".join(
            f"{np.sqrt(np.mean(d[m] ** 2)) if m.any() else float('nan'):9.1f}" for m in masks))
    print("\njitter: each sample's distance from the line between its neighbours, mm "
          "(every joint each series reports)")
    print(f"{'method':44} {'samples':>8} {'rms':>6} {'p50':>6} {'p90':>6}")
    for name, d in jitter.items():
        d = np.array(d) * 1000
        print(f"{name:44} {len(d):8d} {np.sqrt(np.mean(d * d)):6.1f} "
              f"{np.percentile(d, 50):6.1f} {np.percentile(d, 90):6.1f}")
    split = ", ".join(f"{n}: {k}" for n, k in persons_extra.items()) or "none"
    print(f"runs where an engine found more than one person (its samples are left out while "
          f"it holds two): {split}; {seconds:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
