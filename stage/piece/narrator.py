"""What a performer reads: the `stage check` summary and the `stage play` console.

Plain ASCII on purpose: a console with LANG=C must not crash mid-show on an arrow.
"""

from __future__ import annotations

import json
import queue
import sys
from typing import TextIO

from ..events import Event, to_json
from .model import Piece


def check_summary(piece: Piece, path: str) -> list[str]:
    """`stage check`'s report: the piece, its outputs and zones, then one block per section."""
    out = [f"{path}: ok -- \"{piece.title}\"" + (f" ({piece.composer})" if piece.composer else "")
           + f", {len(piece.sections)} section(s), {len(piece.zones)} zone(s), "
           f"{len(piece.phrases)} phrase(s)"]
    outputs = ", ".join(
        f"{o.name} ({o.kind}{' ' + o.target if o.target else ''}"
        + (f", {piece.overlap.get(o.name, 'queue')}" if o.kind == "midi" else "")
        + (", with skeletons" if o.skeletons else "") + ")" for o in piece.outputs.values())
    out.append(f"  outputs: {outputs}")
    e = piece.ending
    out.append(f"  time: {piece.tempo:g} bpm" + (f", {piece.meter}" if piece.meter else "")
               + f", quantize {piece.quantize}; ending: the last notes fade for {e.fade:g} s, "
               f"then ring for {e.ring:g} s")
    for zone in piece.zones.values():
        out.append(f"  zone {zone.name}: {zone.describe()}")
    if piece.rehearsal:
        out.append(f"  rehearsal scenario: {piece.rehearsal}")
    for s in piece.sections:
        start = "  (start)" if s.name == piece.start else ""
        out.append(f"  {s.index + 1}. {s.name}: {len(s.phrases)} phrase(s), {len(s.triggers)} "
                   f"trigger(s), {len(s.mappings)} mapping(s){start}")
        out.extend(_rules(s.triggers, s.mappings))
    if piece.triggers or piece.mappings:
        out.append(f"  everywhere: {len(piece.triggers)} trigger(s), {len(piece.mappings)} "
                   "mapping(s)")
        out.extend(_rules(piece.triggers, piece.mappings))
    return out


def _rules(triggers, mappings) -> list[str]:
    out = []
    for trig in triggers:
        gates = [f"cooldown {trig.cooldown:g} s"] if trig.cooldown else []
        if trig.dwell:
            gates.append(f"dwell {trig.dwell:g} s")
        if trig.after:
            gates.append(f"after {trig.after:g} s")
        if trig.once:
            gates.append("once")
        if trig.probability < 1:
            gates.append(f"probability {trig.probability:g}")
        if trig.performer != "any":
            gates.append(f"performer {trig.performer}")
        out.append(f"       '{trig.name}': {trig.describe()}"
                   + (f"  ({', '.join(gates)})" if gates else ""))
    for m in mappings:
        out.append(f"       '{m.name}': {m.describe()}")
    return out


class Narrator:
    """The narrator of a piece: lines queued from the engine thread, printed elsewhere.

    ``__call__`` (the runtime's narrator) only enqueues; ``print_pending`` runs on
    the main thread, so a slow terminal never holds up the engine.
    """

    def __init__(self, out: TextIO | None = None, origin: float = 0.0, direct: bool = False) -> None:
        self.out = out or sys.stdout
        self.origin = origin
        self.direct = direct
        self.lines: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.printed = 0

    def __call__(self, t: float, text: str) -> None:
        line = f"{t - self.origin:7.1f} s  {text}"
        if self.direct:
            self._print(line)
        else:
            self.lines.put(line)

    def say(self, text: str) -> None:
        self._print(text)

    def print_pending(self) -> None:
        while True:
            try:
                line = self.lines.get_nowait()
            except queue.Empty:
                return
            self._print(line)

    def _print(self, line: str) -> None:
        try:
            print(line, file=self.out, flush=True)
        except UnicodeEncodeError:
            print(line.encode("ascii", "replace").decode("ascii"), file=self.out, flush=True)
        except (BrokenPipeError, ValueError):
            return  # the console went away; the show goes on
        self.printed += 1


class EventsFile:
    """``--events OUT.jsonl``: every event as one JSON line (``stage.events.to_json``).

    An EventSink; written on the engine thread, flushed after each batch so a
    crash loses at most the batch being written.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self.handle = open(path, "w", encoding="utf-8")
        self.count = 0

    def emit(self, events: list[Event]) -> None:
        if self.handle.closed:
            return
        for event in events:
            self.handle.write(json.dumps(to_json(event), separators=(",", ":")) + "\n")
        self.count += len(events)
        self.handle.flush()

    def close(self) -> None:
        if not self.handle.closed:
            self.handle.close()
