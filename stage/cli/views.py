"""``stage plugins`` and ``stage monitor``.

``stage plugins`` lists every installed view and source plugin, the
distribution and module it comes from, and whether it loads (importing it,
never starting it). ``stage monitor`` runs the server (from a rig, or the demo
with virtual Kinects) with the live web monitor and the installed views.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Callable

from ..errors import StageError
from ..views.base import GROUP
from ..views.host import MONITOR_PORT
from ..views.loader import GROUPS, PluginInfo, discover_all
from .common import Exit, add_show_options, hostport, port, show_options

log = logging.getLogger("stage.views")


def register(sub: argparse._SubParsersAction) -> dict[str, Callable[[argparse.Namespace], int]]:
    plugins = sub.add_parser("plugins", help="list installed views and sources and whether they load")
    plugins.add_argument("--json", action="store_true", help="machine-readable output")
    plugins.add_argument("--check", action="store_true",
                         help="exit with status 1 when a plugin fails to load")

    mon = sub.add_parser("monitor", help="the server with the live web monitor (and installed views)")
    mon.add_argument("--rig", help="rig file (sensors, calibration, views, settings)")
    mon.add_argument("--host", help="address to listen on for sensors (default: rig's)")
    mon.add_argument("--port", type=port, help="UDP port for sensors (default: rig's, else 7770)")
    mon.add_argument("--http", type=port, default=MONITOR_PORT, metavar="PORT",
                     help=f"the monitor's web port on localhost (default {MONITOR_PORT}; 0: any)")
    mon.add_argument("--bind", default="127.0.0.1", metavar="ADDRESS",
                     help="serve the page on this address (default 127.0.0.1; 0.0.0.0 shows it "
                          "to the whole network)")
    mon.add_argument("--demo", type=int, nargs="?", const=3, choices=range(1, 7), metavar="N",
                     help="feed the engine with N virtual Kinects around one dancer (default 3)")
    mon.add_argument("--seed", type=int, default=1, help="the demo's seed")
    mon.add_argument("--osc", action="append", type=hostport, default=[], metavar="HOST:PORT",
                     help="the OSC view: bodies and piece events to this target (repeatable)")
    mon.add_argument("--relay", action="append", type=hostport, default=[], metavar="HOST:PORT",
                     help="relay fused bodies to another stage server (repeatable)")
    add_show_options(mon)
    return {"plugins": cmd_plugins, "monitor": cmd_monitor}


def _origin(info: PluginInfo) -> str:
    dist = f"{info.distribution} {info.version}" if info.distribution else "?"
    return dist


def cmd_plugins(args: argparse.Namespace) -> int:
    found = discover_all()
    failed = [i for infos in found.values() for i in infos if not i.loaded]
    if args.json:
        print(json.dumps({group: [i.as_dict() | ({"autostart": bool(getattr(i.obj, "autostart", True))}
                                                 if group == GROUP and i.loaded else {})
                                  for i in infos]
                          for group, infos in found.items()}, indent=2))
    else:
        for group, infos in found.items():
            print(f"{GROUPS[group]} ({group})")
            if not infos:
                print("  (none installed)")
            rows = []
            for i in infos:
                if i.loaded:
                    starts = ""
                    if group == GROUP:
                        starts = "auto" if getattr(i.obj, "autostart", True) else "on request"
                    rows.append((i.name, "loaded", starts, _origin(i), i.value, i.description))
                else:
                    rows.append((i.name, "FAILED", "", _origin(i), i.value, i.error or ""))
            columns = [k for k in range(5) if any(r[k] for r in rows)]  # sources: no 'starts'
            widths = {k: max(len(r[k]) for r in rows) for k in columns}
            for r in rows:
                print("  " + "  ".join(r[k].ljust(widths[k]) for k in columns) + "  " + r[5])
            print()
        print("'auto' views run in every show; 'on request' ones when the command line or the "
              "piece asks (--midi, --osc, --monitor, --relay).")
        if failed:
            print(f"{len(failed)} plugin(s) failed to load; `stage --debug plugins` shows why "
                  "in full.", file=sys.stderr)
    return Exit.FAILURE if failed and args.check else Exit.OK


def cmd_monitor(args: argparse.Namespace) -> int:
    from ..app.show import Show, summary
    from ..app.signals import StopSignals
    fields: dict = {"monitor": args.http, "monitor_bind": args.bind, "osc": list(args.osc),
                    "relay": list(args.relay)}
    if args.demo:
        fields.update(sim="demo", source_options={"sensors": args.demo}, seed=args.seed,
                      host="127.0.0.1", port=args.port or 0)
    else:
        fields.update(rig=args.rig, host=args.host, port=args.port)
    with StopSignals() as signals:
        show = Show(show_options(args, **fields), stop_event=signals.event)
        show.start()
        try:
            host = show.host
            url = host.monitor_url if host is not None else None
            if url is None:
                slot = next((s for s in host.slots if s.name == "monitor"), None) if host else None
                why = (slot.error or "").split(": ", 2)[-1] if slot is not None else (
                    "the monitor plugin is not installed (see `stage plugins`)")
                raise StageError(f"the monitor did not start: {why}")
            address = f"{show.address[0]}:{show.address[1]}"
            print(f"stage monitor: open {url} in a browser; sensors and views on udp "
                  f"{address}. Ctrl-C stops.", flush=True)
            for line in host.summary():
                if not line.startswith("monitor"):
                    log.info("view %s", line)
            show.wait()
        finally:
            result = show.stop()
        print(f"stage monitor: done; {summary(result.stats)}", flush=True)
    return Exit.INTERRUPTED if signals.received else Exit.OK
