"""The ``stage`` command: one entry point, one-line errors, tracebacks only with --debug.

Each subcommand lives in a module of this package with ``register(subparsers)
-> {name: function}``; a function turns its parsed arguments into a call of
the application layer (``stage.app``) and returns an exit status. Global
options (--debug, --quiet) go before or after the subcommand.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from typing import Callable, Sequence

from .. import __version__
from ..errors import BadInput, StageError
from .common import Exit

log = logging.getLogger("stage")

#: Modules that add subcommands: each has ``register(subparsers) -> {name: function}``.
COMMAND_MODULES: list[str] = [
    "stage.cli.serve",
    "stage.cli.views",
    "stage.cli.play",
    "stage.cli.compose",
    "stage.cli.calibrate",
    "stage.cli.sim",
    "stage.cli.replay",
    "stage.cli.importers",
    "stage.cli.client",
    "stage.cli.analyze",
]

_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}

_GLOBAL = (("--debug", "show tracebacks and debug logs"),
           ("--quiet", "warnings and errors only"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stage", description="Music and dance performance with multi-sensor body tracking.")
    parser.add_argument("--version", action="version", version=f"stage {__version__}")
    for flag, text in _GLOBAL:
        parser.add_argument(flag, action="store_true", help=text)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            _COMMANDS.update(importlib.import_module(name).register(sub))
        except Exception as exc:  # one broken command module must not take the others down
            print(f"stage: warning: commands of {name} unavailable: {exc}", file=sys.stderr)
    for subparser in sub.choices.values():
        # accepted after the subcommand too; SUPPRESS keeps a value given before it
        for flag, text in _GLOBAL:
            subparser.add_argument(flag, action="store_true", default=argparse.SUPPRESS,
                                   help=text)
    return parser


def exit_code(exc: StageError) -> Exit:
    """Bad input (a command line, a rig, a piece, a recording the user named) is 2, else 1."""
    return Exit.BAD_INPUT if isinstance(exc, BadInput) else Exit.FAILURE


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                        datefmt="%Y-%m-%d %H:%M:%S", stream=sys.stderr)
    if args.command is None:
        parser.print_help()
        return Exit.BAD_INPUT
    try:
        return int(_COMMANDS[args.command](args))
    except StageError as exc:
        if args.debug:
            raise
        print(f"stage: {exc}", file=sys.stderr)
        return exit_code(exc)
    except KeyboardInterrupt:
        return Exit.INTERRUPTED
    except BrokenPipeError:  # `stage ... | head` closed the pipe: not an error worth a traceback
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return Exit.OK
    except Exception as exc:  # a bug: one line, the traceback with --debug
        if args.debug:
            raise
        log.debug("internal error", exc_info=True)
        print(f"stage: internal error: {type(exc).__name__}: {exc} (run with --debug for the "
              "traceback, and please report it)", file=sys.stderr)
        return Exit.FAILURE


if __name__ == "__main__":
    sys.exit(main())
