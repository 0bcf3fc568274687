"""The ``stage`` command: one entry point, one-line errors, tracebacks with --debug."""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import signal
import socket
import sys
import threading
from enum import IntEnum
from typing import Callable, Sequence

from pythonosc.osc_message import OscMessage

from .. import __version__
from ..errors import ConfigError, StageError
from ..sensors.protocol import encode_message
from ..rig import DEFAULT_PORT, Rig, load_rig
from .args import hostport as _hostport, positive as _positive

log = logging.getLogger("stage")


class Exit(IntEnum):
    OK = 0
    FAILURE = 1      # something went wrong at run time (a port in use, a peer that did not answer)
    BAD_INPUT = 2    # the user's command line or files are wrong
    INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stage", description="Music and dance performance with multi-sensor body tracking.")
    parser.add_argument("--version", action="version", version=f"stage {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    parser.add_argument("--quiet", action="store_true", help="warnings and errors only")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    serve = sub.add_parser("serve", help="run the engine: sensors in, fused bodies out (Kuatro server)")
    serve.add_argument("--host", help="address to listen on (default: rig's, else 0.0.0.0)")
    serve.add_argument("--port", type=int, help=f"UDP port (default: rig's, else {DEFAULT_PORT})")
    serve.add_argument("--rig", help="rig file (sensors, calibration, views, settings)")
    serve.add_argument("--view", action="append", type=_hostport, default=[], metavar="HOST:PORT",
                       help="send fused bodies to this view too (repeatable)")
    serve.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds")
    serve.add_argument("--status", action="store_true", help="print a status line every second")
    serve.add_argument("--replay", metavar="FILE",
                       help="feed the engine from a recording instead of (as well as) the network")
    serve.add_argument("--speed", type=_positive, default=1.0, metavar="X",
                       help="with --replay: X times real time (default 1)")
    serve.add_argument("--loop", action="store_true", help="with --replay: start again at the end")
    serve.add_argument("--no-self-healing", action="store_true",
                       help="do not calibrate uncalibrated sensors or re-calibrate bumped ones")

    demo = sub.add_parser("demo", help="the engine fed by three virtual Kinects over real OSC")
    demo.add_argument("--port", type=int, default=0, help="UDP port (default: any free port)")
    demo.add_argument("--sensors", type=int, default=3, choices=range(1, 7), metavar="N",
                      help="virtual sensors around the stage (1-6, default 3)")
    demo.add_argument("--view", action="append", type=_hostport, default=[], metavar="HOST:PORT",
                      help="also send fused bodies to this view")
    demo.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds")
    demo.add_argument("--seed", type=int, default=1)

    stats = sub.add_parser("stats", help="ask a running server for its counters (JSON)")
    stats.add_argument("--host", default="127.0.0.1")
    stats.add_argument("--port", type=int, default=DEFAULT_PORT)
    stats.add_argument("--timeout", type=_positive, default=2.0, metavar="S")
    for name in COMMAND_MODULES:
        try:
            _COMMANDS.update(importlib.import_module(name).register(sub))
        except Exception as exc:  # one broken command module must not take the others down
            print(f"stage: warning: commands of {name} unavailable: {exc}", file=sys.stderr)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)
    if args.command is None:
        parser.print_help()
        return Exit.BAD_INPUT
    try:
        return int(_COMMANDS[args.command](args))
    except StageError as exc:
        if args.debug:
            raise
        print(f"stage: {exc}", file=sys.stderr)
        return Exit.BAD_INPUT if isinstance(exc, ConfigError) else Exit.FAILURE
    except KeyboardInterrupt:
        return Exit.INTERRUPTED
    except BrokenPipeError:  # `stage ... | head` closed the pipe: not an error worth a traceback
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return Exit.OK


class StopSignals:
    """Turns Ctrl-C and SIGTERM into an event, from before anything starts.

    Installed before the server starts, so a signal that arrives while it is
    starting still ends in a clean stop (exit 0), not a KeyboardInterrupt.
    """

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous: dict = {}

    def __enter__(self) -> "StopSignals":
        self._previous = {sig: signal.signal(sig, lambda *_: self.event.set())
                          for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def wait(self, duration: float | None) -> None:
        """Block until a signal or the end of ``duration`` seconds."""
        self.event.wait(duration)


def cmd_serve(args: argparse.Namespace) -> Exit:
    from ..app.status_line import attach
    from ..sensors.receiver import Server
    rig = load_rig(args.rig) if args.rig else None
    if args.replay and rig is None:  # a recording carries the rig it was made with
        from ..sensors.recording import read_recording
        from ..sensors.replay import rig_from_meta
        rig = rig_from_meta(read_recording(args.replay).meta)
    rig = rig or Rig()
    for view in args.view:
        if view not in rig.views:
            rig.views.append(view)
    server = Server(rig, host=args.host, port=args.port)
    if args.status:
        attach(server.engine)
    source = None
    if args.replay:
        from ..sensors.replay import ReplaySource
        source = ReplaySource(args.replay, engine=server.engine, speed=args.speed, loop=args.loop)
    from ..calibration import attach_live
    calibrator = (attach_live(server.engine, rig, args.rig, heal=False, auto_calibrate=False)
                  if args.no_self_healing else attach_live(server.engine, rig, args.rig))
    with StopSignals() as stop:
        server.start()
        if source is not None:
            source.start()
        try:
            stop.wait(args.duration)
        finally:
            if source is not None:
                source.stop()
            calibrator.stop()
            server.stop()
            log.info("stopped; %s", _summary(server.engine.stats()))
    return Exit.OK


def cmd_demo(args: argparse.Namespace) -> Exit:
    from ..app.status_line import attach
    from ..sensors.receiver import Server
    from ..sensors.sim import SimSource, Simulator, demo_scenario
    sim = Simulator(demo_scenario(args.sensors), args.seed)
    rig, sensors = sim.rig(), sim.scenario.sensors  # an exact rig: no calibration step
    rig.port = args.port
    rig.views.extend(args.view)
    server = Server(rig, host="127.0.0.1")
    attach(server.engine)
    with StopSignals() as stop:
        server.start()
        print(f"stage demo: {len(sensors)} virtual Kinects -> engine on udp {server.address[0]}:"
              f"{server.address[1]}; one dancer walking a circle, arms rising in turn. "
              f"Ctrl-C stops.", flush=True)
        source = SimSource(sim, server.address).start()
        try:
            stop.wait(args.duration)
        finally:
            source.stop()
            server.stop()
            print(f"stage demo: done; {_summary(server.engine.stats())}", flush=True)
    return Exit.OK


def _summary(stats: dict) -> str:
    c = stats["counts"]
    lat = stats["latency_ms"]
    text = (f"{c['frames']} sensor frames in, {c['fused_frames']} fused, "
            f"{c['datagrams_out']} datagrams out, {stats['drops_total']} dropped")
    if lat.get("n"):
        text += f", latency p50 {lat['p50']:.2f} ms p99 {lat['p99']:.2f} ms"
    return text


def cmd_stats(args: argparse.Namespace) -> Exit:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(args.timeout)
    try:
        sock.bind(("0.0.0.0", 0))
        sock.sendto(encode_message("/stage/stats"), (args.host, args.port))
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
    finally:
        sock.close()


_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "serve": cmd_serve, "demo": cmd_demo, "stats": cmd_stats}

#: Modules that add subcommands: each has ``register(subparsers) -> {name: function}``,
#: the function taking the parsed arguments and returning an exit status.
COMMAND_MODULES: list[str] = [
    "stage.cli.views",
    "stage.cli.play",
    "stage.cli.calibrate",
    "stage.cli.sim",
    "stage.cli.replay",
    "stage.cli.importers",
    "stage.cli.client",
]


if __name__ == "__main__":
    sys.exit(main())
