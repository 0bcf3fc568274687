"""The composer's commands: `stage new`, `stage schema`, `stage report`."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Callable

from ..errors import ConfigError
from .common import Exit

#: VS Code's user settings, where `stage schema --vscode` adds the schema
VSCODE_SETTINGS = {"linux": "~/.config/Code/User/settings.json",
                   "darwin": "~/Library/Application Support/Code/User/settings.json",
                   "win32": "~/AppData/Roaming/Code/User/settings.json"}
#: files the editor settings give the schema to (pieces written by `stage new` carry their
#: own schema line; a rehearsal *.sim.yaml is not a piece, so no glob over a whole folder)
PIECE_GLOB = "*.piece.yaml"


def register(sub: argparse._SubParsersAction) -> dict[str, Callable[[argparse.Namespace], int]]:
    new = sub.add_parser("new", help="write a commented starter piece and its rehearsal",
                         description="Write PIECE.yaml, a commented starter piece, and "
                                     "PIECE.sim.yaml beside it, a simulated dancer who plays it "
                                     "(stage play PIECE.yaml --sim). The piece's first line "
                                     "points editors at your copy of the schema, wherever the "
                                     "file is.")
    new.add_argument("piece", metavar="PIECE.yaml")
    new.add_argument("--force", action="store_true", help="overwrite existing files")

    schema = sub.add_parser("schema", help="the JSON Schema of pieces, for editors",
                            description="Print the JSON Schema of piece files; --install writes "
                                        "your copy (the absolute path a piece's schema line "
                                        "names) and prints the editor settings.")
    schema.add_argument("--install", action="store_true",
                        help="write the schema to your data folder and show how to use it")
    schema.add_argument("--vscode", nargs="?", const="", default=None, metavar="SETTINGS.json",
                        help=f"with --install: also add it to VS Code's user settings "
                             f"(yaml.schemas, for {PIECE_GLOB} files)")

    report = sub.add_parser("report", help="what happened in a performance: summary, levels, "
                                           "score",
                            description="Read the events of a performance (stage play --events "
                                        "OUT.jsonl): sections, phrases and the triggers that "
                                        "fired them, notes sounded, cancelled or cut; with "
                                        "--audio its WAV file's level per section and where "
                                        "sound and notes disagree; and draw its score (a piano "
                                        "roll by section and phrase, with zones and triggers).")
    report.add_argument("events", metavar="EVENTS.jsonl")
    report.add_argument("--audio", metavar="WAV", help="the show's --audio file")
    report.add_argument("--score", metavar="OUT.png",
                        help="where to draw the score (default: EVENTS.png beside the events)")
    report.add_argument("--no-score", action="store_true", help="do not draw")
    report.add_argument("--piece", metavar="PIECE.yaml",
                        help="also check that quantised phrases started on the piece's grid")
    return {"new": cmd_new, "schema": cmd_schema, "report": cmd_report}


def cmd_new(args: argparse.Namespace) -> int:
    from ..piece.starter import write_starter
    piece, rehearsal, schema = write_starter(args.piece, force=args.force)
    print(f"stage new: wrote {piece} and its rehearsal {rehearsal}")
    print(f"  schema for editors: {schema}")
    print(f"  next: stage play {piece} --sim --audio {piece.with_suffix('.wav').name} "
          f"--score {piece.with_suffix('.png').name}")
    return Exit.OK


def cmd_schema(args: argparse.Namespace) -> int:
    from ..piece.schema import install_user_copy, modeline, schema_text
    if not args.install:
        if args.vscode is not None:
            raise ConfigError("--vscode goes with --install")
        sys.stdout.write(schema_text())
        return Exit.OK
    path, changed = install_user_copy()
    uri = path.resolve().as_uri()
    print(f"stage schema: {'wrote' if changed else 'up to date:'} {path}")
    print(f"  first line of a piece, wherever it is:\n    {modeline(path)}")
    snippet = {"yaml.schemas": {uri: [PIECE_GLOB]}}
    print(f"  VS Code (YAML extension), user settings, for {PIECE_GLOB} files:\n    "
          + json.dumps(snippet))
    print(f"  Neovim (yamlls): settings = {{ yaml = {{ schemas = {{ [\"{uri}\"] = "
          f"\"{PIECE_GLOB}\" }} }} }}")
    if args.vscode is not None:
        settings = Path(os.path.expanduser(args.vscode or VSCODE_SETTINGS.get(
            sys.platform, VSCODE_SETTINGS["linux"])))
        merge_vscode(settings, uri)
        print(f"  added to {settings}")
    return Exit.OK


def merge_vscode(settings: Path, uri: str) -> None:
    """Add ``uri`` -> [PIECE_GLOB] to ``yaml.schemas`` of a VS Code settings file (plain JSON;
    a file with comments is left alone with a one-line error)."""
    from ..yamlio import write_atomic
    data: dict = {}
    if settings.exists():
        try:
            data = json.loads(settings.read_text(encoding="utf-8") or "{}")
        except json.JSONDecodeError:
            raise ConfigError(f"{settings} is not plain JSON (comments?); add the yaml.schemas "
                              "line above by hand") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{settings}: expected a JSON object")
    elif not settings.parent.is_dir():
        raise ConfigError(f"{settings}: folder '{settings.parent}' does not exist (is VS Code "
                          "installed?)")
    schemas = data.setdefault("yaml.schemas", {})
    if not isinstance(schemas, dict):
        raise ConfigError(f"{settings}: 'yaml.schemas' is not an object")
    globs = schemas.get(uri, [])
    globs = [globs] if isinstance(globs, str) else list(globs)
    if PIECE_GLOB not in globs:
        globs.append(PIECE_GLOB)
    schemas[uri] = globs
    write_atomic(settings, json.dumps(data, indent=4) + "\n")


def cmd_report(args: argparse.Namespace) -> int:
    from ..app.report import Performance, audio_lines, audio_report, grid_lines
    perf = Performance.load(args.events)
    print(f"{args.events}: " + "\n".join(perf.summary()))
    if args.piece:
        from ..piece.loader import load_piece
        print("\n".join(grid_lines(perf, load_piece(args.piece))))
    if args.audio:
        print("\n".join(audio_lines(audio_report(perf, args.audio))))
    if not args.no_score:
        from ..app.score import draw_score
        out = args.score or os.path.splitext(args.events)[0] + ".png"
        print(f"score: {draw_score(perf, out, Path(args.events).stem)}")
    return Exit.OK
