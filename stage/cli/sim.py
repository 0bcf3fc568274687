"""``stage sim``: run a scenario to a server over UDP, or into a recording."""

from __future__ import annotations

import argparse
import math
import time

from ..errors import ConfigError
from .common import Exit, hostport as _hostport, positive as _positive


def register(sub) -> dict:
    p = sub.add_parser("sim", help="virtual Kinects watching scripted performers (UDP or recording)",
                       description="Run a simulator scenario. Without --out it sends to a server "
                       "over UDP (default 127.0.0.1:7770) in real time; with --out alone it writes "
                       "a recording as fast as it can.")
    p.add_argument("scenario", nargs="?", default=None, metavar="SCENARIO",
                   help="a scenario file or a built-in name (default: 'default')")
    p.add_argument("--to", type=_hostport, metavar="HOST:PORT", help="send to this server")
    p.add_argument("--out", metavar="RECORDING", help="write a recording")
    p.add_argument("--truth", metavar="TRUTH", help="write the ground truth (.npz) alongside")
    p.add_argument("--rig-out", metavar="RIG", help="write the exact rig (calibrations from the "
                   "virtual poses) for `stage serve --rig`")
    p.add_argument("--uncalibrated", action="store_true",
                   help="with --rig-out: sensors without calibrations (to test calibration)")
    p.add_argument("--duration", type=_positive, metavar="S",
                   help="seconds to simulate (default: the scenario's 'duration'; a scenario "
                   "without one runs over UDP until Ctrl-C)")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=_positive, default=1.0, metavar="X",
                      help="X times real time over UDP (default 1)")
    pace.add_argument("--max-speed", action="store_true", help="send as fast as possible")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--list", action="store_true", help="list the built-in scenarios and exit")
    return {"sim": cmd_sim}


def cmd_sim(args: argparse.Namespace) -> int:
    from ..app.signals import StopSignals
    from ..sensors.recording import RecordingWriter, check_output_path
    from ..sensors.sim.scenario import builtin_names, load_scenario
    from ..sensors.sim.simulator import Simulator
    from ..sensors.sim.truth import write_truth
    if args.list:
        for name in builtin_names():
            sc = load_scenario(name)
            print(f"{name:12s} {len(sc.sensors)} sensor(s), {len(sc.performers)} performer(s): "
                  f"{sc.description}")
        return Exit.OK
    scenario = load_scenario(args.scenario)
    sim = Simulator(scenario, seed=args.seed)
    duration = args.duration or scenario.duration
    for path in (args.out, args.truth, args.rig_out):
        if path:
            check_output_path(path)
    if args.rig_out:
        rig = sim.rig(calibrated=not args.uncalibrated)
        rig.save(args.rig_out)
        print(f"stage sim: rig with {len(rig.sensors)} sensor(s) written to {args.rig_out}",
              flush=True)
    what = (f"scenario '{scenario.name}' ({len(scenario.sensors)} sensor(s), "
            f"{len(scenario.performers)} performer(s)), seed {args.seed}")
    if args.out and not args.to:
        if duration is None:
            raise ConfigError("give --duration: the scenario has no 'duration' and a recording "
                              "must end")
        started = time.perf_counter()
        n = sim.record(args.out, duration, args.truth)
        elapsed = time.perf_counter() - started
        print(f"stage sim: {what}: {duration:g} s, {n} datagram(s) -> {args.out}"
              + (f", truth -> {args.truth}" if args.truth else "")
              + f" in {elapsed:.1f} s", flush=True)
        return Exit.OK
    target = args.to or ("127.0.0.1", 7770)
    speed = math.inf if args.max_speed else args.speed
    if args.truth:
        if duration is None:
            raise ConfigError("give --duration to write --truth")
        write_truth(sim, args.truth, duration)
    writer = RecordingWriter(args.out, {**sim.meta(), "live": True}) if args.out else None
    pace = "as fast as possible" if args.max_speed else (
        "in real time" if speed == 1 else f"at {speed:g}x real time")
    print(f"stage sim: {what} -> udp {target[0]}:{target[1]} {pace}"
          + (f" for {duration:g} s" if duration else "") + "; Ctrl-C stops", flush=True)
    try:
        with StopSignals() as stop:
            n = sim.run_realtime(target, duration, speed, stop.event, recorder=writer)
    finally:
        if writer is not None:
            writer.close()
    print(f"stage sim: sent {n} datagram(s)" + (f", recorded to {args.out}" if args.out else ""),
          flush=True)
    return Exit.INTERRUPTED if stop.received else Exit.OK
