"""How long a foot's (and a hand's) vertical velocity lasts, measured on motion capture.

The forecast (stage/engine/forecast.py, docs/anticipation.md) carries a joint ahead by
its velocity. A constant-velocity forecast assumes the velocity lasts for ever; a real
foot that rises fast in a step stops 10-20 cm up. This bench measures, on CMU subject
131's takes (120 Hz motion capture, the dancer the anticipation bench uses; no sensor,
no filter), each joint group's vertical velocity autocorrelation ``rho(s)`` and fits it
with a Gaussian ``exp(-s^2 / (2 sigma^2))``: ``sigma`` is the forecast's ``memory_s``.
The least-squares linear prediction of the displacement over ``h`` from the present
velocity is ``v`` times the integral of ``rho`` over ``h`` (the *effective horizon*,
``stage.engine.forecast.effective_horizon``); the bench prints it beside the one fitted
directly (regression of the displacement on the velocity) and the constant-velocity
``h``, as the reference. It also prints the remaining rise of a rising foot against its
speed (how far above its present height a step peaks), for the docs.

With ``--fused`` it also runs the anticipation bench's scene (three simulated Kinects,
60 ms pipeline delay; its tuning seeds 1-3 only) through the engine and compares the
fused feet with the motion capture the sensors showed (60 ms earlier): the error of
their height and vertical speed, the lag at which the fused speed best matches the true
one, and the 50 ms forecast's error -- what a predicted crossing is made of, beside the
motion model's own error above.

    python bench/bench_motion_memory.py            # under a second
    python bench/bench_motion_memory.py --fused    # about half a minute
    python bench/bench_motion_memory.py --fused --quick   # one take, one seed
    python bench/bench_motion_memory.py --fused --kinect 'noise_m: 0.00066, noise_per_m: 0.00044'
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stage.engine.forecast import effective_horizon  # noqa: E402
from stage.joints import JOINT_INDEX as J  # noqa: E402
from stage.sensors.sim import Simulator, parse_scenario  # noqa: E402
from stage.testing.walks import cmu_file  # noqa: E402
from stage.yamlio import loads_marked  # noqa: E402

TAKES = ("131_01", "131_02", "131_03")
RATE = 120.0
#: the forecast's groups (``foot_velocity_memory_s``: ankles and feet,
#: ``hand_velocity_memory_s``: wrists, hands, thumbs and tips; the thumbs and tips are not
#: in the motion capture) and, apart, the joints the bench's triggers watch
GROUPS = {"ankles and feet (foot_velocity_memory_s)": ("AnkleLeft", "AnkleRight", "FootLeft",
                                                       "FootRight"),
          "wrists and hands (hand_velocity_memory_s)": ("WristLeft", "WristRight", "HandLeft",
                                                        "HandRight"),
          "feet": ("FootLeft", "FootRight"), "hands": ("HandLeft", "HandRight")}
SCENARIO = """
sensors: {{ring: {{count: 3, radius: 3.5}}}}
performers:
  - {{name: dancer, height: 1.75, position: [0, -1.5], motion: {path}}}
"""
LAGS = np.arange(0, 19)          # samples: 0-150 ms
HORIZONS_MS = (25, 50, 75, 100)


def heights(take: str) -> np.ndarray:
    """(T, 25) every joint's height (m) at 120 Hz, as the simulator's dancer moves."""
    path = cmu_file(take)
    if path is None:
        raise SystemExit(f"CMU take {take} not found ($STAGE_CMU_DIR or shared/data/cmu)")
    sim = Simulator(parse_scenario(loads_marked(SCENARIO.format(path=path), "b.yaml"),
                                   "b.yaml"), seed=1)
    t = np.arange(0.0, sim.performers[0].length, 1.0 / RATE)
    return np.array([sim.truth(float(x))["dancer"][0][:, 1] for x in t])


def fit_sigma(rho: np.ndarray) -> float:
    """The s.d. (s) of the Gaussian closest (least squares) to ``rho`` at ``LAGS``."""
    grid = np.arange(0.010, 0.300, 0.0005)
    lag_s = LAGS / RATE
    err = [((np.exp(-lag_s ** 2 / (2 * s * s)) - rho) ** 2).sum() for s in grid]
    return float(grid[int(np.argmin(err))])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="a smoke test: with --fused, one take and one seed")
    ap.add_argument("--fused", action="store_true",
                    help="also the fused feet of the anticipation bench's seeds 1-3")
    ap.add_argument("--kinect", default="", metavar="KEYS",
                    help="with --fused: more keys of the scenario's kinect: section")
    ap.add_argument("--forecast", default="", metavar="KEYS",
                    help="with --fused: the rig's forecast keys, e.g. "
                         "'foot_velocity_memory_s: 0' (a constant-velocity forecast)")
    args = ap.parse_args()
    ys = [heights(take) for take in TAKES]
    print(f"CMU {', '.join(TAKES)}: {sum(len(y) for y in ys) / RATE:.1f} s of motion "
          "capture at 120 Hz; vertical axis")
    for group, names in GROUPS.items():
        series = [y[:, J[n]] for y in ys for n in names]
        vel = [np.gradient(y, 1.0 / RATE) for y in series]
        r0 = sum((v * v).sum() for v in vel) / sum(len(v) for v in vel)
        rho = np.array([sum((v[k:] * v[:len(v) - k]).sum() for v in vel)
                        / sum(len(v) - k for v in vel) / r0 for k in LAGS])
        sigma = fit_sigma(rho)
        model = np.exp(-(LAGS / RATE) ** 2 / (2 * sigma * sigma))
        print(f"{group}: velocity autocorrelation at 0, 25, 50, 75, 100, 125, 150 ms: "
              + " ".join(f"{r:.2f}" for r in rho[::3])
              + f"; Gaussian fit sigma = {sigma * 1000:.1f} ms (worst misfit "
              f"{np.abs(model - rho).max():.2f})")
        for h in HORIZONS_MS:
            k = round(h * RATE / 1000)
            num = sum((v[:-k] * (y[k:] - y[:-k])).sum() for y, v in zip(series, vel))
            den = sum((v[:-k] ** 2).sum() for v in vel)
            res_cv = np.sqrt(np.mean(np.concatenate(
                [y[k:] - y[:-k] - v[:-k] * h / 1000 for y, v in zip(series, vel)]) ** 2))
            eff = float(effective_horizon(np.array([h / 1000]), sigma)[0])
            res_m = np.sqrt(np.mean(np.concatenate(
                [y[k:] - y[:-k] - v[:-k] * eff for y, v in zip(series, vel)]) ** 2))
            print(f"  h {h:3d} ms: effective horizon {eff * 1000:5.1f} ms (regression "
                  f"{num / den * 1000:5.1f}, constant velocity {h}); rms error of the "
                  f"prediction {res_m * 1000:5.1f} mm (constant velocity {res_cv * 1000:5.1f})")
        if group == "feet":
            rises(series, vel)
    if args.fused:
        fused(args.kinect, args.forecast, TAKES[:1] if args.quick else TAKES,
              (1,) if args.quick else (1, 2, 3))


def rises(series: list[np.ndarray], vel: list[np.ndarray]) -> None:
    """How much higher a rising foot peaks, by its present upward speed."""
    rows = []
    for y, v in zip(series, vel):
        for i in range(len(y)):
            if v[i] <= 0.5:
                continue
            e = i
            while e + 1 < len(y) and v[e + 1] > 0:
                e += 1
            rows.append((v[i], y[e] - y[i], y[e], y[i]))
    a = np.array(rows)
    print("  a rising foot's remaining rise (m) by upward speed: median [90th pct] of "
          "rise / speed (s)")
    for lo, hi in ((0.5, 1), (1, 2), (2, 3), (3, math.inf)):
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        if m.any():
            q = a[m, 1] / a[m, 0]
            print(f"    {lo:g}-{hi:g} m/s: n {m.sum():4d}, rise {np.median(a[m, 1]):.3f} m, "
                  f"rise/speed {np.median(q) * 1000:.0f} ms [{np.percentile(q, 90) * 1000:.0f}]")
    # the anticipation bench's foot trigger: 0.25 m; where a predicted crossing is decided,
    # the foot is 12-24 cm up (docs/reports/issue-15.md, stop 20)
    band = (a[:, 3] >= 0.12) & (a[:, 3] <= 0.24)
    for name, m in (("steps (peak below 0.25 m)", band & (a[:, 2] < 0.25)),
                    ("lifts (peak above 0.25 m)", band & (a[:, 2] >= 0.25))):
        v = a[m, 0]
        print(f"    {name}, rising and 12-24 cm up: n {m.sum()}, upward speed median "
              f"{np.median(v):.2f} m/s (10-90 %: {np.percentile(v, 10):.2f}-"
              f"{np.percentile(v, 90):.2f})")


def fused(kinect: str, forecast: str = "", takes: tuple[str, ...] = TAKES,
          seeds: tuple[int, ...] = (1, 2, 3)) -> None:
    """The fused feet against the truth the sensors showed (see the module docstring)."""
    from bench_anticipation import sim_engine

    from stage.app.offline import feed
    delay, feet = 0.060, [J["FootLeft"], J["FootRight"]]
    rows = []     # per frame and foot: capture time, fused y, vy, forecast y, truth series
    for take in takes:
        for seed in seeds:
            sim, clock, engine, end = sim_engine(take, seed, delay, kinect, forecast)
            engine.people.want_forecast(0.05)
            got: list = []
            engine.listeners.append(lambda f: got.extend(
                (b.t, b.joints[feet, 1], b.velocity[feet, 1], f.forecasts[0.05][pid].joints[
                    feet, 1]) for pid, b in f.bodies.items() if pid in f.forecasts.get(0.05, {})))
            feed(engine, clock, sim.stream(end), end=end)
            t = np.arange(0.0, end, 1.0 / RATE)
            truth = np.array([sim.truth(float(x))["dancer"][0][feet, 1] for x in t])
            for k in range(2):
                y = truth[:, k]
                rows.append((t, y, np.gradient(y, 1.0 / RATE),
                             np.array([[g[0], g[1][k], g[2][k], g[3][k]] for g in got])))

    def err(col: int, lag: float, shift: float = 0.0) -> np.ndarray:
        out = []
        for t, y, v, f in rows:
            at = f[:, 0] - delay - lag
            keep = at > 0.8               # after the engine has settled on the dancer
            true = np.interp(at + shift, t, v if col == 2 else y)
            out.append((f[:, col] - true)[keep])
        return np.concatenate(out)

    print(f"fused feet, {', '.join(takes)}, seeds {', '.join(map(str, seeds))}, sensor model {'default' + (' + ' + kinect if kinect else '')}"
          f"{', forecast ' + forecast if forecast else ''}"
          f" ({sum(len(r[3]) for r in rows)} foot-frames): against the motion capture "
          f"{delay * 1000:.0f} ms before each capture stamp")
    e = err(1, 0.0)
    print(f"  height error mean {e.mean() * 1000:+.1f} mm, s.d. {e.std() * 1000:.1f} mm")
    lags = np.arange(0.0, 0.061, 0.005)
    sds = [err(2, lag).std() for lag in lags]
    best = int(np.argmin(sds))
    print(f"  vertical speed error s.d. {sds[0]:.2f} m/s; smallest against the truth "
          f"{lags[best] * 1000:.0f} ms earlier still: {sds[best]:.2f} m/s")
    e = err(3, 0.0, shift=0.05)
    print(f"  50 ms forecast's height error mean {e.mean() * 1000:+.1f} mm, "
          f"s.d. {e.std() * 1000:.1f} mm")


if __name__ == "__main__":
    main()
