"""Anticipation: how much earlier triggers fire with a forecast, and at what cost in false triggers.

The simulator's sensors show the dancer 60 ms late (``pipeline_delay_s``, 3 ms
jitter; 5 ms of network latency on top, so some 65 ms end to end, as seed 004's
60-80 ms), and CMU subject 131's takes (``/work/shared/data/cmu``, or
$STAGE_CMU_DIR) drive the dancer. One engine per take and seed, on a manual
clock, feeds one piece runtime per setting at once (the engine predicts every
horizon asked for), so every setting sees the same frames:

- ``none``: the reference, no forecast (what the engine does without this work);
- ``forecast H``: the piece's ``forecast_s: H`` (every trigger on the predicted body);
- ``anticipate H``: ``defaults: {anticipate: H}`` (a predicted crossing fires when it is
  sure enough by its joint group's defaults: s.d. at most ``max_sd``, probability of
  being past the border at least ``min_p``, measured approach at least ``trend``; the
  measurements confirm or contradict it);
- ``anticipate 50 ms {...}``: the same with these keys (``--variant``; by default the
  bare s.d. bound ``min_p: 0, trend: -10``, how it fired before the groups' defaults).

Seeds 1-3 tuned the groups' defaults; seeds 4-5 were held back and check them; seeds
6-10 were never tuned on; any seeds past 10 (``--seeds 20``) were never looked at while
tuning: the tables are printed for each group and for all, with the goal per kind.

Triggers: a hand rising above the head (``rises_above: Head``), a foot lifting
(``rises_above: 0.25``), and the torso centre entering one of three bands
across the dancer's path (``enters``). The ground truth (the motion capture at
120 Hz) gives the true crossings with the same thresholds and hysteresis. A
firing is matched to the first unmatched true crossing of its trigger and
joint that happened at most 200 ms before it or at most 100 ms after it;
a firing with none is a *false trigger* (the truth never crossed within 100
ms of what the firing claims). For matched firings the delay is the firing's
engine time minus the true crossing's time (engine clock = simulation clock).

    python bench/bench_anticipation.py            # 3 takes x 10 seeds, plot in docs/
    python bench/bench_anticipation.py --quick    # one take, one seed, no plot
    python bench/bench_anticipation.py --seeds 21-40 --plot ''   # a fresh set of seeds
    python bench/bench_anticipation.py --seeds 3 --plot '' --why  # every false trigger, classified
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import anticipation_why as why  # noqa: E402
from benchlib import machine_busy_s  # noqa: E402

from stage.app.offline import feed  # noqa: E402
from stage.clock import ManualClock  # noqa: E402
from stage.engine import Engine  # noqa: E402
from stage.events import TriggerContradicted, TriggerFired  # noqa: E402
from stage.joints import JOINT_INDEX as J  # noqa: E402
from stage.piece.loader import loads_piece  # noqa: E402
from stage.piece.runtime import PieceRuntime, RecordingSink  # noqa: E402
from stage.sensors.sim import Simulator, parse_scenario  # noqa: E402
from stage.testing.walks import cmu_file  # noqa: E402
from stage.yamlio import loads_marked  # noqa: E402

TAKES = ("131_01", "131_02", "131_03")
HORIZONS = (0.025, 0.05, 0.075)
HYST = 0.05
FOOT_Y = 0.25
BANDS = {"band_a": (-0.5, 0.0), "band_b": (0.5, 1.0), "band_c": (1.5, 2.0)}  # z ranges, m
TORSO = [J[n] for n in ("SpineBase", "SpineMid", "SpineShoulder", "HipLeft", "HipRight")]
BEFORE, AFTER = 0.2, 0.1     # a true crossing matches a firing from 200 ms before to 100 ms after
#: the bare s.d. bound (no probability, no trend): how anticipation fired before the joint
#: groups' defaults, printed beside them in the same run
BARE = "min_p: 0, trend: -10"
#: the settings ``--why`` classifies the false triggers of (the reference first)
ANATOMY = (("none", 0.0), ("anticipate", 0.05))
SETTLE = 0.8                 # s: crossings before the engine has seen the dancer are not counted

SCENARIO = """
sensors: {{ring: {{count: 3, radius: 3.5}}}}
kinect: {{pipeline_delay_s: {delay}, pipeline_jitter_s: 0.003{kinect}}}
network: {{latency: 0.005}}
performers:
  - {{name: dancer, height: 1.75, position: [0, -1.5], motion: {path}}}
"""

PIECE = """
piece: anticipation bench
{top}
defaults: {{cooldown: 0.3, hysteresis: {h}{anticipate}}}
zones:
{zones}
sections:
  - name: all
    triggers:
      - {{name: hand, rises_above: Head, joint: hands, cooldown_per: joint, do: [{{note: C4}}]{own[hand]}}}
      - {{name: foot, rises_above: {foot}, joint: feet, cooldown_per: joint, do: [{{note: D4}}]{own[foot]}}}
{bands}
"""


def piece_text(mode: str, horizon: float, extra: str = "") -> str:
    """The bench piece. ``extra``: anticipate keys for every trigger ('min_p: 0.9'), or per
    trigger ('foot= min_p: 0.9, ahead: 0.04 / hand= trend: 1.5'; the others anticipate
    ``horizon`` with their defaults)."""
    own = {"hand": "", "foot": "", "zone": ""}
    if "=" in extra:
        for part in extra.split("/"):
            trig, keys = part.split("=", 1)
            keys = keys.strip()
            if "ahead" not in keys:
                keys = f"ahead: {horizon}, {keys}"
            own[trig.strip()] = f", anticipate: {{{keys}}}"
        extra = ""
    zones = "\n".join(f"  {n}: {{shape: box, min: [-3, 0, {z0}], max: [3, 2.5, {z1}]}}"
                      for n, (z0, z1) in BANDS.items())
    bands = "\n".join(f"      - {{name: zone, enters: {n}, cooldown_per: joint, "
                      f"do: [{{note: E4}}]{own['zone']}}}" for n in BANDS)
    top = f"forecast_s: {horizon}" if mode == "forecast" else ""
    anticipate = ""
    if mode == "anticipate":
        anticipate = f", anticipate: {horizon}" if not extra else \
            f", anticipate: {{ahead: {horizon}, {extra}}}"
    return PIECE.format(top=top, h=HYST, anticipate=anticipate, zones=zones, foot=FOOT_Y,
                        bands=bands, own=own)


def schmitt_up(t: np.ndarray, d: np.ndarray) -> list[float]:
    """Times where ``d`` (>0: past the threshold) crosses up, re-armed at d < -HYST (the
    runtime's rule), the first sample only setting the state."""
    out = []
    armed = d[0] <= 0
    for k in range(1, len(d)):
        if armed and d[k] > 0:
            armed = False
            # the crossing between the samples (linear), not the sample after it
            f = d[k - 1] / (d[k - 1] - d[k]) if d[k - 1] < 0 else 0.0
            out.append(float(t[k - 1] + f * (t[k] - t[k - 1])))
        elif not armed and d[k] < -HYST:
            armed = True
    return out


def truth_series(sim: Simulator, duration: float) -> tuple[np.ndarray, dict]:
    """The motion capture at 120 Hz: (times, (trigger, joint) -> how far past the border,
    m, > 0 past it; the zones' the depth into the nearest band)."""
    t = np.arange(0.0, duration, 1.0 / 120.0)
    joints = np.array([sim.truth(float(x))["dancer"][0] for x in t])
    out: dict[tuple[str, str], np.ndarray] = {}
    for side in ("Left", "Right"):
        out[("hand", "Hand" + side)] = joints[:, J["Hand" + side], 1] - joints[:, J["Head"], 1]
        out[("foot", "Foot" + side)] = joints[:, J["Foot" + side], 1] - FOOT_Y
    z = joints[:, TORSO, 2].mean(axis=1)
    # inside > 0: the distance into a band from its nearer border
    inside = [np.minimum(z - z0, z1 - z) for z0, z1 in BANDS.values()]
    out[("zone", "body")] = np.max(inside, axis=0)
    return t, {**out, "bands": inside}


def measured_margins(frames: list) -> tuple[np.ndarray, dict]:
    """The fused (measured) bodies' margins, as ``truth_series``: (engine times, (trigger,
    joint) -> m past the border), NaN where the joint was not seen."""
    t = np.array([f[0] for f in frames])
    out: dict = {}
    for side in ("Left", "Right"):
        h, f, head = J["Hand" + side], J["Foot" + side], J["Head"]
        seen = np.array([b.conf[h] > 0 and b.conf[head] > 0 for _, b in frames], bool)
        out[("hand", "Hand" + side)] = np.where(seen, [b.joints[h, 1] - b.joints[head, 1]
                                                       for _, b in frames], np.nan)
        seen = np.array([b.conf[f] > 0 for _, b in frames], bool)
        out[("foot", "Foot" + side)] = np.where(seen, [b.joints[f, 1] - FOOT_Y
                                                       for _, b in frames], np.nan)
    z = np.array([b.position[2] for _, b in frames])
    out[("zone", "body")] = np.max([np.minimum(z - z0, z1 - z) for z0, z1 in BANDS.values()],
                                   axis=0) if len(z) else z
    return t, out


def true_crossings(series: tuple[np.ndarray, dict]) -> dict[tuple[str, str], list[float]]:
    t, d = series
    out = {k: schmitt_up(t, v) for k, v in d.items() if k not in (("zone", "body"), "bands")}
    out[("zone", "body")] = [c for inside in d["bands"] for c in schmitt_up(t, inside)]
    return {k: sorted(c for c in v if c >= SETTLE) for k, v in out.items()}


def score(firings: list[tuple], truth: dict) -> dict[str, dict]:
    """Per trigger: delays of matched firings, false triggers, misses."""
    out = {}
    for trig in ("hand", "foot", "zone"):
        delays, false, n_true = [], 0, 0
        for (tname, joint), crossings in truth.items():
            if tname != trig:
                continue
            n_true += len(crossings)
            mine = sorted(f for f in firings if f[0] == trig and f[1] == joint)
            for f, k in zip(mine, why.match(mine, crossings, BEFORE, AFTER, SETTLE)):
                if k is None:
                    false += 1
                elif k >= 0:
                    delays.append(f[2] - crossings[k])
        out[trig] = {"true": n_true, "delays": delays, "false": false,
                     "missed": n_true - len(delays)}
    return out


def sim_engine(take: str, seed: int, delay: float, kinect: str = "",
               forecast: str = "") -> tuple[Simulator, ManualClock, Engine, float]:
    """The bench's simulator (CMU ``take`` danced before three Kinects, ``kinect`` extra
    sensor-model keys) and an engine on a manual clock with the rig's forecast settings
    overridden by ``forecast`` keys; the take's duration in seconds."""
    path = cmu_file(take)
    if path is None:
        raise SystemExit(f"CMU take {take} not found ($STAGE_CMU_DIR or shared/data/cmu)")
    text = SCENARIO.format(delay=delay, path=path, kinect=f", {kinect}" if kinect else "")
    sim = Simulator(parse_scenario(loads_marked(text, "bench.yaml"), "bench.yaml"), seed=seed)
    duration = sim.performers[0].length + 0.5 if hasattr(sim.performers[0], "length") else 11.0
    clock = ManualClock(0.0)
    rig = sim.rig()
    if forecast:
        rig.forecast = dataclasses.replace(rig.forecast, **loads_marked(
            "{" + forecast + "}", "--forecast"))
    return sim, clock, Engine(rig, clock), duration


def run(take: str, seed: int, delay: float, settings: list[tuple], kinect: str = "",
        forecast: str = "", anatomy: tuple = ()) -> dict:
    """One take and seed through every setting; ``anatomy``: the settings whose false
    triggers are classified (``anticipation_why``)."""
    sim, clock, engine, duration = sim_engine(take, seed, delay, kinect, forecast)
    runtimes = {}
    for mode, h, *extra in settings:
        piece = loads_piece(piece_text(mode, h, *extra), "bench.yaml")
        sink = RecordingSink()
        rt = PieceRuntime(piece, sink, seed=seed)
        for horizon in piece.horizons():
            engine.people.want_forecast(horizon)
        engine.listeners.append(rt)
        runtimes[(mode, h, *extra)] = (rt, sink)
    measured: list = []
    if anatomy:
        engine.listeners.append(lambda frame: measured.extend(
            (frame.t, b) for b in frame.bodies.values()))
    feed(engine, clock, sim.stream(duration), end=duration)
    series = truth_series(sim, duration)
    truth = true_crossings(series)
    out = {}
    for key, (rt, sink) in runtimes.items():
        fired = [(e.trigger, e.joint, e.t, e.anticipated) for e in sink.events
                 if isinstance(e, TriggerFired)]
        out[key] = {"score": score(fired, truth), "counts": dict(rt.counts)}
        if key in anatomy:
            told = {(e.trigger, e.joint, e.fired) for e in sink.events
                    if isinstance(e, TriggerContradicted)}
            out[key]["why"] = [dict(r, seed=seed, take=take) for r in why.classify(
                fired, told, truth, series, HYST, BEFORE, AFTER, SETTLE,
                measured_margins(measured))]
    out["forecast_stats"] = engine.people.forecast_stats()
    out["seed"] = seed
    return out


def summarise(results: list[dict], settings: list[tuple[str, float]]) -> dict:
    table = {}
    for key in settings:
        row = {}
        for trig in ("hand", "foot", "zone", "all"):
            trigs = ("hand", "foot", "zone") if trig == "all" else (trig,)
            delays = [d for r in results for tr in trigs for d in r[key]["score"][tr]["delays"]]
            row[trig] = {
                "true": sum(r[key]["score"][tr]["true"] for r in results for tr in trigs),
                "matched": len(delays),
                "false": sum(r[key]["score"][tr]["false"] for r in results for tr in trigs),
                "p50_ms": float(np.median(delays) * 1000) if delays else float("nan"),
                "p90_ms": float(np.percentile(delays, 90) * 1000) if delays else float("nan")}
        row["counts"] = {k: sum(r[key]["counts"].get(k, 0) for r in results)
                         for k in ("fired", "anticipated", "confirmed", "contradicted", "unsure")}
        table[key] = row
    return table


def bootstrap(results: list[dict], settings: list[tuple], n: int, seed: int = 0) -> dict:
    """The goal's two figures (all kinds) for every 50 ms setting, over ``n`` resamples of
    the seeds with replacement (each seed with all its takes: the takes are fixed
    choreography, the seeds the sensor noise, jitter and misreads a show may get): per
    setting the 5th, 50th and 95th percentiles of the earliness (ms) and of the false
    triggers over the no-forecast count, and the share of resamples meeting the goal."""
    by_seed: dict[int, list[dict]] = {}
    for r in results:
        by_seed.setdefault(r["seed"], []).append(r)
    seeds = sorted(by_seed)
    kinds = ("hand", "foot", "zone")

    def pooled(key: tuple, picks: np.ndarray) -> tuple[np.ndarray, int]:
        runs = [r for k in picks for r in by_seed[seeds[k]]]
        delays = np.array([d for r in runs for t in kinds for d in r[key]["score"][t]["delays"]])
        return delays, sum(r[key]["score"][t]["false"] for r in runs for t in kinds)

    rng = np.random.default_rng(seed)
    draws = [rng.integers(0, len(seeds), len(seeds)) for _ in range(n)]
    ref = [pooled(("none", 0.0), k) for k in draws]
    out = {}
    for key in settings:
        if key[1] != 0.05:
            continue
        gain, ratio = np.empty(n), np.empty(n)
        for i, k in enumerate(draws):
            delays, false = pooled(key, k)
            gain[i] = (np.median(ref[i][0]) - np.median(delays)) * 1000
            ratio[i] = false / max(ref[i][1], 1)
        out[key] = {"earlier_ms": np.percentile(gain, [5, 50, 95]).round(2).tolist(),
                    "false_ratio": np.percentile(ratio, [5, 50, 95]).round(3).tolist(),
                    "goal_met": float(np.mean((gain >= 30) & (ratio <= 1.1)))}
    return out


def print_bootstrap(boot: dict, n: int, seeds: range) -> None:
    print(f"-- the goal over {n} resamples of seeds {seeds[0]}-{seeds[-1]} (with replacement, "
          "each seed with all its takes): 5th/50th/95th percentiles")
    for key, b in boot.items():
        e, f = b["earlier_ms"], b["false_ratio"]
        print(f"{label(key):<40} earlier {e[0]:5.1f} /{e[1]:5.1f} /{e[2]:5.1f} ms   false "
              f"x{f[0]:.3f} / x{f[1]:.3f} / x{f[2]:.3f}   goal met in {b['goal_met']:.0%}")


def label(key: tuple) -> str:
    return key[0] + (f" {key[1] * 1000:.0f} ms" if key[1] else "") + \
        (f" {{{key[2]}}}" if len(key) > 2 else "")


def print_table(title: str, table: dict, settings: list[tuple]) -> None:
    ref = table[("none", 0.0)]
    print(f"-- {title}")
    width = max(16, max(len(label(k)) for k in settings) + 1)
    print(f"{'setting':<{width}}" + "".join(
        f"{t + ' p50/p90':>16}{'earlier':>8}{'false':>6}{'miss':>5}" for t in
        ("hand", "foot", "zone", "all")))
    for key in settings:
        row = table[key]
        line = f"{label(key):<{width}}"
        for t in ("hand", "foot", "zone", "all"):
            c = row[t]
            line += f"{c['p50_ms']:8.1f}/{c['p90_ms']:<7.1f}{ref[t]['p50_ms'] - c['p50_ms']:8.1f}" \
                    f"{c['false']:6d}{c['true'] - c['matched']:5d}"
        print(line)
    print("true crossings: " + ", ".join(f"{t} {ref[t]['true']}" for t in ("hand", "foot", "zone")))
    for key in settings[1:]:
        if key[1] != 0.05:
            continue
        parts = []
        for t in ("hand", "foot", "zone", "all"):
            r0, c = ref[t], table[key][t]
            gain, limit = r0["p50_ms"] - c["p50_ms"], r0["false"] * 1.1
            ok = gain >= 30 and c["false"] <= limit
            parts.append(f"{t} {gain:.1f} ms (p50 {c['p50_ms']:.1f} after the truth), false "
                         f"{c['false']}/{r0['false']} {'yes' if ok else 'NO'}")
        print(f"goal at {label(key)} (>= 30 ms earlier, false <= 1.1 x without): "
              + "; ".join(parts))


def seed_group(lo: int, hi: int) -> str:
    """What a group of seeds was used for (docs/anticipation.md, "Seeds"): the name of the
    group its last seed falls in."""
    return ("tuning" if hi <= 3 else "checking (held back while tuning)" if hi <= 5 else
            "check (never tuned on)" if hi <= 20 else "fresh check" if hi <= 40 else
            "fresh (run once per candidate)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one take, one seed, no plot")
    ap.add_argument("--seeds", default="10",
                    help="N: seeds 1-N; A-B: seeds A to B (e.g. 21-40, seeds nobody tuned on "
                         "or looked at)")
    ap.add_argument("--groups", default="3,5,10",
                    help="seed groups printed apart, by their last seeds: 1-3 tuned the groups' "
                         "defaults, 4-5 were held back while tuning, 6-10 were never tuned on "
                         "(their false triggers were looked at once), and any beyond were never "
                         "looked at")
    ap.add_argument("--delay", type=float, default=0.060, help="pipeline delay, s")
    ap.add_argument("--kinect", default="", metavar="KEYS",
                    help="more keys of the scenario's kinect: section, e.g. 'feet_noise: 1.0' "
                    "(the sensor model; default: the simulator's)")
    ap.add_argument("--forecast", default="", metavar="KEYS",
                    help="rig forecast: keys for the engine, e.g. 'foot_memory_s: 0' (default: "
                         "the rig's defaults)")
    ap.add_argument("--plot", default=str(ROOT / "docs" / "anticipation.png"))
    ap.add_argument("--json", default=None, help="write the table here too")
    ap.add_argument("--variant", action="append", default=[], metavar="KEYS",
                    help="also anticipate 50 ms with these anticipate keys, e.g. "
                         f"'min_p: 0.9, trend: 0.5' (repeatable; default: '{BARE}')")
    ap.add_argument("--why", action="store_true",
                    help="classify every false trigger of none and anticipate 50 ms (contradicted "
                         "prediction, second firing, noise, window; bench/anticipation_why.py)")
    ap.add_argument("--ci", type=int, default=0, metavar="N",
                    help="also the goal's figures over N bootstrap resamples of the seeds "
                         "(percentiles, and how often the goal is met; seeded: deterministic)")
    args = ap.parse_args()
    takes = TAKES[:1] if args.quick else TAKES
    first, _, last = args.seeds.partition("-")
    seeds = range(1, 2) if args.quick else \
        range(int(first), int(last) + 1) if last else range(1, int(first) + 1)
    settings: list[tuple] = [("none", 0.0)] + [(m, h) for m in ("forecast", "anticipate")
                                                for h in HORIZONS]
    settings += [("anticipate", 0.05, v) for v in args.variant or [BARE]]
    busy0, wall0 = machine_busy_s(), time.monotonic()
    results, sd = [], {}
    for take in takes:
        for seed in seeds:
            r = run(take, seed, args.delay, settings, args.kinect, args.forecast,
                    ANATOMY if args.why else ())
            results.append(r)
            for h, v in r["forecast_stats"]["sd_mm"].items():
                sd.setdefault(h, []).append(v)
    load = (machine_busy_s() - busy0) / (time.monotonic() - wall0)
    table = summarise(results, settings)
    print(f"pipeline delay {args.delay * 1000:.0f} ms (+3 ms jitter, +5 ms network); "
          f"sensor model {'default' + (' + ' + args.kinect if args.kinect else '')}; takes "
          f"{', '.join(takes)}; seeds {list(seeds)}; machine busy {load:.2f} cores "
          f"(of {os.cpu_count()}) during the run")
    print("delay = firing minus true crossing (ms, matched firings); false = firings with no "
          "true crossing 200 ms before to 100 ms after; earlier = p50 of none minus p50")
    ends = [int(x) for x in args.groups.split(",") if int(x) < seeds[-1]] + [seeds[-1]]
    lo = 1
    for hi in ends:
        part = [r for r in results if max(lo, seeds[0]) <= r["seed"] <= hi]
        if part and len(part) < len(results):
            print_table(f"{seed_group(max(lo, seeds[0]), hi)} seeds {max(lo, seeds[0])}-{hi}",
                        summarise(part, settings), settings)
        lo = hi + 1
    print_table(f"all seeds {seeds[0]}-{seeds[-1]}", table, settings)
    for key in settings[1:]:
        print(f"{label(key)} runtime counts: {table[key]['counts']}")
    print("mean forecast s.d. of seen joints, last frame of each run (mm): "
          + ", ".join(f"{h} s: {np.mean(v):.1f}" for h, v in sorted(sd.items())))
    boot = bootstrap(results, settings, args.ci) if args.ci else {}
    if boot:
        print_bootstrap(boot, args.ci, seeds)
    if args.why:
        anatomy(results)
    if args.json:
        out = {label(k): v for k, v in table.items()}
        if boot:
            out["bootstrap"] = {label(k): v for k, v in boot.items()}
        if args.why:    # every classified false trigger, for the team's own cuts
            out["why"] = {label(k): [rec for r in results for rec in r[k]["why"]]
                          for k in ANATOMY}
        Path(args.json).write_text(json.dumps(out, indent=1))
    if not args.quick and args.plot:
        plot(table, settings, args.plot)
        print(f"plot: {args.plot}")


def anatomy(results: list[dict]) -> None:
    """Print the classified false triggers of ``ANATOMY``'s settings (bench/anticipation_why.py),
    the forecast's marked ``NEW`` where the reference has none of the same joint near it."""
    print("\n" + why.__doc__.split("\n\n", 1)[1].split("\n\nEach record")[0])
    ref = [rec for r in results for rec in r[ANATOMY[0]]["why"]]
    for key in ANATOMY[1:]:
        mine = []
        for r in results:
            part = r[key]["why"]
            why.mark_shared(part, r[ANATOMY[0]]["why"])
            mine += part
        why.report(label(key), mine)
    why.report(label(ANATOMY[0]), ref)


def plot(table: dict, settings: list, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ref = table[("none", 0.0)]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    xs = [0.0] + [h * 1000 for h in HORIZONS]
    names = {"forecast": "forecast_s", "anticipate": "anticipate, group defaults"}
    b.axhline(ref["all"]["false"] * 1.1, color="grey", lw=0.5)   # the goal: +10 % at most
    for mode, style in (("forecast", "-"), ("anticipate", "--")):
        keys = [("none", 0.0)] + [(mode, h) for h in HORIZONS]
        for trig, colour in (("hand", "C0"), ("foot", "C1"), ("zone", "C2"), ("all", "k")):
            a.plot(xs, [ref[trig]["p50_ms"] - table[k][trig]["p50_ms"] for k in keys], style,
                   color=colour, marker="o", label=f"{trig} ({names[mode]})")
            b.plot(xs, [table[k][trig]["false"] for k in keys], style, color=colour, marker="o",
                   label=f"{trig} ({names[mode]})")
    a.set_xlabel("forecast, ms")
    a.set_ylabel("earlier than no forecast, ms (median)")
    a.axhline(30, color="grey", lw=0.5)
    b.set_xlabel("forecast, ms")
    b.set_ylabel("false triggers (all runs)")
    a.legend(fontsize=7)
    a.set_title("earliness")
    b.set_title("false triggers")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
