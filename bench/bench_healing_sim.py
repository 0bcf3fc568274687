"""Self-healing on the simulator: a bumped sensor, with the realistic Kinect model beside the
clean one; the fused output against the truth throughout; the simulated rigid-fit residuals
beside the real ones.

    python bench/bench_healing_sim.py            # seeds 1-5
    python bench/bench_healing_sim.py --quick    # seed 1
    python bench/bench_healing_sim.py --real bench/data/nucla --cache OPT.json
    python bench/bench_healing_sim.py --json
    python bench/bench_healing_sim.py --set fusion.carry_untracked=false   # A/B one setting

Two shows, each run twice per seed (quiet, and with the bump) on an injected clock:

- ``default``: the simulator's default rehearsal (three Kinects 120 degrees apart, one
  dancer), kinect-b turned 10 degrees at 10 s, 16 s in all (what
  tests/test_calibration_healing.py::test_simulated_kinects_bumped_mid_show runs);
- ``ring``: three Kinects on a 2.5 m ring round the demo dancer (``VirtualKinect``), s1
  turned 10 degrees at 5 s, 12 s in all (the live tests' rig).

Models: ``real`` (the simulator's default: view-dependent bias, limb swaps, inferred joints
guessed 10-30 cm off) and ``clean`` (the preset without those heavy tails). Reported per
model: the bump detected after (suspect event), healed after (calibrated or restored), false
alarms in the quiet run, and the fused output's error against the truth THROUGHOUT:

- a frame's error is the mean, over the joints the fused body reports (conf > 0), of the
  distance between the fused joint and the true joint at the instant the body shows. The
  fused body's time ``Body.t`` is a capture time on the engine clock, which the reference
  sensor's clock defines: the simulator's sensors stamp a frame when it is captured, it
  arrives ``latency`` later (the engine's clock offset absorbs that), and it shows the body
  ``pipeline_delay_s`` before its stamp. So the truth is taken at ``Body.t - (reference
  latency + pipeline delay)`` (123-140 ms on the default show; the bench also prints the
  delay that fits the quiet run best, as a check). The ring's VirtualKinects have no clock
  or delay: the truth there is at the frame's own instant;
- phases: before the bump, detecting (bump -> suspect event), healing (suspect ->
  calibrated/restored), after; per phase the median and the max over frames of the frame
  error (one dancer, so "over people" is that one person); and per second the max;
- the same frames split by the fused confidence, beside that figure (never instead of it):
  the error over the joints reported as tracked (conf 1: some sensor tracks it now) and
  over those reported as inferred (0 < conf < 1: every sensor only infers it), how many
  joints the body reports per frame (median, min: a joint held back is not reported) and
  the share of frames reporting an inferred joint. The Must-show figure stays the error
  over every reported joint: a split alone could hide a bad joint by calling it inferred;
- the reference, in the same run: each sensor's own view placed with its TRUE pose (the
  best single sensor, judged by its median over the quiet run), the same error measure;
  and the clean model.

Finally the rigid-fit residual statistics of two simulated views (median, rms / median of
the brute-force optimum fit, bench_calibration_real.simulated_residuals) for both models,
beside the real N-UCLA figures when ``--real DATA_DIR`` is given (development subjects only;
``--cache`` reuses bench_calibration_real's cache of the optimum, which otherwise costs ~20 s
per triple).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from importlib import resources

import numpy as np
import yaml

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from benchlib import exact_ring_rig  # noqa: E402
from stage.app.offline import feed  # noqa: E402
from stage.calibration.healing import attach_live  # noqa: E402
from stage.clock import ManualClock  # noqa: E402
from stage.engine.engine import Engine  # noqa: E402
from stage.sensors import sim as sim_mod  # noqa: E402
from stage.sensors.protocol import encode_client_joints  # noqa: E402
from stage.settings import FusionSettings, KalmanSettings  # noqa: E402
from stage.testing import simdata  # noqa: E402
from stage.yamlio import loads_marked  # noqa: E402

PHASES = ("before", "detecting", "healing", "after")
#: --no-unswap: the fusion without ``FusionSettings.unswap_limbs`` (the before of that change);
#: --set fusion.KEY=VALUE / smoothing.KEY=VALUE: any rig setting, for A/B runs of one change
FUSION: dict = {}
SMOOTHING: dict = {}


def frame_error(joints: np.ndarray, conf: np.ndarray, truth: np.ndarray) -> float:
    """Mean distance (m) over the reported joints (conf > 0); NaN if none."""
    seen = conf > 0
    if not seen.any():
        return float("nan")
    return float(np.linalg.norm(joints[seen] - truth[seen], axis=1).mean())


def frame_split(joints: np.ndarray, conf: np.ndarray, truth: np.ndarray) -> tuple:
    """(tracked error m, inferred error m, joints reported, of them inferred): the frame
    error split by the fused confidence (1: some sensor tracks the joint; 0 < c < 1: the
    body reports it as inferred); NaN where the body reports no such joint."""
    d = np.linalg.norm(joints - truth, axis=1)
    tracked, inferred = conf >= 1.0, (conf > 0) & (conf < 1.0)
    return (float(d[tracked].mean()) if tracked.any() else float("nan"),
            float(d[inferred].mean()) if inferred.any() else float("nan"),
            int((conf > 0).sum()), int(inferred.sum()))


class Show:
    """One run's record: events, fused bodies, single-sensor views and how to judge them."""

    def __init__(self, truth, delay_s: float, at: float, sensor: str, end: float) -> None:
        self.truth = truth            # t -> (25, 3) true joints, stage space, or None
        self.delay_s = delay_s        # how long before Body.t the fused body shows
        self.at, self.sensor, self.end = at, sensor, end
        self.events: list = []        # (kind, sensor, t)
        self.fused: list = []         # (frame t, body t, joints, conf, sensors)
        self.singles: dict = {}       # sensor -> [(t shown, error m)]

    def errors(self, delay_s: float | None = None) -> list[tuple[float, float]]:
        """(frame t, error m) per fused body."""
        d = self.delay_s if delay_s is None else delay_s
        out = []
        for t, bt, joints, conf, _ in self.fused:
            truth = self.truth(bt - d)
            if truth is not None:
                out.append((t, frame_error(joints, conf, truth)))
        return out

    def split(self) -> list[tuple]:
        """``frame_split`` per fused body."""
        out = []
        for _, bt, joints, conf, _ in self.fused:
            truth = self.truth(bt - self.delay_s)
            if truth is not None:
                out.append(frame_split(joints, conf, truth))
        return out


def default_show(preset: str, seed: int, bump: bool) -> Show:
    text = (resources.files("stage.sensors.sim") / "scenarios" / "default.yaml").read_text()
    text += f"\nkinect: {{preset: {preset}}}\n"
    if bump:
        text += "\nevents:\n  - {bump: kinect-b, at: 10, yaw: 10}\n"
    scenario = sim_mod.parse_scenario(loads_marked(text), "bump.yaml")
    sim = sim_mod.Simulator(scenario, seed=seed)
    rig = sim.rig(calibrated=True)
    rig.fusion = dataclasses.replace(rig.fusion, **FUSION)
    rig.smoothing = dataclasses.replace(rig.smoothing, **SMOOTHING)
    clocks = sim.sensor_clocks()[rig.reference]

    def truth(t):
        state = sim.truth(t) if t >= 0 else None
        return next(iter(state.values()))[0] if state else None
    show = Show(truth, clocks["latency_s"] + clocks["pipeline_delay_s"], 10.0, "kinect-b", 16.0)
    clock = ManualClock(0.0)
    engine = Engine(rig, clock)

    def listen(frame):
        for body in frame.bodies.values():
            show.fused.append((frame.t, body.t, body.joints.copy(), body.conf.copy(),
                               body.sensors))
    engine.listeners.append(listen)
    cal = attach_live(engine, None, threaded=False)
    feed(engine, clock, sim.stream(16.0), until=16.0)
    show.events = [(e.kind, e.sensor, e.t) for e in cal.events]
    if not bump:
        # each sensor's own view with its true pose (the same datagrams, decoded)
        for sid, st in simdata.streams(sim_mod.Simulator(scenario, seed=seed), 16.0).items():
            m = rig.stage_frame @ rig.sensors[sid].calibration.matrix
            rows = show.singles.setdefault(sid, [])
            for k in range(len(st)):
                shown = st.t[k] - clocks["pipeline_delay_s"]
                tj = truth(shown)
                if tj is not None:
                    joints = st.joints[k] @ m[:3, :3].T + m[:3, 3]
                    rows.append((shown, frame_error(joints, st.conf[k], tj)))
    return show


def ring_show(preset: str, seed: int, bump: bool) -> Show:
    dancer = sim_mod.demo_scenario(1).performers[0]
    poses = sim_mod.ring_poses(3)
    ids = ["s0", "s1", "s2"]
    fps = 30

    def truth(t):
        # frames are stamped 0-4 ms after their instant (sensors in turn): the frame grid
        return dancer.state(np.floor(t * fps + 1e-6) / fps)[0] if t >= 0 else None
    show = Show(truth, 0.0, 5.0, "s1", 12.0)
    clock = ManualClock(0.0)
    rig = exact_ring_rig(poses)
    rig.fusion = dataclasses.replace(rig.fusion, **FUSION)
    rig.smoothing = dataclasses.replace(rig.smoothing, **SMOOTHING)
    engine = Engine(rig, clock)

    def listen(frame):
        for body in frame.bodies.values():
            show.fused.append((frame.t, body.t, body.joints.copy(), body.conf.copy(),
                               body.sensors))
    engine.listeners.append(listen)
    cal = attach_live(engine, None, threaded=False)
    rng = np.random.default_rng(seed)
    kinects = [sim_mod.VirtualKinect(p, simdata.kinect_model(preset=preset), rng) for p in poses]
    for k in range(12 * fps):
        t = k / fps
        if bump and k == 5 * fps:
            kinects[1].pose = poses[1].moved(yaw=np.radians(10.0))
        true = dancer.state(t)[0]
        for i, sid in enumerate(ids):
            clock.set(max(clock.now(), t + 0.002 * i))
            seen = kinects[i].observe(true)
            if seen is not None:
                engine.handle_datagram(encode_client_joints(sid, 0, *seen),
                                       ("127.0.0.1", 9000 + i))
                if not bump:
                    m = poses[i].to_stage
                    joints = seen[0] @ m[:3, :3].T + m[:3, 3]
                    show.singles.setdefault(sid, []).append(
                        (t, frame_error(joints, seen[1], true)))
        engine.tick()
    show.events = [(e.kind, e.sensor, e.t) for e in cal.events]
    return show


def _stats(values) -> dict:
    v = np.array([x for x in values if np.isfinite(x)])
    if not len(v):
        return {"frames": 0, "median_mm": float("nan"), "max_mm": float("nan")}
    return {"frames": int(len(v)), "median_mm": 1000 * float(np.median(v)),
            "max_mm": 1000 * float(v.max())}


def best_delay(show: Show) -> float:
    """The delay (s, 10 ms steps up to 300 ms) whose truth fits the fused output best
    (lowest median frame error): a check on the stated one."""
    grid = np.arange(0.0, 0.301, 0.01)
    meds = [np.nanmedian([e for _, e in show.errors(d)]) for d in grid]
    return float(grid[int(np.argmin(meds))])


def episode(make, preset: str, seed: int) -> dict:
    quiet = make(preset, seed, False)
    bumped = make(preset, seed, True)
    at, sensor, end = bumped.at, bumped.sensor, bumped.end
    events = bumped.events
    suspect = [t for k, s, t in events if k == "suspect" and s == sensor]
    healed = [t for k, s, t in events if k in ("calibrated", "restored") and s == sensor]
    suspect_t = suspect[0] if suspect else end
    healed_t = healed[0] if healed else end
    errs = bumped.errors()
    bounds = {"before": (0.0, at), "detecting": (at, suspect_t),
              "healing": (suspect_t, healed_t), "after": (healed_t, end + 1.0)}
    phases = {name: _stats(e for t, e in errs if lo <= t < hi)
              for name, (lo, hi) in bounds.items()}
    per_second = [_stats(e for t, e in errs if s <= t < s + 1) for s in range(int(end))]
    quiet_errs = quiet.errors()
    ref = {round(t, 4): e for t, e in quiet_errs}
    diffs = [abs(e - ref[round(t, 4)]) for t, e in errs if at <= t <= healed_t
             and round(t, 4) in ref]
    split = bumped.split()
    singles = {sid: _stats(e for _, e in rows) for sid, rows in quiet.singles.items()}
    best = min(singles, key=lambda s: singles[s]["median_mm"])
    best_rows = quiet.singles[best]
    return {
        "false_alarms": sum(k == "suspect" for k, _, _ in quiet.events),
        "other_events": [(k, s, round(t, 2)) for k, s, t in events
                         if s != sensor or k not in ("suspect", "calibrated", "restored")],
        "detected_after_s": (suspect[0] - at) if suspect else float("nan"),
        "healed_after_s": (healed[0] - at) if healed else float("nan"),
        "delay_ms": 1000 * bumped.delay_s, "best_fit_delay_ms": 1000 * best_delay(quiet),
        "phases": phases,
        "per_second": per_second,
        "quiet": _stats(e for _, e in quiet_errs),
        "all": _stats(e for _, e in errs),
        "tracked": _stats(x[0] for x in split),
        "inferred": _stats(x[1] for x in split),
        "reported": [int(np.median([x[2] for x in split])), int(min(x[2] for x in split))],
        "with_inferred": float(np.mean([x[3] > 0 for x in split])),
        "bumped_vs_quiet_max_mm": 1000 * max(diffs) if diffs else float("nan"),
        "best_single": {"sensor": best, **singles[best],
                        "phases": {name: _stats(e for t, e in best_rows if lo <= t < hi)
                                   for name, (lo, hi) in bounds.items()}},
        "left_out_while_suspect": all(sensor not in s for t, _, _, _, s in bumped.fused
                                      if suspect and suspect[0] <= t < healed_t),
    }


def real_residuals(data_dir: str, every: int, cache: str | None, hypotheses: int) -> dict:
    """The brute-force optimum's residual statistics on N-UCLA development triples (the
    figures bench_calibration_real.py prints; --cache shares its cache file)."""
    import bench_calibration_real as bcr
    import nucla
    if cache:
        bcr._CACHE = {}
        if os.path.exists(cache):
            with open(cache, encoding="utf-8") as f:
                bcr._CACHE = json.load(f)
    med, ratio = [], []
    found = nucla.triples(data_dir)[::every]     # development subjects only
    for sample, paths in found:
        views = [bcr.load_view(p) for p in paths]
        ids = [f"nucla-v{k}" for k in (1, 2, 3)]
        # a view bit-identical to an earlier one is a copy: its pairs are left out, as
        # bench_calibration_real.py leaves them out
        copies = {k for i in range(3) for k in range(i + 1, 3)
                  if views[i].shape == views[k].shape and np.array_equal(views[i], views[k])}
        for i in range(3):
            for k in range(i + 1, 3):
                if i in copies or k in copies:
                    continue
                best = bcr.cached_optimum(sample, ids[i], ids[k], views[i], views[k],
                                          hypotheses)
                if best is not None and best.median_m > 0:
                    med.append(best.median_m)
                    ratio.append(best.rms_m / best.median_m)
    if cache:
        with open(cache, "w", encoding="utf-8") as f:
            json.dump(bcr._CACHE, f)
    return {"triples": len(found), "pairs": len(med),
            "median_m": [float(v) for v in np.percentile(med, [10, 25, 50, 75, 90])],
            "rms_over_median": [float(v) for v in np.percentile(ratio, [10, 25, 50, 75, 90])]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="seed 1 only")
    parser.add_argument("--seeds", default="1,2,3,4,5")
    parser.add_argument("--real", metavar="DATA_DIR",
                        help="N-UCLA all_sqe folder: the real residual statistics beside the "
                             "simulated ones (development subjects only)")
    parser.add_argument("--every", type=int, default=3, help="with --real: every K-th triple")
    parser.add_argument("--cache", metavar="FILE", help="with --real: bench_calibration_real's "
                        "optimum cache (read, and extended)")
    parser.add_argument("--no-unswap", action="store_true",
                        help="fuse without trading back swapped limbs (the earlier fusion)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="a rig setting for both shows, e.g. fusion.carry_untracked=false "
                             "or smoothing.inferred_sd_m=0 (repeatable)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.no_unswap:
        FUSION["unswap_limbs"] = False
    for item in args.set:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        if section not in ("fusion", "smoothing") or not name or not value:
            parser.error(f"--set {item!r}: expected fusion.KEY=VALUE or smoothing.KEY=VALUE")
        cls = FusionSettings if section == "fusion" else KalmanSettings
        if name not in {f.name for f in dataclasses.fields(cls)}:
            parser.error(f"--set {item!r}: {section} has no setting {name!r}")
        (FUSION if section == "fusion" else SMOOTHING)[name] = yaml.safe_load(value)
    seeds = [1] if args.quick else [int(s) for s in args.seeds.split(",")]
    load0 = os.getloadavg()[0]
    report: dict = {}
    for name, show in (("default", default_show), ("ring", ring_show)):
        for preset in ("real", "clean"):
            report[f"{name}/{preset}"] = [episode(show, preset, s) for s in seeds]
    import bench_calibration_real as bcr
    residuals = {"simulated_real": bcr.simulated_residuals(),
                 "simulated_clean": bcr.simulated_residuals(model={"preset": "clean"})}
    if args.real:
        residuals["nucla"] = real_residuals(args.real, args.every, args.cache, 300)
    load = (load0, os.getloadavg()[0])
    if args.json:
        print(json.dumps({"seeds": seeds, "load": load, "runs": report,
                          "residuals": residuals}, indent=1, default=float))
        return 0
    print_report(report, residuals, seeds, load)
    return 0


def print_report(report: dict, residuals: dict, seeds: list[int], load) -> None:
    print(f"self-healing on the simulator, a 10 degree bump, seeds {seeds} "
          f"(load {load[0]:.1f} -> {load[1]:.1f})")
    if FUSION or SMOOTHING:
        print(f"  rig settings changed: fusion {FUSION}, smoothing {SMOOTHING}")
    print(f"  {'show/model':<15}{'detected s':>11}{'healed s':>10}{'false':>7}"
          f"{'delay ms (best fit)':>22}{'bumped-quiet mm':>17}")
    for key, runs in report.items():
        def worst(k):
            return max(r[k] for r in runs)
        fits = ", ".join(f"{r['best_fit_delay_ms']:.0f}" for r in runs)
        print(f"  {key:<15}{worst('detected_after_s'):>11.2f}{worst('healed_after_s'):>10.2f}"
              f"{sum(r['false_alarms'] for r in runs):>7}"
              f"{max(r['delay_ms'] for r in runs):>8.0f} ({fits})"
              f"{worst('bumped_vs_quiet_max_mm'):>12.0f}")
        other = [e for r in runs for e in r["other_events"]]
        if other or not all(r["left_out_while_suspect"] for r in runs):
            print(f"    other events {other}; left out while suspect: "
                  f"{[r['left_out_while_suspect'] for r in runs]}")
    print("  fused output against the truth, frame error = mean over the body's reported "
          "joints, mm: median / max over frames (worst seed), bumped run")
    print(f"  {'show/model':<15}" + "".join(f"{p:>14}" for p in PHASES)
          + f"{'quiet run':>14}{'best single':>18}")
    for key, runs in report.items():
        cells = []
        for p in PHASES:
            med = max(r["phases"][p]["median_mm"] for r in runs)
            mx = max(r["phases"][p]["max_mm"] for r in runs)
            cells.append(f"{med:>7.0f} /{mx:>5.0f}")
        quiet = f"{max(r['quiet']['median_mm'] for r in runs):>7.0f} /" \
                f"{max(r['quiet']['max_mm'] for r in runs):>5.0f}"
        single = min(runs, key=lambda r: -r["best_single"]["max_mm"])["best_single"]
        print(f"  {key:<15}" + "".join(cells) + quiet
              + f"{single['median_mm']:>7.0f} /{single['max_mm']:>5.0f} {single['sensor']}")
    print("  the same frames split by the fused confidence (bumped run, median / max over frames, "
          "worst seed): all reported joints (the Must-show figure), tracked joints (conf 1), "
          "inferred joints (0 < conf < 1); joints reported per frame, median (min); frames "
          "reporting an inferred joint")
    for key, runs in report.items():
        cells = []
        for k in ("all", "tracked", "inferred"):
            med = max(r[k]["median_mm"] for r in runs)
            mx = max(r[k]["max_mm"] for r in runs)
            cells.append(f"{med:>7.0f} /{mx:>5.0f}")
        rep = min(runs, key=lambda r: r["reported"][1])["reported"]
        share = 100 * max(r["with_inferred"] for r in runs)
        print(f"  {key:<15}" + "".join(cells)
              + f"{min(r['reported'][0] for r in runs):>6} ({rep[1]}){share:>7.1f} %")
    print("  per second, max frame error mm (worst seed), bumped run:")
    for key, runs in report.items():
        n = len(runs[0]["per_second"])
        row = [max(r["per_second"][s]["max_mm"] for r in runs) for s in range(n)]
        print(f"    {key:<13}" + " ".join(f"{v:>4.0f}" for v in row))
    over = {k: sum(1 for r in runs for s in r["per_second"] if s["max_mm"] > 60)
            for k, runs in report.items()}
    later = {k: sum(1 for r in runs for s in r["per_second"][1:] if s["max_mm"] > 60)
             for k, runs in report.items()}
    seconds = {k: sum(len(r["per_second"]) for r in runs) for k, runs in report.items()}
    print("  seconds with a frame over 60 mm, of all seeds' seconds (from second 1 on, i.e. "
          "after the person's first second in view): "
          + ", ".join(f"{k} {over[k]}/{seconds[k]} ({later[k]})" for k in over))
    print("  rigid-fit residuals between two views (brute-force optimum), median cm; rms/median:")
    for name in ("simulated_real", "simulated_clean"):
        sims = residuals[name]
        print(f"    {name.replace('_', ' model ')}: 2 views 90 deg apart, seeds "
              f"{[x['seed'] for x in sims]}: median "
              + ", ".join(f"{x['median_m'] * 100:.1f}" for x in sims) + " cm; rms/median "
              + ", ".join(f"{x['rms_m'] / x['median_m']:.2f}" for x in sims))
    real = residuals.get("nucla")
    if real:
        print(f"    real N-UCLA (development, {real['pairs']} pairs of {real['triples']} "
              f"triples): median p10/25/50/75/90 "
              + " / ".join(f"{v * 100:.1f}" for v in real["median_m"]) + " cm; rms/median "
              "p10/25/50/75/90 " + " / ".join(f"{v:.2f}" for v in real["rms_over_median"]))
    else:
        print("    real N-UCLA: pass --real DATA_DIR (and --cache FILE) to print it beside")


if __name__ == "__main__":
    sys.exit(main())
