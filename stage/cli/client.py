"""``stage client NAME``: run a source (a real sensor) as a stage client.

The sensor is found by name among the installed sources (``stage.sources.v1``:
the built-in ``webcam``, ``kinect2`` and ``azure``, or a third party's) and
sends its skeletons to a server with the Client-to-Server OSC API.
"""

from __future__ import annotations

import argparse
import os
import socket

from .. import install_hint
from ..errors import ConfigError
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
    p.add_argument("--check", action="store_true",
                   help="say what this sensor needs, what is installed and missing, and (with a "
                   "device) print one tracked skeleton; then exit (webcam: load the models)")
    p.add_argument("--to", type=hostport, default=("127.0.0.1", 7770), metavar="HOST:PORT",
                   help="the server (default 127.0.0.1:7770)")
    p.add_argument("--id", dest="client_id", default=None,
                   help="client id sent as clientID (default: this machine's name + sensor)")
    p.add_argument("--camera", type=int, default=0, help="webcam: camera index (default 0)")
    p.add_argument("--fov", type=positive, default=60.0, metavar="DEG",
                   help="webcam: horizontal field of view in degrees (default 60)")
    p.add_argument("--video", metavar="FILE", help="webcam: play a video file (anything OpenCV "
                   "reads) as if a camera filmed it; capture times are the video's frame times")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=positive, default=1.0, metavar="X",
                      help="webcam --video: play at X times the pace it was filmed (default 1; "
                      "late frames are skipped), stamped as a camera filming at that pace")
    pace.add_argument("--max-speed", action="store_true", help="webcam --video: every frame as "
                      "fast as the model goes, stamped with the video's own times")
    p.add_argument("--people", type=_people, default=1, metavar="N",
                   help="webcam: look for up to N people (1-6, default 1)")
    p.add_argument("--no-hands", dest="hands", action="store_false",
                   help="webcam: send no hand states (saves the hand model's time)")
    p.add_argument("--model", metavar="FILE", help="webcam: a MediaPipe pose_landmarker .task file "
                   "instead of the model inside the mediapipe package")
    p.add_argument("--hand-model", metavar="FILE", help="webcam: a MediaPipe hand_landmarker .task "
                   "file instead of the model inside the mediapipe package")
    p.add_argument("--show", action="store_true", help="webcam: show the camera image")
    return {"client": cmd_client}


def _people(text: str) -> int:
    n = int(text)
    if not 1 <= n <= 6:
        raise argparse.ArgumentTypeError("give 1 to 6 (the API's user ids 0-5)")
    return n


def cmd_check(sensor: str) -> int:
    """``--check``: one report; exit 0 when everything needed is there (and a body was seen)."""
    if sensor == "webcam":
        from ..sensors.clients.mediapipe_models import check
        lines = check()
        print("stage client webcam --check\n  " + "\n  ".join(lines), flush=True)
        return Exit.OK
    if sensor == "kinect2":
        from ..sensors.clients.kinect2 import check as check_kinect2
        text, ok = check_kinect2()
    elif sensor == "azure":
        from ..sensors.clients.azure import check as check_azure
        text, ok = check_azure()
    else:
        raise ConfigError(f"--check knows {', '.join(CLIENTS)}; '{sensor}' has no check")
    print(text, flush=True)
    return Exit.OK if ok else Exit.FAILURE


def cmd_client(args: argparse.Namespace) -> int:
    from ..app.signals import StopSignals
    from ..sensors.source import load_source
    if args.check:
        return cmd_check(args.sensor)
    client_id = args.client_id or f"{socket.gethostname()}-{args.sensor}"
    options: dict = {"client_id": client_id} if args.sensor in CLIENTS else {}
    if args.sensor == "webcam":
        if args.video is not None and not os.path.isfile(args.video):
            raise ConfigError("no such video file", path=args.video)
        options.update(camera=args.camera, fov=args.fov, model=args.model, show=args.show,
                       video=args.video, realtime=not args.max_speed, people=args.people,
                       hands=args.hands, hand_model=args.hand_model, speed=args.speed)
    elif args.video or args.max_speed or args.speed != 1.0:
        raise ConfigError("--video, --speed and --max-speed are webcam options")
    source = load_source(args.sensor, **options)
    print(f"stage client: {args.sensor} as '{client_id}' -> udp {args.to[0]}:{args.to[1]}; "
          "Ctrl-C stops", flush=True)
    with StopSignals() as stop:
        source.start(args.to)
        while not stop.event.is_set() and not source.done.is_set():
            stop.event.wait(0.2)
        source.stop()
    summary = getattr(source, "summary", None)
    error = getattr(source, "error", None)
    if callable(summary) and not (error and not source.sent and not getattr(
            getattr(source, "stats", None), "read", 0)):
        print(f"stage client: {args.sensor}: {summary()}", flush=True)
    if error:
        print(f"stage: {args.sensor}: {error}", flush=True)
        return Exit.FAILURE
    return Exit.INTERRUPTED if stop.received else Exit.OK
