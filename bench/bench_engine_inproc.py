"""Engine CPU per second of show, in-process (decode + fusion + encode, no sockets).

Complements bench_engine.py (the real server over loopback): here the same
input is replayed into an Engine with an injected clock and a null transport,
and CPU time (process_time) is divided by the seconds of show it covers, so the
figure hardly depends on what else the machine is doing. With ``--self-healing``
(what ``stage serve`` runs by default) the live calibrator is attached as in an
offline show (``threaded=False``: its worker's polls run inline at the frames'
own times), and its share (observer + polls) is printed on its own; run at
least 12 s of show so that the tracked lag searches (every 10 s) are in it.
``--self-healing --worker`` measures the calibrator as ``stage serve`` runs it
instead: threaded, the observer only queues each frame and the worker's poll
(drain the queue, judge, collect) runs whenever a poll is due -- here on the
bench's own thread, right after the datagram that made it due, so its CPU is
counted without the other threads' noise (the live worker is woken the same way).
``--paced`` sends the datagrams at their real times (the bench sleeps between them, as the
engine thread does live) instead of back to back: each datagram then pays what waking up
costs -- caches refilled after other work ran, the core's idle states -- which on this
2-core VM added ~0.55 ms of CPU per datagram, 1.5x the back-to-back cost at 6x6 and 2.5x
at 1x1.
Per datagram, the CPU time of its ``handle_datagram`` + ``tick`` (``time.thread_time``: this
thread's own CPU, so other processes' load changes it only through the caches they share)
is printed as p50/p90/p99. To compare two trees in one session, run this script against
each in turn with ``PYTHONPATH=<tree>`` (it uses only the engine's public API), alternating.
The input: P people
on a grid, each observed on its own by S simulated Kinects (the simulator's
VirtualKinect) on a 4.5 m ring, whose range is widened to the ring so that
every sensor reports every person every frame (the load the configuration
names).

Run: python bench/bench_engine_inproc.py [--seconds 3] [--configs 6x6,3x3] [--self-healing
[--worker]] [--paced] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from stage.clock import ManualClock
from stage.engine.engine import Engine
from stage.sensors.protocol import encode_bundle, encode_client_joints, encode_message
from stage.rig import Rig, set_calibration
from stage.sensors.sim import KinectModel, VirtualKinect, ring_poses, standing_pose

FPS = 30.0


class NullTransport:
    def send(self, data: bytes, address: tuple[str, int]) -> None:
        pass


def datagrams(n_sensors: int, n_people: int, seconds: float, seed: int = 0,
              aligned: bool = False):
    """(poses, [(t, datagram)]): P people standing on a grid, each of S simulated Kinects on a
    ring sending one bundle a frame; the sensors' frames spread over the frame period, or
    all at the frame's instant (``aligned``: sensors in step, a burst of S datagrams)."""
    rng = np.random.default_rng(seed)
    poses = ring_poses(n_sensors, radius=4.5)
    kinects = [VirtualKinect(p, KinectModel(far=7.0), rng) for p in poses]
    grid = [(x, z) for z in (-0.75, 0.75) for x in (-1.5, 0.0, 1.5)][:n_people]
    out = []
    for f in range(int(seconds * FPS)):
        for s in range(n_sensors):
            msgs = []
            for u in range(n_people):
                truth = standing_pose(grid[u], 0.3 * u + 0.02 * f, 0.5 + 0.3 * np.sin(f / 10))
                joints, conf = kinects[s].observe(truth, user=u)
                msgs += [encode_client_joints(f"s{s}", u, joints, conf),
                         encode_message("/handState", f"s{s}", u, "left", "open"),
                         encode_message("/handState", f"s{s}", u, "right", "closed")]
            t = f / FPS if aligned else f / FPS + s / (FPS * n_sensors)
            out.append((t, encode_bundle(msgs, None)))
    return poses, out


def sleep_until(start: float, t: float) -> None:
    """Sleep until ``t`` s of show after ``start`` (a ``perf_counter`` reading): a datagram
    replayed at its real time, the thread asleep in between as the engine thread is live."""
    wait = start + t - time.perf_counter()
    if wait > 0:
        time.sleep(wait)


def _timed(fn, acc: list):
    """``fn`` adding its CPU time to acc[0]; acc[1] is the nesting depth (offline, the
    observer runs the poll inline: counted once)."""
    def wrapped(*a, **k):
        acc[1] += 1
        c0 = time.process_time()
        try:
            return fn(*a, **k)
        finally:
            acc[1] -= 1
            if acc[1] == 0:
                acc[0] += time.process_time() - c0
    return wrapped


def make_engine(poses) -> tuple[Engine, ManualClock]:
    """An engine on a manual clock whose rig calibrates the sensors at ``poses`` exactly
    (sensor 0 the reference), with one view and a transport that sends nothing."""
    rig = Rig(reference="s0", views=[("127.0.0.1", 9)])
    rig.stage_frame = poses[0].to_stage
    inverse = np.linalg.inv(poses[0].to_stage)
    for k, p in enumerate(poses):
        set_calibration(rig, f"s{k}", inverse @ p.to_stage, "bench")
    clock = ManualClock(0.0)
    return Engine(rig, clock, NullTransport()), clock


def run(n_sensors: int, n_people: int, seconds: float, healing: bool = False,
        worker: bool = False, paced: bool = False) -> dict:
    poses, data = datagrams(n_sensors, n_people, seconds)
    engine, clock = make_engine(poses)
    calibrator_cpu = [0.0, 0]
    cal = None
    if healing:
        from stage.calibration.healing import LiveCalibrator, attach_live
        if worker:  # threaded, but its worker's polls are run below, on this thread
            cal = LiveCalibrator(engine, None, threaded=True)
            cal._start_worker = lambda: None
            cal.start()
        else:
            cal = attach_live(engine, None, threaded=False)
        cal._poll = _timed(cal._poll, calibrator_cpu)
        engine.frame_observers.remove(cal._observe)
        engine.frame_observers.append(_timed(cal._observe, calibrator_cpu))
    per_datagram = []
    cpu0 = time.process_time()
    start = time.perf_counter()
    for t, d in data:
        if paced:  # at the datagram's real time: the thread sleeps between them, as live
            sleep_until(start, t)
        clock.set(t)
        c0 = time.thread_time()
        engine.handle_datagram(d)
        engine.tick()
        per_datagram.append(time.thread_time() - c0)
        if worker and cal is not None and cal._wake.is_set():
            cal._wake.clear()
            cal._poll()
            cal._send()
            engine.drain()  # what the worker asked of the engine thread
    cpu = time.process_time() - cpu0
    us = np.array(per_datagram) * 1e6
    return {"config": f"{n_sensors}x{n_people}", "show_s": seconds, "cpu_s": cpu,
            "core_fraction": cpu / seconds, "persons": len(engine.persons),
            "calibrator_core_fraction": calibrator_cpu[0] / seconds if healing else None,
            "datagram_us_p50": float(np.percentile(us, 50)),
            "datagram_us_p90": float(np.percentile(us, 90)),
            "datagram_us_p99": float(np.percentile(us, 99))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--configs", default="1x1,3x3,6x6")
    parser.add_argument("--self-healing", action="store_true",
                        help="attach the live calibrator, as stage serve does by default")
    parser.add_argument("--worker", action="store_true",
                        help="with --self-healing: the calibrator threaded, as live (see above)")
    parser.add_argument("--paced", action="store_true",
                        help="send the datagrams at their real times, not back to back")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = [run(*map(int, c.split("x")), args.seconds, args.self_healing, args.worker,
                args.paced)
            for c in args.configs.split(",")]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'config':>7} {'CPU % of a core':>16} {'of it calibrator':>17} {'persons':>8} "
          f"{'per datagram p50 us':>20} {'p90 us':>8} {'p99 us':>8}")
    for r in rows:
        cal = r["calibrator_core_fraction"]
        cal = "-" if cal is None else f"{100 * cal:.1f}"
        print(f"{r['config']:>7} {100 * r['core_fraction']:>16.1f} {cal:>17} {r['persons']:>8} "
              f"{r['datagram_us_p50']:>20.0f} {r['datagram_us_p90']:>8.0f} {r['datagram_us_p99']:>8.0f}")
    six = [r for r in rows if r["config"] == "6x6"]
    if six:
        ok = six[0]["core_fraction"] < 0.25
        print(f"target 6x6 under 25% of a core (in-process part): {100 * six[0]['core_fraction']:.1f}% "
              f"-> {'PASS' if ok else 'FAIL'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
