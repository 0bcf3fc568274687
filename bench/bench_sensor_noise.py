r"""Joint jitter on real Kinect recordings beside the simulator's Kinect model.

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

With ``--kinect2 DIR`` (repeatable) it does the same on real Kinect v2
recordings, NTU RGB+D ``.skeleton`` files (25 joints, 30 Hz, per-joint
tracking states) or Kinectron ``.json`` takes (no states), docs/datasets.md
says where to get public ones, against the simulator at each folder's median
depth: tracked joints (tracked in all three frames of a second difference) and
inferred ones (inferred in at least one) apart. For Kinect v2 it also prints a
second statistic, the median |x - its 0.5 s centred moving mean| (mm): jitter
that is correlated from frame to frame shows there where the second difference
misses it.

    python bench/bench_sensor_noise.py bench/data/nucla
    python bench/bench_sensor_noise.py bench/data/nucla --kinect2 bench/data/kinect2/ntu \
        --kinect2 bench/data/kinect2/kinectron
    python bench/bench_sensor_noise.py --kinect2 bench/data/kinect2/ntu --quick
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

from stage.errors import ConfigError  # noqa: E402
from stage.joints import JOINT_INDEX as J  # noqa: E402
from stage.sensors.importers.ntu import read_skeleton_file  # noqa: E402
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
#: the same groups in Kinect v2 joint indices (the v2-only joints, Neck, hand tips and
#: thumbs, are left out so that every column compares like with like)
V2_GROUPS = {g: [J[_V2.get(n, n)] for n in names] for g, names in GROUPS.items()}
WINDOW = 15     # frames in the moving mean of the second statistic (0.5 s at 30 Hz)
TRACKED, INFERRED = 2, 1


def second_differences(skeletons: np.ndarray) -> np.ndarray:
    """(T, J, 3) positions -> (T-2, J, 3) |second differences|, NaN where a joint is missing
    (all zeros, N-UCLA's mark, or NaN) in any of the three frames."""
    s = np.where((skeletons == 0).all(axis=2, keepdims=True), np.nan, skeletons)
    return np.abs(s[2:] - 2 * s[1:-1] + s[:-2])


def window_deviations(skeletons: np.ndarray, width: int = WINDOW) -> np.ndarray:
    """(T, J, 3) positions -> (T-width+1, J, 3) |x - centred moving mean over ``width``
    frames|, NaN where a joint is missing anywhere in the window."""
    if len(skeletons) < width:
        return np.empty((0,) + skeletons.shape[1:])
    windows = np.lib.stride_tricks.sliding_window_view(skeletons, width, axis=0)
    half = width // 2
    return np.abs(skeletons[half:len(skeletons) - half] - windows.mean(axis=-1))


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


def ntu_bodies(path: str) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Every body (tracking id) of one NTU RGB+D ``.skeleton`` file over the whole take:
    (id, (F, 25, 3) positions in metres with NaN in frames without it, (F, 25) joint
    tracking states: 2 tracked, 1 inferred, 0 not tracked, -1 absent). ConfigError on a
    malformed file."""
    frames = read_skeleton_file(path)
    ids = sorted({b.body_id for bodies in frames for b in bodies})
    out = []
    for body_id in ids:
        pos = np.full((len(frames), 25, 3), np.nan)
        state = np.full((len(frames), 25), -1)
        for k, bodies in enumerate(frames):
            for b in bodies:
                if b.body_id == body_id:
                    pos[k], state[k] = b.joints[:, :3], b.joints[:, 11]
        out.append((body_id, pos, state))
    return out


def kinectron_bodies(path: str, fps: float = 30.0) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Every body of one Kinectron recording (a JSON list of Kinect v2 SDK body frames, each
    {"trackingId", "joints": 25 x {"cameraX", "cameraY", "cameraZ", ...},
    "record_timestamp": ms}), as ``ntu_bodies`` gives them. Frames are placed on the 30 Hz
    grid by their time stamps, so frames the recorder missed become absent frames, not
    shorter steps. The format has no joint tracking states: every joint present is given
    state 2. ConfigError on anything else."""
    try:
        with open(path, encoding="utf-8") as f:
            frames = json.load(f)
        rows = []
        for frame in frames:
            joints = frame["joints"]
            if len(joints) != 25:
                raise ValueError(f"{len(joints)} joints, not 25")
            rows.append((str(frame["trackingId"]), float(frame["record_timestamp"]),
                         [[float(j["cameraX"]), float(j["cameraY"]), float(j["cameraZ"])]
                          for j in joints]))
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise ConfigError(f"not a Kinectron body recording ({type(exc).__name__}: {exc})",
                          path=path) from None
    if not rows:
        return []
    t0 = min(t for _, t, _ in rows)
    slots = [round((t - t0) * fps / 1000) for _, t, _ in rows]
    out = []
    for k, body_id in enumerate(sorted({b for b, _, _ in rows})):
        pos = np.full((max(slots) + 1, 25, 3), np.nan)
        state = np.full((max(slots) + 1, 25), -1)
        for (b, _, xyz), slot in zip(rows, slots):
            if b == body_id and state[slot, 0] < 0:      # two frames in one slot: the first
                pos[slot], state[slot] = xyz, TRACKED
        out.append((int(body_id) if body_id.isdigit() else k, pos, state))
    return out


READERS = {"ntu": (".skeleton", ntu_bodies), "kinectron": (".json", kinectron_bodies)}


def detect_format(folder: str) -> str:
    """The format of a folder's recordings, by the files' extensions ('ntu' if mixed)."""
    names = [n.lower() for n in os.listdir(folder)]
    for fmt, (ext, _) in READERS.items():
        if any(n.endswith(ext) for n in names):
            return fmt
    return "ntu"


def _pool(values: list[np.ndarray]) -> tuple[np.ndarray, int]:
    """(median per axis in mm, number of joint samples) of pooled (N, 3) |differences|."""
    v = np.concatenate(values) if values else np.empty((0, 3))
    v = v[~np.isnan(v).any(axis=1)]
    return (np.median(v, axis=0) * 1000 if len(v) else np.full(3, np.nan)), len(v)


def kinect2_jitter(folder: str, fmt: str = "ntu") -> dict:
    """The statistics on every recording of format ``fmt`` (``READERS``) in ``folder``:
    {"tracked", "inferred", "window"} -> group -> (mm per axis, samples), "bodies"
    (per-body torso and feet medians) and "facts" ("states": whether the format has joint
    tracking states; without them every joint counts as tracked)."""
    ext, reader = READERS[fmt]
    names = sorted(n for n in os.listdir(folder) if n.lower().endswith(ext))
    d2 = {k: {g: [] for g in GROUPS} for k in ("tracked", "inferred")}
    dev = {g: [] for g in GROUPS}
    bodies, depths, performers, triples = [], [], set(), 0
    states = np.zeros(3, int)
    for name in names:
        perf = name.upper().find("P") if fmt == "ntu" else -1
        performers.add(name[perf:perf + 4] if perf >= 0 else name)
        for body_id, pos, state in reader(os.path.join(folder, name)):
            if np.isfinite(pos[:, 0, 0]).sum() < WINDOW:
                continue        # a body seen for under 0.5 s (NTU's spurious detections)
            diff = second_differences(pos)
            s3 = np.stack([state[2:], state[1:-1], state[:-2]])
            tracked = (s3 == TRACKED).all(axis=0)
            inferred = (s3 >= INFERRED).all(axis=0) & (s3 == INFERRED).any(axis=0)
            # the moving mean is only as good as its window: tracked all through it
            win = np.lib.stride_tricks.sliding_window_view(state, WINDOW, axis=0)
            calm = (win == TRACKED).all(axis=-1)
            deviation = window_deviations(pos)
            for group, idx in V2_GROUPS.items():
                d2["tracked"][group].append(diff[:, idx][tracked[:, idx]])
                d2["inferred"][group].append(diff[:, idx][inferred[:, idx]])
                dev[group].append(deviation[:, idx][calm[:, idx]])
            seen = state[state >= 0]
            states += np.bincount(seen, minlength=3)[:3]
            triples += int(np.isfinite(diff[:, 0, 0]).sum())
            base = pos[:, J["SpineBase"], 2][state[:, J["SpineBase"]] == TRACKED]
            depth = float(np.median(base)) if len(base) else float("nan")
            depths.extend(base.tolist())
            bodies.append({"file": name, "body": body_id, "depth_m": depth,
                           "torso": _pool([diff[:, V2_GROUPS["torso"]][
                               tracked[:, V2_GROUPS["torso"]]]])[0].tolist(),
                           "ankles, feet": _pool([diff[:, V2_GROUPS["ankles, feet"]][
                               tracked[:, V2_GROUPS["ankles, feet"]]]])[0].tolist()})
    out = {k: {g: _pool(v) for g, v in d2[k].items()} for k in d2}
    out["window"] = {g: _pool(v) for g, v in dev.items()}
    out["bodies"] = bodies
    out["facts"] = {"format": fmt, "states": fmt == "ntu",
                    "files": len(names), "bodies": len(bodies), "performers": len(performers),
                    "frame_triples": triples,
                    "joint_states": {"tracked": int(states[2]), "inferred": int(states[1]),
                                     "not tracked": int(states[0])},
                    "depth_m": ([float(np.percentile(depths, q)) for q in (10, 50, 90)]
                                if depths else [])}
    return out


def _model(preset: str, overrides: dict | None) -> KinectModel:
    model = KinectModel.preset(preset)
    if overrides:
        from dataclasses import replace
        model = replace(model, **overrides)
    return model


def _simulate(model: KinectModel, depth: float, seed: int, frames: int) -> np.ndarray:
    cam = VirtualKinect(VirtualPose.looking_at((0, 0.8, 0), (0, 0.9, depth)), model, seed)
    truth = standing_pose((0.0, depth), math.pi)
    seen = [cam.observe(truth) for _ in range(frames)]
    return np.stack([s[0] for s in seen if s is not None])


def sim_jitter(preset: str, depth: float, seeds: int = 5, frames: int = 600,
               overrides: dict | None = None, window: bool = False) -> dict:
    """The same statistic for a person standing still ``depth`` metres from one simulated
    sensor 0.8 m above the floor (group -> mm per axis); ``window``: the moving-mean
    statistic instead of the second difference."""
    model = _model(preset, overrides)
    stat = window_deviations if window else second_differences
    d2 = np.concatenate([stat(_simulate(model, depth, seed, frames)) for seed in range(seeds)])
    return {group: np.nanmedian(d2[:, [J[_V2.get(n, n)] for n in names]].reshape(-1, 3),
                                axis=0) * 1000
            for group, names in GROUPS.items()}


def _cells(*rows: np.ndarray, width: int = 22) -> str:
    return "".join(f"{' / '.join(f'{x:4.1f}' for x in r):>{width}}" for r in rows)


def print_nucla(real: dict, facts: dict, sims: dict, frames: str) -> None:
    lo, mid, hi = facts["depth_m"]
    print(f"N-UCLA development subjects ({', '.join(nucla.DEVELOPMENT)}): {facts['views']} "
          f"views, {facts['frames']} frame triples; hip depth p10/50/90 {lo:.2f}/{mid:.2f}/"
          f"{hi:.2f} m")
    print(f"simulated: one person standing still {mid:.2f} m from one sensor, {frames} "
          "frames, presets 'real' (the default) and 'clean'")
    print("median |second difference| per axis x/y/z, mm (real: noise + motion, an upper "
          "bound of the noise; simulated: noise alone)")
    print(f"{'group':<15}{'N-UCLA':>22}{'sim real':>22}{'sim clean':>22}"
          f"{'sim/N-UCLA real, clean':>24}")
    torso = {k: v["torso"].mean() for k, v in sims.items()}
    for group in GROUPS:
        ratios = " / ".join(f"{sims[p][group].mean() / real[group].mean():.2f}"
                            for p in ("real", "clean"))
        print(f"{group:<15}{_cells(real[group], sims['real'][group], sims['clean'][group])}"
              f"{ratios:>24}")
    print("relative to the torso (mean of axes): N-UCLA "
          + ", ".join(f"{g} {real[g].mean() / real['torso'].mean():.2f}" for g in GROUPS)
          + "; simulator " + ", ".join(f"{g} {sims['real'][g].mean() / torso['real']:.2f}"
                                       for g in GROUPS))
    print("caveats: N-UCLA is Kinect v1 (the model is of Kinect v2); whether its skeletons "
          "were smoothed by the SDK is not documented; wrists and hands move in most of its "
          "actions, so their real figure is mostly motion")


def implied(v2: dict, sims: dict) -> dict:
    """What the tracked Kinect v2 figures imply for the model's noise settings, as upper
    bounds (the real figures hold motion too): the scale of its noise s.d. at this depth,
    and the feet and hands factors relative to its torso."""
    tr = {g: v2["tracked"][g][0].mean() for g in GROUPS}
    scale = tr["torso"] / sims["real"]["torso"].mean()
    base = KinectModel()
    return {"scale": float(scale), "noise_m": base.noise_m * scale,
            "noise_per_m": base.noise_per_m * scale,
            "feet_noise": float(tr["ankles, feet"] / tr["torso"]),
            "hands_noise": float(tr["wrists, hands"] / tr["torso"])}


def print_kinect2(folder: str, v2: dict, sims: dict, wins: dict, matched: dict,
                  imp: dict, frames: str) -> None:
    f = v2["facts"]
    lo, mid, hi = f["depth_m"]
    name = {"ntu": "NTU RGB+D samples", "kinectron": "Kinectron recordings"}[f["format"]]
    short = {"ntu": "NTU", "kinectron": "Kinectron"}[f["format"]]
    if f["states"]:
        st = f["joint_states"]
        total = sum(st.values())
        states = (f"joint states {100 * st['tracked'] / total:.1f}% tracked, "
                  f"{100 * st['inferred'] / total:.1f}% inferred, "
                  f"{100 * st['not tracked'] / total:.1f}% not tracked")
        who = f"{f['performers']} performer ids in the names"
    else:
        states = "no joint tracking states in this format (every joint counted)"
        who = "performers not named"
    print(f"\nKinect v2, {name} in {folder}: {f['files']} files, {f['bodies']} bodies, {who}, "
          f"{f['frame_triples']} frame triples; SpineBase depth p10/50/90 "
          f"{lo:.2f}/{mid:.2f}/{hi:.2f} m; {states}")
    print(f"simulated: one person standing still {mid:.2f} m from one sensor, {frames} frames")
    print("median |second difference| per axis x/y/z, mm (n: joint samples)")
    col = f"{short} tracked" if f["states"] else f"{short} all joints"
    print(f"{'group':<15}{col:>22}{short + ' inferred (n)':>30}{'sim real':>22}"
          f"{'sim clean':>22}{'sim real/' + short:>20}")
    for group in GROUPS:
        (t, _), (i, ni) = v2["tracked"][group], v2["inferred"][group]
        inferred = _cells(i) + f" ({ni})" if f["states"] else "-"
        print(f"{group:<15}{_cells(t)}{inferred:>30}"
              f"{_cells(sims['real'][group], sims['clean'][group])}"
              f"{sims['real'][group].mean() / t.mean():>20.1f}")
    tr = {g: v2["tracked"][g][0].mean() for g in GROUPS}
    print(f"relative to the torso (mean of axes): {col} "
          + ", ".join(f"{g} {tr[g] / tr['torso']:.2f}" for g in GROUPS)
          + "; simulator " + ", ".join(
              f"{g} {sims['real'][g].mean() / sims['real']['torso'].mean():.2f}"
              for g in GROUPS))
    print(f"per body ({col}, mean of axes, mm): " + "; ".join(
        f"{b['file'].split('.')[0][:24]}#{b['body'] % 1000:03d} {b['depth_m']:.2f} m torso "
        f"{np.mean(b['torso']):.1f} feet {np.mean(b['ankles, feet']):.1f}"
        for b in v2["bodies"]))
    print(f"median |x - {WINDOW}-frame centred moving mean| per axis, mm (joints "
          f"{'tracked' if f['states'] else 'present'} all through the window)")
    print(f"{'group':<15}{col:>22}{'sim real':>22}{'sim real/' + short:>20}")
    for group in GROUPS:
        t = v2["window"][group][0]
        print(f"{group:<15}{_cells(t, wins[group])}{wins[group].mean() / t.mean():>20.1f}")
    print(f"implied upper bounds for KinectModel (defaults unchanged): noise s.d. x"
          f"{imp['scale']:.3f} at {mid:.2f} m (noise_m {1000 * imp['noise_m']:.2f} mm and "
          f"noise_per_m {1000 * imp['noise_per_m']:.2f} mm/m if both scale alike), feet_noise "
          f"{imp['feet_noise']:.2f}, hands_noise {imp['hands_noise']:.2f} (relative to the "
          "torso; the model's torso factor is 1)")
    print("check, the 'real' preset with those four settings: " + ", ".join(
        f"{g} {' / '.join(f'{x:.1f}' for x in matched[g])}" for g in GROUPS))
    print("caveats: real figures hold the joints' motion (hands and arms most); whether the "
          "recordings were smoothed beyond what the Kinect v2 SDK does is not documented; "
          "one depth cannot split noise_m from noise_per_m")


def kinect2_report(folder: str, fmt: str, seeds: int, frames: int) -> tuple:
    """(v2 statistics, sims real/clean, sim window statistic, sim with the implied settings,
    implied settings) for one folder of Kinect v2 recordings; ConfigError on a bad file or
    a folder without a body seen for 0.5 s."""
    v2 = kinect2_jitter(folder, fmt)
    if not v2["facts"]["bodies"]:
        raise ConfigError(f"no {fmt} bodies seen for 0.5 s or more", path=folder)
    depth = v2["facts"]["depth_m"][1]
    sims = {p: sim_jitter(p, depth, seeds, frames) for p in ("real", "clean")}
    wins = sim_jitter("real", depth, seeds, frames, window=True)
    imp = implied(v2, sims)
    matched = sim_jitter("real", depth, seeds, frames, overrides={
        k: imp[k] for k in ("noise_m", "noise_per_m", "feet_noise", "hands_noise")})
    return v2, sims, wins, matched, imp


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", nargs="?", help="folder of N-UCLA JSON files "
                    "(docs/datasets.md); only the development subjects are read")
    ap.add_argument("--kinect2", metavar="DIR", action="append", default=[],
                    help="folder of Kinect v2 recordings too (repeatable)")
    ap.add_argument("--format", choices=("auto",) + tuple(READERS), default="auto",
                    help="format of the --kinect2 files: NTU RGB+D .skeleton, Kinectron "
                    ".json, or by extension (auto)")
    ap.add_argument("--quick", action="store_true", help="1 simulated seed x 200 frames "
                    "instead of 5 x 600 (a smoke test)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.data_dir is None and not args.kinect2:
        ap.error("give an N-UCLA folder, --kinect2 DIR, or both")
    for folder in [args.data_dir] + args.kinect2:
        if folder is not None and not os.path.isdir(folder):
            print(f"bench: {folder}: no such folder (docs/datasets.md says how to get the "
                  "data)", file=sys.stderr)
            return 2
    seeds, frames = (1, 200) if args.quick else (5, 600)
    label = f"{seeds} seed{'s' if seeds > 1 else ''} x {frames}"
    nucla_report = None
    if args.data_dir is not None:
        real, facts = real_jitter(args.data_dir)
        if not facts["views"]:
            print(f"bench: no development N-UCLA views in {args.data_dir}", file=sys.stderr)
            return 2
        sims = {p: sim_jitter(p, facts["depth_m"][1], seeds, frames) for p in ("real", "clean")}
        nucla_report = (real, facts, sims)
    v2_reports = {}
    for folder in args.kinect2:
        fmt = detect_format(folder) if args.format == "auto" else args.format
        try:
            v2_reports[folder] = kinect2_report(folder, fmt, seeds, frames)
        except ConfigError as exc:
            print(f"bench: {exc}", file=sys.stderr)
            return 2
    if args.json:
        out: dict = {}
        if nucla_report is not None:
            real, facts, sims = nucla_report
            out.update({"real": {g: v.tolist() for g, v in real.items()}, "facts": facts,
                        "sim": {p: {g: v.tolist() for g, v in s.items()}
                                for p, s in sims.items()}})
        out["kinect2"] = {}
        for folder, (v2, sims2, wins, matched, imp) in v2_reports.items():
            out["kinect2"][folder] = {
                **{k: {g: {"mm": v[0].tolist(), "n": v[1]} for g, v in v2[k].items()}
                   for k in ("tracked", "inferred", "window")},
                "bodies": v2["bodies"], "facts": v2["facts"], "implied": imp,
                "sim": {p: {g: v.tolist() for g, v in s.items()} for p, s in sims2.items()},
                "sim_window": {g: v.tolist() for g, v in wins.items()},
                "sim_implied": {g: v.tolist() for g, v in matched.items()}}
        print(json.dumps(out, indent=1))
        return 0
    if nucla_report is not None:
        print_nucla(*nucla_report, frames=label)
    for folder, report in v2_reports.items():
        print_kinect2(folder, *report, frames=label)
    return 0


if __name__ == "__main__":
    sys.exit(main())
