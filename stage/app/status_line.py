"""A console view: one readable line a second about who is on stage."""

from __future__ import annotations

import sys
from typing import Callable, TextIO

from ..engine.engine import Engine
from ..frames import FusedFrame
from ..joints import JOINT_INDEX

_HEAD = JOINT_INDEX["Head"]


class StatusLine:
    """Engine listener printing a status line at most every ``every_s`` seconds."""

    def __init__(self, engine: Engine, every_s: float = 1.0, out: TextIO | None = None,
                 time_origin: float | None = None) -> None:
        self.engine, self.every_s = engine, every_s
        self.out: TextIO = out or sys.stdout
        self._origin = engine.clock.now() if time_origin is None else time_origin
        self._next = self._origin + every_s
        self._frames_at_last = 0
        self.lines = 0

    def __call__(self, frame: FusedFrame) -> None:
        if frame.t < self._next:
            return
        elapsed = frame.t - (self._next - self.every_s)
        self._next = frame.t + self.every_s
        counts = self.engine.counts
        rate = (counts["frames"] - self._frames_at_last) / max(elapsed, 1e-6)
        self._frames_at_last = counts["frames"]
        active = sum(1 for c in self.engine.clients.values() if c.active)
        parts = [f"{frame.t - self._origin:6.1f} s", f"{active} sensor(s), {rate:4.0f} frames/s in"]
        for pid, body in sorted(frame.bodies.items()):
            x, y, z = body.position
            parts.append(f"person {pid} at ({x:+.2f}, {z:+.2f}) m, head {body.joints[_HEAD][1]:.2f} m, "
                         f"hands {body.hands[0].wire_name}/{body.hands[1].wire_name}, "
                         f"seen by {len(body.sensors)}")
        if not frame.bodies:
            parts.append("nobody on stage")
        lat = self.engine.latency.summary_ms()
        parts.append(f"drops {self.engine.drops.total()}")
        if lat.get("n"):
            parts.append(f"latency p99 {lat['p99']:.2f} ms")
        print(" | ".join(parts), file=self.out, flush=True)
        self.lines += 1


    def idle(self, now: float) -> None:
        """Engine thread: a line even when no fused frame comes (an empty stage, silent
        sensors), so an idle server does not look hung."""
        if now >= self._next:
            self(FusedFrame(now, self.engine.bodies(), (), (), ()))


def attach(engine: Engine, **kwargs) -> Callable[[FusedFrame], None]:
    status = StatusLine(engine, **kwargs)
    engine.listeners.append(status)
    return status
