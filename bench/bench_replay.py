"""Replay speed through the whole engine at --max-speed (offline, deterministic).

Makes a recording of D seconds with the simulator (3 sensors x 1 person, the
default scenario; and 6 x 6, the crowd scenario, for information), then
replays it R times with `stage.app.offline.replay_offline` into a fresh Engine
with the recording's exact rig: decode, clock-offset estimation, calibration,
association, fusion with outlier rejection, Kalman smoothing, hand votes and
the per-tick housekeeping. No network, no sleeping. Prints per configuration
the median x real time (recorded seconds per CPU second) with its spread,
the cost per datagram, and whether the repeats gave identical fused output
(they must, bit for bit; see tests/test_replay.py).

Target (issue 4): at least 20x real time for 3 sensors x 1 person.

    python bench/bench_replay.py           # 60 s recordings, 5 repeats
    python bench/bench_replay.py --quick   # 15 s, 2 repeats
    python bench/bench_replay.py --json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import statistics
import tempfile
import time

from stage.app.offline import offline_engine, replay_offline
from stage.frames import fused_json
from stage.sensors.sim import Simulator

CONFIGS = {"3x1": "default", "6x6": "crowd"}
TARGET = 20.0


def replay_once(path: str) -> tuple[float, int, str, int]:
    engine, clock = offline_engine(path)
    digest = hashlib.sha256()
    engine.listeners.append(lambda f: digest.update(json.dumps(fused_json(f)).encode()))
    started = time.perf_counter()
    n = replay_offline(path, engine, clock)
    return time.perf_counter() - started, n, digest.hexdigest(), engine.counts["fused_frames"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="recorded seconds")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--quick", action="store_true", help="15 s, 2 repeats")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.repeats = 15.0, 2
    logging.getLogger("stage").setLevel(logging.ERROR)  # the engine's once-a-minute drop report
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.configs.split(","):
            path = os.path.join(tmp, f"{name}.rec")
            Simulator(CONFIGS[name], seed=1).record(path, args.duration)
            runs = [replay_once(path) for _ in range(args.repeats)]
            speed = [args.duration / r[0] for r in runs]
            rows.append({"config": name, "scenario": CONFIGS[name], "recorded_s": args.duration,
                         "datagrams": runs[0][1], "fused_frames": runs[0][3],
                         "x_real_time": round(statistics.median(speed), 1),
                         "x_real_time_min": round(min(speed), 1),
                         "x_real_time_max": round(max(speed), 1),
                         "us_per_datagram": round(statistics.median(r[0] for r in runs)
                                                  / runs[0][1] * 1e6, 1),
                         "identical_output": len({r[2] for r in runs}) == 1,
                         "recording_kib": round(os.path.getsize(path) / 1024)})
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"replay_offline through the engine: {args.duration:g} s recordings, median of "
          f"{args.repeats} run(s)")
    print(f"{'config':7s} {'datagrams':>9s} {'x real time':>12s} {'(min-max)':>15s} "
          f"{'us/datagram':>11s} {'same output':>11s} {'KiB':>6s}")
    for r in rows:
        print(f"{r['config']:7s} {r['datagrams']:9d} {r['x_real_time']:12.1f} "
              f"({r['x_real_time_min']:6.1f}-{r['x_real_time_max']:6.1f}) "
              f"{r['us_per_datagram']:11.1f} {str(r['identical_output']):>11s} "
              f"{r['recording_kib']:6d}")
    base = next((r for r in rows if r["config"] == "3x1"), None)
    if base is not None:
        verdict = "PASS" if base["x_real_time"] >= TARGET else "FAIL"
        print(f"{verdict}: 3 sensors x 1 person replays at {base['x_real_time']:.1f}x real time "
              f"(target >= {TARGET:g}x)")


if __name__ == "__main__":
    main()
