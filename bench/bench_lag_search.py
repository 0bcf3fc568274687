"""The live calibrator's lag search (``find_lag`` as it tracks a calibrated sensor), two
source trees side by side: the time per search and whether the results are the same.

Each tree runs in its own process (``--worker``), alternately, ``--rounds`` times, on
the same ``--cases`` pairs of 4-s streams (the calibrator's buffer at 30 Hz): one
person's 25 joints on a random walk, seen by a second sensor turned, moved, with
1-3 cm of noise, 2 % of joints 30 cm off, a clock offset within the search window and
Kinect-like confidences (0, 0.5, 1). The search is the tracking one (within 0.25 s of
the lag in use, ``fine_steps=2``), as ``Collector._search_lag`` calls it. A hash of
every lag, confidence, pair count and residual tells whether the trees agree.

    python bench/bench_lag_search.py /tmp/A .          # trees from `git archive`, or the repo
    python bench/bench_lag_search.py /tmp/A . --rounds 5 --cases 80
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import subprocess
import sys
import time

import numpy as np


def case(seed: int, n: int = 120):
    from stage.calibration.streams import Stream
    rng = np.random.default_rng(seed)
    t = np.sort(np.arange(n) / 30.0 + rng.uniform(0, 0.01, n) * (seed % 2))
    walk = np.cumsum(rng.normal(size=(n, 25, 3)) * 0.02, axis=0) + rng.normal(size=(25, 3)) * 0.3
    conf = rng.choice([0.0, 0.5, 1.0], size=(n, 25), p=[0.02, 0.3, 0.68])
    a = rng.uniform(-3, 3)
    c, s = np.cos(a), np.sin(a)
    turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    lag = rng.uniform(-0.2, 0.2)
    ref = Stream("ref", t, np.zeros(n, int), walk, conf)
    seen = walk @ turn.T + rng.normal(size=3) + rng.normal(size=walk.shape) * 0.01 * (1 + seed % 3)
    off = rng.random((n, 25)) < 0.02
    seen[off] += rng.normal(size=(int(off.sum()), 3)) * 0.3
    other_conf = np.clip(conf + rng.choice([0, -0.5], size=conf.shape, p=[0.95, 0.05]), 0, 1)
    return ref, Stream("other", t + lag, np.zeros(n, int), seen, other_conf)


def worker(tree: str, cases: int) -> None:
    sys.path.insert(0, tree)
    from stage.calibration import pairs
    assert pairs.__file__.startswith(str(tree)), pairs.__file__
    streams = [case(k) for k in range(cases)]
    pairs.find_lag(*streams[0], 0.25, fine_steps=2, min_pairs=30)   # imports, caches
    results, times = [], []
    for ref, other in streams:
        t0 = time.perf_counter()
        r = pairs.find_lag(ref, other, 0.25, fine_steps=2, min_pairs=30)
        times.append(time.perf_counter() - t0)
        results.append((r.lag_s, r.confidence, r.pairs, r.overlap, r.lags.tobytes(),
                        r.residual.tobytes()))
    digest = hashlib.sha1(pickle.dumps(results)).hexdigest()[:12]
    print(f"{np.median(times) * 1000:.2f} {np.mean(times) * 1000:.2f} {digest}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("trees", nargs="*", help="source trees (default: this repository)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker, args.cases)
        return
    trees = args.trees or ["."]
    print(f"{args.cases} tracking lag searches per run, trees alternating, {args.rounds} rounds")
    print(f"{'round':>5}  {'tree':<28} {'median ms':>9} {'mean ms':>8}  results")
    medians: dict[str, list[float]] = {t: [] for t in trees}
    digests: dict[str, set[str]] = {t: set() for t in trees}
    for r in range(args.rounds):
        for tree in trees:
            out = subprocess.run([sys.executable, __file__, "--worker", tree, "--cases",
                                  str(args.cases)], capture_output=True, text=True, check=True)
            med, mean, digest = out.stdout.split()
            medians[tree].append(float(med))
            digests[tree].add(digest)
            print(f"{r + 1:>5}  {tree:<28} {float(med):>9.2f} {float(mean):>8.2f}  {digest}")
    first = trees[0]
    for tree in trees[1:]:
        ratio = np.median(medians[tree]) / np.median(medians[first])
        same = "identical" if digests[tree] == digests[first] else "DIFFERENT"
        print(f"{tree} / {first}: median of medians x{ratio:.2f}; results {same}")


if __name__ == "__main__":
    main()
