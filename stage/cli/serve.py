"""``stage serve``, ``stage demo`` and ``stage stats``."""

from __future__ import annotations

import argparse
import json
import logging
import socket
import sys

from ..errors import ConfigError
from ..rig import DEFAULT_PORT
from .common import Exit, add_show_options, port, positive, show_options

log = logging.getLogger("stage")


def register(sub) -> dict:
    serve = sub.add_parser("serve", help="run the engine: sensors in, fused bodies out (Kuatro "
                           "server)")
    serve.add_argument("--host", help="address to listen on (default: rig's, else 0.0.0.0)")
    serve.add_argument("--port", type=port, help=f"UDP port (default: rig's, else {DEFAULT_PORT})")
    serve.add_argument("--rig", help="rig file (sensors, calibration, views, settings)")
    serve.add_argument("--replay", metavar="FILE",
                       help="feed the engine from a recording as well as the network")
    serve.add_argument("--speed", type=positive, default=1.0, metavar="X",
                       help="with --replay: X times real time (default 1)")
    serve.add_argument("--loop", action="store_true", help="with --replay: start again at the end")
    add_show_options(serve)

    demo = sub.add_parser("demo", help="the engine fed by virtual Kinects over real OSC")
    demo.add_argument("--port", type=port, default=0, help="UDP port (default: any free port)")
    demo.add_argument("--sensors", type=int, default=3, choices=range(1, 7), metavar="N",
                      help="virtual sensors around the stage (1-6, default 3)")
    demo.add_argument("--seed", type=int, default=1)
    add_show_options(demo, status=False)

    stats = sub.add_parser("stats", help="ask a running server for its counters (JSON)")
    stats.add_argument("--host", default="127.0.0.1")
    stats.add_argument("--port", type=port, default=DEFAULT_PORT)
    stats.add_argument("--timeout", type=positive, default=2.0, metavar="S")
    return {"serve": cmd_serve, "demo": cmd_demo, "stats": cmd_stats}


def cmd_serve(args: argparse.Namespace) -> int:
    from ..app.show import Show, summary
    from ..app.signals import StopSignals
    # with --replay the server still listens for real sensors where it would without it,
    # and goes on when the recording ends
    opts = show_options(args, rig=args.rig, host=args.host, port=args.port, replay=args.replay,
                        speed=args.speed, loop=args.loop, listen=True, end_with_source=False)
    with StopSignals() as signals:
        show = Show(opts, stop_event=signals.event)
        result = show.run()
        log.info("stopped; %s", summary(result.stats))
    return Exit.INTERRUPTED if signals.received else Exit.OK


def cmd_demo(args: argparse.Namespace) -> int:
    from ..app.show import Show, summary
    from ..app.signals import StopSignals
    opts = show_options(args, sim="demo", source_options={"sensors": args.sensors},
                        seed=args.seed, host="127.0.0.1", port=args.port, status_line=True)
    with StopSignals() as signals:
        show = Show(opts, stop_event=signals.event)
        show.start()
        try:
            host, udp = show.address
            print(f"stage demo: {args.sensors} virtual Kinects -> engine on udp {host}:{udp}; one "
                  "dancer walking a circle, arms rising in turn. Ctrl-C stops.", flush=True)
            show.wait()
        finally:
            result = show.stop()
        print(f"stage demo: done; {summary(result.stats)}", flush=True)
    return Exit.INTERRUPTED if signals.received else Exit.OK


def cmd_stats(args: argparse.Namespace) -> int:
    from pythonosc.osc_message import OscMessage
    from ..sensors.protocol import encode_message
    try:
        address = socket.getaddrinfo(args.host, args.port, socket.AF_INET, socket.SOCK_DGRAM)[0][4]
    except (socket.gaierror, UnicodeError):
        raise ConfigError(f"--host {args.host}: no such host") from None
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(args.timeout)
    try:
        sock.bind(("0.0.0.0", 0))
        sock.sendto(encode_message("/stage/stats"), address)
        while True:
            data, _ = sock.recvfrom(1 << 20)
            try:
                reply = OscMessage(data)
            except Exception:  # not OSC: keep waiting for the real answer
                continue
            if reply.address == "/stage/stats" and reply.params:
                print(json.dumps(json.loads(reply.params[0]), indent=2))
                return Exit.OK
    except socket.timeout:
        print(f"stage: no answer from {args.host}:{args.port} within {args.timeout:g} s "
              "(is `stage serve` running there?)", file=sys.stderr)
        return Exit.FAILURE
    except OSError as exc:
        print(f"stage: cannot ask {args.host}:{args.port}: {exc.strerror or exc}", file=sys.stderr)
        return Exit.FAILURE
    finally:
        sock.close()
