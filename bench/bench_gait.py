"""Seed 003's central experiment on real walking: one-sided vs two-sided tracking against the truth.

Real walking comes from motion capture: the CMU takes 131_01 and 131_02
("start, walk, stop"; 120 Hz). Each take is played by the simulator's
performer along seed 003's walkway (six virtual Kinect v2 sensors in three
rows of two, facing the oncoming walker; the built-in ``walkway``
scenario, whose Kinect model is spelled out in full), at four body heights
and mirrored left for right: 16 virtual subjects, each walked ``--seeds``
times from a different start on the walkway. Every recording is analysed
twice from the very same datagrams, as seed 003 did: with the three sensors
on the walker's left only (one-sided) and with all six (two-sided); the
truth is the motion capture itself, analysed the same way (foot events,
steps). Optionally (``--engine``) a third row: stage's own live fusion
(engine + Kalman smoothing, all six sensors) over the same datagrams.

Printed, in the layout of seed 003's Tables 1-3: per parameter and side,
measured and true mean +- SD, Pearson's r, N, Bland-Altman bias, RPC (1.96
SD of the differences), CV (%), ICC(A,1), on three levels: single steps,
subject averages (AV) per side, and subject averages over both sides (AV
AVG). The closing note checks seed 003's shape: two-sided agrees better
with the truth than one-sided, especially in step width.

    python bench/bench_gait.py               # 16 subjects x 2 walks (about 3 minutes)
    python bench/bench_gait.py --quick       # 2 subjects x 1 walk, a smoke test
    python bench/bench_gait.py --seeds 3 --engine --json
    python bench/bench_gait.py --set-gait    # walks with a set gait instead (no CMU needed)

The CMU data are not part of the repository: $STAGE_CMU_DIR or a
``shared/data/cmu`` folder above the checkout (the bench says where it
looked and stops if they are missing). "The data used in this project was
obtained from mocap.cs.cmu.edu. The database was created with funding from
NSF EIA-0196217."
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import machine_busy_s  # noqa: E402

from stage.analysis.agreement import agreement, category  # noqa: E402
from stage.analysis.analyze import Subset, analyse_trajectory, compare  # noqa: E402
from stage.analysis.integrate import integrate  # noqa: E402
from stage.analysis.trajectory import Trajectory  # noqa: E402
from stage.testing.walks import LEFT, cmu_file, cmu_walker, simulate, truth, walkway  # noqa: E402

TAKES = ("131_01", "131_02")
HEIGHTS = (1.60, 1.70, 1.80, 1.90)
SPATIAL = (("stride_length", "Stride length"), ("step_length", "Step length"),
           ("step_width", "Step width"))
FIELD = {"stride_length": "stride", "step_length": "length", "step_width": "width",
         "step_time": "time"}


def engine_trajectory(sim, duration: float) -> Trajectory:
    """stage's live fusion (engine, Kalman) of the same datagrams, as a trajectory."""
    from stage.app.offline import feed
    from stage.clock import ManualClock
    from stage.engine import Engine
    clock = ManualClock(0.0)
    engine = Engine(sim.rig(), clock)
    frames = []
    engine.listeners.append(frames.append)
    feed(engine, clock, sim.stream(duration), until=duration + 0.5)
    return Trajectory.from_frames(frames, label="engine")


def straight(true, max_turn_deg: float = 30.0) -> set[int]:
    """ids of the true steps walked along the walkway (pelvis heading within ``max_turn_deg``
    of +z at the placement): seed 003's subjects walked a straight corridor; the CMU takes
    also turn on the spot before they set off."""
    from stage.analysis.gait import walking_direction
    d, speed = walking_direction(true.trajectory)
    out = set()
    for s in true.steps:
        k = int(np.clip(np.searchsorted(true.trajectory.t, s.t), 0, len(d) - 1))
        if speed[k] >= 0.2 and d[k, 1] >= math.cos(math.radians(max_turn_deg)):
            out.add(id(s))
    return out


def run_trial(take: str, height: float, mirrored: bool, seed: int, engine: bool) -> dict:
    """One walk: the truth's steps and each method's paired steps."""
    start_z = 0.6 + 0.5 * (seed % 3)
    performer = cmu_walker(cmu_file(take), height=height, mirrored=mirrored,
                           start=(0.0, start_z))
    duration = performer.length + 0.5
    frames, rig, sim = simulate(walkway(performer, duration), seed)
    true = analyse_trajectory(truth(performer, duration), Subset("truth"))
    out = {"truth": true, "methods": {}, "straight": straight(true)}
    subsets = {"one-sided": list(LEFT), "two-sided": None}
    for name, sensors in subsets.items():
        r = analyse_trajectory(integrate(frames, rig, sensors, label=name), Subset(name, sensors))
        compare(r, true)
        out["methods"][name] = r
    if engine:
        from stage.analysis.analyze import align_truth
        traj = engine_trajectory(sim, duration)
        # the engine's clock: arrival time (capture + 60-80 ms latency); align like any recording
        shift = align_truth(traj, true.trajectory)
        traj = Trajectory(traj.t - shift, traj.joints, None, "engine")
        r = analyse_trajectory(traj, Subset("engine"))
        compare(r, true)
        out["methods"]["engine"] = r
    return out


def _v(step, parameter: str) -> float:
    v = getattr(step, FIELD[parameter])
    return math.nan if v is None else float(v)


def tables(trials: list[dict], methods: list[str], all_steps: bool = False) -> dict:
    """Seed 003's statistics per method, parameter and level (steps, AV, AV AVG)."""
    out: dict = {}
    for method in methods:
        rows: dict = {}
        for parameter in ("step_time", "stride_length", "step_length", "step_width"):
            for side in ("left", "right"):
                m, t, subj_m, subj_t = [], [], {}, {}
                for trial in trials:
                    r = trial["methods"][method]
                    key = trial["subject"]
                    for ms, ts in r.pairs:
                        if ts.side != side or ms.first or ts.first:
                            continue
                        if not all_steps and id(ts) not in trial["straight"]:
                            continue
                        a, b = _v(ms, parameter), _v(ts, parameter)
                        if math.isfinite(a) and math.isfinite(b):
                            m.append(a)
                            t.append(b)
                            subj_m.setdefault(key, []).append(a)
                            subj_t.setdefault(key, []).append(b)
                rows[(parameter, side, "steps")] = agreement(np.array(m), np.array(t))
                keys = sorted(subj_m)
                rows[(parameter, side, "AV")] = agreement(
                    np.array([np.mean(subj_m[k]) for k in keys]),
                    np.array([np.mean(subj_t[k]) for k in keys]))
                rows[(parameter, side, "_subjects")] = (subj_m, subj_t)
            lm, lt = rows[(parameter, "left", "_subjects")]
            rm, rt = rows[(parameter, "right", "_subjects")]
            keys = sorted(set(lm) & set(rm))
            rows[(parameter, "AVG", "AV")] = agreement(
                np.array([0.5 * (np.mean(lm[k]) + np.mean(rm[k])) for k in keys]),
                np.array([0.5 * (np.mean(lt[k]) + np.mean(rt[k])) for k in keys]))
        speeds_m, speeds_t = {}, {}
        for trial in trials:
            r = trial["methods"][method]
            if math.isfinite(r.gait["speed"]) and math.isfinite(trial["truth"].gait["speed"]):
                speeds_m.setdefault(trial["subject"], []).append(r.gait["speed"])
                speeds_t.setdefault(trial["subject"], []).append(trial["truth"].gait["speed"])
        keys = sorted(speeds_m)
        rows[("speed", "AV", "AV")] = agreement(np.array([np.mean(speeds_m[k]) for k in keys]),
                                                np.array([np.mean(speeds_t[k]) for k in keys]))
        out[method] = {k: v for k, v in rows.items() if k[2] != "_subjects"}
    return out


def print_table(method: str, rows: dict) -> None:
    print(f"\n{method}: measured vs motion-capture truth (units: cm, s for step time, cm/s "
          "for speed)")
    print(f"{'parameter':26s} {'measured':>15s} {'truth':>15s} {'r':>6s} {'N':>4s} {'bias':>6s} "
          f"{'RPC':>6s} {'CV %':>6s} {'ICC(A,1)':>9s}")
    order = [("speed", "AV", "AV", "AV walking speed")]
    for p, label in (("step_time", "Step time"),) + SPATIAL:
        order += [(p, "left", "steps", f"{label} L"), (p, "right", "steps", f"{label} R")]
    for p, label in (("step_time", "step time"), ("stride_length", "stride length"),
                     ("step_length", "step length"), ("step_width", "step width")):
        order += [(p, "left", "AV", f"AV {label} L"), (p, "right", "AV", f"AV {label} R"),
                  (p, "AVG", "AV", f"AV {label} AVG")]
    for p, side, level, label in order:
        a = rows.get((p, side, level))
        if a is None:
            continue
        scale = 1.0 if p == "step_time" else 100.0
        d = 3 if p == "step_time" else 2

        def f(v, digits=d):
            return "-" if v is None or not math.isfinite(v) else f"{v * scale:.{digits}f}"
        print(f"{label:26s} {f(a['mean'])+' ±'+f(a['sd']):>15s} "
              f"{f(a['truth_mean'])+' ±'+f(a['truth_sd']):>15s} "
              f"{'-' if not math.isfinite(a['r']) else format(a['r'], '.3f'):>6s} {a['n']:>4d} "
              f"{f(a['bias']):>6s} {f(a['rpc']):>6s} "
              f"{'-' if not math.isfinite(a['cv']) else format(a['cv'], '.2f'):>6s} "
              f"{'-' if not math.isfinite(a['icc']) else format(a['icc'], '.3f'):>9s}")


def shape(results: dict) -> list[tuple[str, bool]]:
    """Seed 003's claims, checked on this run's numbers (single steps)."""
    one, two = results["one-sided"], results["two-sided"]
    checks = []
    for p, label in SPATIAL:
        for side in ("left", "right"):
            a, b = one[(p, side, "steps")], two[(p, side, "steps")]
            checks.append((f"{label} {side[0].upper()}: two-sided agrees better (ICC "
                           f"{a['icc']:.3f} -> {b['icc']:.3f}, RPC {100 * a['rpc']:.2f} -> "
                           f"{100 * b['rpc']:.2f} cm)",
                           b["icc"] >= a["icc"] and b["rpc"] <= a["rpc"]))

    def gain(p: str, key: str) -> float:
        return float(np.mean([one[(p, s, "steps")][key] - two[(p, s, "steps")][key]
                              for s in ("left", "right")]))
    width_rpc = gain("step_width", "rpc") / np.mean([one[("step_width", s, "steps")]["rpc"]
                                                     for s in ("left", "right")])
    other = [gain(p, "rpc") / np.mean([one[(p, s, "steps")]["rpc"] for s in ("left", "right")])
             for p in ("step_length", "stride_length")]
    w_icc = -gain("step_width", "icc")
    o_icc = max(-gain(p, "icc") for p in ("step_length", "stride_length"))
    checks.append((f"step width gains most: ICC +{w_icc:.3f} (length, stride: at most "
                   f"+{o_icc:.3f}); RPC -{100 * width_rpc:.0f} % (length -{100 * other[0]:.0f} %, "
                   f"stride -{100 * other[1]:.0f} %)", w_icc >= o_icc))
    return checks


def closing_note(results: dict, methods: list[str]) -> None:
    """Bias, RPC and ICC(A,1) of single steps, method by method (seed 003's comparison)."""
    print("\nclosing note: single steps vs the motion-capture truth, bias / RPC (cm, s) and "
          "ICC(A,1)")
    print(f"{'':18s}" + "".join(f"{m:>30s}" for m in methods))
    for p, label in (("step_time", "Step time"),) + SPATIAL:
        scale = 1.0 if p == "step_time" else 100.0
        for side in ("left", "right"):
            cells = []
            for m in methods:
                a = results[m][(p, side, "steps")]
                cells.append(f"{a['bias'] * scale:+.2f} / {a['rpc'] * scale:.2f} / "
                             f"{a['icc']:.3f} {category(a['icc'])[:4]}")
            print(f"{label + ' ' + side[0].upper():18s}" + "".join(f"{c:>30s}" for c in cells))


def set_gait(seeds: list[int]) -> None:
    """Walks whose gait is set in the simulator: how far each analysis is from the set values."""
    from stage.testing.walks import gait_walker
    gaits = ((0.70, 0.12, 110.0), (0.55, 0.20, 95.0), (0.80, 0.08, 125.0))
    print("set gait (the simulator's planted-feet walker, 10 steps), walkway scenario; errors of "
          "the means vs the set values and per-step RMS vs the true steps")
    print(f"{'gait (m, m, /min)':22s} {'seed':>4s} {'subset':>9s} {'len cm':>7s} {'wid cm':>7s} "
          f"{'cadence':>8s} {'speed':>7s} {'RMS len':>8s} {'RMS wid':>8s} {'RMS time':>9s} "
          f"{'steps':>5s}")
    worst: dict = {}
    for length, width, cadence in gaits:
        for seed in seeds:
            performer, _ = gait_walker(10, length, width, cadence)
            duration = performer.length + 0.5
            frames, rig, _ = simulate(walkway(performer, duration), seed)
            true = analyse_trajectory(truth(performer, duration), Subset("truth"))
            for name, sensors in (("two-sided", None), ("one-sided", list(LEFT))):
                r = analyse_trajectory(integrate(frames, rig, sensors), Subset(name, sensors))
                compare(r, true)
                g, a = r.gait, r.agreement
                row = (100 * (g["step_length"]["all"]["mean"] - length),
                       100 * (g["step_width"]["all"]["mean"] - width),
                       100 * (g["cadence"] / cadence - 1),
                       100 * (g["speed"] / (length * cadence / 60) - 1),
                       100 * a["step_length"]["all"]["rmse"], 100 * a["step_width"]["all"]["rmse"],
                       1000 * a["step_time"]["all"]["rmse"])
                w = worst.setdefault(name, [0.0] * 7)
                worst[name] = [max(x, abs(v)) for x, v in zip(w, row)]
                print(f"{f'{length}, {width}, {cadence:g}':22s} {seed:4d} {name:>9s} "
                      f"{row[0]:+7.1f} {row[1]:+7.1f} {row[2]:+7.1f}% {row[3]:+6.1f}% "
                      f"{row[4]:5.1f} cm {row[5]:5.1f} cm {row[6]:6.0f} ms {len(r.pairs):5d}")
    for name, w in worst.items():
        print(f"worst {name}: mean length {w[0]:.1f} cm, width {w[1]:.1f} cm, cadence "
              f"{w[2]:.1f} %, speed {w[3]:.1f} %, RMS {w[4]:.1f} / {w[5]:.1f} cm, {w[6]:.0f} ms "
              "(tests/test_analysis_gait.py allows two-sided 2 / 3 cm, 3 %, 3.5 cm, 25 ms; "
              "one-sided 2 / 4 cm, 3 %, 5 cm, 30 ms)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="2 subjects x 1 walk (smoke test)")
    parser.add_argument("--seeds", type=int, default=2, help="walks per subject (default 2)")
    parser.add_argument("--engine", action="store_true",
                        help="also stage's live fusion (engine + Kalman) of all six sensors")
    parser.add_argument("--json", action="store_true", help="print the tables as JSON")
    parser.add_argument("--set-gait", action="store_true",
                        help="instead: walks with a gait set in the simulator (no CMU needed), "
                             "the errors against the set values (seeds 1, 2, 3, 5)")
    parser.add_argument("--all-steps", action="store_true",
                        help="also the steps of turning on the spot (default: straight walking "
                             "along the walkway only, as in seed 003's corridor)")
    args = parser.parse_args()
    if args.set_gait:
        set_gait([1] if args.quick else [1, 2, 3, 5])
        return 0
    missing = [t for t in TAKES if cmu_file(t) is None]
    if missing:
        print(f"bench_gait: CMU take(s) {', '.join(missing)} not found ($STAGE_CMU_DIR or "
              "shared/data/cmu above the checkout); nothing measured")
        return 0
    heights = (1.75,) if args.quick else HEIGHTS
    mirrors = (False,) if args.quick else (False, True)
    seeds = range(1, 2 if args.quick else args.seeds + 1)
    busy0, wall0 = machine_busy_s(), time.monotonic()
    trials = []
    for take in TAKES:
        for height in heights:
            for mirrored in mirrors:
                for seed in seeds:
                    trial = run_trial(take, height, mirrored, seed, args.engine)
                    trial["subject"] = f"{take}{' mirrored' if mirrored else ''} {height:.2f} m"
                    trials.append(trial)
    wall = time.monotonic() - wall0
    load = (machine_busy_s() - busy0) / wall / (os.cpu_count() or 1)
    methods = ["one-sided", "two-sided"] + (["engine"] if args.engine else [])
    results = tables(trials, methods, args.all_steps)
    subjects = len({t["subject"] for t in trials})
    steps = sum(len(t["truth"].steps) for t in trials)
    kept = sum(len(t["straight"]) for t in trials)
    if args.json:
        print(json.dumps({m: {" ".join(k): v for k, v in rows.items()}
                          for m, rows in results.items()}, indent=1))
        return 0
    print(f"bench_gait: {len(trials)} walks of {subjects} virtual subjects (CMU {', '.join(TAKES)}"
          f"; heights {', '.join(f'{h:.2f}' for h in heights)} m; mirrored: "
          f"{'yes and no' if len(mirrors) > 1 else 'no'}), {steps} true foot placements "
          f"({'all used' if args.all_steps else f'{kept} in straight walking used'}); "
          f"seed 003 walkway, Kinect model of the 'walkway' scenario; {wall:.0f} s, machine "
          f"load {100 * load:.0f} % of {os.cpu_count()} cores")
    for m in methods:
        print_table(m, results[m])
    closing_note(results, methods)
    print("\nseed 003's shape (its Tables 2 and 3: two-sided agrees better, especially step "
          "width):")
    for text, ok in shape(results):
        print(f"  {'PASS' if ok else 'FAIL'}  {text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
