"""Time-varying values of a performer: each channel is a list of segments.

A segment starts at ``t0`` from the channel's value at that moment and
moves towards its goal; the latest segment that has started decides the
value (so a new arm gesture takes over from the previous one smoothly, from
wherever the arm is). Pure functions of time: the same t gives the same value.
"""

from __future__ import annotations

import bisect
import math
from typing import Any, Callable

import numpy as np


def smooth(u: float) -> float:
    """Ease in and out: 0 -> 0, 1 -> 1, zero speed at both ends."""
    u = min(max(u, 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u)


def wrap_near(angle: float, reference: float) -> float:
    """``angle`` plus a multiple of 2 pi, as close as possible to ``reference``."""
    return reference + (angle - reference + math.pi) % (2 * math.pi) - math.pi


class Segment:
    t0: float = 0.0
    t1: float = 0.0

    def value(self, t: float) -> Any:
        raise NotImplementedError


class Hold(Segment):
    """A value set at ``t0`` (instant actions: hand states, enter, leave)."""

    def __init__(self, t0: float, value: Any) -> None:
        self.t0 = self.t1 = t0
        self._value = value

    def value(self, t: float) -> Any:
        return self._value


class Ease(Segment):
    """From ``start`` to ``goal`` (numbers or arrays) over [t0, t1], eased."""

    def __init__(self, t0: float, t1: float, start: Any, goal: Any) -> None:
        self.t0, self.t1 = t0, max(t1, t0)
        self.start, self.goal = np.asarray(start, float), np.asarray(goal, float)

    def value(self, t: float) -> Any:
        if self.t1 <= self.t0 or t >= self.t1:
            return self.goal
        return self.start + (self.goal - self.start) * smooth((t - self.t0) / (self.t1 - self.t0))


class EaseTo(Segment):
    """Eases from ``start`` to a goal that is itself a function of time (a reach that follows
    the body), then keeps following it."""

    def __init__(self, t0: float, t1: float, start: np.ndarray, goal: Callable[[float], np.ndarray],
                 blend: Callable[[np.ndarray, np.ndarray, float], np.ndarray]) -> None:
        self.t0, self.t1 = t0, max(t1, t0)
        self.start, self.goal, self.blend = start, goal, blend

    def value(self, t: float) -> Any:
        goal = self.goal(t)
        if self.t1 <= self.t0 or t >= self.t1:
            return goal
        return self.blend(self.start, goal, smooth((t - self.t0) / (self.t1 - self.t0)))


class Motion(Segment):
    """Movement over the floor at a constant speed: a polyline or an arc.

    ``value`` is the (x, z) position; ``distance`` the metres walked since
    the start of the show (drives the stride), ``speed`` m/s while moving.
    """

    def __init__(self, t0: float, t1: float, dist0: float) -> None:
        self.t0, self.t1, self.dist0 = t0, t1, dist0
        self.length = 0.0

    @property
    def speed(self) -> float:
        return self.length / (self.t1 - self.t0) if self.t1 > self.t0 else 0.0

    def moving(self, t: float) -> bool:
        return self.t0 <= t < self.t1

    def distance(self, t: float) -> float:
        return self.dist0 + self.length * self._u(t)

    def _u(self, t: float) -> float:
        if self.t1 <= self.t0:
            return 1.0
        return min(max((t - self.t0) / (self.t1 - self.t0), 0.0), 1.0)


class Still(Motion):
    def __init__(self, t0: float, position: np.ndarray, dist0: float) -> None:
        super().__init__(t0, t0, dist0)
        self.position = np.asarray(position, float)

    def value(self, t: float) -> np.ndarray:
        return self.position


class Polyline(Motion):
    def __init__(self, t0: float, t1: float, points: np.ndarray, dist0: float) -> None:
        super().__init__(t0, t1, dist0)
        self.points = np.asarray(points, float)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.cum[-1])

    def value(self, t: float) -> np.ndarray:
        if self.length <= 0:
            return self.points[-1]
        s = self.length * self._u(t)
        k = min(int(np.searchsorted(self.cum, s, side="right")) - 1, len(self.points) - 2)
        span = self.cum[k + 1] - self.cum[k]
        f = 0.0 if span <= 0 else (s - self.cum[k]) / span
        return self.points[k] + f * (self.points[k + 1] - self.points[k])


class Arc(Motion):
    def __init__(self, t0: float, t1: float, centre: np.ndarray, radius: float, angle0: float,
                 sweep: float, dist0: float) -> None:
        super().__init__(t0, t1, dist0)
        self.centre, self.radius, self.angle0, self.sweep = np.asarray(centre, float), radius, \
            angle0, sweep
        self.length = abs(sweep) * radius

    def value(self, t: float) -> np.ndarray:
        a = self.angle0 + self.sweep * self._u(t)
        return self.centre + self.radius * np.array([math.sin(a), math.cos(a)])


class Travel(Segment):
    """Heading that turns to face the direction of travel of a Motion (eased in)."""

    def __init__(self, motion: Motion, start_heading: float, backwards: bool = False,
                 turn_s: float = 0.4) -> None:
        self.t0, self.t1 = motion.t0, motion.t1
        self.motion, self.start, self.backwards, self.turn_s = motion, start_heading, backwards, \
            turn_s
        self._end = self._travel(self.t1)

    def _travel(self, t: float) -> float:
        m = self.motion
        # a central difference rounds the corners of a path over ~0.3 s, as people do
        a, b = max(t - 0.15, m.t0), min(t + 0.15, m.t1)
        if b - a < 1e-6:
            a, b = m.t0, m.t1
        d = m.value(b) - m.value(a)
        if float(d @ d) < 1e-12:
            return self.start
        h = math.atan2(float(d[0]), float(d[1]))
        return h + math.pi if self.backwards else h

    def value(self, t: float) -> float:
        travel = self._travel(min(t, self.t1)) if t < self.t1 else self._end
        travel = wrap_near(travel, self.start)
        w = smooth((t - self.t0) / self.turn_s) if self.turn_s > 0 else 1.0
        return self.start + (travel - self.start) * w


class Channel:
    """Segments ordered by start time; the latest started one gives the value."""

    def __init__(self, initial: Any) -> None:
        self.initial = initial
        self._t0s: list[tuple[float, int]] = []
        self._segments: list[Segment] = []
        self._n = 0

    def add(self, segment: Segment) -> Segment:
        key = (segment.t0, self._n)
        self._n += 1
        i = bisect.bisect_right(self._t0s, key)
        self._t0s.insert(i, key)
        self._segments.insert(i, segment)
        return segment

    def segment_at(self, t: float) -> Segment | None:
        i = bisect.bisect_right(self._t0s, (t, math.inf)) - 1
        return self._segments[i] if i >= 0 else None

    def value(self, t: float) -> Any:
        seg = self.segment_at(t)
        return self.initial if seg is None else seg.value(t)

    def last_end(self) -> float:
        return max((s.t1 for s in self._segments), default=0.0)
