"""Sensors in step: how long each datagram of a burst waits for its skeleton to go out, in
process, with a burst's hand votes and listeners' frame after its last datagram (what the
engine thread does, ``Engine.process_taken``) against the reference: every datagram
processed whole before the next (``Engine.process`` each, what it did before stop 52).

Every frame of ``bench_engine_inproc``'s aligned show (S simulated Kinects, P people, all
S datagrams at the frame's instant) is handed to two engines of this tree, alternating
which goes first, on an injected clock. A datagram's wait is the engine thread's CPU time
from the start of its burst until its skeletons are sent (the end of the ``_send_joints``
that sends them): the order the engine works in, without this VM's scheduling noise.
``--piece`` adds a listener to both engines, the Liminal Space piece evaluating every
fused frame as in ``stage play`` (its events kept in memory). The first fifth of the show
(persons being found) is left out.

Run: python bench/bench_burst.py [--configs 3x6,6x3,6x6] [--seconds 20] [--piece]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_engine_inproc as inproc  # noqa: E402

from stage.sensors.protocol import Inbound, decode_datagram  # noqa: E402


def _engine(poses, piece: bool):
    engine, clock = inproc.make_engine(poses)
    if piece:
        from stage.piece import PieceRuntime, RecordingSink, load_piece
        root = Path(__file__).resolve().parent.parent
        engine.listeners.append(PieceRuntime(load_piece(root / "pieces" / "liminal.yaml"),
                                             RecordingSink(limit=1000), seed=1))
    marks: list[int] = []
    send_joints = engine.people._send_joints

    def marked(new):
        out = send_joints(new)
        marks.append(time.thread_time_ns())
        return out
    engine.people._send_joints = marked
    return engine, clock, marks


def run(n_sensors: int, n_people: int, seconds: float, piece: bool) -> dict:
    poses, data = inproc.datagrams(n_sensors, n_people, seconds, aligned=True)
    bursts = [list(g) for _, g in itertools.groupby(data, key=lambda td: td[0])]
    sides = {"burst": _engine(poses, piece), "each": _engine(poses, piece)}
    waits: dict[str, list[float]] = {k: [] for k in sides}
    totals: dict[str, list[float]] = {k: [] for k in sides}
    skip = len(bursts) // 5
    for b, burst in enumerate(bursts):
        t = burst[0][0]
        order = ("burst", "each") if b % 2 == 0 else ("each", "burst")
        for side in order:
            engine, clock, marks = sides[side]
            clock.set(t)
            items = []
            for k, (_, d) in enumerate(burst):
                source = (f"10.0.0.{k + 1}", 5000)
                items += [Inbound(m, t, source, tt)
                          for m, tt in decode_datagram(d, f"{source[0]}:5000").messages]
            marks.clear()
            start = time.thread_time_ns()
            if side == "burst":
                engine.process_taken(items)
            else:
                for k in range(len(burst)):
                    engine.process([i for i in items if i.source[0] == f"10.0.0.{k + 1}"])
            end = time.thread_time_ns()
            engine.tick()
            if b >= skip:
                waits[side] += [(m - start) / 1e3 for m in marks[:len(burst)]]
                totals[side].append((end - start) / 1e3)
    out = {"config": f"{n_sensors}x{n_people}", "bursts": len(bursts) - skip}
    for side in sides:
        w = np.array(waits[side])
        out[side] = {"wait_p50_us": float(np.percentile(w, 50)),
                     "wait_p90_us": float(np.percentile(w, 90)),
                     "wait_mean_us": float(w.mean()),
                     "burst_mean_us": float(np.mean(totals[side]))}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", default="3x6,6x3,6x6")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--piece", action="store_true",
                        help="Liminal Space listening to both engines, as in stage play")
    args = parser.parse_args()
    print(f"in step, {args.seconds:g} s of show per config"
          f"{', Liminal Space listening' if args.piece else ''}; engine-thread CPU from a "
          f"burst's start to each datagram's skeletons, us; load "
          f"{open('/proc/loadavg').read().split()[0]}")
    print(f"{'config':>7} {'bursts':>6}   {'each p50/p90/mean':>20} {'burst':>7}   "
          f"{'after last p50/p90/mean':>24} {'burst':>7}   mean wait ratio")
    for config in args.configs.split(","):
        r = run(*map(int, config.split("x")), args.seconds, args.piece)
        e, b = r["each"], r["burst"]
        print(f"{r['config']:>7} {r['bursts']:>6}   "
              f"{e['wait_p50_us']:6.0f}/{e['wait_p90_us']:6.0f}/{e['wait_mean_us']:6.0f} "
              f"{e['burst_mean_us']:7.0f}   "
              f"{b['wait_p50_us']:8.0f}/{b['wait_p90_us']:6.0f}/{b['wait_mean_us']:6.0f} "
              f"{b['burst_mean_us']:7.0f}   {b['wait_mean_us'] / e['wait_mean_us']:.2f}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
