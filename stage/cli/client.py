"""``stage client webcam|kinect2|azure``: run a real sensor as a stage client."""

from __future__ import annotations

import argparse
import socket

from .. import install_hint


def register(sub) -> dict:
    from .main import _hostport, _positive
    # the description is laid out by hand: argparse would wrap 'stage-kuatro' at its hyphen
    p = sub.add_parser("client", help="run a real sensor (webcam, Kinect v2, Azure Kinect/Orbbec) "
                       "as a client", formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Send a real sensor's skeletons to a stage server with the "
                       "Client-to-Server OSC API.\nEach sensor needs the optional extra of its "
                       f"name (likewise kinect2, azure):\n  {install_hint('webcam')}")
    p.add_argument("sensor", choices=("webcam", "kinect2", "azure"))
    p.add_argument("--to", type=_hostport, default=("127.0.0.1", 7770), metavar="HOST:PORT",
                   help="the server (default 127.0.0.1:7770)")
    p.add_argument("--id", dest="client_id", default=None,
                   help="client id sent as clientID (default: this machine's name + sensor)")
    p.add_argument("--camera", type=int, default=0, help="webcam: camera index (default 0)")
    p.add_argument("--fov", type=_positive, default=60.0, metavar="DEG",
                   help="webcam: horizontal field of view in degrees (default 60)")
    p.add_argument("--model", metavar="FILE", help="webcam: MediaPipe pose_landmarker .task file "
                   "(only for mediapipe versions without solutions.pose)")
    p.add_argument("--show", action="store_true", help="webcam: show the camera image")
    return {"client": cmd_client}


def cmd_client(args: argparse.Namespace) -> int:
    from .main import Exit, StopSignals
    client_id = args.client_id or f"{socket.gethostname()}-{args.sensor}"
    print(f"stage client: {args.sensor} as '{client_id}' -> udp {args.to[0]}:{args.to[1]}; "
          "Ctrl-C stops", flush=True)
    with StopSignals() as stop:
        if args.sensor == "webcam":
            from ..sensors.clients.webcam import run
            run(args.to, client_id, args.camera, args.fov, args.model, args.show, stop.event)
        elif args.sensor == "kinect2":
            from ..sensors.clients.kinect2 import run as run_kinect2
            run_kinect2(args.to, client_id, stop.event)
        else:
            from ..sensors.clients.azure import run as run_azure
            run_azure(args.to, client_id, stop.event)
    return Exit.OK
