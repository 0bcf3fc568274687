"""Calibration methods compared on the same simulated data, plus the GA's speed and curve,
the chain refinement gain, the lag search and the live calibrator's cost.

    python bench/bench_calibration.py            # everything (about a minute)
    python bench/bench_calibration.py --quick    # fewer repeats and runs
    python bench/bench_calibration.py --json

Data: the simulator (``stage.testing.simdata``): two Kinect v2 sensors 100
degrees apart around a 2.4 m x 1.6 m figure of eight, the second 0.7 m higher
and tilted down 8 degrees (both report their floor plane), with
``simdata.CLEAN_KINECT`` (the budget docs/calibration.md states the methods' accuracy for:
1 cm noise per axis, occluded joints inferred and pulled 3 cm towards the sensor, no heavy
tails), 40 s at 30 Hz; the realistic default model's figures are bench_calibration_real.py
(real recordings beside it) and bench_healing_sim.py;
300 paired frames per method (trajectory: 500, as in seed 002). Errors against ground truth: rotation (degrees),
translation (mm, the sensor's position), and RMS (mm) of where the estimate
and the truth put the sensor's points. Target: the GA in the paper's
configuration (200 x 250) under 0.5 s. Prints PASS/FAIL; always exits 0.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stage.geometry import transform_error  # noqa: E402
from stage.calibration.methods import METHODS, calibrate  # noqa: E402
from stage.calibration.methods.ga import run_ga  # noqa: E402
from stage.calibration.methods.rigid import kabsch  # noqa: E402
from stage.calibration.offline import calibrate_streams  # noqa: E402
from stage.calibration.pairs import find_lag, pair_streams  # noqa: E402
from stage.sensors.sim import Simulator  # noqa: E402
from stage.testing import simdata  # noqa: E402

GA_TARGET_S = 0.5
CURVE_EPOCHS = (0, 1, 2, 5, 10, 25, 50, 100, 150, 200, 250)


def _timed(fn, repeats: int) -> tuple[list[float], object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return times, out


def methods_table(repeats: int) -> dict:
    sim = Simulator(simdata.two_sensors(8.0, kinect=simdata.CLEAN_KINECT), seed=11)
    streams = simdata.streams(sim, 40.0)
    pairs = pair_streams(streams["kinect-a"], streams["kinect-b"])
    truth = simdata.true_transform(sim, "kinect-b")
    rows = {}
    for method in METHODS:
        used = pairs.evenly(500 if method == "trajectory" else 300)
        times, res = _timed(lambda: calibrate(used, method), repeats)
        err = transform_error(res.matrix, truth, pairs.other)
        rows[method] = {"pairs": len(used), "ms_median": statistics.median(times) * 1000,
                        "rms_data_mm": res.rms_m * 1000, "fitness": res.fitness,
                        "rot_deg": err["rot_deg"], "trans_mm": err["trans_mm"],
                        "truth_rms_mm": err["rms_mm"]}
    for robust in ("none", "ransac"):
        used = pairs.evenly(300)
        times, res = _timed(lambda: calibrate(used, "rigid", robust=robust), repeats)
        err = transform_error(res.matrix, truth, pairs.other)
        rows[f"rigid/{robust}"] = {"pairs": 300, "ms_median": statistics.median(times) * 1000,
                                   "rms_data_mm": res.rms_m * 1000, "fitness": res.fitness,
                                   "rot_deg": err["rot_deg"], "trans_mm": err["trans_mm"],
                                   "truth_rms_mm": err["rms_mm"]}
    return {"rows": rows, "paired_frames": len(pairs)}


def ga_figures(runs: int, timing_runs: int, points: bool) -> dict:
    streams = simdata.streams(Simulator(simdata.two_sensors(8.0, kinect=simdata.CLEAN_KINECT),
                                        seed=11), 40.0)
    pairs = pair_streams(streams["kinect-a"], streams["kinect-b"]).evenly(300)
    moments = pairs.moments()
    optimum = moments.mse_of(kabsch(moments))
    out: dict = {}
    for dims in (2, 3):
        times, _ = _timed(lambda: run_ga(moments, dims, 0), timing_runs)
        out[f"ga{dims}d_s"] = {"median": statistics.median(times), "max": max(times)}
    if points:  # the same run scored from the ~7500 raw joint pairs instead of the moments
        keep = pairs.weight.reshape(-1) > 0
        flat = (pairs.other.reshape(-1, 3)[keep], pairs.ref.reshape(-1, 3)[keep],
                pairs.weight.reshape(-1)[keep])
        t = time.perf_counter()
        by_points = run_ga(moments, 3, 0, objective="points", points=flat)
        out["ga3d_points_s"] = time.perf_counter() - t
        out["points_vs_moments_best"] = [float(by_points.best[-1]),
                                         float(run_ga(moments, 3, 0).best[-1])]
    curves, ratios = [], []
    for seed in range(runs):
        r = run_ga(moments, 3, seed)
        curves.append(r.best)
        ratios.append(r.mse / optimum)
    curves = np.array(curves)
    mean = curves.mean(axis=0)
    half = 1.96 * curves.std(axis=0, ddof=1) / np.sqrt(runs) if runs > 1 else np.zeros_like(mean)
    out["curve"] = {int(e): [float(mean[e]), float(half[e])] for e in CURVE_EPOCHS}
    out["runs"] = runs
    out["mse_ratio_to_closed_form"] = {"min": min(ratios), "median": statistics.median(ratios),
                                       "max": max(ratios)}
    return out


def chain_gain() -> dict:
    out = {}
    for label, spacing in (("neighbours only (a tree)", 2.5), ("every other overlaps too (loops)", 1.6)):
        sim = Simulator(simdata.row_of_sensors(4, spacing, simdata.CLEAN_KINECT), seed=0)
        streams = simdata.streams(sim, 80.0)
        t = time.perf_counter()
        composed = calibrate_streams(streams, "k0", refine=False, progress=lambda _: None)
        refined = calibrate_streams(streams, "k0", progress=lambda _: None)
        seconds = time.perf_counter() - t
        rows = {}
        for sid in ("k1", "k2", "k3"):
            truth = simdata.true_transform(sim, sid)
            pts = streams[sid].joints[::5]
            b = transform_error(composed.sensors[sid].matrix, truth, pts)
            a = transform_error(refined.sensors[sid].matrix, truth, pts)
            rows[sid] = {"path": refined.sensors[sid].path, "before": b, "after": a}
        out[label] = {"overlaps": len(refined.graph.edges), "sensors": rows,
                      "objective_mm2": None if refined.refinement is None else
                      [refined.refinement["before"] * 1e6, refined.refinement["after"] * 1e6],
                      "seconds_both_runs": seconds}
    return out


def lag_search() -> dict:
    sim = Simulator(simdata.two_sensors(8.0, offset_s=0.37, phase_s=0.013,
                                        kinect=simdata.CLEAN_KINECT), seed=12)
    streams = simdata.streams(sim, 30.0, clocks="sensor")
    t = time.perf_counter()
    found = find_lag(streams["kinect-a"], streams["kinect-b"])
    return {"true_s": 0.37, "found_s": found.lag_s, "seconds": time.perf_counter() - t,
            "lags_tried": len(found.lags)}


def live_costs() -> dict:
    """The live calibrator's cost: its observer on the engine thread (per frame) and its
    polls (worker thread), for 3 sensors x 1 dancer with a bump, and 6 sensors x 6 people."""
    from benchlib import exact_ring_rig
    from stage.calibration.healing import attach_live
    from stage.clock import ManualClock
    from stage.engine.engine import Engine
    from stage.sensors.protocol import encode_client_joints
    from stage.sensors.sim import VirtualKinect, demo_scenario, ring_poses, standing_pose

    dancer = demo_scenario(1).performers[0]

    def episode(n_sensors: int, n_people: int, seconds: float, bump: bool) -> dict:
        poses = ring_poses(n_sensors, radius=2.5 if n_people == 1 else 4.0)
        ids = [f"s{k}" for k in range(n_sensors)]
        rig = exact_ring_rig(poses)
        clock = ManualClock(0.0)
        engine = Engine(rig, clock)
        cal = attach_live(engine, None, threaded=False)
        polls: list[float] = []
        observed: list[float] = []
        real_poll, real_observe = cal._poll, cal._observe

        def timed_poll():
            t0 = time.perf_counter()
            real_poll()
            polls.append(time.perf_counter() - t0)

        def timed_observe(frame):
            t0 = time.perf_counter()
            real_observe(frame)
            observed.append(time.perf_counter() - t0)
        cal._poll = timed_poll
        engine.frame_observers[:] = [timed_observe]
        rng = np.random.default_rng(3)
        kinects = [VirtualKinect(p, simdata.kinect_model(), rng) for p in poses]
        frames = []
        for k in range(int(seconds * 30)):
            t = k / 30
            if bump and k == 5 * 30:
                kinects[1].pose = poses[1].moved(yaw=np.radians(10.0))
            for u in range(n_people):
                if n_people == 1:
                    truth = dancer.state(t)[0]
                else:
                    a = 2 * np.pi * u / n_people
                    truth = standing_pose((1.5 * np.cos(a) + 0.3 * np.sin(t), 1.5 * np.sin(a)),
                                          a + t)
                for i, sid in enumerate(ids):
                    seen = kinects[i].observe(truth, user=u)   # people observed one by one
                    if seen is not None:                       # (out of range: not sent)
                        frames.append((t + 0.002 * i, encode_client_joints(sid, u, *seen),
                                       ("127.0.0.1", 9000 + i)))
        frames.sort(key=lambda f: f[0])
        for t, data, source in frames:
            clock.set(max(clock.now(), t))
            engine.handle_datagram(data, source)
        # the observer's own cost: its total minus the polls it ran inline
        own = (sum(observed) - sum(polls)) / len(observed)
        ps = sorted(polls)
        out = {"frames": len(frames), "observer_us_per_frame": own * 1e6,
               "polls": len(ps), "poll_ms_p50": ps[len(ps) // 2] * 1000,
               "poll_ms_max": ps[-1] * 1000,
               "worker_share_of_a_core_at_10hz": ps[len(ps) // 2] * 10}
        if bump:
            ev = {e.kind: e.t for e in cal.events if e.sensor == "s1"}
            out["detected_after_s"] = ev.get("suspect", np.nan) - 5.0
            out["recovered_after_s"] = ev.get("calibrated", np.nan) - 5.0
        return out

    return {"3x1 with a bump": episode(3, 1, 12.0, True), "6x6": episode(6, 6, 4.0, False)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and GA runs")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    repeats = 2 if args.quick else 5
    report = {"methods": methods_table(repeats),
              "ga": ga_figures(5 if args.quick else 20, 3 if args.quick else 10, not args.quick),
              "chain": chain_gain(), "lag": lag_search(), "live": live_costs()}
    if args.json:
        print(json.dumps(report, indent=2, default=float))
        return 0
    m = report["methods"]
    print(f"methods on the same data ({m['paired_frames']} paired frames available):")
    print(f"  {'method':<13}{'pairs':>6}{'ms':>9}{'rms data mm':>13}{'fitness':>9}"
          f"{'rot deg':>9}{'trans mm':>10}{'truth rms mm':>14}")
    for name, r in m["rows"].items():
        print(f"  {name:<13}{r['pairs']:>6}{r['ms_median']:>9.1f}{r['rms_data_mm']:>13.1f}"
              f"{r['fitness']:>9.3f}{r['rot_deg']:>9.2f}{r['trans_mm']:>10.1f}"
              f"{r['truth_rms_mm']:>14.1f}")
    g = report["ga"]
    verdict = "PASS" if g["ga2d_s"]["median"] < GA_TARGET_S and g["ga3d_s"]["median"] < GA_TARGET_S \
        else "FAIL"
    print("\nGA, paper's configuration (population 200, 250 epochs), 300 pairs x 25 joints:")
    print(f"  2-D {g['ga2d_s']['median'] * 1000:.1f} ms (max {g['ga2d_s']['max'] * 1000:.1f}), "
          f"3-D {g['ga3d_s']['median'] * 1000:.1f} ms (max {g['ga3d_s']['max'] * 1000:.1f}) "
          f"-> target < {GA_TARGET_S} s: {verdict}")
    if "ga3d_points_s" in g:
        print(f"  the same 3-D run scored from the raw points instead of the moments: "
              f"{g['ga3d_points_s']:.2f} s, best fitness {g['points_vs_moments_best'][0]:.6f} "
              f"vs {g['points_vs_moments_best'][1]:.6f} from the moments")
    r = g["mse_ratio_to_closed_form"]
    print(f"  GA mse / closed-form mse over {g['runs']} seeds: min {r['min']:.4f} median "
          f"{r['median']:.4f} max {r['max']:.4f} (never below 1: the closed form is the optimum)")
    print(f"  convergence, best fitness by epoch (mean +- 95% CI over {g['runs']} runs, 3-D):")
    print("   " + "  ".join(f"{e}:{v[0]:.3f}+-{v[1]:.3f}" for e, v in g["curve"].items()))
    print("\nchain of 4 sensors along a wall, error of each against the truth "
          "(rot deg / RMS mm), composed chain -> jointly refined:")
    for label, c in report["chain"].items():
        obj = c["objective_mm2"]
        tail = "" if obj is None else f", mean squared disagreement {obj[0]:.0f} -> {obj[1]:.0f} mm^2"
        print(f"  {label}: {c['overlaps']} overlaps{tail}")
        for sid, row in c["sensors"].items():
            b, a = row["before"], row["after"]
            print(f"    {sid} via {'-'.join(row['path'])}: {b['rot_deg']:.2f} / {b['rms_mm']:.0f}"
                  f" -> {a['rot_deg']:.2f} / {a['rms_mm']:.0f}")
    lag = report["lag"]
    print(f"\nlag search: true {lag['true_s']:+.3f} s, found {lag['found_s']:+.4f} s in "
          f"{lag['seconds'] * 1000:.0f} ms ({lag['lags_tried']} lags tried)")
    print("\nlive calibrator (observer on the engine thread; polls on the worker, 10 a second):")
    for label, w in report["live"].items():
        print(f"  {label}: observer {w['observer_us_per_frame']:.1f} us/frame; poll p50 "
              f"{w['poll_ms_p50']:.2f} ms, max {w['poll_ms_max']:.1f} ms "
              f"(~{w['worker_share_of_a_core_at_10hz'] * 100:.1f} % of a core)")
        if "detected_after_s" in w:
            print(f"    s1 turned 10 degrees at 5 s: detected {w['detected_after_s']:.3f} s after, "
                  f"re-calibrated {w['recovered_after_s']:.2f} s after (max poll includes the fit)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
