"""Two trees' engines in one process, fed the same datagrams, alternating datagram by datagram.

On a shared machine the CPU a datagram costs moves with other processes' load (caches,
the other hyperthread), so two runs minutes apart differ by 20-50 %. Here both engines
(``stage/`` of tree A and of tree B, imported side by side as two packages) see every
datagram in turn -- A then B, then B then A -- so each pair is measured under the same load;
the figure is the median over datagrams of B's CPU / A's CPU (``time.thread_time`` around
``handle_datagram`` + ``tick``), with each side's p50/p90. The input is
``bench_engine_inproc``'s: P people, each seen by S simulated Kinects, every sensor every
person every frame. The first fifth of the datagrams (persons being found) is left out.

Both trees' final fused joints are compared (``identical``), and a digest of every datagram
each engine sent (``sent identical``): a change meant to give the same floats and bytes
shows here if it does not. Both rigs run the Python path (``fusion.native`` off) unless
``--native`` turns the native core (``stage.engine.native``) on in both, to compare two
trees' cores; ``--native-b`` turns it on in B's rig only: with the same tree as A and B, it
measures the core against the Python path.

``--forecast H`` asks both engines for every body predicted H s ahead (as ``stage play``
does for a piece that anticipates: Liminal Space asks for 0.05) and gives them a listener
that digests each frame's forecasts (``forecasts identical``); ``--forecast-b H`` asks B's
only: with the same tree as A and B, it measures what the forecasts cost.

``--piece YAML`` gives each engine its own tree's piece runtime of YAML as a listener, the
piece's horizons asked for as that tree's ``stage play`` asks (lazily where the tree can):
the performer's case in process, the piece's calls inside each datagram's CPU; the events
of both are compared (``events identical``). To measure one section, start the piece there
(a copy of the YAML with another ``start:``).

``--paced`` sleeps the datagrams' real spacing (spread: 1 / (30 x sensors)) before each
engine's datagram, so each finds its caches cold as the live engine thread does after waiting
(issue 10, stop 37: that doubles a datagram's CPU here); a change that saves calls at the cost
of building arrays can win back to back and lose paced (stop 40).

``--timetags`` stamps each bundle with its capture time (as a Unix time), as live sensor
clients and ``bench_engine.py`` do; without it the bundles are "immediately", as in
``bench_engine_inproc``, and the engine's per-message clock work is left out. ``--aligned``
sends every sensor's frame at the frame's instant (sensors in step), so each person's views
of a frame form one instant that the fold checks for agreement (``fuser``), as live aligned
sensors do; the simulated Kinects' errors make those views disagree, and replays follow.

Run: python bench/bench_engine_ab.py TREE_A TREE_B [--configs 1x1,3x3,6x6] [--seconds 6]
     [--quick] [--timetags] [--aligned] [--paced] [--native | --native-b]
     [--forecast H | --forecast-b H | --piece YAML]
     (TREE: a directory holding stage/, e.g. a `git archive main` and `.`)
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib
import inspect
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


class ForecastDigest:
    """An engine listener: a digest of every frame's forecast bodies (joints, velocity, s.d.),
    in order; with no forecast asked for, of nothing (it still makes the engine build its
    frames, as a piece listening does)."""

    def __init__(self) -> None:
        self.digest = hashlib.blake2b(digest_size=16)
        self.count = 0
        self.joints: list[np.ndarray] = []     # every forecast's joints, in order

    def __call__(self, frame) -> None:
        for horizon in sorted(frame.forecasts):
            for pid, body in sorted(frame.forecasts[horizon].items()):
                self.joints.append(body.joints.copy())
                self.digest.update(np.ascontiguousarray(body.joints).tobytes())
                self.digest.update(np.ascontiguousarray(body.velocity).tobytes())
                self.digest.update(np.ascontiguousarray(body.sd).tobytes())
                self.count += 1


class HashTransport:
    """Sends nothing; keeps a digest of every datagram it was given, in order."""

    def __init__(self) -> None:
        self.digest = hashlib.blake2b(digest_size=16)
        self.count = 0

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        self.digest.update(data)
        self.count += 1


def load(tree: str, name: str, root: Path) -> dict:
    """``tree``'s stage package imported as ``name`` (a copy under ``root``)."""
    shutil.copytree(Path(tree) / "stage", root / name)
    return {m: importlib.import_module(f"{name}.{m}")
            for m in ("engine.engine", "clock", "rig", "sensors.protocol", "sensors.sim",
                      "piece")}


#: a Unix time for the bundles' timetags (--timetags): the engine's clock starts at 0
EPOCH = 1.7e9


def datagrams(mods: dict, n_sensors: int, n_people: int, seconds: float, seed: int = 0,
              timetags: bool = False, aligned: bool = False):
    """bench_engine_inproc's input, built with one tree's simulator and encoders (``aligned``:
    every sensor's frame at the frame's instant, as ``bench_engine_inproc.datagrams``)."""
    sim, proto = mods["sensors.sim"], mods["sensors.protocol"]
    rng = np.random.default_rng(seed)
    poses = sim.ring_poses(n_sensors, radius=4.5)
    kinects = [sim.VirtualKinect(p, sim.KinectModel(far=7.0), rng) for p in poses]
    grid = [(x, z) for z in (-0.75, 0.75) for x in (-1.5, 0.0, 1.5)][:n_people]
    out = []
    for f in range(int(seconds * 30)):
        for s in range(n_sensors):
            msgs = []
            for u in range(n_people):
                truth = sim.standing_pose(grid[u], 0.3 * u + 0.02 * f, 0.5 + 0.3 * np.sin(f / 10))
                joints, conf = kinects[s].observe(truth, user=u)
                msgs += [proto.encode_client_joints(f"s{s}", u, joints, conf),
                         proto.encode_message("/handState", f"s{s}", u, "left", "open"),
                         proto.encode_message("/handState", f"s{s}", u, "right", "closed")]
            t = f / 30 if aligned else f / 30 + s / (30 * n_sensors)
            out.append((t, proto.encode_bundle(msgs, EPOCH + t if timetags else None)))
    return poses, out


def listen(mods: dict, e, piece: str) -> None:
    """``piece`` played on ``e`` as the tree's ``stage play`` plays it: the tree's runtime
    listening, its horizons asked for lazily where the tree can (``e.piece_sink``: the
    events)."""
    pm = mods["piece"]
    model = pm.load_piece(piece)
    e.piece_sink = pm.RecordingSink()
    lazy = "lazy" in inspect.signature(e.people.want_forecast).parameters
    for h in sorted(model.horizons()):
        e.people.want_forecast(h, lazy=True) if lazy else e.people.want_forecast(h)
    e.listeners.append(pm.PieceRuntime(model, e.piece_sink, seed=1))


def engine(mods: dict, poses, native: bool = False, forecast: float = 0.0):
    rig_mod = mods["rig"]
    rig = rig_mod.Rig(reference="s0", views=[("127.0.0.1", 9)])
    if hasattr(rig.fusion, "native"):     # (trees before the core have none)
        rig.fusion = dataclasses.replace(rig.fusion, native=native)
    rig.stage_frame = poses[0].to_stage
    inverse = np.linalg.inv(poses[0].to_stage)
    for k, p in enumerate(poses):
        rig_mod.set_calibration(rig, f"s{k}", inverse @ p.to_stage, "bench")
    clock = mods["clock"].ManualClock(0.0)
    e = mods["engine.engine"].Engine(rig, clock, HashTransport())
    if forecast > 0:
        e.people.want_forecast(forecast)
    e.forecast_digest = ForecastDigest()
    if forecast >= 0:        # (-1: no listener at all, the engine builds no frames)
        e.listeners.append(e.forecast_digest)
    return e, clock


def run(a: dict, b: dict, n_sensors: int, n_people: int, seconds: float,
        timetags: bool = False, aligned: bool = False, paced: bool = False,
        native_b: bool = False, native_a: bool = False, forecast: tuple = (-1.0, -1.0),
        piece: str | None = None) -> dict:
    poses, data = datagrams(a, n_sensors, n_people, seconds, timetags=timetags, aligned=aligned)
    (ea, ca) = engine(a, poses, native_a, forecast[0])
    (eb, cb) = engine(b, poses, native_b or native_a, forecast[1])
    if piece:
        listen(a, ea, piece)
        listen(b, eb, piece)
    ta: list[float] = []
    tb: list[float] = []
    gap = 1.0 / (30 * n_sensors)       # --paced: the datagrams' real spacing, spread
    for k, (t, d) in enumerate(data):
        pair = [(ea, ca, ta), (eb, cb, tb)]
        for e, c, acc in (pair if k % 2 == 0 else pair[::-1]):
            if paced:
                time.sleep(gap)
            c.set(t)
            c0 = time.thread_time()
            e.handle_datagram(d)
            e.tick()
            acc.append(time.thread_time() - c0)
    skip = len(data) // 5
    us_a, us_b = np.array(ta[skip:]) * 1e6, np.array(tb[skip:]) * 1e6
    same = len(ea.persons) == len(eb.persons) and all(
        np.array_equal(pa.joints, pb.joints) for pa, pb in zip(ea.persons.values(),
                                                              eb.persons.values()))
    return {"config": f"{n_sensors}x{n_people}", "datagrams": len(us_a),
            "a_p50": float(np.percentile(us_a, 50)), "a_p90": float(np.percentile(us_a, 90)),
            "b_p50": float(np.percentile(us_b, 50)), "b_p90": float(np.percentile(us_b, 90)),
            "a_mean": float(us_a.mean()), "b_mean": float(us_b.mean()),
            "ratio": float(np.median(us_b / us_a)), "identical": same,
            "events": (len(ea.piece_sink.events), len(eb.piece_sink.events)) if piece else None,
            "events_same": piece is not None and ([repr(e) for e in ea.piece_sink.events]
                                                  == [repr(e) for e in eb.piece_sink.events]),
            "forecasts": eb.forecast_digest.count,
            "forecast_max_diff_m": _max_diff(ea.forecast_digest.joints, eb.forecast_digest.joints),
            "forecasts_same": (ea.forecast_digest.digest.digest()
                               == eb.forecast_digest.digest.digest()
                               and ea.forecast_digest.count == eb.forecast_digest.count),
            "sent_same": (ea.output.transport.digest.digest() == eb.output.transport.digest.digest()
                          and ea.output.transport.count == eb.output.transport.count)}


def _max_diff(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """The largest difference between two runs' forecast joints (m; NaN where one has a
    joint the other has not, inf if their numbers differ)."""
    if len(a) != len(b):
        return float("inf")
    if not a:
        return 0.0
    x, y = np.array(a), np.array(b)
    if not np.array_equal(np.isnan(x), np.isnan(y)):
        return float("nan")
    d = np.abs(x - y)
    return float(np.nanmax(d)) if np.isfinite(d).any() else 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tree_a")
    parser.add_argument("tree_b")
    parser.add_argument("--configs", default="1x1,3x3,6x6")
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--quick", action="store_true", help="1 s of show per config")
    parser.add_argument("--timetags", action="store_true",
                        help="bundles stamped with their capture time, as live sensors send them")
    parser.add_argument("--paced", action="store_true",
                        help="each engine's datagram after a sleep of the spread spacing "
                             "(1 / (30 x sensors)), as live: caches cold")
    parser.add_argument("--aligned", action="store_true",
                        help="sensors in step: each frame's datagrams at one instant")
    parser.add_argument("--native-b", action="store_true",
                        help="B's rig with fusion.native on (A and B may be the same tree)")
    parser.add_argument("--native", action="store_true",
                        help="both rigs with fusion.native on: two trees' native cores")
    parser.add_argument("--forecast", type=float, default=0.0, metavar="H",
                        help="both engines asked for bodies H s ahead, with a listener")
    parser.add_argument("--forecast-b", type=float, default=0.0, metavar="H",
                        help="B's engine only asked for bodies H s ahead (both with a listener)")
    parser.add_argument("--piece", metavar="YAML",
                        help="each engine plays YAML with its own tree's piece runtime")
    args = parser.parse_args()
    if sum(map(bool, (args.forecast, args.forecast_b, args.piece))) > 1:
        parser.error("--forecast (both), --forecast-b (B only) or --piece")
    forecast = ((args.forecast, args.forecast) if args.forecast else
                (0.0, args.forecast_b) if args.forecast_b else (-1.0, -1.0))
    seconds = 1.0 if args.quick else args.seconds
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        a = load(args.tree_a, "stage_a", Path(tmp))
        b = load(args.tree_b, "stage_b", Path(tmp))
        asked = (f"; forecast {args.forecast:g} s, both" if args.forecast else
                 f"; forecast {args.forecast_b:g} s, B only" if args.forecast_b else
                 f"; playing {args.piece}" if args.piece else "")
        print(f"A = {args.tree_a}, B = {args.tree_b}{' with fusion.native' if args.native_b else ''}{'; both with fusion.native' if args.native else ''}{asked}; CPU per datagram (thread_time), us; "
              f"{seconds:g} s of show per config; "
              f"{'capture-time timetags' if args.timetags else 'no timetags'}; "
              f"{'aligned' if args.aligned else 'spread'}{'; paced' if args.paced else ''}; load {open('/proc/loadavg').read().split()[0]}")
        print(f"{'config':>7} {'datagrams':>9} {'A p50':>7} {'A p90':>7} {'A mean':>7} "
              f"{'B p50':>7} {'B p90':>7} {'B mean':>7} {'median B/A':>10} {'mean B/A':>8}  "
              f"final joints identical, every datagram sent identical")
        for config in args.configs.split(","):
            r = run(a, b, *map(int, config.split("x")), seconds, args.timetags, args.aligned,
                    args.paced, args.native_b, args.native, forecast, args.piece)
            print(f"{r['config']:>7} {r['datagrams']:>9} {r['a_p50']:>7.0f} {r['a_p90']:>7.0f} "
                  f"{r['a_mean']:>7.0f} {r['b_p50']:>7.0f} {r['b_p90']:>7.0f} {r['b_mean']:>7.0f} "
                  f"{r['ratio']:>10.2f} {r['b_mean'] / r['a_mean']:>8.2f}  {r['identical']}, "
                  f"{r['sent_same']}"
                  + (f"; {r['forecasts']} forecasts, identical {r['forecasts_same']} (max "
                     f"difference {r['forecast_max_diff_m']:.1e} m)" if forecast[0] > 0 else
                     f"; {r['forecasts']} forecasts, B's only" if forecast[1] > 0 else
                     f"; events {r['events'][0]}/{r['events'][1]}, identical "
                     f"{r['events_same']}" if args.piece else ""),
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
