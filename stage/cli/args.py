"""Argument types shared by the subcommands: errors read as one line from argparse."""

from __future__ import annotations

import argparse

from ..rig import parse_hostport


def hostport(text: str) -> tuple[str, int]:
    """'HOST:PORT' or 'PORT' -> (host, port)."""
    try:
        return parse_hostport(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def positive(text: str) -> float:
    """A number greater than zero (seconds, speeds)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"'{text}' must be greater than 0")
    return value
