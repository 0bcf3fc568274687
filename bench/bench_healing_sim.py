"""Self-healing on the simulator: a bumped sensor, with the realistic Kinect model beside the
clean one.

    python bench/bench_healing_sim.py            # seeds 1-5
    python bench/bench_healing_sim.py --quick    # seed 1
    python bench/bench_healing_sim.py --json

Two shows, each run twice per seed (quiet, and with the bump) on an injected clock:

- ``default``: the simulator's default rehearsal (three Kinects 120 degrees apart, one
  dancer), kinect-b turned 10 degrees at 10 s, 16 s in all (what
  tests/test_calibration_healing.py::test_simulated_kinects_bumped_mid_show runs);
- ``ring``: three Kinects on a 2.5 m ring round the demo dancer (``VirtualKinect``), s1
  turned 10 degrees at 5 s, 12 s in all (the live tests' rig).

Models: ``real`` (the simulator's default: view-dependent bias, limb swaps, inferred joints
guessed 10-30 cm off) and ``clean`` (the preset without those heavy tails). Reported per
model: the bump detected after (suspect event), healed after (calibrated or restored), the
fused skeleton's error against the truth (mean and median over its joints; worst frame of
the quiet run and of the bumped run from the bump on), the worst difference between the
bumped and the quiet run at the same instants while the sensor was left out, and false
alarms in the quiet run. The reference is the same show without the bump, measured in the
same run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from importlib import resources

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchlib import exact_ring_rig  # noqa: E402
from stage.app.offline import feed  # noqa: E402
from stage.calibration.healing import attach_live  # noqa: E402
from stage.clock import ManualClock  # noqa: E402
from stage.engine.engine import Engine  # noqa: E402
from stage.sensors import sim as sim_mod  # noqa: E402
from stage.sensors.protocol import encode_client_joints  # noqa: E402
from stage.testing import simdata  # noqa: E402
from stage.yamlio import loads_marked  # noqa: E402


def _errors(body, truth) -> tuple[float, float]:
    seen = body.conf > 0
    d = np.linalg.norm(body.joints[seen] - truth[seen], axis=1)
    return float(d.mean()), float(np.median(d))


def default_show(preset: str, seed: int, bump: bool):
    """(events [(kind, sensor, t)], fused [(t, mean m, median m, sensors)])."""
    text = (resources.files("stage.sensors.sim") / "scenarios" / "default.yaml").read_text()
    text += f"\nkinect: {{preset: {preset}}}\n"
    if bump:
        text += "\nevents:\n  - {bump: kinect-b, at: 10, yaw: 10}\n"
    sim = sim_mod.Simulator(sim_mod.parse_scenario(loads_marked(text), "bump.yaml"), seed=seed)
    clock = ManualClock(0.0)
    engine = Engine(sim.rig(calibrated=True), clock)
    fused: list = []

    def listen(frame):
        truth = sim.truth(frame.t)
        if truth:
            joints = next(iter(truth.values()))[0]
            for body in frame.bodies.values():
                fused.append((frame.t, *_errors(body, joints), body.sensors))
    engine.listeners.append(listen)
    cal = attach_live(engine, None, threaded=False)
    feed(engine, clock, sim.stream(16.0), until=16.0)
    return [(e.kind, e.sensor, e.t) for e in cal.events], fused, 10.0, "kinect-b"


def ring_show(preset: str, seed: int, bump: bool):
    dancer = sim_mod.demo_scenario(1).performers[0]
    poses = sim_mod.ring_poses(3)
    ids = ["s0", "s1", "s2"]
    rig = exact_ring_rig(poses)
    clock = ManualClock(0.0)
    engine = Engine(rig, clock)
    fused: list = []

    def listen(frame):
        truth = dancer.state(frame.t)[0]
        for body in frame.bodies.values():
            fused.append((frame.t, *_errors(body, truth), body.sensors))
    engine.listeners.append(listen)
    cal = attach_live(engine, None, threaded=False)
    rng = np.random.default_rng(seed)
    kinects = [sim_mod.VirtualKinect(p, simdata.kinect_model(preset=preset), rng) for p in poses]
    for k in range(12 * 30):
        t = k / 30
        if bump and k == 5 * 30:
            kinects[1].pose = poses[1].moved(yaw=np.radians(10.0))
        truth = dancer.state(t)[0]
        for i, sid in enumerate(ids):
            clock.set(max(clock.now(), t + 0.002 * i))
            seen = kinects[i].observe(truth)
            if seen is not None:
                engine.handle_datagram(encode_client_joints(sid, 0, *seen),
                                       ("127.0.0.1", 9000 + i))
        engine.tick()
    return [(e.kind, e.sensor, e.t) for e in cal.events], fused, 5.0, "s1"


def episode(show, preset: str, seed: int) -> dict:
    quiet_events, quiet, _, _ = show(preset, seed, False)
    events, bumped, at, sensor = show(preset, seed, True)
    suspect = [t for k, s, t in events if k == "suspect" and s == sensor]
    healed = [t for k, s, t in events if k in ("calibrated", "restored") and s == sensor]
    healed_t = healed[0] if healed else float("inf")
    ref = {round(t, 4): (m, md) for t, m, md, _ in quiet}
    diffs = [abs(m - ref[round(t, 4)][0]) for t, m, _, _ in bumped
             if at <= t <= healed_t and round(t, 4) in ref]
    diffs_md = [abs(md - ref[round(t, 4)][1]) for t, _, md, _ in bumped
                if at <= t <= healed_t and round(t, 4) in ref]
    return {
        "false_alarms": sum(k == "suspect" for k, _, _ in quiet_events),
        "other_events": [(k, s, round(t, 2)) for k, s, t in events
                         if s != sensor or k not in ("suspect", "calibrated", "restored")],
        "detected_after_s": (suspect[0] - at) if suspect else float("nan"),
        "healed_after_s": (healed_t - at) if healed else float("nan"),
        "quiet_mean_max_mm": 1000 * max(m for _, m, _, _ in quiet),
        "quiet_median_max_mm": 1000 * max(md for _, _, md, _ in quiet),
        "bumped_mean_max_mm": 1000 * max(m for t, m, _, _ in bumped if t >= at),
        "bumped_median_max_mm": 1000 * max(md for t, _, md, _ in bumped if t >= at),
        "episode_vs_quiet_max_mm": 1000 * max(diffs) if diffs else float("nan"),
        "episode_vs_quiet_median_max_mm": 1000 * max(diffs_md) if diffs_md else float("nan"),
        "left_out_while_suspect": all(sensor not in s for t, _, _, s in bumped
                                      if suspect and suspect[0] <= t < healed_t),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="seed 1 only")
    parser.add_argument("--seeds", default="1,2,3,4,5")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    seeds = [1] if args.quick else [int(s) for s in args.seeds.split(",")]
    report: dict = {}
    for name, show in (("default", default_show), ("ring", ring_show)):
        for preset in ("real", "clean"):
            report[f"{name}/{preset}"] = [episode(show, preset, s) for s in seeds]
    load = os.getloadavg()[0]
    if args.json:
        print(json.dumps({"seeds": seeds, "load": load, "runs": report}, indent=2,
                         default=float))
        return 0
    print(f"self-healing on the simulator, a 10 degree bump, seeds {seeds} (load {load:.1f})")
    print(f"  {'show/model':<15}{'detected s':>11}{'healed s':>10}{'quiet mm':>14}"
          f"{'bumped mm':>14}{'vs quiet mm':>14}{'false':>7}  (mm: worst frame, mean / median"
          " over joints)")
    for key, runs in report.items():
        def worst(k):
            return max(r[k] for r in runs)
        print(f"  {key:<15}{worst('detected_after_s'):>11.2f}{worst('healed_after_s'):>10.2f}"
              f"{worst('quiet_mean_max_mm'):>8.0f} /{worst('quiet_median_max_mm'):>4.0f}"
              f"{worst('bumped_mean_max_mm'):>8.0f} /{worst('bumped_median_max_mm'):>4.0f}"
              f"{worst('episode_vs_quiet_max_mm'):>8.0f} /{worst('episode_vs_quiet_median_max_mm'):>4.0f}"
              f"{sum(r['false_alarms'] for r in runs):>7}")
        other = [e for r in runs for e in r["other_events"]]
        if other or not all(r["left_out_while_suspect"] for r in runs):
            print(f"    other events {other}; left out while suspect: "
                  f"{[r['left_out_while_suspect'] for r in runs]}")
    print("  (worst over the seeds; detected/healed: seconds after the bump; 'vs quiet': the "
          "bumped run's fused error minus the quiet run's at the same instants, while healing)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
