"""What every subcommand shares: exit codes, argument types, the options of a show.

Argument types raise ``argparse.ArgumentTypeError``, so a mistyped value is
one line from argparse and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import math
from enum import IntEnum
from typing import TYPE_CHECKING

from ..network import parse_hostport

if TYPE_CHECKING:
    from ..app.show import ShowOptions


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


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None


def positive(text: str) -> float:
    """A number greater than zero (seconds, speeds)."""
    value = _number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"'{text}' must be greater than 0")
    return value


def non_negative(text: str) -> float:
    """A finite number at least 0 (seconds ahead)."""
    value = _number(text)
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"'{text}' must be a number of seconds, 0 or more")
    return value


def add_show_options(p: argparse.ArgumentParser, *, status: bool = True) -> None:
    """Options every live show takes, with the same meaning everywhere."""
    p.add_argument("--view", action="append", type=hostport, default=[], metavar="HOST:PORT",
                   help="also send fused bodies to this view (Server-to-View OSC, repeatable)")
    p.add_argument("--view-forecast", type=non_negative, metavar="S", dest="view_forecast",
                   help="the views (--view and the rig's) get each body predicted S seconds "
                        "past its capture time (the rig's forecast: views_s; 0: as measured; "
                        "at most forecast: max_s, 0.2 s; docs/anticipation.md)")
    p.add_argument("--duration", type=positive, metavar="S", help="stop after S seconds")
    p.add_argument("--no-self-healing", action="store_true",
                   help="do not calibrate uncalibrated sensors or re-calibrate bumped ones")
    p.add_argument("--no-plugins", action="store_true",
                   help="do not run the installed third-party views")
    p.add_argument("--fused", metavar="OUT.jsonl",
                   help="write every fused frame as a JSON line (exact floats)")
    if status:
        p.add_argument("--status", action="store_true",
                       help="print a status line every second")
    p.add_argument("--alert-command", metavar="CMD",
                   help="run CMD when a sensor, view, synth or the engine has been down or "
                        "suspect for --alert-after seconds (and when it recovers); the alert is "
                        "in STAGE_ALERT_* environment variables (default: the rig's alerts)")
    p.add_argument("--alert-osc", type=hostport, metavar="HOST:PORT",
                   help="send /stage/alert there when something is down (see docs/osc-api.md)")
    p.add_argument("--alert-after", type=positive, metavar="S",
                   help="seconds down or suspect before an alert (default: the rig's, else 60)")


def show_options(args: argparse.Namespace, **fields) -> "ShowOptions":
    """ShowOptions from the options ``add_show_options`` added, plus ``fields``."""
    from ..app.show import ShowOptions
    osc = getattr(args, "alert_osc", None)
    common = dict(views=list(args.view), view_forecast_s=getattr(args, "view_forecast", None),
                  duration=args.duration,
                  self_healing=not args.no_self_healing, plugins=not args.no_plugins,
                  fused=args.fused, status_line=getattr(args, "status", False),
                  alert_command=getattr(args, "alert_command", None),
                  alert_osc=None if osc is None else f"{osc[0]}:{osc[1]}",
                  alert_after_s=getattr(args, "alert_after", None),
                  # a command owns its process: start-up's objects can be set aside
                  freeze_heap=True)
    return ShowOptions(**{**common, **fields})
