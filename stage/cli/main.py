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
from ..errors import BadInput, ConfigError, StageError
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
    "stage.cli.service",
]

_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}

_GLOBAL = (("--debug", "show tracebacks and debug logs"),
           ("--quiet", "warnings and errors only"))
#: a log file rotates at this size, keeping this many old ones (weeks of running)
LOG_FILE_BYTES = 10 << 20
LOG_FILE_KEEP = 5
_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
_DATE = "%Y-%m-%d %H:%M:%S"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stage", description="Music and dance performance with multi-sensor body tracking.")
    parser.add_argument("--version", action="version", version=f"stage {__version__}")
    for flag, text in _GLOBAL:
        parser.add_argument(flag, action="store_true", help=text)
    parser.add_argument("--log-file", metavar="PATH",
                        help=f"also log to PATH, rotated at {LOG_FILE_BYTES >> 20} MB "
                             f"({LOG_FILE_KEEP} old files kept)")
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
        subparser.add_argument("--log-file", metavar="PATH", default=argparse.SUPPRESS,
                               help="also log to PATH (rotated)")
    return parser


class _JournalFormatter(logging.Formatter):
    """systemd's journal dates each line itself and reads a ``<N>`` prefix as its priority."""

    _PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
                 logging.CRITICAL: 2}

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        priority = self._PRIORITY.get(record.levelno, 6)
        return "\n".join(f"<{priority}>{line}" for line in text.splitlines() or [""])


def setup_logging(level: int, log_file: str | None = None) -> None:
    """stderr (to journald without our own dates, when systemd runs us), plus a rotating
    file. Every line outside the journal carries the full date: a show runs for weeks."""
    root = logging.getLogger()
    for handler in [h for h in root.handlers if getattr(h, "_stage", False)]:
        root.removeHandler(handler)  # main() run again in one process (tests)
        handler.close()
    if not root.handlers:  # as logging.basicConfig: someone else (pytest) configured it
        root.setLevel(level)
        err = logging.StreamHandler(sys.stderr)
        if os.environ.get("JOURNAL_STREAM") and _stderr_is_journal():
            err.setFormatter(_JournalFormatter("%(levelname)s %(name)s: %(message)s"))
        else:
            err.setFormatter(logging.Formatter(_FORMAT, _DATE))
        err._stage = True  # type: ignore[attr-defined]
        root.addHandler(err)
    if log_file:
        from logging.handlers import RotatingFileHandler
        try:
            handler = RotatingFileHandler(log_file, maxBytes=LOG_FILE_BYTES,
                                          backupCount=LOG_FILE_KEEP, encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"--log-file {log_file}: cannot write: {exc.strerror}") from None
        handler.setFormatter(logging.Formatter(_FORMAT, _DATE))
        handler.setLevel(level)
        handler._stage = True  # type: ignore[attr-defined]
        root.addHandler(handler)
        if root.level > level or root.level == logging.NOTSET:
            root.setLevel(level)


def _stderr_is_journal() -> bool:
    """JOURNAL_STREAM is "device:inode" of the journal's stream (systemd.exec(5))."""
    try:
        device, inode = (int(v) for v in os.environ["JOURNAL_STREAM"].split(":"))
        st = os.fstat(sys.stderr.fileno())
        return st.st_dev == device and st.st_ino == inode
    except (KeyError, ValueError, OSError, AttributeError):
        return False


def exit_code(exc: StageError) -> Exit:
    """Bad input (a command line, a rig, a piece, a recording the user named) is 2, else 1."""
    return Exit.BAD_INPUT if isinstance(exc, BadInput) else Exit.FAILURE


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO
    if args.command is None:
        parser.print_help()
        return Exit.BAD_INPUT
    try:
        setup_logging(level, getattr(args, "log_file", None))
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
