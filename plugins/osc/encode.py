"""OSC encoding of fused frames and piece events (pure functions over bytes).

Server-to-View (paper 4.1.3), the same bytes the engine sends to registered views:

    /newUser id x y z            /lostUser id
    /jointCoordinates id (jointName x y z confidence)*
    /handState id hand state     (when a hand's voted state changes)

Piece events (stage additions, new addresses only):

    /stage/section  s section  i index  s previous ("" at the start)  s cause
    /stage/trigger  s section  s trigger  i person (-1: none)  s joint ("": none)  f value (0: none)
    /stage/mapping  s mapping  f value
    /stage/zone     s zone  i occupied (1/0)  i person*
    /stage/event    s json     (option ``json_events``: every other event as one JSON object)
"""

from __future__ import annotations

import json
import math
from typing import Any, Iterable

import numpy as np

from stage.frames import Body, FusedFrame
from stage.events import (Event, MappingValue, OscOut, SectionChange, TriggerFired, ZoneState,
                          to_json)
from stage.sensors.protocol import (encode_bundle, encode_message, encode_view_hand_state,
                                    encode_view_joints, encode_view_lost_user, encode_view_new_user)


def piece_event_message(event: Event) -> bytes | None:
    """The OSC message of a piece event, or None for events that are not sent this way."""
    if isinstance(event, SectionChange):
        return encode_message("/stage/section", event.section, int(event.index),
                              event.previous or "", event.cause or "")
    if isinstance(event, TriggerFired):
        value = 0.0 if event.value is None or not math.isfinite(event.value) else float(event.value)
        return encode_message("/stage/trigger", event.section, event.trigger,
                              -1 if event.person is None else int(event.person),
                              event.joint or "", value)
    if isinstance(event, MappingValue):
        if not math.isfinite(event.value):
            return None
        return encode_message("/stage/mapping", event.mapping, float(event.value))
    if isinstance(event, ZoneState):
        return encode_message("/stage/zone", event.zone, int(bool(event.occupied)),
                              *(int(p) for p in event.persons))
    return None


def event_json_message(event: Event) -> bytes:
    return encode_message("/stage/event", json.dumps(to_json(event), separators=(",", ":")))


def osc_out_message(event: OscOut) -> bytes:
    """The piece's own message; ValueError when an argument cannot be sent as OSC."""
    if not isinstance(event.address, str) or not event.address.startswith("/"):
        raise ValueError(f"OSC address {event.address!r} must start with '/'")
    return encode_message(event.address, *(_arg(a) for a in event.args))


def _arg(value: Any) -> int | float | str:
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (int, np.integer)):
        v = int(value)
        if not -2**31 <= v < 2**31:
            raise ValueError(f"integer {v} does not fit an OSC int32")
        return v
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, str):
        return value
    raise ValueError(f"cannot send {type(value).__name__} {value!r} as an OSC argument")


class FrameEncoder:
    """Server-to-View messages for successive frames; remembers the hand states sent."""

    def __init__(self) -> None:
        self._hands: dict[int, list[int]] = {}

    def messages(self, frame: FusedFrame) -> list[bytes]:
        out: list[bytes] = []
        new = set(frame.new)
        for pid in frame.updated:
            body = frame.bodies.get(pid)
            if body is None:
                continue
            if pid in new or pid not in self._hands:
                out.append(encode_view_new_user(pid, body.position))
                self._hands[pid] = [-1, -1]
            if body.sensors:  # an orphan kept for its grace period has no fresh joints
                out.append(encode_view_joints(pid, body.joints, body.conf))
            out.extend(self._hand_changes(pid, body))
        for pid in frame.lost:
            self._hands.pop(pid, None)
            out.append(encode_view_lost_user(pid))
        return out

    def _hand_changes(self, pid: int, body: Body) -> Iterable[bytes]:
        sent = self._hands[pid]
        for hand in (0, 1):
            if int(body.hands[hand]) != sent[hand]:
                sent[hand] = int(body.hands[hand])
                yield encode_view_hand_state(pid, hand, body.hands[hand])


def bundles(messages: list[bytes], timetag: float | None, max_bytes: int = 8192) -> list[bytes]:
    """``messages`` as timetagged bundles of at most ``max_bytes`` each (one message may exceed it)."""
    out: list[bytes] = []
    chunk: list[bytes] = []
    size = 16
    for m in messages:
        if chunk and size + 4 + len(m) > max_bytes:
            out.append(encode_bundle(chunk, timetag))
            chunk, size = [], 16
        chunk.append(m)
        size += 4 + len(m)
    if chunk:
        out.append(encode_bundle(chunk, timetag))
    return out


def address_of(message: bytes) -> str:
    return message[:message.index(b"\0")].decode("ascii", "replace")

