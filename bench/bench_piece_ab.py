"""Two trees' piece runtimes in one process, on the same fused frames, alternating frame by frame.

``bench_piece.py`` times the runtime on frames it makes itself, without forecasts; in
``stage play`` the runtime gets the engine's frames, and a piece that anticipates (Liminal
Space asks for 0.05 s) gets every body predicted ahead too, which its anticipating
triggers read. Here one engine of tree A (``bench_engine_ab``'s input: P people seen by S
simulated Kinects, the native core, capture-time timetags, forecasts asked for as the piece
asks) makes the frames, and each frame is handed to the runtime of tree A and to the
runtime of tree B in turn (A then B, then B then A), each timed with ``time.thread_time``.
It prints each side's p50 and mean CPU a frame, the mean and the median of B / A, and
whether both emitted the same events (a digest of their reprs) and counts. The first fifth
of the frames (persons being found) is left out.

    python bench/bench_piece_ab.py TREE_A TREE_B [--configs 6x6] [--seconds 30] [--aligned]
        [--piece pieces/liminal.yaml] [--sections]

``--sections`` adds a row per section, forced there with ``goto`` and kept there (as
``bench_piece.py`` does): the simulated people sway in place, so the show alone stays in
the first section.
    (TREE: a directory holding stage/, e.g. `git archive REV | tar -x -C /tmp/A`, and `.`)
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_engine_ab as ab  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


class DigestSink:
    """Counts the events and digests their reprs (package names left out)."""

    def __init__(self, package: str) -> None:
        self.package = package + "."
        self.count = 0
        self.digest = hashlib.blake2b(digest_size=16)

    def emit(self, events: list) -> None:
        self.count += len(events)
        for event in events:
            self.digest.update(repr(event).replace(self.package, "").encode())


def run(mods: list[dict], names: list[str], piece_path: str, sensors: int, people: int,
        seconds: float, aligned: bool, section: str | None = None) -> dict:
    poses, data = ab.datagrams(mods[0], sensors, people, seconds, timetags=True,
                               aligned=aligned)
    engine, clock = ab.engine(mods[0], poses, native=True, forecast=-1.0)
    sides = []
    for m, name in zip(mods, names):
        piece = m["piece"].load_piece(piece_path)
        sink = DigestSink(name)
        runtime = m["piece"].PieceRuntime(piece, sink, seed=1)
        if section is not None:      # (as bench_piece.py: forced there, and kept there)
            runtime.start(0.0)
            if section != piece.start:
                runtime.goto(section, 0.0, "bench")
            runtime._change_section = lambda *a, **k: False
        sides.append((runtime, sink, []))
    for horizon in sorted(piece.horizons()):      # (not lazily: neither timed runtime
        engine.people.want_forecast(horizon)      # pays for making them)
    turn = [0]

    def both(frame) -> None:
        order = sides if turn[0] % 2 == 0 else sides[::-1]
        for runtime, _, times in order:
            c0 = time.thread_time()
            runtime(frame)
            times.append(time.thread_time() - c0)
        turn[0] += 1

    engine.listeners.append(both)
    for t, d in data:
        clock.set(t)
        engine.handle_datagram(d)
        engine.tick()
    skip = turn[0] // 5
    a, b = (np.array(times[skip:]) * 1e6 for _, _, times in sides)
    (ra, sa, _), (rb, sb, _) = sides
    return {"config": f"{sensors}x{people}", "frames": len(a),
            "a_p50": float(np.median(a)), "a_mean": float(a.mean()),
            "b_p50": float(np.median(b)), "b_mean": float(b.mean()),
            "mean_ratio": float(b.mean() / a.mean()), "median_ratio": float(np.median(b / a)),
            "events": (sa.count, sb.count),
            "identical": sa.digest.digest() == sb.digest.digest() and ra.counts == rb.counts,
            "sections": (ra.section.name, rb.section.name)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tree_a")
    parser.add_argument("tree_b")
    parser.add_argument("--configs", default="6x6")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--aligned", action="store_true",
                        help="sensors in step (one frame per datagram: no bursts in process)")
    parser.add_argument("--piece", default=str(REPO / "pieces" / "liminal.yaml"))
    parser.add_argument("--sections", action="store_true",
                        help="also each section on its own (forced with goto and kept), as "
                             "bench_piece.py does: the show alone may not leave the first")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        names = ["piece_a", "piece_b"]
        mods = [ab.load(tree, name, Path(tmp))
                for tree, name in zip((args.tree_a, args.tree_b), names)]
        print(f"A = {args.tree_a}, B = {args.tree_b}; {Path(args.piece).name}; CPU per frame "
              f"(thread_time), us; {args.seconds:g} s of show; "
              f"{'aligned' if args.aligned else 'spread'}; load "
              f"{open('/proc/loadavg').read().split()[0]}")
        print(f"{'config':>7} {'frames':>7} {'A p50':>6} {'A mean':>6} {'B p50':>6} "
              f"{'B mean':>6} {'mean B/A':>8} {'median B/A':>10}  events A/B, identical, section")
        sections = [None]
        if args.sections:
            sections += [sec.name for sec in mods[0]["piece"].load_piece(
                args.piece).sections]
        for config, section in [(c, sec) for c in args.configs.split(",") for sec in sections]:
            s, p = map(int, config.split("x"))
            r = run(mods, names, args.piece, s, p, args.seconds, args.aligned, section)
            print(f"{r['config']:>7} {r['frames']:>7} {r['a_p50']:>6.0f} {r['a_mean']:>6.0f} "
                  f"{r['b_p50']:>6.0f} {r['b_mean']:>6.0f} {r['mean_ratio']:>8.2f} "
                  f"{r['median_ratio']:>10.2f}  {r['events'][0]}/{r['events'][1]}, "
                  f"{r['identical']}, {r['sections'][0]} / {r['sections'][1]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
