"""The compiled kernels (stage/engine/jit.py) against the numpy code, in the same run.

The input is bench_engine_inproc.py's (S simulated Kinects on a ring, P people on a grid,
every sensor seeing every person, 30 Hz), replayed into a fresh Engine on an injected
clock; the CPU time (process_time) of ``handle_datagram`` + ``tick`` over the whole
replay is divided by the number of datagrams. Each repetition runs the kernels, then
the numpy code (``jit.disabled()``) on the same datagrams, so that the ratio is taken
pair by pair: this machine's speed drifts by tens of percent from one minute to the next,
and a pair a few seconds apart shares the drift. Also printed: how long ``jit.warm()``
took in this process (numba's on-disk cache loaded; the first run after an install
compiles, which takes a few seconds).

``--self-healing`` attaches the live calibrator as ``stage serve`` runs it (threaded; its
worker's polls run on this thread right after the datagram that made them due: see
bench_engine_inproc.py ``--worker``) and prints its CPU share of a core, kernels and
numpy, beside the engine's; run 12 s or more so that lag searches are in it.

Last, the hand votes on their own: one sensor frame's two reports and the vote after
it, with six sensors reporting in turn (what the engine does per skeleton at six
sensors), ``hands.HandVoter`` against the compiled ``handbank.ArrayHandVoter``, in pairs.

Run: python bench/bench_jit.py [--configs 1x1,3x3,6x6] [--seconds 4] [--reps 5]
[--self-healing]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench_engine_inproc import datagrams, make_engine, run
from stage.engine import jit


def replay(poses, data) -> float:
    """CPU us per datagram of one fresh engine over ``data``."""
    engine, clock = make_engine(poses)
    c0 = time.process_time()
    for t, d in data:
        clock.set(t)
        engine.handle_datagram(d)
        engine.tick()
    return (time.process_time() - c0) / len(data) * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", default="1x1,3x3,6x6")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--self-healing", action="store_true",
                        help="with the live calibrator (threaded, as stage serve runs it)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    if not jit.warm():
        print(f"compiled kernels unavailable ({jit.why_not()}): nothing to compare")
        return 1
    print(f"jit.warm() in this process: {time.perf_counter() - t0:.2f} s")
    if args.self_healing:
        return healing(args)
    print(f"{'config':>7} {'kernels us':>11} {'numpy us':>9} {'ratio (pairs)':>14}  range")
    for config in args.configs.split(","):
        n_sensors, n_people = map(int, config.split("x"))
        poses, data = datagrams(n_sensors, n_people, args.seconds)
        on, off = [], []
        for _ in range(args.reps):
            on.append(replay(poses, data))
            with jit.disabled():
                off.append(replay(poses, data))
        ratio = np.array(on) / np.array(off)
        print(f"{config:>7} {np.median(on):11.0f} {np.median(off):9.0f} {np.median(ratio):14.3f}"
              f"  {ratio.min():.3f}-{ratio.max():.3f}")
    hand_votes(args.reps)
    return 0


def hand_votes(reps: int, n: int = 20000) -> None:
    """us per skeleton of the hand votes, reference and compiled, pair by pair."""
    from stage.engine.handbank import ArrayHandVoter
    from stage.engine.hands import HandVoter
    from stage.joints import HandState

    keys = [(f"s{k}", 0) for k in range(6)]
    states = (HandState.OPEN, HandState.CLOSED)

    def cost(cls) -> float:
        voter = cls(0.03, 0.1)
        c0 = time.process_time()
        for i in range(n):
            t = i / 180.0
            voter.add_frame(keys[i % 6], states[(i // 97) % 2], 1.0, HandState.OPEN, 0.9, t)
            voter.update(t)
        return (time.process_time() - c0) / n * 1e6

    pairs = np.array([(cost(HandVoter), cost(ArrayHandVoter)) for _ in range(reps)])
    ratio = pairs[:, 1] / pairs[:, 0]
    print(f"hand votes per skeleton (6 sensors): HandVoter {np.median(pairs[:, 0]):.2f} us, "
          f"compiled {np.median(pairs[:, 1]):.2f} us, ratio {np.median(ratio):.3f} "
          f"({ratio.min():.3f}-{ratio.max():.3f})")


def healing(args) -> int:
    """Engine and calibrator CPU, % of a core, kernels and numpy, pair by pair."""
    print(f"{'config':>7} | {'all, kernels':>12} {'numpy':>6} {'ratio':>6} | {'calibrator, kernels':>19}"
          f" {'numpy':>6} {'ratio':>6}")
    for config in args.configs.split(","):
        n_sensors, n_people = map(int, config.split("x"))
        rows = {True: [], False: []}
        for _ in range(args.reps):
            rows[True].append(run(n_sensors, n_people, args.seconds, True, True))
            with jit.disabled():
                rows[False].append(run(n_sensors, n_people, args.seconds, True, True))
        total = {k: np.array([r["core_fraction"] for r in v]) * 100 for k, v in rows.items()}
        cal = {k: np.array([r["calibrator_core_fraction"] for r in v]) * 100
               for k, v in rows.items()}
        print(f"{config:>7} | {np.median(total[True]):12.1f} {np.median(total[False]):6.1f} "
              f"{np.median(total[True] / total[False]):6.3f} | {np.median(cal[True]):19.1f} "
              f"{np.median(cal[False]):6.1f} {np.median(cal[True] / cal[False]):6.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
