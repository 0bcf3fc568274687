"""Anticipation: how much earlier triggers fire with a forecast, and at what cost in false triggers.

The simulator's sensors show the dancer 60 ms late (``pipeline_delay_s``, 3 ms
jitter; 5 ms of network latency on top, so some 65 ms end to end, as seed 004's
60-80 ms), and CMU subject 131's takes (``/work/shared/data/cmu``, or
$STAGE_CMU_DIR) drive the dancer. One engine per take and seed, on a manual
clock, feeds one piece runtime per setting at once (the engine predicts every
horizon asked for), so every setting sees the same frames:

- ``none``: the reference, no forecast (what the engine does without this work);
- ``forecast H``: the piece's ``forecast_s: H`` (every trigger on the predicted body);
- ``anticipate H``: ``defaults: {anticipate: H}`` (a predicted crossing fires when its
  s.d. is at most ``max_sd``; the measurements confirm or contradict it).

Triggers: a hand rising above the head (``rises_above: Head``), a foot lifting
(``rises_above: 0.25``), and the torso centre entering one of three bands
across the dancer's path (``enters``). The ground truth (the motion capture at
120 Hz) gives the true crossings with the same thresholds and hysteresis. A
firing is matched to the first unmatched true crossing of its trigger and
joint that happened at most 200 ms before it or at most 100 ms after it;
a firing with none is a *false trigger* (the truth never crossed within 100
ms of what the firing claims). For matched firings the delay is the firing's
engine time minus the true crossing's time (engine clock = simulation clock).

    python bench/bench_anticipation.py            # 3 takes x 5 seeds, plot in docs/
    python bench/bench_anticipation.py --quick    # one take, one seed, no plot
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import machine_busy_s  # noqa: E402

from stage.app.offline import feed  # noqa: E402
from stage.clock import ManualClock  # noqa: E402
from stage.engine import Engine  # noqa: E402
from stage.events import TriggerFired  # noqa: E402
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
SETTLE = 0.8                 # s: crossings before the engine has seen the dancer are not counted

SCENARIO = """
sensors: {{ring: {{count: 3, radius: 3.5}}}}
kinect: {{pipeline_delay_s: {delay}, pipeline_jitter_s: 0.003}}
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
      - {{name: hand, rises_above: Head, joint: hands, cooldown_per: joint, do: [{{note: C4}}]}}
      - {{name: foot, rises_above: {foot}, joint: feet, cooldown_per: joint, do: [{{note: D4}}]}}
{bands}
"""


def piece_text(mode: str, horizon: float, max_sd: float | None = None) -> str:
    zones = "\n".join(f"  {n}: {{shape: box, min: [-3, 0, {z0}], max: [3, 2.5, {z1}]}}"
                      for n, (z0, z1) in BANDS.items())
    bands = "\n".join(f"      - {{name: zone, enters: {n}, cooldown_per: joint, do: [{{note: E4}}]}}"
                      for n in BANDS)
    top = f"forecast_s: {horizon}" if mode == "forecast" else ""
    anticipate = ""
    if mode == "anticipate":
        anticipate = f", anticipate: {horizon}" if max_sd is None else \
            f", anticipate: {{ahead: {horizon}, max_sd: {max_sd}}}"
    return PIECE.format(top=top, h=HYST, anticipate=anticipate, zones=zones, foot=FOOT_Y,
                        bands=bands)


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


def true_crossings(sim: Simulator, duration: float) -> dict[tuple[str, str], list[float]]:
    t = np.arange(0.0, duration, 1.0 / 120.0)
    joints = np.array([sim.truth(float(x))["dancer"][0] for x in t])
    out: dict[tuple[str, str], list[float]] = {}
    for side in ("Left", "Right"):
        out[("hand", "Hand" + side)] = schmitt_up(t, joints[:, J["Hand" + side], 1]
                                                  - joints[:, J["Head"], 1])
        out[("foot", "Foot" + side)] = schmitt_up(t, joints[:, J["Foot" + side], 1] - FOOT_Y)
    z = joints[:, TORSO, 2].mean(axis=1)
    for name, (z0, z1) in BANDS.items():
        # inside > 0: the distance into the band from its nearer border
        inside = np.minimum(z - z0, z1 - z)
        out.setdefault(("zone", "body"), []).extend(schmitt_up(t, inside))
    return {k: sorted(c for c in v if c >= SETTLE) for k, v in out.items()}


def score(firings: list[tuple[str, str, float]], truth: dict) -> dict[str, dict]:
    """Per trigger: delays of matched firings, false triggers, misses."""
    out = {}
    for trig in ("hand", "foot", "zone"):
        delays, false, n_true = [], 0, 0
        for (tname, joint), crossings in truth.items():
            if tname != trig:
                continue
            n_true += len(crossings)
            used = [False] * len(crossings)
            for _, _, tf in sorted(f for f in firings if f[0] == trig and f[1] == joint):
                if tf < SETTLE:
                    continue
                k = next((i for i, c in enumerate(crossings)
                          if not used[i] and c - AFTER <= tf <= c + BEFORE), None)
                if k is None:
                    false += 1
                else:
                    used[k] = True
                    delays.append(tf - crossings[k])
        out[trig] = {"true": n_true, "delays": delays, "false": false,
                     "missed": n_true - len(delays)}
    return out


def run(take: str, seed: int, delay: float, settings: list[tuple[str, float]],
        max_sd: float | None = None) -> dict:
    path = cmu_file(take)
    if path is None:
        raise SystemExit(f"CMU take {take} not found ($STAGE_CMU_DIR or shared/data/cmu)")
    text = SCENARIO.format(delay=delay, path=path)
    sim = Simulator(parse_scenario(loads_marked(text, "bench.yaml"), "bench.yaml"), seed=seed)
    duration = sim.performers[0].length + 0.5 if hasattr(sim.performers[0], "length") else 11.0
    clock = ManualClock(0.0)
    engine = Engine(sim.rig(), clock)
    runtimes = {}
    for mode, h in settings:
        piece = loads_piece(piece_text(mode, h, max_sd), "bench.yaml")
        sink = RecordingSink()
        rt = PieceRuntime(piece, sink, seed=seed)
        for horizon in piece.horizons():
            engine.people.want_forecast(horizon)
        engine.listeners.append(rt)
        runtimes[(mode, h)] = (rt, sink)
    feed(engine, clock, sim.stream(duration), end=duration)
    truth = true_crossings(sim, duration)
    out = {}
    for key, (rt, sink) in runtimes.items():
        fired = [(e.trigger, e.joint, e.t) for e in sink.events if isinstance(e, TriggerFired)]
        out[key] = {"score": score(fired, truth), "counts": dict(rt.counts)}
    out["forecast_stats"] = engine.people.forecast_stats()
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one take, one seed, no plot")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--delay", type=float, default=0.060, help="pipeline delay, s")
    ap.add_argument("--plot", default=str(ROOT / "docs" / "anticipation.png"))
    ap.add_argument("--json", default=None, help="write the table here too")
    ap.add_argument("--max-sd", type=float, default=None,
                    help="anticipate's max_sd, m (default: the language's default)")
    args = ap.parse_args()
    takes = TAKES[:1] if args.quick else TAKES
    seeds = range(1, 2 if args.quick else args.seeds + 1)
    settings = [("none", 0.0)] + [(m, h) for m in ("forecast", "anticipate") for h in HORIZONS]
    busy0, wall0 = machine_busy_s(), time.monotonic()
    results, sd = [], {}
    for take in takes:
        for seed in seeds:
            r = run(take, seed, args.delay, settings, args.max_sd)
            results.append(r)
            for h, v in r["forecast_stats"]["sd_mm"].items():
                sd.setdefault(h, []).append(v)
    load = (machine_busy_s() - busy0) / (time.monotonic() - wall0)
    table = summarise(results, settings)
    print(f"anticipate max_sd: {'default' if args.max_sd is None else args.max_sd} m")
    print(f"pipeline delay {args.delay * 1000:.0f} ms (+3 ms jitter, +5 ms network); takes "
          f"{', '.join(takes)}; seeds {list(seeds)}; machine busy {load:.2f} cores "
          f"(of {os.cpu_count()}) during the run")
    print("delay = firing minus true crossing (ms, matched firings); false = firings with no "
          "true crossing 200 ms before to 100 ms after; earlier = p50 of none minus p50")
    ref = table[("none", 0.0)]
    header = f"{'setting':<16}" + "".join(
        f"{t + ' p50/p90':>16}{'earlier':>8}{'false':>6}{'miss':>5}" for t in
        ("hand", "foot", "zone", "all"))
    print(header)
    for key in settings:
        row = table[key]
        line = f"{key[0] + (f' {key[1] * 1000:.0f} ms' if key[1] else ''):<16}"
        for t in ("hand", "foot", "zone", "all"):
            c = row[t]
            line += f"{c['p50_ms']:8.1f}/{c['p90_ms']:<7.1f}{ref[t]['p50_ms'] - c['p50_ms']:8.1f}" \
                    f"{c['false']:6d}{c['true'] - c['matched']:5d}"
        print(line)
    print("true crossings: " + ", ".join(f"{t} {ref[t]['true']}" for t in ("hand", "foot", "zone")))
    for key in settings[1:]:
        print(f"{key[0]} {key[1] * 1000:.0f} ms runtime counts: {table[key]['counts']}")
    print("mean forecast s.d. of seen joints, last frame of each run (mm): "
          + ", ".join(f"{h} s: {np.mean(v):.1f}" for h, v in sorted(sd.items())))
    for mode in ("forecast", "anticipate"):
        c, r0 = table[(mode, 0.05)]["all"], ref["all"]
        gain = r0["p50_ms"] - c["p50_ms"]
        limit = r0["false"] * 1.1
        print(f"goal at {mode} 50 ms: {gain:.1f} ms earlier (>= 30: "
              f"{'yes' if gain >= 30 else 'NO'}); false {c['false']} vs {r0['false']} without "
              f"(<= {limit:.1f}: {'yes' if c['false'] <= limit else 'NO'})")
    if args.json:
        Path(args.json).write_text(json.dumps({f"{k[0]} {k[1]}": v for k, v in table.items()},
                                              indent=1))
    if not args.quick and args.plot:
        plot(table, settings, args.plot)
        print(f"plot: {args.plot}")


def plot(table: dict, settings: list, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ref = table[("none", 0.0)]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    xs = [0.0] + [h * 1000 for h in HORIZONS]
    for mode, style in (("forecast", "-"), ("anticipate", "--")):
        keys = [("none", 0.0)] + [(mode, h) for h in HORIZONS]
        for trig, colour in (("hand", "C0"), ("foot", "C1"), ("zone", "C2"), ("all", "k")):
            a.plot(xs, [ref[trig]["p50_ms"] - table[k][trig]["p50_ms"] for k in keys], style,
                   color=colour, marker="o", label=f"{trig} ({mode})")
            b.plot(xs, [table[k][trig]["false"] for k in keys], style, color=colour, marker="o",
                   label=f"{trig} ({mode})")
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
