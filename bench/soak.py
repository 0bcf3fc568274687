"""Soak: hours of a show through the whole pipeline at maximum replay speed; is anything growing?

The stage is ``bench/scenarios/soak.yaml``: three Kinects, six visitors
coming and going over a 10-minute cycle (from nobody to six at once), one
sensor unplugged for 12 s and another for 60 s each cycle. The simulator
records one cycle once; this script then replays it again and again, every
pass's arrival times and timetags moved forwards (as ``stage replay --loop``
does), through the whole pipeline on one manual clock, as fast as the CPU
goes: decode, the engine (registry, tracking, fusion, Kalman), the live
calibrator (inline, as offline shows run it), the piece ``pieces/circles.yaml``
and its MIDI view writing a Standard MIDI File, with the same bounded
event memory a live show keeps.

Every simulated half hour it prints: resident memory (RSS), the clients the
engine knows, person ids issued so far and persons on stage now, the person bank's
slots, events kept, the engine's time per datagram (p50/p99 of that half hour's last
4096), and the wall time. The closing lines give RSS at the start and end,
the id count, and the frame time at the start and end.

    python bench/soak.py                  # 8 simulated hours (about an hour of CPU here)
    python bench/soak.py --hours 24
    python bench/soak.py --quick          # 20 simulated minutes of a 2-minute cycle
    python bench/soak.py --native off     # the rig's fusion.native forced off (or on)

With ``--native`` the report lines also give the native core's counts (persons
held, views folded, declined, persons given back).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import logging
import sys
import tempfile
import time
from pathlib import Path

from benchlib import machine_busy_s

from stage.app.show import KEEP_EVENTS, PIECE_TICK_S, TickingClock
from stage.calibration import attach_live
from stage.engine.engine import TICK_S, Engine
from stage.piece.loader import load_piece
from stage.piece.runtime import FanoutSink, PieceRuntime, RecordingSink
from stage.sensors.recording import read_recording
from stage.sensors.replay import _retimed
from stage.sensors.sim import Simulator
from stage.stats import LatencyWindow
from stage.views import ViewHost

HERE = Path(__file__).resolve().parent
SCENARIO = HERE / "scenarios" / "soak.yaml"
PIECE = HERE.parent / "pieces" / "circles.yaml"


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hours", type=float, default=8.0, help="simulated hours (default 8)")
    parser.add_argument("--cycle", type=float, default=600.0,
                        help="seconds of the scenario recorded and looped (default 600)")
    parser.add_argument("--report-every", type=float, default=1800.0, metavar="S",
                        help="simulated seconds between report lines (default 1800)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="20 minutes of a 120 s cycle")
    parser.add_argument("--native", choices=("on", "off"), default=None,
                        help="force the rig's fusion.native (default: the rig's own setting)")
    args = parser.parse_args()
    if args.quick:
        args.hours, args.cycle, args.report_every = 1 / 3, 120.0, 300.0
    logging.basicConfig(level=logging.ERROR)  # hours of visitors: their log lines are not wanted

    busy0, wall0 = machine_busy_s(), time.monotonic()
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        sim = Simulator(str(SCENARIO), seed=args.seed)
        rec = tmp / "cycle.rec"
        t = time.monotonic()
        sim.record(str(rec), duration=args.cycle)
        records = read_recording(str(rec))
        first = next(iter(records)).arrival
        print(f"soak: recorded one {args.cycle:g} s cycle of {SCENARIO.name} in "
              f"{time.monotonic() - t:.0f} s; replaying {args.hours:g} simulated hours through "
              f"engine, calibrator, {PIECE.name} and its MIDI file", flush=True)

        clock = TickingClock(0.0)
        rig = sim.rig()
        if args.native is not None:
            rig.fusion = dataclasses.replace(rig.fusion, native=args.native == "on")
        engine = Engine(rig, clock)
        print(f"soak: fusion.native {'on' if rig.fusion.native else 'off'}"
              f"{'' if engine.people.core is not None or not rig.fusion.native else ' (no core)'}",
              flush=True)
        engine.rig_store.threaded = False
        calibrator = attach_live(engine, None, threaded=False, save=False)
        piece = load_piece(str(PIECE))
        host = ViewHost.for_play(list(piece.outputs.values()), midi_file=str(tmp / "soak.mid"),
                                 clock=clock, plugins=False, threaded=False)
        host.attach(engine)
        kept = RecordingSink(KEEP_EVENTS)
        runtime = PieceRuntime(piece, FanoutSink(host, kept), seed=args.seed)
        engine.listeners.append(runtime)
        host.start()
        next_piece_tick = [0.0]

        def hook(now: float) -> None:
            if now >= next_piece_tick[0]:
                next_piece_tick[0] = now + PIECE_TICK_S
                runtime.tick(now)
            host.pump()
        clock.hook = hook
        runtime.start(clock.now())

        total = args.hours * 3600.0
        next_tick = TICK_S
        next_report = args.report_every
        rows = []
        datagrams = 0
        passes = 0
        wall_start = time.monotonic()

        def report(now: float) -> None:
            lat = engine.batch_time.summary_ms()
            gc.collect()
            row = {"sim_h": now / 3600, "rss_mb": rss_mb(), "clients": len(engine.clients),
                   "ids": engine.tracker._next_id - 1, "persons": len(engine.persons),
                   # the person bank's slots (bank.PersonBank): they must not grow with ids
                   "slots": len(engine.people.bank.owners),
                   "events_kept": len(kept.events), "p50_ms": lat.get("p50", float("nan")),
                   "p99_ms": lat.get("p99", float("nan")), "datagrams": datagrams,
                   "wall_s": time.monotonic() - wall_start,
                   "drops": engine.drops.total(), "calibrator_crashes": calibrator.crashes}
            native = engine.stats().get("fusion", {}).get("native")
            rows.append(row)
            print(f"{row['sim_h']:6.2f} h  rss {row['rss_mb']:7.1f} MB  clients {row['clients']}"
                  f"  ids {row['ids']:5d}  on stage {row['persons']}  slots {row['slots']}"
                  f"  events kept "
                  f"{row['events_kept']:5d}  per datagram p50 {row['p50_ms']:.3f} ms p99 "
                  f"{row['p99_ms']:.3f} ms  drops {row['drops']}  wall {row['wall_s']:.0f} s"
                  + (f"  native held {native['held']} folded {native['folded']} declined "
                     f"{native['declined']} given back {native['given_back']}" if native else ""),
                  flush=True)
            engine.batch_time = LatencyWindow(4096)

        report(0.0)
        done = False
        while not done:
            offset = passes * (args.cycle + 1.0 / 30.0)
            for r in records:
                arrival = r.arrival - first + offset
                if arrival >= total:
                    done = True
                    break
                while next_tick <= arrival:
                    clock.set(max(clock.now(), next_tick))
                    engine.tick(clock.now())
                    next_tick += TICK_S
                    if clock.now() >= next_report:
                        report(clock.now())
                        next_report += args.report_every
                clock.set(max(clock.now(), arrival))
                data = _retimed(r.data, lambda tag: tag + offset) if offset else r.data
                engine.handle_datagram(data, r.source, clock.now())
                datagrams += 1
            passes += 1
        while next_tick <= total:
            clock.set(next_tick)
            engine.tick(clock.now())
            next_tick += TICK_S
        report(clock.now())
        runtime.stop(clock.now())
        host.stop()
        calibrator.stop()

    first_row, last_row = rows[1] if len(rows) > 2 else rows[0], rows[-1]
    busy = (machine_busy_s() - busy0) / (time.monotonic() - wall0)
    print(f"soak: {total / 3600:g} simulated hours ({passes} passes of the cycle, {datagrams} "
          f"datagrams) in {last_row['wall_s']:.0f} s wall ({total / last_row['wall_s']:.0f}x "
          f"real time); machine busy {busy:.2f} cores of 2 meanwhile")
    print(f"soak: RSS start {rows[0]['rss_mb']:.1f} MB (after the first report window "
          f"{first_row['rss_mb']:.1f} MB), end {last_row['rss_mb']:.1f} MB")
    print(f"soak: ids: {last_row['ids']} person ids issued, {last_row['clients']} clients known "
          f"at the end, {last_row['events_kept']} events kept")
    print(f"soak: frame time (per datagram) start p50 {first_row['p50_ms']:.3f} ms p99 "
          f"{first_row['p99_ms']:.3f} ms, end p50 {last_row['p50_ms']:.3f} ms p99 "
          f"{last_row['p99_ms']:.3f} ms; calibrator restarts {last_row['calibrator_crashes']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
