"""Where a live engine datagram's CPU goes, by its place in what the engine thread took at once.

``bench_engine_parts.py`` times the engine's parts in process, back to back or paced, with a
transport that sends nothing and no calibrator. This is the same table from the running
server: a wrapper around the real CLI (``stage serve`` or ``stage play``) for
``bench_engine.py --server-cmd``, which wraps the same parts (``bench_engine_parts.PARTS``)
plus the engine thread's ``sendto`` calls, on the engine thread only, and splits each part's
CPU by where its datagram was in what the engine thread took from the queue at once
(``Engine.process_taken``): the first of several (it meets caches the 33 ms since the last
burst left cold), one in the middle, and the last or only one (which votes the hands and
calls the listeners); what the engine thread does between datagrams (the tick) has a column
of its own, per datagram. Each ``Engine.process`` is also timed on the wall clock: the
difference from its CPU is what the thread waited (the GIL, mostly, given up at each send).

Run (sensors in step, the server `stage serve`; the table is written every 3 s)::

    STAGE_LIVE_PARTS=/tmp/parts.txt python bench/bench_engine.py --configs 6x6 \\
        --modes aligned --no-offline --duration 10 --live \\
        --server-cmd "python bench/live_parts.py serve"

``play PIECE --midi-file F`` instead of ``serve`` runs the performer's command. The wrappers
cost about 1 us a call (``bench_engine_parts``'s reference), so the server reads slower than
unwrapped: compare the parts with each other, not the totals with another run.
"""

from __future__ import annotations

import collections
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_engine_parts  # noqa: E402

PLACES = ("first of several", "middle", "last or alone", "between (tick)")
#: the place of work done outside any datagram (the tick), shown per datagram of all places
BETWEEN = 3
SEND = "sendto (each view's datagram)"
#: what ``stage play`` adds on the engine thread, timed beside bench_engine_parts' parts
EXTRA = (("stage.engine.callbacks", "Callbacks", "call", "callbacks (listeners, observers)"),
         ("stage.piece.runtime", "PieceRuntime", "_on_frame", "  the piece, a frame"),
         ("stage.engine.people", "People", "_forecast_bodies", "    forecasts (as read)"))


class Parts:
    """Per (part, place): CPU ns and calls; per place: datagrams, CPU and wall of a process."""

    def __init__(self) -> None:
        self.cpu: collections.Counter = collections.Counter()
        self.calls: collections.Counter = collections.Counter()
        self.datagrams: collections.Counter = collections.Counter()
        self.wall: collections.Counter = collections.Counter()
        self.thread: threading.Thread | None = None
        self.place = BETWEEN
        self.k = 0

    def table(self) -> str:
        n = [self.datagrams[p] or 1 for p in range(3)]
        n.append(sum(self.datagrams[p] for p in range(3)) or 1)
        places = range(len(PLACES))
        lines = [f"{'part, us a datagram':34s}" + "".join(f"{p:>18s}" for p in PLACES)]
        lines.append(f"{'datagrams':34s}"
                     + "".join(f"{self.datagrams[p]:18d}" for p in range(3)) + f"{'(all)':>18s}")
        lines.append(f"{'process, wall clock':34s}"
                     + "".join(f"{self.wall[p] / n[p] / 1e3:18.1f}" for p in range(3)))
        labels = [label for *_, label in bench_engine_parts.PARTS + EXTRA] + [SEND]
        for label in labels:
            if not any(self.calls[(label, p)] for p in places):
                continue
            lines.append(f"{label:34s}" + "".join(
                f"{self.cpu[(label, p)] / n[p] / 1e3:11.1f} ({self.calls[(label, p)] / n[p]:4.1f})"
                for p in places))
        lines.append("(CPU us a datagram, calls a datagram in brackets; nested parts are included"
                     " in their callers)")
        return "\n".join(lines) + "\n"


def install(parts: Parts) -> None:
    from stage.engine import engine as engine_mod
    from stage.engine import jit

    process_taken, process = engine_mod.Engine.process_taken, engine_mod.Engine.process

    def taken(self, batch):
        if parts.thread is None:        # the first take: this is the engine thread
            parts.thread = threading.current_thread()
            jit.ready()
            timed = [p for p in bench_engine_parts.PARTS + EXTRA
                     if p[:3] != ("stage.engine.engine", "Engine", "process")]  # (below)
            bench_engine_parts._wrap(
                parts.cpu, parts.calls, timed + [("stage.sensors.receiver", "UdpTransport",
                                                  "send", SEND)],
                key=lambda label: (label, parts.place),
                when=lambda: threading.current_thread() is parts.thread)
        parts.k = 0
        return process_taken(self, batch)

    def one(self, batch, votes=True):
        if threading.current_thread() is not parts.thread:
            return process(self, batch, votes)
        place = parts.place = 2 if votes else (0 if parts.k == 0 else 1)
        c, w = time.thread_time_ns(), time.perf_counter_ns()
        try:
            return process(self, batch, votes)
        finally:
            parts.cpu[("process (one datagram)", place)] += time.thread_time_ns() - c
            parts.calls[("process (one datagram)", place)] += 1
            parts.wall[place] += time.perf_counter_ns() - w
            parts.datagrams[place] += 1
            parts.k += 1
            parts.place = BETWEEN

    engine_mod.Engine.process_taken = taken
    engine_mod.Engine.process = one


def run_cli(table, out: str, name: str, argv: list[str]) -> int:
    """The real CLI (``argv``: ``serve ...`` or ``play ...``) with ``table()`` written to
    ``out`` every 3 s on a thread of its own (live_parts.py, live_switch.py)."""
    def write() -> None:
        while True:
            time.sleep(3.0)
            tmp = out + ".tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(table())
            os.replace(tmp, out)
    threading.Thread(target=write, name=name, daemon=True).start()
    from stage.cli.main import main as cli
    return cli(["--quiet", *argv])


def main() -> int:
    parts = Parts()
    install(parts)
    return run_cli(parts.table, os.environ.get("STAGE_LIVE_PARTS", "/tmp/stage-live-parts.txt"),
                   "live-parts", sys.argv[1:])


if __name__ == "__main__":
    sys.exit(main())
