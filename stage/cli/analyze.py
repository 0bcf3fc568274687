"""``stage analyze``: gait parameters and body KPIs of a recording, as a report.

    stage analyze walk.rec                                   # a summary on the console
    stage analyze walk.rec --report walk.html                # charts, to look at
    stage analyze walk.rec --json > walk.json                # everything, for machines
    stage analyze walk.rec --sensors left=kinect-l1,kinect-l2,kinect-l3 --sensors all
                                                             # one-sided vs two-sided (seed 003)
    stage analyze walk.rec --rig rig.yaml --truth walk.npz   # against the simulator's truth
"""

from __future__ import annotations

import argparse
import json
import math
import os
from typing import Callable

from ..errors import ConfigError
from .common import Exit, positive as _positive


def register(sub: argparse._SubParsersAction) -> dict[str, Callable[[argparse.Namespace], int]]:
    p = sub.add_parser(
        "analyze", help="gait parameters and body KPIs of a recording (seed 003 / seed 004)",
        description="Integrate the sensors of a recording into one skeleton the way seed 003 "
                    "does (30 Hz, linear interpolation, untracked and inferred joints missing, "
                    "equal weights), find the foot placements and gait parameters (step length, "
                    "width, time, stride length, walking speed; first step of each walk left "
                    "out) and seed 004's body KPIs. Give --sensors several times to compare "
                    "subsets of the same recording.")
    p.add_argument("recording", metavar="RECORDING",
                   help="a stage recording (stage record, stage sim --out, stage import)")
    p.add_argument("--sensors", action="append", default=[], metavar="[NAME=]ID,ID,...|all",
                   help="the sensors to use (repeatable: each is analysed and shown side by "
                        "side; default all)")
    p.add_argument("--rig", metavar="RIG.yaml",
                   help="the calibrations (default: the rig the recording carries)")
    p.add_argument("--report", metavar="OUT.html", help="write the report (charts) here")
    p.add_argument("--json", action="store_true", help="print the whole analysis as JSON")
    p.add_argument("--truth", metavar="TRUTH.npz",
                   help="ground truth to compare with (stage sim --truth); its clock is "
                        "aligned to the recording's")
    p.add_argument("--performer", metavar="NAME", help="--truth: which performer (default the "
                   "first)")
    p.add_argument("--keep-inferred", action="store_true",
                   help="average inferred joints too (seed 003 treats them as missing)")
    p.add_argument("--rate", type=_positive, default=30.0, metavar="HZ",
                   help="the resampling rate (default 30, as seed 003)")
    return {"analyze": cmd_analyze}


def cmd_analyze(args: argparse.Namespace) -> int:
    from ..analysis.analyze import analyze_recording, parse_subset, truth_trajectory
    from ..rig import load_rig
    subsets = [parse_subset(s) for s in args.sensors] or None
    names = [s.name for s in subsets or []]
    if len(set(names)) != len(names):
        raise ConfigError("--sensors: give each subset its own NAME (NAME=ID,ID,...)")
    if args.report:
        folder = os.path.dirname(os.path.abspath(args.report))
        if not os.path.isdir(folder):
            raise ConfigError(f"--report {args.report}: no folder {folder}")
    rig = load_rig(args.rig) if args.rig else None
    truth = truth_trajectory(args.truth, args.performer) if args.truth else None
    analysis = analyze_recording(args.recording, subsets, rig, truth, rate=args.rate,
                                 keep_inferred=args.keep_inferred)
    if args.report:
        from ..analysis.report import write_report
        write_report(analysis, args.report)
    if args.json:
        print(json.dumps(analysis.as_json(), indent=1))
        return Exit.OK
    for line in summary_lines(analysis.as_json()):
        print(line)
    if args.report:
        print(f"stage analyze: report written to {args.report}", flush=True)
    return Exit.OK


def _f(v, scale: float = 1.0, digits: int = 1) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v * scale:.{digits}f}"


def summary_lines(data: dict) -> list[str]:
    """The console summary: per subset, the gait table (and agreement with the truth)."""
    out = [f"stage analyze: {data['source']}: sensors {', '.join(data['sensors'])}"]
    truth = data.get("truth")
    for name, r in data["subsets"].items():
        g = r["gait"]
        out.append(f"{name} ({', '.join(r['sensors'])}): {r['duration_s']:.1f} s, "
                   f"{g['steps']} foot placements in {g['bouts']} walk(s), {g['used']} steps "
                   f"used; speed {_f(g['speed'], 1, 2)} m/s, cadence {_f(g['cadence'], 1, 0)} "
                   f"steps/min")
        out.append("  parameter          left mean±sd     right mean±sd"
                   + ("    bias    RPC  ICC(A,1)  (L+R vs truth)" if truth else ""))
        for p, unit, scale, digits in (("step_length", "cm", 100, 1), ("step_width", "cm", 100, 1),
                                       ("step_time", "s", 1, 3), ("stride_length", "cm", 100, 1)):
            cells = [_f(g[p][s]["mean"], scale, digits)
                     + (f"±{_f(g[p][s]['sd'], scale, digits)}" if g[p][s]["sd"] is not None
                        else "") for s in ("left", "right")]
            label = f"{p.replace('_', ' ')} ({unit})"
            line = f"  {label:18s} {cells[0]:>14s} {cells[1]:>16s}"
            if truth and "agreement" in r:
                a = r["agreement"][p]["all"]
                line += (f"  {_f(a['bias'], scale, digits):>6s} {_f(a['rpc'], scale, digits):>6s}"
                         f"  {_f(a['icc'], 1, 3):>8s}")
            out.append(line)
        kpi = r["kpi"]
        env = kpi.get("envelope_m3", {})
        if env:
            out.append("  working envelope (litres): " + ", ".join(
                f"{k} {_f(v, 1000, 1)}" for k, v in env.items()))
    if truth:
        g = truth["gait"]
        out.append(f"truth: {g['steps']} placements, step length "
                   f"{_f(g['step_length']['all']['mean'], 100)} cm, width "
                   f"{_f(g['step_width']['all']['mean'], 100)} cm, speed {_f(g['speed'], 1, 2)} "
                   f"m/s (clock shifted {truth['shift_s']:+.2f} s)")
    return out
