"""What every subcommand shares: exit codes, argument types, and running a show.

Argument types raise ``argparse.ArgumentTypeError``, so a mistyped value is
one line from argparse and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
from enum import IntEnum

from ..network import parse_hostport


class Exit(IntEnum):
    OK = 0
    FAILURE = 1      # something went wrong at run time (a port in use, a peer that did not answer)
    BAD_INPUT = 2    # the user's command line or files are wrong
    INTERRUPTED = 130  # Ctrl-C or SIGTERM


def hostport(text: str) -> tuple[str, int]:
    """'HOST:PORT' or 'PORT' -> (host, port)."""
    try:
        return parse_hostport(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def port(text: str) -> int:
    """A UDP or TCP port, 0-65535 (0: any free port)."""
    if not text.strip().isdigit() or not 0 <= int(text) <= 65535:
        raise argparse.ArgumentTypeError(f"'{text}' is not a port (0-65535)")
    return int(text)


def positive(text: str) -> float:
    """A number greater than zero (seconds, speeds)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"'{text}' must be greater than 0")
    return value


def finished(interrupted: bool, signals) -> Exit:
    """The exit status of a show: 130 when a signal (Ctrl-C, SIGTERM) stopped it."""
    return Exit.INTERRUPTED if signals.received is not None else Exit.OK
