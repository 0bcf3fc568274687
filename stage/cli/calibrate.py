"""``stage calibrate``: a recording (or live sensors) -> the rig's calibration section.

    stage calibrate rehearsal.stagerec --rig rig.yaml            # write the rig
    stage calibrate rehearsal.stagerec --method ga --json        # per-sensor JSON
    stage calibrate rehearsal.stagerec --plot calib.png          # the paper's Figure 5
    stage calibrate --live --rig rig.yaml                        # calibrate now, live

``--live`` runs its own engine on the rig's port (stop ``stage serve``
first, or give ``--port``): every sensor but the reference is re-calibrated
from fresh pairs while exactly one person walks where the sensors overlap,
and each accepted calibration is written to the rig at once.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from typing import Any, Callable

import numpy as np

from ..errors import ConfigError, StageError, TransportError
from ..rig import Rig, SensorConfig, load_rig
from ..geometry import invert
from ..calibration.methods import DEFAULT_PAIRS, METHODS
from ..calibration.coverage import Gates
from ..calibration.offline import RigCalibration, calibrate_streams
from ..rig import store_reference_transform
from .common import Exit, port as _port, positive as _positive

log = logging.getLogger("stage.calibration")


def register(sub: argparse._SubParsersAction) -> dict[str, Callable[[argparse.Namespace], int]]:
    p = sub.add_parser(
        "calibrate", help="calibrate the sensors from a recording (or live) into the rig",
        description="Find each sensor's transform into the reference sensor's space from "
                    "moments when one person was seen by several sensors.")
    p.add_argument("recording", nargs="?", help="a stage recording (stage record / the simulator)")
    p.add_argument("--method", choices=list(METHODS), default="rigid",
                   help="rigid (default, least squares), regression and ga (the paper's), ga3d, "
                        "trajectory (seed 002), floor (seed 004, needs /floorPlane)")
    p.add_argument("--reference", metavar="ID",
                   help="the sensor whose space is stage space (default: the rig's, else the "
                        "first by name)")
    p.add_argument("--rig", metavar="RIG.yaml",
                   help="write the calibration into this rig file (created if missing)")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument("--plot", metavar="PNG", help="draw the points and fitness over time (PNG)")
    p.add_argument("--pairs", type=int, metavar="N",
                   help="paired frames per sensor pair, spread over the recording (default 300, "
                        "trajectory 500; 0 = all)")
    p.add_argument("--lag", default="auto", metavar="S|auto",
                   help="clock offset between sensors: auto (search, default) or seconds")
    p.add_argument("--max-lag", type=_positive, default=1.0, metavar="S",
                   help="search the lag within +-S seconds (default 1)")
    p.add_argument("--robust", choices=("irls", "ransac", "none"), default="irls",
                   help="rigid: outlier handling (default irls)")
    p.add_argument("--min-fitness", type=float, default=Gates.min_fitness, metavar="F",
                   help="ignore an overlap whose fit is below F (default 0.5: a median joint "
                        "distance of 8.9 cm; they were watching different people)")
    p.add_argument("--poor-fitness", type=float, default=Gates.poor_fitness, metavar="F",
                   help="... but use a poorer fit, down to F (default 0.1: 26.6 cm), when the "
                        "lag search found its timing clear (confidence >= --min-lag-confidence)")
    p.add_argument("--min-lag-confidence", type=float, default=Gates.min_lag_confidence,
                   metavar="C", help=f"default {Gates.min_lag_confidence:g}")
    p.add_argument("--min-pairs", type=int, default=Gates.min_pairs, metavar="N",
                   help=f"an overlap needs N paired frames (default {Gates.min_pairs})")
    p.add_argument("--min-poses", type=int, default=Gates.min_poses, metavar="N",
                   help=f"... showing N distinct poses, 5 cm apart (default {Gates.min_poses}: a "
                        "person standing still says little however long the take)")
    p.add_argument("--tolerance-deg", type=float, default=Gates.max_rot_deg, metavar="D",
                   help="refuse a fit whose rotation spreads more than D degrees (rms) over a "
                        "bootstrap of its independent poses (default "
                        f"{Gates.max_rot_deg:g}; 0: not judged)")
    p.add_argument("--tolerance-cm", type=float, default=Gates.max_far_m * 100, metavar="C",
                   help="... or that moves a point at the stage's far edge (--edge-m from the "
                        f"sensor) more than C cm (default {Gates.max_far_m * 100:g}; 0: not judged)")
    p.add_argument("--edge-m", type=_positive, default=Gates.edge_m, metavar="M",
                   help=f"the stage's far edge, metres from a sensor (default {Gates.edge_m:g})")
    p.add_argument("--loop-tolerance-deg", type=float, default=Gates.max_loop_deg,
                   metavar="D", help="three sensors that overlap pairwise: when their three "
                   "fits composed round the triangle turn more than D degrees, the one with the "
                   f"largest median joint distance is not used (default {Gates.max_loop_deg:g}; "
                   "0: not judged)")
    p.add_argument("--no-refine", action="store_true",
                   help="keep the composed chains (no joint refinement over all overlaps)")
    p.add_argument("--seed", type=int, default=0, help="seed of the GA and RANSAC (default 0)")
    p.add_argument("--live", action="store_true",
                   help="calibrate live sensors now (runs its own engine on the rig's port)")
    p.add_argument("--sensor", action="append", default=[], metavar="ID",
                   help="--live: only these sensors (repeatable; default all but the reference)")
    p.add_argument("--host", help="--live: address to listen on (default: the rig's)")
    p.add_argument("--port", type=_port, help="--live: UDP port (default: the rig's, else 7770)")
    p.add_argument("--timeout", type=_positive, default=120.0, metavar="S",
                   help="--live: give up after S seconds (default 120)")
    return {"calibrate": cmd_calibrate}


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.live:
        if args.recording:
            raise ConfigError("give a recording or --live, not both")
        return _live(args)
    if not args.recording:
        raise ConfigError("give a RECORDING to calibrate from (or --live)")
    if not os.path.isfile(args.recording):
        raise ConfigError(f"{args.recording}: no such file" if not os.path.exists(args.recording)
                          else f"{args.recording}: not a file")
    if args.pairs is not None and args.pairs < 0:
        raise ConfigError("--pairs must be 0 (all) or more")
    if not 0 <= args.min_fitness < 1:
        raise ConfigError("--min-fitness must be from 0 to below 1")
    if args.min_pairs < 3 or args.min_poses < 1:
        raise ConfigError("--min-pairs must be 3 or more and --min-poses 1 or more")
    lag: str | float = args.lag
    if lag != "auto":
        try:
            lag = float(lag)
        except ValueError:
            raise ConfigError(f"--lag must be 'auto' or seconds, not '{args.lag}'") from None
    rig = _load_rig(args.rig)
    from ..calibration.streams import load_recording
    streams, drops = load_recording(args.recording)
    if not streams:
        raise StageError(f"{args.recording}: no skeletons in this recording")
    reference = args.reference or (rig.reference if rig and rig.reference in streams else None)
    if args.reference and args.reference not in streams:
        raise ConfigError(f"--reference {args.reference}: that sensor sent no skeletons; "
                          f"sensors in the recording: {', '.join(sorted(streams))}")
    options: dict[str, Any] = {}
    if args.method in ("ga", "ga3d"):
        options["seed"] = args.seed
    if args.method == "rigid":
        options.update(robust=args.robust, seed=args.seed)
    # a CalibrationError (the data give no transform) leaves as a run-time failure, exit 1
    if not 0 <= args.poor_fitness <= args.min_fitness:
        raise ConfigError("--poor-fitness must be from 0 to --min-fitness")
    if args.tolerance_deg < 0 or args.tolerance_cm < 0 or args.loop_tolerance_deg < 0:
        raise ConfigError("--tolerance-deg, --tolerance-cm and --loop-tolerance-deg must be 0 "
                          "(not judged) or more")
    gates = Gates(args.min_pairs, args.min_poses, args.min_fitness, args.poor_fitness,
                  args.min_lag_confidence, args.tolerance_deg, args.tolerance_cm / 100,
                  args.edge_m, args.loop_tolerance_deg)
    result = calibrate_streams(streams, reference, args.method, args.pairs, lag,
                               args.max_lag, refine=not args.no_refine, options=options,
                               progress=lambda text: log.info("%s", text), gates=gates)
    for warning in result.warnings:
        log.warning("%s", warning)
    if args.rig:
        _write_rig(rig or Rig(), args.rig, result)
    if args.plot:
        from ..calibration.plot import plot_calibration
        plot_calibration(args.plot, result, streams, seed=args.seed)
        log.info("wrote %s", args.plot)
    if args.json:
        print(dumps(_as_json(result, args.method, drops, gates)))
    else:
        _print_table(result)
    missing = [s for s, c in result.sensors.items() if c.matrix is None]
    if missing:
        print(f"stage: not calibrated: {', '.join(missing)}", file=sys.stderr)
        return Exit.FAILURE
    return Exit.OK


def dumps(obj: Any) -> str:
    """Indented JSON with each innermost list of numbers on one line (matrix rows)."""
    text = json.dumps(obj, indent=2)
    return re.sub(r"\[\s+([-+\d.eE,\s]+?)\s+\]",
                  lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", text)


def _load_rig(path: str | None) -> Rig | None:
    if path is None:
        return None
    if not os.path.exists(path):
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise ConfigError(f"{path}: folder {folder} does not exist")
        return None
    return load_rig(path)


def _write_rig(rig: Rig, path: str, result: RigCalibration) -> None:
    ref = result.reference
    if rig.reference not in (None, ref):
        log.warning("the rig's reference was %s; it is now %s (its stage frame no longer "
                    "applies and is reset)", rig.reference, ref)
        rig.stage_frame = np.eye(4)
    rig.reference = ref
    rig.sensors.setdefault(ref, SensorConfig(ref))
    for sid, c in result.sensors.items():
        if c.matrix is not None and sid != ref:
            store_reference_transform(rig, sid, c.matrix, ref, c.method or "?", c.fitness,
                                      c.rms_m)
    rig.save(path)
    log.info("wrote the calibration of %d sensor(s) to %s",
             sum(1 for s, c in result.sensors.items() if c.matrix is not None and s != ref), path)


#: what the JSON's figures are (printed with them, so nobody has to guess)
ABOUT = {
    "median_m": "median joint distance (m) between this sensor and the sensors it overlaps, "
                "final transforms: the robust figure fitness is computed from",
    "rms_m": "rms of the same joint distances (m), every joint pair, tails included",
    "fitness": "1 / (1 + (1.1265 median_m / 0.1 m)^2): 1 perfect, 0.5 = 8.9 cm median",
    "lag_s": "this sensor's clock minus the reference's, as the lag search found it, summed "
             "along path",
    "method": "what produced the matrix; ', refined' when the joint refinement over every "
              "overlap changed it (by 'refined': rot_deg, trans_mm)",
    "refinement": "disagreement over every used overlap, all sensors together, before and "
                  "after the joint refinement: rms (m) over every joint pair, and the mean "
                  "over overlaps of each one's median (m); kept only when the latter drops",
    "overlaps": "every pair of sensors: paired frames, distinct poses, lag and its confidence, "
                "the pairwise fit, its uncertainty, and why it was not used",
    "uncertainty": "how well the pairs determine the fit: the rms spread of the fit over a "
                   "bootstrap of its independent poses (poses both sensors see the body move "
                   "to), as rotation (rot_deg) and as the displacement of a point edge_m from "
                   "the sensor (far_m); null when fewer than 3 poses leave it undetermined; a "
                   "sensor's: its chain's overlaps in quadrature. Precision, not accuracy: a "
                   "bias common to every pose does not show in it",
    "loops": "every three sensors whose pairs were all fitted: the turn (rot_deg) and the "
             "displacement of a point edge_m in front of the first (far_m) of their three "
             "fits composed round the triangle (none for fits that agree); open when over "
             "the loop tolerance, and which fit was then not used (dropped)",
}


def _as_json(result: RigCalibration, method: str, drops: dict[str, int],
             gates: Gates | None = None) -> dict[str, Any]:
    g = gates or Gates()
    return {"reference": result.reference, "method": method,
            "sensors": {sid: c.as_json() for sid, c in result.sensors.items()},
            "refinement": None if result.refinement is None else
            {"before_rms_m": round(float(np.sqrt(result.refinement["before"])), 5),
             "after_rms_m": round(float(np.sqrt(result.refinement["after"])), 5),
             "before_median_m": round(float(result.refinement["robust_before"]), 5),
             "after_median_m": round(float(result.refinement["robust_after"]), 5),
             "kept": result.refinement["kept"],
             "iterations": result.refinement["iterations"]},
            "overlaps": [o.as_json() for o in result.overlaps],
            "loops": result.loops,
            "tolerance": {"rot_deg": g.max_rot_deg or None, "far_m": g.max_far_m or None,
                          "edge_m": g.edge_m, "loop_deg": g.max_loop_deg or None},
            "warnings": result.warnings, "drops": drops, "about": ABOUT}


def _print_table(result: RigCalibration) -> None:
    print(f"reference: {result.reference}")
    print(f"{'sensor':<16} {'method':<16} {'median mm':>9} {'rms mm':>7} {'fitness':>7} "
          f"{'pairs':>6} {'lag s':>7} {'+-deg':>6} {'+-cm':>5}  path")
    for sid, c in result.sensors.items():
        if c.matrix is None:
            print(f"{sid:<16} {'-':<16} {'':>9} {'':>7} {'':>7} {'':>6} {'':>7}  {c.error}")
            continue
        u = c.uncertainty or {}
        deg = "-" if u.get("rot_deg") is None else f"{u['rot_deg']:.2f}"
        cm = "-" if u.get("far_m") is None else f"{u['far_m'] * 100:.1f}"
        print(f"{sid:<16} {c.method:<16} {(c.median_m or 0) * 1000:9.1f} {c.rms_m * 1000:7.1f} "
              f"{c.fitness:7.3f} {c.pairs:6d} {c.lag_s:+7.3f} {deg:>6} {cm:>5}  "
              f"{' -> '.join(c.path[::-1])}")
    print("median/rms: joint distances to the overlapping sensors with the final transforms; "
          "+-deg/+-cm: how far the fit spreads over a bootstrap of its independent poses "
          "(the cm at the stage's far edge)")
    if result.refinement:
        r = result.refinement
        print(f"joint refinement: rms disagreement over every overlap {np.sqrt(r['before']) * 1000:.1f}"
              f" -> {np.sqrt(r['after']) * 1000:.1f} mm")


def _live(args: argparse.Namespace) -> int:
    from ..app.show import Show, ShowOptions
    from ..app.signals import StopSignals
    from ..calibration.live import LiveSettings
    _load_rig(args.rig)  # a rig file that cannot be written fails now, with one line
    pairs = args.pairs or DEFAULT_PAIRS.get(args.method, 300)
    if args.tolerance_deg < 0 or args.tolerance_cm < 0:
        raise ConfigError("--tolerance-deg and --tolerance-cm must be 0 (not judged) or more")
    settings = LiveSettings(method=args.method, pairs=pairs, max_rot_deg=args.tolerance_deg,
                            max_far_m=args.tolerance_cm / 100, edge_m=args.edge_m)
    opts = ShowOptions(rig=args.rig, create_rig=True, host=args.host, port=args.port,
                       calibration=settings, plugins=False)
    with StopSignals() as signals:
        show = Show(opts, stop_event=signals.event)
        try:
            show.start()
        except TransportError as exc:
            raise StageError(f"{exc} (is `stage serve` running? stop it, or use --port)") from None
        calibrator = show.calibrator
        assert calibrator is not None and show.address is not None
        calibrator.request(args.sensor or None, pairs)
        print(f"stage calibrate: listening on udp {show.address[0]}:{show.address[1]}; walk "
              f"where the sensors overlap, one person at a time. Ctrl-C stops.", file=sys.stderr,
              flush=True)
        done: dict[str, Any] = {}
        deadline = time.monotonic() + args.timeout
        try:
            while not signals.event.is_set() and time.monotonic() < deadline:
                signals.wait(1.0)
                for event in list(calibrator.events):
                    if event.kind == "calibrated" and event.sensor not in done:
                        done[event.sensor] = event
                states = calibrator.states()
                wanted = args.sensor or [s for s in states if s != calibrator.reference]
                line = "; ".join(f"{s}: {states[s].get('state')} "
                                 f"{states[s].get('progress', '')}".strip()
                                 for s in wanted if s in states)
                if line:
                    print(f"  {line}", file=sys.stderr, flush=True)
                if wanted and all(s in done for s in wanted):
                    break
        finally:
            show.stop()
    # the show has stopped: the engine thread no longer owns the rig, we may read it
    rig = show.rig
    reference = rig.reference if rig.reference is not None else show.engine.reference
    frame = rig.stage_frame
    out = {}
    for sid, event in done.items():
        m = invert(frame) @ event.matrix
        st = calibrator.states().get(sid, {})
        out[sid] = {"matrix": [[round(float(v), 6) for v in row] for row in m],
                    "rms_m": None, "fitness": None if event.fitness is None else
                    round(event.fitness, 4), "pairs": pairs, "method": args.method,
                    "lag_s": 0.0, "state": st.get("state")}
        cal = rig.sensors.get(sid)
        if cal is not None and cal.calibration is not None:
            out[sid]["rms_m"] = cal.calibration.rms_m
    wanted = args.sensor or [s for s in calibrator.states() if s != reference]
    if args.json:
        print(dumps({"reference": reference, "method": args.method, "sensors": out}))
    else:
        for sid, entry in out.items():
            print(f"{sid}: fitness {entry['fitness']}, written to {args.rig or '(no rig file)'}")
    missing = [s for s in wanted if s not in done]
    if signals.received:
        return Exit.INTERRUPTED
    if missing or not wanted:
        print(f"stage: not calibrated: {', '.join(missing) or 'no sensor besides the reference'}"
              " (was one person visible to it and a calibrated sensor?)", file=sys.stderr)
        return Exit.FAILURE
    return Exit.OK
