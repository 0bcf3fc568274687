"""Joint jitter on real Kinect recordings beside the simulator's Kinect model.

The simulator's noise (``stage/sensors/sim/kinect.py``: about 6 mm per axis at
1 m, +4 mm per metre, x2 at ankles and feet, x1.5 at wrists and hands, AR(1)
correlation 0.6) was an assumption. This bench puts one statistic of it beside
the same statistic on N-UCLA's development subjects (Kinect v1, three views,
people standing and doing everyday actions 2-3.5 m from the sensors).

Statistic: per joint group and axis, the median over frames of the absolute
second difference of a joint's position (x[t+1] - 2 x[t] + x[t-1], mm): the
frame-to-frame jitter, which for a still joint is noise alone. On the real
recordings it also holds the joints' real motion, so it is an upper bound of
their noise; the simulated person stands still at the real recordings' median
depth, so the simulated figure is noise alone. A simulated group whose figure
is above the real one has more jitter than the real sensor, whatever the real
motion.

    python bench/bench_sensor_noise.py bench/data/nucla
    python bench/bench_sensor_noise.py bench/data/nucla --json

Caveats printed with the figures: N-UCLA is Kinect v1, our model is of Kinect
v2; whether the recordings were smoothed by the SDK is not documented.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import nucla  # noqa: E402

from stage.joints import JOINT_INDEX as J  # noqa: E402
from stage.sensors.importers.nucla import KINECT1_JOINTS  # noqa: E402
from stage.sensors.sim import standing_pose  # noqa: E402
from stage.sensors.sim.kinect import KinectModel, VirtualKinect, VirtualPose  # noqa: E402

GROUPS = {"torso": ("HipCenter", "Spine", "ShoulderCenter", "HipLeft", "HipRight",
                    "ShoulderLeft", "ShoulderRight"),
          "head": ("Head",),
          "elbows, knees": ("ElbowLeft", "ElbowRight", "KneeLeft", "KneeRight"),
          "wrists, hands": ("WristLeft", "WristRight", "HandLeft", "HandRight"),
          "ankles, feet": ("AnkleLeft", "AnkleRight", "FootLeft", "FootRight")}
_V2 = {"HipCenter": "SpineBase", "Spine": "SpineMid", "ShoulderCenter": "SpineShoulder"}


def second_differences(skeletons: np.ndarray) -> np.ndarray:
    """(T, J, 3) positions -> (T-2, J, 3) |second differences|, NaN where a joint is missing
    (all zeros, N-UCLA's mark) in any of the three frames."""
    s = np.where((skeletons == 0).all(axis=2, keepdims=True), np.nan, skeletons)
    return np.abs(s[2:] - 2 * s[1:-1] + s[:-2])


def real_jitter(folder: str) -> tuple[dict, dict]:
    """(group -> median |2nd diff| per axis in mm, facts about the files)."""
    per_joint: list[np.ndarray] = []
    depths, views = [], 0
    for _, paths in nucla.triples(folder):
        for path in paths:
            with open(path, encoding="utf-8") as f:
                sk = np.asarray(json.load(f)["skeletons"], float)
            if sk.ndim != 3 or sk.shape[1:] != (20, 3) or len(sk) < 3:
                continue
            views += 1
            per_joint.append(second_differences(sk))
            hip = sk[:, 0, 2][sk[:, 0, 2] > 0]
            if len(hip):
                depths.append(float(np.median(hip)))
    d2 = np.concatenate(per_joint)
    out = {}
    for group, names in GROUPS.items():
        idx = [KINECT1_JOINTS.index(n) for n in names]
        values = d2[:, idx].reshape(-1, 3)
        out[group] = np.nanmedian(values, axis=0) * 1000
    return out, {"views": views, "frames": int(len(d2)),
                 "depth_m": [float(np.percentile(depths, q)) for q in (10, 50, 90)]}


def sim_jitter(preset: str, depth: float, seeds: int = 5, frames: int = 600,
               overrides: dict | None = None) -> dict:
    """The same statistic for a person standing still ``depth`` metres from one simulated
    sensor 0.8 m above the floor (group -> mm per axis)."""
    model = KinectModel.preset(preset)
    if overrides:
        from dataclasses import replace
        model = replace(model, **overrides)
    runs = []
    for seed in range(seeds):
        cam = VirtualKinect(VirtualPose.looking_at((0, 0.8, 0), (0, 0.9, depth)), model, seed)
        truth = standing_pose((0.0, depth), math.pi)
        seen = [cam.observe(truth) for _ in range(frames)]
        runs.append(second_differences(np.stack([s[0] for s in seen if s is not None])))
    d2 = np.concatenate(runs)
    return {group: np.nanmedian(d2[:, [J[_V2.get(n, n)] for n in names]].reshape(-1, 3),
                                axis=0) * 1000
            for group, names in GROUPS.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", help="folder of N-UCLA JSON files (docs/datasets.md); only the "
                    "development subjects are read")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if not os.path.isdir(args.data_dir):
        print(f"bench: {args.data_dir}: no such folder (docs/datasets.md says how to get the "
              "data)", file=sys.stderr)
        return 2
    real, facts = real_jitter(args.data_dir)
    if not facts["views"]:
        print(f"bench: no development N-UCLA views in {args.data_dir}", file=sys.stderr)
        return 2
    depth = facts["depth_m"][1]
    sims = {name: sim_jitter(name, depth) for name in ("real", "clean")}
    if args.json:
        print(json.dumps({"real": {g: v.tolist() for g, v in real.items()}, "facts": facts,
                          "sim": {p: {g: v.tolist() for g, v in s.items()}
                                  for p, s in sims.items()}}, indent=1))
        return 0
    lo, mid, hi = facts["depth_m"]
    print(f"N-UCLA development subjects ({', '.join(nucla.DEVELOPMENT)}): {facts['views']} "
          f"views, {facts['frames']} frame triples; hip depth p10/50/90 {lo:.2f}/{mid:.2f}/"
          f"{hi:.2f} m")
    print(f"simulated: one person standing still {mid:.2f} m from one sensor, 5 seeds x 600 "
          "frames, presets 'real' (the default) and 'clean'")
    print("median |second difference| per axis x/y/z, mm (real: noise + motion, an upper "
          "bound of the noise; simulated: noise alone)")
    print(f"{'group':<15}{'N-UCLA':>22}{'sim real':>22}{'sim clean':>22}"
          f"{'ratio real/clean':>20}")
    torso = {k: v["torso"].mean() for k, v in sims.items()}
    for group in GROUPS:
        row = [real[group]] + [sims[p][group] for p in ("real", "clean")]
        cells = "".join(f"{' / '.join(f'{x:4.1f}' for x in r):>22}" for r in row)
        ratios = " / ".join(f"{sims[p][group].mean() / real[group].mean():.2f}"
                            for p in ("real", "clean"))
        print(f"{group:<15}{cells}{ratios:>20}")
    print("relative to the torso (mean of axes): N-UCLA "
          + ", ".join(f"{g} {real[g].mean() / real['torso'].mean():.2f}" for g in GROUPS)
          + "; simulator " + ", ".join(f"{g} {sims['real'][g].mean() / torso['real']:.2f}"
                                       for g in GROUPS))
    print("caveats: N-UCLA is Kinect v1 (the model is of Kinect v2); whether its skeletons "
          "were smoothed by the SDK is not documented; wrists and hands move in most of its "
          "actions, so their real figure is mostly motion")
    return 0


if __name__ == "__main__":
    sys.exit(main())
