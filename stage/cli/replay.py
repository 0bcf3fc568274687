"""``stage record`` and ``stage replay``."""

from __future__ import annotations

import logging
import math
import socket
import time

from ..errors import ConfigError
from ..sensors.replay import ReplaySource
from .common import Exit, hostport as _hostport, port as _port, positive as _positive

log = logging.getLogger("stage.replay")


def register(sub) -> dict:
    """``stage record`` and ``stage replay``."""
    rec = sub.add_parser("record", help="record every sensor datagram to a file (crash-safe)")
    rec.add_argument("--out", required=True, metavar="FILE", help="the recording to write")
    rec.add_argument("--port", type=_port, default=7770, help="UDP port to listen on (default 7770)")
    rec.add_argument("--host", default="0.0.0.0", help="address to listen on (default 0.0.0.0)")
    rec.add_argument("--forward", type=_hostport, metavar="HOST:PORT",
                     help="also pass every datagram on to a server (one socket per sensor)")
    rec.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds")
    rep = sub.add_parser("replay", help="play a recording to a server, or through an engine here")
    rep.add_argument("file", metavar="FILE", help="a recording (stage record, stage sim --out, "
                     "stage import)")
    rep.add_argument("--to", type=_hostport, default=None, metavar="HOST:PORT",
                     help="send to this server (default 127.0.0.1:7770)")
    pace = rep.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=_positive, default=1.0, metavar="X",
                      help="X times real time (default 1)")
    pace.add_argument("--max-speed", action="store_true", help="as fast as possible")
    rep.add_argument("--loop", action="store_true", help="start again at the end")
    rep.add_argument("--offline", action="store_true",
                     help="no network: run the engine here, deterministically, and print a summary")
    rep.add_argument("--rig", help="rig for --offline (default: the one stored in the recording)")
    rep.add_argument("--fused", metavar="OUT", help="with --offline: write the fused frames as "
                     "JSON lines (exact floats) to OUT")
    rep.add_argument("--no-self-healing", action="store_true",
                     help="with --offline: no live calibration (as `stage serve --no-self-healing`)")
    return {"record": cmd_record, "replay": cmd_replay}


def cmd_record(args) -> int:
    from ..app.signals import StopSignals
    from ..sensors.recording import RecordingWriter, check_output_path
    from ..sensors.receiver import open_udp
    check_output_path(args.out)
    sock = open_udp(args.host, args.port)
    sock.settimeout(0.2)
    meta = {"source": "stage record", "listen": f"{args.host}:{args.port}",
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    forward: dict[tuple[str, int], socket.socket] = {}
    senders: dict[tuple[str, int], int] = {}
    n = 0
    with StopSignals() as stop, RecordingWriter(args.out, meta) as writer:
        print(f"stage record: udp {args.host}:{sock.getsockname()[1]} -> {args.out}"
              + (f" (forwarding to {args.forward[0]}:{args.forward[1]})" if args.forward else "")
              + "; Ctrl-C stops", flush=True)
        end = None if args.duration is None else time.monotonic() + args.duration
        try:
            while not stop.event.is_set() and (end is None or time.monotonic() < end):
                try:
                    data, source = sock.recvfrom(65536)
                except socket.timeout:
                    continue
                except OSError as exc:
                    log.debug("recvfrom: %s", exc)
                    continue
                writer.write(time.monotonic(), source, data)
                n += 1
                senders[source] = senders.get(source, 0) + 1
                if args.forward:
                    out = forward.get(source)
                    if out is None:
                        out = forward[source] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                    try:
                        out.sendto(data, args.forward)
                    except OSError:
                        pass
        finally:
            sock.close()
            for out in forward.values():
                out.close()
    print(f"stage record: {n} datagram(s) from {len(senders)} sender(s) written to {args.out}",
          flush=True)
    return Exit.INTERRUPTED if stop.received else Exit.OK


def cmd_replay(args) -> int:
    from ..app.signals import StopSignals
    speed = math.inf if args.max_speed else args.speed
    if args.offline:
        if args.to is not None or args.loop:
            raise ConfigError("--offline runs the engine here: it takes no --to or --loop")
        return _replay_offline_cmd(args)
    if args.rig or args.fused or args.no_self_healing:
        raise ConfigError("--rig, --fused and --no-self-healing go with --offline")
    target = args.to or ("127.0.0.1", 7770)
    source = ReplaySource(args.file, speed=speed, loop=args.loop)
    info = source.info()
    print(f"stage replay: {args.file}: {info['records']} datagram(s), {info['duration_s']:.1f} s, "
          f"{len(info['sources'])} sender(s) -> udp {target[0]}:{target[1]} at "
          f"{'max speed' if args.max_speed else f'{speed:g}x'}"
          f"{', looping' if args.loop else ''}; Ctrl-C stops", flush=True)
    with StopSignals() as stop:
        started = time.perf_counter()
        source.start(target)
        while not stop.event.is_set() and not source.done.is_set():
            stop.event.wait(0.01 if args.max_speed else 0.2)
        source.stop()
        elapsed = time.perf_counter() - started
    pace = "" if args.loop or elapsed <= 0 else (
        f" in {elapsed:.2f} s ({info['duration_s'] / elapsed:.0f}x real time)")
    print(f"stage replay: sent {source.sent} datagram(s){pace}"
          + (f", {source.loops} loop(s)" if args.loop else ""), flush=True)
    return Exit.INTERRUPTED if stop.received else Exit.OK


def _replay_offline_cmd(args) -> int:
    """The engine here on a manual clock: the same show `stage play --replay --offline` runs."""
    from ..app.show import Show, ShowOptions, summary
    opts = ShowOptions(replay=args.file, offline=True, rig=args.rig, fused=args.fused,
                       self_healing=not args.no_self_healing, plugins=False)
    show = Show(opts)
    info = show.source.info()  # type: ignore[union-attr]
    started = time.perf_counter()
    result = show.run()
    elapsed = time.perf_counter() - started
    ratio = info["duration_s"] / elapsed if elapsed > 0 else math.inf
    print(f"stage replay: {result.datagrams_fed} datagram(s), {info['duration_s']:.1f} s of "
          f"recording in {elapsed:.2f} s ({ratio:.0f}x real time); {summary(result.stats)}; "
          f"{len(show.engine.persons)} person(s) at the end", flush=True)  # type: ignore[union-attr]
    if info["ignored_bytes"]:
        print(f"stage replay: {info['ignored_bytes']} byte(s) after the last whole record "
              "ignored (a cut recording)", flush=True)
    return Exit.OK
