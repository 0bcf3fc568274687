"""``stage import ntu|nucla|bvh FILE... --out RECORDING``."""

from __future__ import annotations

import argparse

from ..errors import ConfigError
from .common import Exit, positive as _positive


def register(sub) -> dict:
    p = sub.add_parser("import", help="turn dataset files (NTU RGB+D, N-UCLA, BVH) into a "
                       "recording", description="Import skeleton data into a stage recording; "
                       "several cameras of one take become one multi-sensor recording.")
    p.add_argument("format", choices=("ntu", "nucla", "bvh"),
                   help="ntu: NTU RGB+D .skeleton files (the cameras of one performance); "
                   "nucla: N-UCLA JSON (the views of one sample); bvh: one BVH file")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument("--out", required=True, metavar="RECORDING", help="the recording to write")
    p.add_argument("--fps", type=_positive, default=30.0,
                   help="frame rate of the source (ntu, nucla) or of the output (bvh); default 30")
    p.add_argument("--align", choices=("start", "stretch"), default="start",
                   help="nucla: views start together, or are stretched to the longest")
    p.add_argument("--height", type=_positive, default=None, metavar="M",
                   help="bvh: scale the performer to this height in metres (default: keep the "
                   "file's lengths, in --units)")
    p.add_argument("--units", choices=("auto", "m", "cm", "mm", "in", "cmu"), default="auto",
                   help="bvh: the file's length unit (cmu: the CMU database's 1/0.45 inch); "
                   "default auto: the one in which the performer is 1.2-2.3 m tall")
    p.add_argument("--joint-map", metavar="FILE", help="bvh: YAML mapping our joint names to the "
                   "file's (e.g. 'HandLeft: LeftHandMiddle1'), over the built-in maps (CMU, "
                   "Bandai Namco, Mixamo, LAFAN, detected by the joint names)")
    p.add_argument("--sensor", default="bvh", help="bvh: the sensor id (default 'bvh')")
    return {"import": cmd_import}


def cmd_import(args: argparse.Namespace) -> int:
    from ..sensors.recording import read_recording
    if args.format == "ntu":
        from ..sensors.importers.ntu import import_ntu
        n = import_ntu(args.files, args.out, args.fps)
    elif args.format == "nucla":
        from ..sensors.importers.nucla import import_nucla
        n = import_nucla(args.files, args.out, args.fps, args.align)
    else:
        if len(args.files) != 1:
            raise ConfigError("bvh: give one file (one performer) per recording")
        from ..sensors.importers.bvh import import_bvh
        from ..sensors.importers.bvh_maps import load_joint_map
        joint_map = load_joint_map(args.joint_map) if args.joint_map else None
        n, take = import_bvh(args.files[0], args.out, args.height, args.fps, args.sensor,
                             joint_map, None if args.units == "auto" else args.units)
        print(f"stage import: bvh naming: {take.scheme or 'generic aliases'}"
              f"{' + ' + args.joint_map if args.joint_map else ''}; lengths: "
              + (f"scaled to {args.height} m" if take.units is None else
                 f"{take.units} ({'detected' if args.units == 'auto' else 'given'})"), flush=True)
    info = read_recording(args.out).scan()
    print(f"stage import: {len(args.files)} file(s) -> {args.out}: {n} datagram(s), "
          f"{len(info['sources'])} sensor(s), {info['duration_s']:.2f} s", flush=True)
    return Exit.OK
