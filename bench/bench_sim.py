"""Simulator speed: sensor-frames per second of CPU, per rig size.

For each configuration (S sensors x P people, from a built-in scenario) the
simulator generates D simulated seconds of datagrams, exactly what `stage
sim --out` writes (Kinect model, occlusion, noise, OSC encoding; no engine),
R times. Prints per configuration the median over the repeats of:

- sensor-frames/s: bundles produced per second of CPU (one per sensor frame
  that had something to say), and skeletons/s (/jointCoordinates messages);
- x real time: simulated seconds per CPU second (real time needs 1x;
  S sensors produce S x 30 frames a simulated second);
- the spread (min-max) of x real time over the repeats, since this machine
  is shared.

    python bench/bench_sim.py              # 3x1, 3x2, 6x6; 20 s simulated, 3 repeats
    python bench/bench_sim.py --quick      # 5 s, 1 repeat
    python bench/bench_sim.py --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from stage.sensors.sim import Simulator

CONFIGS = {"3x1": "default", "3x2": "duet", "6x6": "crowd"}


def run(scenario: str, duration: float, seed: int = 1) -> dict:
    sim = Simulator(scenario, seed=seed)
    started = time.perf_counter()
    frames = skeletons = nbytes = 0
    for _, _, data in sim.datagrams(duration):
        frames += data.startswith(b"#bundle")
        skeletons += data.count(b"/jointCoordinates")
        nbytes += len(data)
    elapsed = time.perf_counter() - started
    return {"elapsed_s": elapsed, "frames": frames, "skeletons": skeletons, "bytes": nbytes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="simulated seconds")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--quick", action="store_true", help="5 s, 1 repeat")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.repeats = 5.0, 1
    rows = []
    for name in args.configs.split(","):
        runs = [run(CONFIGS[name], args.duration) for _ in range(args.repeats)]
        speed = [args.duration / r["elapsed_s"] for r in runs]
        med = statistics.median(r["elapsed_s"] for r in runs)
        rows.append({"config": name, "scenario": CONFIGS[name], "simulated_s": args.duration,
                     "repeats": args.repeats,
                     "sensor_frames_per_s": round(runs[0]["frames"] / med),
                     "skeletons_per_s": round(runs[0]["skeletons"] / med),
                     "x_real_time": round(statistics.median(speed), 2),
                     "x_real_time_min": round(min(speed), 2), "x_real_time_max": round(max(speed), 2),
                     "frames": runs[0]["frames"], "skeletons": runs[0]["skeletons"],
                     "kbytes_per_sim_s": round(runs[0]["bytes"] / args.duration / 1024, 1)})
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"simulator: {args.duration:g} simulated s per run, median of {args.repeats} run(s)")
    print(f"{'config':7s} {'scenario':9s} {'frames/s':>9s} {'skel/s':>8s} {'x real time':>12s} "
          f"{'(min-max)':>13s} {'skel/frame':>10s} {'KiB/sim s':>9s}")
    for r in rows:
        print(f"{r['config']:7s} {r['scenario']:9s} {r['sensor_frames_per_s']:9d} "
              f"{r['skeletons_per_s']:8d} {r['x_real_time']:12.2f} "
              f"({r['x_real_time_min']:5.2f}-{r['x_real_time_max']:5.2f}) "
              f"{r['skeletons'] / max(r['frames'], 1):10.2f} {r['kbytes_per_sim_s']:9.1f}")
    print("(real time needs x >= 1; frames/s is sensor frames generated per CPU second)")


if __name__ == "__main__":
    main()
