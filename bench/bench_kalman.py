"""Benchmark of stage.kalman: lag and noise at Kinect-like rates, and cost against filterpy.

Run ``python bench/bench_kalman.py`` (a table) or ``python bench/bench_kalman.py --json``.
Every figure comes from a seeded generator; the timings of course vary by machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from filterpy.common import Q_discrete_white_noise  # noqa: E402
from filterpy.kalman import IMMEstimator, KalmanFilter  # noqa: E402

from stage.engine.kalman import FilterState, JointKalman, initial_mu, step, transition
from stage.settings import KalmanSettings  # noqa: E402

FPS = 30.0
FRAME = 1.0 / FPS
JITTER = 0.003  # s, uniform +- on each frame's capture time
SIGMA = 0.01  # m, measurement noise per axis
WARMUP = 2.0  # s
LAG_TARGET = 1.0  # frames
DIRECTION = np.array([1.0, 0.2, -0.4]) / np.linalg.norm([1.0, 0.2, -0.4])
START = np.array([0.0, 1.0, 2.5])


def frame_times(rng: np.random.Generator, seconds: float) -> np.ndarray:
    k = np.arange(int(seconds * FPS))
    return k * FRAME + rng.uniform(-JITTER, JITTER, k.size)


def run_filter(t: np.ndarray, z: np.ndarray, settings: KalmanSettings) -> np.ndarray:
    """Filter one point's track; t (K,), z (K, 3) -> (K, 3)."""
    kf, conf = JointKalman(1, settings), np.ones(1)
    return np.array([kf.step(tk, zk[None], conf)[0] for tk, zk in zip(t, z)])


def best_shift(t: np.ndarray, est: np.ndarray, truth_at) -> float:
    """The delay s (frames) minimising the RMS of est(t) - truth(t - s); > 0 means est trails."""
    shifts = np.round(np.arange(-3.0, 3.0001, 0.01), 2)
    err = [np.mean(np.sum((est - truth_at(t - s * FRAME)) ** 2, axis=1)) for s in shifts]
    return float(shifts[int(np.argmin(err))]) + 0.0  # + 0.0: no "-0.00"


def lag_case(speed: float, settings: KalmanSettings, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    t = frame_times(rng, 60.0)

    def truth_at(tt):
        return START + speed * tt[:, None] * DIRECTION

    truth = truth_at(t)
    z = truth + rng.normal(0.0, SIGMA, truth.shape)
    est = run_filter(t, z, settings)
    keep = t > WARMUP
    rms_raw = float(np.sqrt(np.mean(np.sum((z - truth)[keep] ** 2, axis=1))))
    rms_filt = float(np.sqrt(np.mean(np.sum((est - truth)[keep] ** 2, axis=1))))
    along = float(np.mean((est - truth)[keep] @ DIRECTION))
    return {
        "speed_m_s": speed,
        "lag_frames_along_track": -along / (speed * FRAME),
        "lag_frames_best_shift": best_shift(t[keep], est[keep], truth_at),
        "rms_raw_mm": 1000 * rms_raw,
        "rms_filtered_mm": 1000 * rms_filt,
        "noise_ratio": rms_filt / rms_raw,
    }


def stop_case(speed: float, settings: KalmanSettings, seed: int, tol: float = 0.005) -> dict:
    """Move at ``speed`` then stop dead at 3 s: overshoot and settling of the filter's response
    to the noise-free track (settle = time until it stays within ``tol``), and the peak error
    of a noisy run."""
    rng = np.random.default_rng(seed)
    t = frame_times(rng, 6.0)
    t_stop = 3.0
    travel = speed * np.minimum(t, t_stop)
    truth = START + travel[:, None] * DIRECTION
    est = run_filter(t, truth, settings)
    err = np.linalg.norm(est - truth, axis=1)
    after = t >= t_stop
    outside = np.flatnonzero(after & (err > tol))
    settle = float(t[outside[-1] + 1] - t_stop) if outside.size else 0.0
    overshoot = float(np.max((est - truth)[after] @ DIRECTION))
    noisy = run_filter(t, truth + rng.normal(0.0, SIGMA, truth.shape), settings)
    return {
        "speed_m_s": speed,
        "overshoot_mm": 1000 * overshoot,
        "settle_ms": 1000 * settle,
        "settle_frames": settle / FRAME,
        "settle_tol_mm": 1000 * tol,
        "noisy_peak_error_mm": 1000 * float(np.max(np.linalg.norm(noisy - truth, axis=1)[after])),
    }


def percentiles(ns: list[int]) -> tuple[float, float]:
    p50, p99 = np.percentile(np.asarray(ns) / 1000.0, [50, 99])
    return float(p50), float(p99)


def cost_ours(people: int, calls: int, seed: int) -> tuple[float, float]:
    """One step for all people at once, as the engine folds a batch (``kalman.step``)."""
    rng = np.random.default_rng(seed)
    n = 25 * people
    s = KalmanSettings()
    state = FilterState.empty(n)
    z = rng.normal(0.0, 1.0, (n, 3))
    r = np.full(n, s.measurement_noise)
    ns, t = [], 0.0
    for k in range(calls + 200):
        t += FRAME + rng.uniform(-JITTER, JITTER)
        z += rng.normal(0.0, 0.01, z.shape)
        t0 = time.perf_counter_ns()
        step(state, np.full(n, t), z, r, s)
        if k >= 200:  # skip the first calls (initialisation, caches)
            ns.append(time.perf_counter_ns() - t0)
    return percentiles(ns)


def cost_filterpy(people: int, calls: int, seed: int, settings: KalmanSettings) -> tuple[float, float]:
    """The straightforward way: filterpy's IMMEstimator of two 2-state KalmanFilters per joint
    and axis, F, Q and the transition matrix built once per step."""
    rng = np.random.default_rng(seed)
    n = people * 25 * 3
    imms = []
    for _ in range(n):
        filters = []
        for _ in range(2):
            kf = KalmanFilter(dim_x=2, dim_z=1)
            kf.H = np.array([[1.0, 0.0]])
            kf.R = np.array([[settings.measurement_noise]])
            kf.P = np.diag([settings.measurement_noise, settings.initial_velocity_var])
            filters.append(kf)
        imms.append(IMMEstimator(filters, initial_mu(settings).copy(), np.eye(2)))
    z = rng.normal(0.0, 1.0, n)
    ns = []
    for k in range(calls + 5):
        dt = FRAME + rng.uniform(-JITTER, JITTER)
        z += rng.normal(0.0, 0.01, z.shape)
        t0 = time.perf_counter_ns()
        p01, p10 = (float(p[0]) for p in transition(np.array([dt]), settings))
        M = np.array([[1.0 - p01, p01], [p10, 1.0 - p10]])
        F = np.array([[1.0, dt], [0.0, 1.0]])
        Qs = [Q_discrete_white_noise(dim=2, dt=dt, var=q)
              for q in (settings.quiet_noise, settings.fast_noise)]
        for imm, zi in zip(imms, z):
            imm.M = M
            imm._compute_mixing_probabilities()
            for kf, Q in zip(imm.filters, Qs):
                kf.F, kf.Q = F, Q
            imm.predict()
            imm.update(np.array([zi]))
        if k >= 5:
            ns.append(time.perf_counter_ns() - t0)
    return percentiles(ns)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--quick", action="store_true", help="fewer timed calls")
    args = parser.parse_args(argv)
    s = KalmanSettings()
    scale = 10 if args.quick else 1
    lag = [lag_case(v, s, seed=100 + i) for i, v in enumerate((0.5, 1.0, 2.0))]
    stop = [stop_case(v, s, seed=200 + i) for i, v in enumerate((1.0, 2.0))]
    cost = []
    for people, ours_calls, fp_calls in ((1, 20000, 40), (6, 5000, 10)):
        o50, o99 = cost_ours(people, ours_calls // scale, seed=300)
        f50, f99 = cost_filterpy(people, fp_calls // scale, seed=300, settings=s)
        cost.append({"points": 25 * people, "people": people, "ours_p50_us": o50, "ours_p99_us": o99,
                     "filterpy_p50_us": f50, "filterpy_p99_us": f99, "speedup_p50": f50 / o50})
    worst = max(max(abs(r["lag_frames_along_track"]), abs(r["lag_frames_best_shift"])) for r in lag)
    verdict = "PASS" if worst < LAG_TARGET else "FAIL"
    result = {"settings": asdict(s), "fps": FPS, "jitter_ms": 1000 * JITTER, "sigma_mm": 1000 * SIGMA,
              "lag": lag, "stop": stop, "cost": cost,
              "lag_target_frames": LAG_TARGET, "worst_lag_frames": worst, "verdict": verdict}
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"settings: quiet_noise={s.quiet_noise}, fast_noise={s.fast_noise} (m/s^2)^2, "
          f"measurement_noise={s.measurement_noise} m^2, gate {s.gate_sigma:g} sigma, "
          f"initial_velocity_var={s.initial_velocity_var} (m/s)^2")
    print(f"track: {FPS:.0f} Hz +-{1000 * JITTER:.0f} ms jitter, noise {1000 * SIGMA:.0f} mm/axis, "
          f"60 s, first {WARMUP:.0f} s dropped")
    print("\nconstant velocity   lag(along) lag(shift)  rms raw  rms filt  ratio")
    for r in lag:
        print(f"  {r['speed_m_s']:4.1f} m/s        {r['lag_frames_along_track']:+7.3f} fr {r['lag_frames_best_shift']:+6.2f} fr"
              f"  {r['rms_raw_mm']:6.2f} mm {r['rms_filtered_mm']:6.2f} mm  {r['noise_ratio']:5.3f}")
    print(f"  lag target < {LAG_TARGET:.0f} frame: worst {worst:.3f} frames -> {verdict}")
    print("\nstop at 3 s         overshoot  settle (noise-free track, within 5 mm)  noisy peak err")
    for r in stop:
        print(f"  {r['speed_m_s']:4.1f} m/s -> 0    {r['overshoot_mm']:6.1f} mm  {r['settle_ms']:6.0f} ms"
              f" = {r['settle_frames']:4.1f} frames{'':16}{r['noisy_peak_error_mm']:6.1f} mm")
    print("\ncost per step (all people at once)  ours p50/p99 us   filterpy IMM p50/p99 us   speed-up (p50)")
    for r in cost:
        label = f"{r['people']} x 25 points"
        print(f"  {label:16}  {r['ours_p50_us']:8.1f} / {r['ours_p99_us']:<8.1f} "
              f"{r['filterpy_p50_us']:9.0f} / {r['filterpy_p99_us']:<9.0f} x{r['speedup_p50']:.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
