"""Soak: a long show with self-healing on must keep fusing everybody, every second.

Runs a built-in scenario (default ``crowd``: six sensors, six people crossing,
occluding and standing close) with the scenario's exact rig, self-healing on,
and counts, per second of show time, the people in the fused output, and the
calibrator's ``suspect`` / ``restored`` / ``calibrated`` events.

- ``offline`` (default): the engine on an injected (manual) clock, exactly as
  ``stage replay --offline`` / the tests run it; deterministic per seed.
- ``live``: a real ``stage serve`` process with the scenario's rig, fed over
  UDP by a real ``stage sim --to`` process in real time (so ``--duration 180``
  takes three minutes); events are read from the server's log, people from
  its ``--fused`` file.

The reference the figures are read against is the truth: every second the
scenario has its people on stage (the simulator knows), so "seconds with
fewer people fused than on stage" should be 0, and without a bump in the
scenario every suspect event is a false alarm.

    python bench/bench_soak.py                      # crowd, offline, 180 s, seeds 1 and 2
    python bench/bench_soak.py --mode live          # crowd through real processes, 180 s
    python bench/bench_soak.py --quick              # 30 s offline, one seed
    python bench/bench_soak.py --json

The script uses only the public API (``Show``, ``ShowOptions``, the commands),
so it also runs against an older checkout (``PYTHONPATH=OLD python bench/...``)
for before/after figures.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time

import benchlib  # noqa: F401  (sys.path: this folder)


def offline(scenario: str, duration: float, seed: int) -> dict:
    from stage.app.show import Show, ShowOptions
    from stage.sensors.sim import Simulator

    show = Show(ShowOptions(sim=scenario, offline=True, duration=duration, seed=seed,
                            plugins=False))
    show.start()
    per_second: dict[int, set] = collections.defaultdict(set)
    show.engine.listeners.append(lambda f: per_second[int(f.t)].update(f.bodies))
    started = time.perf_counter()
    show.stop(show.wait())
    wall = time.perf_counter() - started
    events = collections.Counter(e.kind for e in show.calibrator.events)
    sim = Simulator(scenario, seed)
    return _summary(per_second, _on_stage(sim, duration), events, duration, wall,
                    [(round(e.t, 2), e.sensor, e.kind, e.detail) for e in show.calibrator.events
                     if e.kind in ("suspect", "restored", "calibrated")][:12])


def live(scenario: str, duration: float, seed: int) -> dict:
    from stage.sensors.sim import Simulator

    tmp = tempfile.mkdtemp(prefix="stage-soak-")
    rig, fused = os.path.join(tmp, "rig.yaml"), os.path.join(tmp, "fused.jsonl")
    stage = [sys.executable, "-m", "stage.cli"]
    subprocess.run(stage + ["sim", scenario, "--seed", str(seed), "--rig-out", rig,
                            "--duration", "0.1", "--out", os.path.join(tmp, "x.stagerec")],
                   check=True, capture_output=True)
    port = _free_port()
    log_path = os.path.join(tmp, "serve.log")   # kept for a look when the run fails
    # a file, not a pipe read at the end: a burst of log lines over the pipe's 64 KB would
    # block the server's engine thread for the rest of the run (seen once: a 75 s stall)
    log_file = open(log_path, "w", encoding="utf-8")
    server = subprocess.Popen(stage + ["serve", "--rig", rig, "--port", str(port),
                                       "--host", "127.0.0.1", "--no-plugins",
                                       "--fused", fused, "--duration", str(duration + 8)],
                              stderr=log_file, text=True)
    time.sleep(3.0)  # let the server bind before the sensors send
    started = time.perf_counter()
    subprocess.run(stage + ["sim", "--quiet", scenario, "--seed", str(seed), "--to",
                            f"127.0.0.1:{port}", "--duration", str(duration)], check=True)
    wall = time.perf_counter() - started
    server.send_signal(signal.SIGINT)
    server.wait(timeout=30)
    log_file.close()
    with open(log_path, encoding="utf-8") as f:
        log = f.read()
    per_second: dict[int, set] = collections.defaultdict(set)
    t0 = None
    with open(fused, encoding="utf-8") as f:
        for line in f:
            frame = json.loads(line)
            t0 = frame["t"] if t0 is None else t0
            per_second[int(frame["t"] - t0)].update(frame["bodies"])
    events = collections.Counter()
    for line in log.splitlines():
        if re.search(r"sensor \S+ is suspect", line):
            events["suspect"] += 1
        elif re.search(r"restored", line):
            events["restored"] += 1
        elif re.search(r"sensor \S+ (re-)?calibrated", line):
            events["calibrated"] += 1
    sim = Simulator(scenario, seed)
    out = _summary(per_second, _on_stage(sim, duration), events, duration, wall,
                   [line for line in log.splitlines() if "suspect" in line or "stage" in
                    line and "dark" in line][:12])
    out["note"] = "seconds counted from the first fused frame"
    out["files"] = tmp
    return out


def _on_stage(sim, duration: float) -> list[int]:
    """People on stage during each whole second (the smallest count within it)."""
    return [min(len(sim.truth(s + k / 10)) for k in range(10)) for s in range(int(duration))]


def _summary(per_second, on_stage, events, duration, wall, first) -> dict:
    seconds = int(duration) - 1  # the last second may be cut short
    fused = [len(per_second.get(s, ())) for s in range(seconds)]
    short = [s for s in range(1, seconds) if fused[s] < on_stage[s]]  # second 0: acquisition
    dark = [s for s in range(1, seconds) if fused[s] == 0]
    return {"seconds": seconds, "seconds_everyone_fused": seconds - 1 - len(short),
            "seconds_someone_missing": len(short), "dark_seconds": len(dark),
            "first_dark_second": dark[0] if dark else None,
            "min_people_fused_per_second": min(fused[1:]) if seconds > 1 else None,
            "people_on_stage": max(on_stage), "events": dict(events), "wall_s": round(wall, 1),
            "first_events": first}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="crowd")
    parser.add_argument("--mode", choices=("offline", "live"), default="offline")
    parser.add_argument("--duration", type=float, default=180.0)
    parser.add_argument("--seeds", default="1,2")
    parser.add_argument("--quick", action="store_true", help="30 s offline, seed 1")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.seeds = 30.0, "1"
    load = os.getloadavg()[0]
    rows = []
    for seed in [int(s) for s in args.seeds.split(",")]:
        fn = offline if args.mode == "offline" else live
        row = {"scenario": args.scenario, "mode": args.mode, "seed": seed,
               **fn(args.scenario, args.duration, seed)}
        rows.append(row)
    if args.json:
        print(json.dumps({"load_avg_1min": load, "rows": rows}, indent=2))
        return
    print(f"machine load (1 min avg) at start: {load:.2f}")
    for r in rows:
        verdict = "PASS" if r["dark_seconds"] == 0 and r["seconds_someone_missing"] == 0 \
            else "FAIL"
        print(f"{r['scenario']} {r['mode']} seed {r['seed']}: {r['seconds']} s, everyone fused in "
              f"{r['seconds_everyone_fused']} s, someone missing in "
              f"{r['seconds_someone_missing']} s, nobody fused in {r['dark_seconds']} s "
              f"(first {r['first_dark_second']}), min people fused in a second "
              f"{r['min_people_fused_per_second']}/{r['people_on_stage']}; events "
              f"{r['events']}; {r['wall_s']} s wall  {verdict}")
        for e in r["first_events"]:
            print("    ", e)
        if "files" in r:
            print(f"     server log and fused frames: {r['files']}")


if __name__ == "__main__":
    main()
