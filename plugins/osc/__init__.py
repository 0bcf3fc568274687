"""The OSC view: fused bodies and piece events to named OSC targets.

Targets, and what each gets:

- the piece's OSC outputs with an address (``kind: osc, target: host:port``)
  and the command line's ``--osc HOST:PORT``: the piece events
  (``/stage/section``, ``/stage/trigger``, ``/stage/mapping``, ``/stage/zone``)
  and the piece's own ``OscOut`` messages for that output (the command line's
  targets take the outputs declared without an address). The skeleton stream
  (the Server-to-View API: the paper's ``/newUser /lostUser /jointCoordinates
  /handState``) goes only where the piece asks for it (``skeletons: true`` on an
  output), or to a command-line target that carries no piece output at all (a
  plain view, as in ``stage monitor --osc``);
- the views the engine already streams bodies to (rig ``views:``, ``--view``,
  ``/registerView``): the piece events only, so a Kuatro view that registers
  also hears the piece.

Events are sent at their time ``t`` (future events wait in the view, never in
the engine). With ``bundles=True`` every datagram is an OSC bundle whose
timetag is the engine time of its content as Unix time (NTP format), so a
receiver can order and align what it gets. Addresses: plugins/osc/encode.py
and docs/views.md.
"""

from __future__ import annotations

import heapq
import logging
import socket
from dataclasses import dataclass, field
from typing import Any, Sequence

from stage.frames import FusedFrame
from stage.errors import ConfigError
from stage.events import Event, OscOut, OutputDecl
from stage.network import parse_hostport
from stage.views import Status, View, ViewContext

from .encode import FrameEncoder, bundles, event_json_message, osc_out_message, piece_event_message


@dataclass
class Target:
    host: str
    port: int
    bodies: bool = True                       # the Server-to-View API (the skeleton stream)
    outputs: set[str] = field(default_factory=set)  # OscOut of these outputs
    sources: set[str] = field(default_factory=set)  # where it came from, for logs

    @property
    def address(self) -> tuple[str, int]:
        return self.host, self.port


class OscView(View):
    """OSC out: the Server-to-View API and piece events to targets from the piece and command line."""

    description = ("OSC out: Server-to-View API and piece events to named targets, "
                   "optionally in timetagged bundles")
    autostart = False
    max_pending_frames = 8

    def __init__(self, outputs: Sequence[OutputDecl] = (), targets: Sequence[Any] = (),
                 bundles: bool = False, registered: bool = True, json_events: bool = False,
                 max_bundle_bytes: int = 8192) -> None:
        """outputs: the piece's OSC outputs; targets: ``--osc`` (host, port) pairs or "host:port";
        registered: also send piece events to the engine's registered views."""
        self.bundles, self.registered, self.json_events = bundles, registered, json_events
        self.max_bundle_bytes = max_bundle_bytes
        self.targets: dict[tuple[str, int], Target] = {}
        osc_outputs = [o for o in outputs if o.kind == "osc"]
        self.declared = {o.name for o in osc_outputs}
        unaddressed = {o.name for o in osc_outputs if not o.target}
        for o in osc_outputs:
            if o.target:
                self._target(_address(o.target, f"output '{o.name}'"), f"piece output '{o.name}'",
                             {o.name}, o.skeletons)
        # a command-line target carries the outputs without an address: it gets the skeletons
        # if one of them asks, or if it carries none (then it is a plain view)
        cli_bodies = any(o.skeletons for o in osc_outputs if not o.target) or not unaddressed
        for t in targets:
            address = _address(t, "--osc") if isinstance(t, str) else (str(t[0]), int(t[1]))
            self._target(address, "command line", unaddressed | {"*"}, cli_bodies)
        self.unrouted = sorted(n for n in unaddressed if not targets)
        # no target takes the skeleton stream (piece events only, or registered views only):
        # no frame is worth encoding, nor waking this view's thread for
        self.wants_frames = any(t.bodies for t in self.targets.values())
        self._frames = FrameEncoder()
        self._timed: list[tuple[float, int, bytes, tuple]] = []   # (t, seq, message, routing)
        self._seq = 0
        self._engine_views: tuple[tuple[str, int], ...] = ()
        self._sock: socket.socket | None = None
        self._ctx: ViewContext | None = None
        self._warned: set[str] = set()
        self.counts = {"datagrams": 0, "messages": 0, "send_errors": 0, "dropped": 0}
        self.summary = ""

    def _target(self, address: tuple[str, int], source: str, outputs: set[str],
                bodies: bool) -> None:
        if address not in self.targets:
            self.targets[address] = Target(*address, bodies=bodies)
        target = self.targets[address]
        target.bodies = target.bodies or bodies
        target.outputs |= outputs
        target.sources.add(source)

    # ------------------------------------------------------------ life cycle
    def start(self, ctx: ViewContext) -> None:
        self._ctx = ctx
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("0.0.0.0", 0))
        self.summary = ", ".join(f"{h}:{p}" for h, p in self.targets) or "registered views only"
        for name in self.unrouted:
            ctx.log.warning("OSC output '%s' has no address in the piece and no --osc was "
                            "given: its messages are dropped (counted)", name)
        ctx.log.info("OSC to %s%s", self.summary, " (bundles)" if self.bundles else "")

    def stop(self) -> None:
        if self._sock is not None:
            now = self._ctx.now() if self._ctx else 0.0
            self.tick(now)   # what was due is sent; what lies further ahead is dropped with the show
            self._sock.close()
            self._sock = None

    # ------------------------------------------------------------ inputs
    def on_status(self, status: Status) -> None:
        self._engine_views = status.registered_views

    def on_frame(self, frame: FusedFrame) -> None:
        messages = self._frames.messages(frame)
        if not messages:
            return
        for target in self.targets.values():
            if target.bodies and target.address not in self._engine_views:
                self._send(messages, frame.t, target.address)

    def on_events(self, events: Sequence[Event]) -> None:
        for event in events:
            if isinstance(event, OscOut):
                try:
                    message = osc_out_message(event)
                except ValueError as exc:
                    self._drop(f"OscOut to '{event.output}' dropped (counted): {exc}")
                    continue
                self._schedule(event.t, message, ("out", event.output))
                continue
            message = piece_event_message(event)
            if message is None and self.json_events:
                message = event_json_message(event)
            if message is not None:
                self._schedule(event.t, message, ("piece",))

    def _schedule(self, t: float, message: bytes, routing: tuple) -> None:
        self._seq += 1
        heapq.heappush(self._timed, (t, self._seq, message, routing))

    def tick(self, now: float) -> float | None:
        due: dict[tuple[float, tuple[str, int]], list[bytes]] = {}
        while self._timed and self._timed[0][0] <= now:
            t, _, message, routing = heapq.heappop(self._timed)
            for address in self._route(routing):
                due.setdefault((t, address), []).append(message)
        for (t, address), messages in due.items():
            self._send(messages, t, address)
        return self._timed[0][0] if self._timed else None

    def _route(self, routing: tuple) -> list[tuple[str, int]]:
        if routing[0] == "piece":
            out = list(self.targets)
            if self.registered:
                out.extend(a for a in self._engine_views if a not in self.targets)
            return out
        output = routing[1]
        hits = [a for a, t in self.targets.items() if output in t.outputs]
        if not hits and output not in self.declared:
            hits = [a for a, t in self.targets.items() if "*" in t.outputs]
            if hits and output not in self._warned:
                self._warned.add(output)
                self._log("OscOut for undeclared output '%s' goes to the --osc targets", output)
        if not hits:  # (outputs known to have no target were named once, at start)
            self._drop(f"OSC output '{output}' has no target: give it one in the piece or --osc",
                       warn=output not in self.unrouted)
        return hits

    # ------------------------------------------------------------ wire
    def _send(self, messages: list[bytes], t: float, address: tuple[str, int]) -> None:
        if self._sock is None:
            return
        if self.bundles:
            wall = t + (self._ctx.wall_minus_clock if self._ctx else 0.0)
            datagrams = bundles(messages, wall, self.max_bundle_bytes)
        else:
            datagrams = messages
        for data in datagrams:
            try:
                self._sock.sendto(data, address)
                self.counts["datagrams"] += 1
            except OSError:  # an unreachable target must not stop the show; counted
                self.counts["send_errors"] += 1
        self.counts["messages"] += len(messages)

    def _drop(self, why: str, warn: bool = True) -> None:
        self.counts["dropped"] += 1
        if warn and why not in self._warned:
            self._warned.add(why)
            self._log("%s", why)

    def _log(self, fmt: str, *args: Any) -> None:
        (self._ctx.log if self._ctx else logging.getLogger("stage.views.osc")).warning(fmt, *args)

    def stats(self) -> dict[str, Any]:
        return {**self.counts, "targets": [f"{h}:{p}" for h, p in self.targets],
                "pending": len(self._timed), "summary": self.summary}


def _address(text: str, what: str) -> tuple[str, int]:
    try:
        return parse_hostport(str(text))
    except ValueError as exc:
        raise ConfigError(f"{what}: {exc}") from None
