"""``stage client NAME``: run a source (a real sensor) as a stage client.

The sensor is found by name among the installed sources (``stage.sources.v1``:
the built-in ``webcam``, ``kinect2`` and ``azure``, or a third party's) and
sends its skeletons to a server with the Client-to-Server OSC API.
"""

from __future__ import annotations

import argparse
import socket

from .. import install_hint
from .common import Exit, hostport, positive

CLIENTS = ("webcam", "kinect2", "azure")


def register(sub) -> dict:
    # the description is laid out by hand: argparse would wrap 'stage-kuatro' at its hyphen
    p = sub.add_parser("client", help="run a real sensor (webcam, Kinect v2, Azure Kinect/Orbbec) "
                       "as a client", formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Send a real sensor's skeletons to a stage server with the "
                       "Client-to-Server OSC API.\nEach sensor needs the optional extra of its "
                       f"name (likewise kinect2, azure):\n  {install_hint('webcam')}\n"
                       "Any other installed source (see `stage plugins`) runs by its name too.")
    p.add_argument("sensor", metavar="SENSOR", help=f"{', '.join(CLIENTS)}, or another installed "
                   "source")
    p.add_argument("--to", type=hostport, default=("127.0.0.1", 7770), metavar="HOST:PORT",
                   help="the server (default 127.0.0.1:7770)")
    p.add_argument("--id", dest="client_id", default=None,
                   help="client id sent as clientID (default: this machine's name + sensor)")
    p.add_argument("--camera", type=int, default=0, help="webcam: camera index (default 0)")
    p.add_argument("--fov", type=positive, default=60.0, metavar="DEG",
                   help="webcam: horizontal field of view in degrees (default 60)")
    p.add_argument("--model", metavar="FILE", help="webcam: MediaPipe pose_landmarker .task file "
                   "(only for mediapipe versions without solutions.pose)")
    p.add_argument("--show", action="store_true", help="webcam: show the camera image")
    return {"client": cmd_client}


def cmd_client(args: argparse.Namespace) -> int:
    from ..app.signals import StopSignals
    from ..sensors.source import load_source
    client_id = args.client_id or f"{socket.gethostname()}-{args.sensor}"
    options: dict = {"client_id": client_id} if args.sensor in CLIENTS else {}
    if args.sensor == "webcam":
        options.update(camera=args.camera, fov=args.fov, model=args.model, show=args.show)
    source = load_source(args.sensor, **options)
    print(f"stage client: {args.sensor} as '{client_id}' -> udp {args.to[0]}:{args.to[1]}; "
          "Ctrl-C stops", flush=True)
    with StopSignals() as stop:
        source.start(args.to)
        while not stop.event.is_set() and not source.done.is_set():
            stop.event.wait(0.2)
        source.stop()
    error = getattr(source, "error", None)
    if error:
        print(f"stage: {args.sensor}: {error}", flush=True)
        return Exit.FAILURE
    return Exit.INTERRUPTED if stop.received else Exit.OK
