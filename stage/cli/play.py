"""`stage check` and `stage play` (registered through ``stage.cli.COMMAND_MODULES``)."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Callable

from ..errors import ConfigError
from .common import (Exit, add_show_options, hostport as _hostport, port as _port,
                     positive as _positive, show_options)


def register(sub: argparse._SubParsersAction) -> dict[str, Callable[[argparse.Namespace], int]]:
    check = sub.add_parser("check", help="check piece files (and their rehearsal scenarios) and "
                                         "summarise them",
                           description="Check piece files: every mistake is reported as "
                                       "file:line:column with what was expected (exit status 2). "
                                       "A rehearsal scenario kept beside the pieces (a file with "
                                       "'performers' and no 'piece') is checked as a scenario, "
                                       "and its choreography printed with the time of each step.")
    check.add_argument("pieces", nargs="+", metavar="PIECE.yaml")
    check.add_argument("--quiet-summary", action="store_true", dest="brief",
                       help="one line per piece instead of the summary")

    play = sub.add_parser(
        "play", help="perform a piece: sensors, simulator or recording in; MIDI and OSC out",
        description="Perform a piece. With no source option, listen for sensor clients like "
                    "`stage serve`. Ctrl-C stops: every sounding note gets its note-off.")
    play.add_argument("piece", metavar="PIECE.yaml")
    source = play.add_mutually_exclusive_group()
    source.add_argument("--sim", nargs="?", const="", default=None, metavar="SCENARIO",
                        help="a simulated dancer (default: the piece's rehearsal scenario)")
    source.add_argument("--replay", metavar="FILE", help="replay a recording")
    source.add_argument("--port", type=_port, help="UDP port for sensors (default: the rig's)")
    play.add_argument("--host", help="address to listen on (default: the rig's)")
    play.add_argument("--rig", help="rig file (sensors, calibration, settings)")
    midi = play.add_mutually_exclusive_group()
    midi.add_argument("--midi", metavar="PORT", help="MIDI port for the piece's MIDI outputs")
    midi.add_argument("--midi-file", metavar="OUT.mid", help="write the MIDI to a file instead")
    play.add_argument("--audio", metavar="OUT.wav",
                      help="hear it: render the MIDI through FluidSynth into a WAV file")
    play.add_argument("--synth", action="store_true",
                      help="hear it live: play the MIDI through FluidSynth on JACK")
    play.add_argument("--soundfont", metavar="FILE.sf2",
                      help="for --audio/--synth (default: the General MIDI soundfont of "
                           "fluid-soundfont-gm)")
    play.add_argument("--score", metavar="OUT.png",
                      help="see it: draw what was played (a piano roll by section and phrase, "
                           "with triggers and zones) when the show ends")
    play.add_argument("--osc", action="append", type=_hostport, default=[], metavar="HOST:PORT",
                      help="target of the piece's OSC outputs (repeatable)")
    play.add_argument("--seed", type=int, help="seed of the aleatoric choices (default: the "
                                                "piece's, else random and printed)")
    play.add_argument("--events", metavar="OUT.jsonl",
                      help="write every trigger, section change and output message as JSON lines")
    play.add_argument("--monitor", nargs="?", const=True, default=False, type=_port,
                      metavar="PORT", help="live monitor in a browser (default port 7780)")
    play.add_argument("--speed", type=_positive, default=1.0,
                      help="--sim/--replay: play faster or slower than real time")
    play.add_argument("--offline", action="store_true",
                      help="--sim/--replay: run ahead of time on a manual clock (no waiting); "
                           "with --midi-file renders the rehearsal")
    add_show_options(play, status=False)
    return {"check": cmd_check, "play": cmd_play}


def cmd_check(args: argparse.Namespace) -> int:
    from ..piece.narrator import check_summary
    from ..piece.loader import load_piece
    from ..sensors.sim.scenario import describe, load_scenario, looks_like_scenario
    status = 0
    for path in args.pieces:
        try:
            if looks_like_scenario(path):
                scenario = load_scenario(path)
                lines = [f"{path}: ok -- rehearsal scenario '{scenario.name}': "
                         + describe(scenario)[0]] + describe(scenario)[1:]
            else:
                lines = check_summary(load_piece(path), path)
        except ConfigError as exc:
            print(f"stage: {exc}", file=sys.stderr)
            status = 2
            continue
        try:
            print("\n".join(lines[:1] if args.brief else lines), flush=True)
        except BrokenPipeError:  # `stage check x.yaml | head`: the reader has had enough
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return status
    return status


def cmd_play(args: argparse.Namespace) -> int:
    from ..app.play import Player
    from ..app.signals import StopSignals
    opts = show_options(args, piece=args.piece, sim=args.sim, replay=args.replay, port=args.port,
                        host=args.host, rig=args.rig, midi=args.midi, midi_file=args.midi_file,
                        osc=list(args.osc), seed=args.seed, events=args.events,
                        monitor=args.monitor, offline=args.offline, speed=args.speed,
                        audio=args.audio, synth=args.synth, soundfont=args.soundfont,
                        score=args.score)
    with StopSignals() as signals:
        Player(opts, stop_event=signals.event).run()
    return Exit.INTERRUPTED if signals.received else Exit.OK
