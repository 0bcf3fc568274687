"""Mappings at play time: a joint's value, ranged, curved and smoothed, to a control."""

from __future__ import annotations

import math
from typing import Any

from ..analysis.features import ANGLE_JOINTS, angle_at
from ..events import ControlChange, MappingValue, OscOut
from .actions import holds
from .model import Mapping
from .triggers import Person


class MappingRun:
    """A mapping with its state: smoothed value, last time, last sent value."""

    __slots__ = ("mapping", "smoothed", "last_t", "sent", "active")

    def __init__(self, mapping: Mapping) -> None:
        self.mapping = mapping
        self.smoothed: float | None = None
        self.last_t = 0.0
        self.sent: float | None = None
        self.active = False

    def update(self, rt: Any, t: float) -> None:
        """One frame: measure, condition, range, curve, smoothing; send on change."""
        m = self.mapping
        chosen = rt._select(m.performer)
        value = None
        if chosen:
            p = chosen[0]
            if m.condition is None or holds(m.condition, p, m.joint):
                value = measure(m, p)
                if value is None and self.active:
                    return  # joint unseen this frame: hold the last value
        if value is None:
            if self.active and m.otherwise is not None:
                self.send(rt._out, t, m.otherwise, force=True)
            self.active, self.smoothed = False, None
            return
        lo, hi = m.in_range
        u = min(1.0, max(0.0, (value - lo) / (hi - lo)))
        if self.smoothed is None or m.smoothing <= 0.0:
            self.smoothed = u
        else:
            alpha = 1.0 - math.exp(-max(0.0, t - self.last_t) / m.smoothing)
            self.smoothed += alpha * (u - self.smoothed)
        self.last_t = t
        self.active = True
        o_lo, o_hi = m.out_range
        self.send(rt._out, t, o_lo + m.curve(self.smoothed) * (o_hi - o_lo))

    def send(self, events: list, t: float, out: float, force: bool = False) -> None:
        """Send ``out`` (the output value) if it changed, with its MappingValue."""
        m = self.mapping
        if m.kind == "cc":
            value = int(min(127, max(0, round(out))))
            if value == self.sent and not force:
                return
            self.sent = value
            events.append(ControlChange(t, m.output, m.channel - 1, m.control, value))
            events.append(MappingValue(t, m.name, float(value)))
            return
        span = abs(m.out_range[1] - m.out_range[0]) or 1.0
        if self.sent is not None and abs(out - self.sent) < 1e-4 * span and not force:
            return
        self.sent = out
        events.append(OscOut(t, m.output, m.address, (float(out),)))
        events.append(MappingValue(t, m.name, float(out)))


def measure(m: Mapping, p: Person) -> float | None:
    """The mapping's input for ``p`` this frame (metres, m/s or degrees), None if unseen."""
    if m.measure == "speed":
        return p.speed(m.joint) if p.xyz(m.joint) is not None else None
    pos = p.xyz(m.joint)
    if pos is None:
        return None
    if m.measure == "angle":
        return angle_at({k: p.xyz(k) for k in ANGLE_JOINTS[m.joint]}, m.joint)
    if m.measure == "distance":
        other = p.xyz(m.to_joint)
        if other is None:
            return None
        return math.dist(pos, other)
    return pos[{"x": 0, "y": 1, "height": 1, "z": 2}[m.measure]]

