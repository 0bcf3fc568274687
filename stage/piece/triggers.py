"""Trigger detectors: small state machines per (person, joint), one per trigger.

A detector turns a stream of frames into *firings*; whether a firing sounds
(cooldown, once, after, while, probability) is decided by the runtime.
Rules that keep a jittering joint from firing forty times (the "Midas touch"
problem of Liminal Space: not every movement should sound):

* The first observation of a joint only sets its state; only changes fire.
  A section that begins while a hand is already raised does not fire
  "rises above" until the hand has come down and gone up again.
* Zones and heights have hysteresis (Schmitt triggers): a joint enters at the
  border but counts as out again only ``hysteresis`` metres beyond it.
* Speeds re-arm only below ``threshold - hysteresis``.
* ``dwell``: a new state must last that long before it counts; hand states
  (which flicker, and go ``unknown`` when a hand turns away) default to 0.1 s
  and ignore unknown / notTracked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ..analysis.gait import LiveSteps
from ..joints import JOINTS, HandState
from .model import BODY, Trigger

KNOWN_HANDS = (HandState.OPEN, HandState.CLOSED, HandState.LASSO)
#: step detection: a foot "swings" above ``speed`` (m/s, default 0.8) and is
#: "placed" when it slows below a third of that (at most 0.25 m/s) this near the floor
STEP_MAX_HEIGHT = 0.3
_SIDE = {i: (0 if name.endswith("Left") else 1) for i, name in enumerate(JOINTS)}
#: times are sums of float frame periods: 44/30 - 41/30 < 0.1; a dwell must not miss by 1e-16 s
EPS = 1e-6


class Person:
    """One fused body in one frame, as plain Python floats (cheap scalar access).

    ``xyz(j)``: (x, y, z) metres of joint j, or None when its confidence is below
    the piece's minimum this frame (unseen joints keep stale positions in the
    engine; they must not move triggers). ``BODY`` is the torso centre.
    ``joint(j)``: the same whatever the confidence. A joint (and its velocity, ``vel``)
    becomes a list of floats when first asked for: a piece reads a few joints of each body
    a frame, and making all 25 (25 lists, 75 floats, a dozen bodies a frame with
    forecasts) and freeing them a frame later was about a quarter of the runtime's time
    (issue 10, stop 53).
    """

    __slots__ = ("id", "body", "_joints", "_rows", "conf", "min_conf", "_vel", "position",
                 "hands", "since")

    def __init__(self, body, min_conf: float, since: float) -> None:
        self.id = body.id
        self.body = body
        self._joints = body.joints
        self._rows: list | None = None
        self.conf = body.conf.tolist()
        self.min_conf = min_conf
        self._vel = None
        self.position = body.position.tolist()
        self.hands = body.hands
        self.since = since

    def joint(self, j: int) -> list[float]:
        """[x, y, z] metres of joint ``j`` (not ``BODY``), whatever its confidence."""
        rows = self._rows
        if rows is None:
            rows = self._rows = [None] * len(self.conf)
        row = rows[j]
        if row is None:
            row = rows[j] = self._joints[j].tolist()
        return row

    def xyz(self, j: int):
        if j == BODY:
            return self.position
        if self.conf[j] < self.min_conf:
            return None
        return self.joint(j)

    def vel(self, j: int):
        """[vx, vy, vz] m/s of joint ``j`` (``BODY``: SpineMid's, as the torso centre moves),
        made when first asked for, as ``joint``."""
        k = 1 if j == BODY else j
        vels = self._vel
        if vels is None:
            vels = self._vel = [None] * len(self.conf)
        v = vels[k]
        if v is None:
            v = vels[k] = self.body.velocity[k].tolist()
        return v

    def speed(self, j: int) -> float:
        v = self.vel(j)
        return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@dataclass(slots=True)
class Firing:
    person: int | None
    joint: int | None
    value: float | None      # what crossed: metres, m/s, seconds
    speed: float = 0.0       # the joint's speed then (for velocity: speed)
    detail: dict | None = None  # more values for $references (step: gait: step_width, ...)


class Detector:
    """Firings of one trigger; ``reset`` when its section begins again."""

    def __init__(self, trigger: Trigger) -> None:
        self.t = trigger
        self.states: dict[tuple[int, int], list] = {}
        self.fired = False          # stage_empty / elapsed: fired in this visit or emptiness

    def reset(self) -> None:
        self.states.clear()
        self.fired = False

    def forget(self, pids: Iterable[int]) -> None:
        gone = set(pids)
        if gone and self.states:
            self.states = {k: v for k, v in self.states.items() if k[0] not in gone}

    def frame(self, t: float, persons: list[Person], out: list[Firing]) -> None:
        """Append this frame's firings for ``persons`` (already filtered by performer)."""
        raise NotImplementedError

    def armed(self, key: tuple[int, int]) -> bool | None:
        """Whether (person, joint) ``key`` can fire on its next crossing (it is behind the
        border, by the hysteresis since it last fired); None where the detector has no
        such state or has not seen the joint yet."""
        return None


class ZoneDetector(Detector):
    """enters / leaves / dwells. State: [committed, raw, raw_since, entered_at, dwelled]."""

    def armed(self, key):
        st = self.states.get(key)
        kind = self.t.kind
        if st is None or kind == "dwells":
            return None
        return (not st[0]) if kind == "enters" else st[0]

    def frame(self, t, persons, out):
        trig, zone, states = self.t, self.t.zone, self.states
        kind, margin, dwell = trig.kind, trig.hysteresis, trig.dwell
        for p in persons:
            for j in trig.joints:
                pos = p.xyz(j)
                if pos is None:
                    continue
                key = (p.id, j)
                st = states.get(key)
                if st is None:
                    raw = zone.contains(pos[0], pos[1], pos[2])
                    states[key] = [raw, raw, t, None, False]
                    continue
                raw = zone.contains(pos[0], pos[1], pos[2], margin if st[1] else 0.0)
                if raw != st[1]:
                    st[1], st[2] = raw, t
                if raw != st[0] and t - st[2] >= dwell - EPS:
                    st[0] = raw
                    if raw:
                        st[3], st[4] = st[2], False
                        if kind == "enters":
                            out.append(Firing(p.id, j, None, p.speed(j)))
                    else:
                        st[3] = None
                        if kind == "leaves":
                            out.append(Firing(p.id, j, None, p.speed(j)))
                if kind == "dwells" and st[0] and st[3] is not None and not st[4] \
                        and t - st[3] >= trig.duration - EPS:
                    st[4] = True
                    out.append(Firing(p.id, j, t - st[3], p.speed(j)))


class SpeedDetector(Detector):
    """speed_above / moves (speed along a direction). State: [armed]."""

    def frame(self, t, persons, out):
        trig, states = self.t, self.states
        threshold, rearm = trig.threshold, trig.threshold - trig.hysteresis
        along = trig.kind == "moves"
        dx, dy, dz = trig.direction
        for p in persons:
            for j in trig.joints:
                if j != BODY and p.conf[j] < p.min_conf:
                    continue
                v = p.vel(j)
                s = v[0] * dx + v[1] * dy + v[2] * dz if along else \
                    math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
                key = (p.id, j)
                st = states.get(key)
                if st is None:
                    states[key] = [s <= threshold]
                elif st[0]:
                    if s > threshold:
                        st[0] = False
                        out.append(Firing(p.id, j, s, p.speed(j)))
                elif s < rearm:
                    st[0] = True


class HeightDetector(Detector):
    """rises_above / falls_below a height or another joint. State: [armed, since]."""

    def armed(self, key):
        st = self.states.get(key)
        return None if st is None else st[0]

    def frame(self, t, persons, out):
        trig, states = self.t, self.states
        sign = 1.0 if trig.kind == "rises_above" else -1.0
        h, dwell, ref = trig.hysteresis, trig.dwell, trig.threshold_joint
        for p in persons:
            if ref is None:
                level = trig.threshold
            else:
                r = p.xyz(ref)
                if r is None:
                    continue
                level = r[1]
            for j in trig.joints:
                pos = p.xyz(j)
                if pos is None:
                    continue
                d = sign * (pos[1] - level)   # > 0: past the threshold
                key = (p.id, j)
                st = states.get(key)
                if st is None:
                    states[key] = [d <= 0.0, None]
                    continue
                if st[0]:
                    if d > 0.0:
                        if st[1] is None:
                            st[1] = t
                        if t - st[1] >= dwell - EPS:
                            st[0], st[1] = False, None
                            out.append(Firing(p.id, j, pos[1], p.speed(j)))
                    else:
                        st[1] = None
                elif d < -h:
                    st[0] = True


class HandDetector(Detector):
    """A hand becomes open / closed / lasso. State per hand: [committed, raw, since]."""

    def __init__(self, trigger: Trigger) -> None:
        super().__init__(trigger)
        self.sides = tuple(sorted({(_SIDE[j], j) for j in trigger.joints}))

    def frame(self, t, persons, out):
        states, target, dwell = self.states, self.t.hand_state, self.t.dwell
        for p in persons:
            for side, j in self.sides:
                state = p.hands[side]
                key = (p.id, j)
                st = states.get(key)
                if state not in KNOWN_HANDS:
                    continue  # unknown / notTracked: no news about this hand
                if st is None:
                    states[key] = [state, state, t]
                    continue
                if state != st[1]:
                    st[1], st[2] = state, t
                if state != st[0] and t - st[2] >= dwell - EPS:
                    st[0] = state
                    if state == target:
                        out.append(Firing(p.id, j, None, p.speed(j)))


class StepDetector(Detector):
    """A foot swings (speed above ``speed``) and is put down near the floor. State: [lifted, peak]."""

    def frame(self, t, persons, out):
        trig, states = self.t, self.states
        swing = trig.threshold
        rest = min(0.25, swing / 3.0)
        for p in persons:
            for j in trig.joints:
                pos = p.xyz(j)
                if pos is None:
                    continue
                s = p.speed(j)
                key = (p.id, j)
                st = states.get(key)
                if st is None:
                    states[key] = st = [False, 0.0]
                if not st[0]:
                    if s > swing:
                        st[0], st[1] = True, s
                elif s < rest and pos[1] < STEP_MAX_HEIGHT:
                    st[0] = False
                    out.append(Firing(p.id, j, st[1], st[1]))
                elif s > st[1]:
                    st[1] = s


class GaitStepDetector(Detector):
    """step: gait -- seed 003's foot events, one ``LiveSteps`` per person.

    Fires when one foot passes the other, for the step the standing foot
    ended: value = step length (m), speed = walking speed (m/s), detail =
    step_length, step_width (m), step_time (s). A walk's first placement
    (no step before it) and feet the trigger does not watch do not fire.
    """

    def __init__(self, trigger: Trigger) -> None:
        super().__init__(trigger)
        self.feet = {_SIDE[j]: j for j in trigger.joints}
        self.walkers: dict[int, LiveSteps] = {}

    def reset(self) -> None:
        super().reset()
        self.walkers.clear()

    def forget(self, pids: Iterable[int]) -> None:
        for pid in pids:
            self.walkers.pop(pid, None)

    def frame(self, t, persons, out):
        for p in persons:
            walker = self.walkers.get(p.id)
            if walker is None:
                walker = self.walkers[p.id] = LiveSteps()
            joints = np.array(p.body.joints, dtype=float)
            joints[np.asarray(p.body.conf) < p.min_conf] = np.nan
            step = walker.update(t, joints)
            if step is None or step.length is None or step.time is None:
                continue
            joint = self.feet.get(0 if step.side == "left" else 1)
            if joint is None:
                continue
            out.append(Firing(p.id, joint, step.length, step.length / step.time,
                              {"step_length": step.length, "step_width": step.width,
                               "step_time": step.time}))


class PresenceDetector(Detector):
    """appears / disappears: from the frame's new and lost ids (see ``presence``)."""

    def frame(self, t, persons, out):
        pass

    def presence(self, new: Iterable[int], lost: Iterable[int], out: list[Firing]) -> None:
        for pid in (new if self.t.kind == "appears" else lost):
            out.append(Firing(pid, None, None))


class ClockDetector(Detector):
    """stage_empty / elapsed: time-based, evaluated on frames and on ticks."""

    def frame(self, t, persons, out):
        pass

    def check(self, t: float, section_start: float, empty_since: float | None,
              out: list[Firing]) -> None:
        if self.t.kind == "elapsed":
            if not self.fired and t - section_start >= self.t.threshold - EPS:
                self.fired = True
                out.append(Firing(None, None, t - section_start))
            return
        if empty_since is None:
            self.fired = False
            return
        since = max(empty_since, section_start)
        if not self.fired and t - since >= self.t.threshold - EPS:
            self.fired = True
            out.append(Firing(None, None, t - since))


def detector_for(trigger: Trigger) -> Detector:
    kind = trigger.kind
    if kind in ("enters", "leaves", "dwells"):
        return ZoneDetector(trigger)
    if kind in ("speed_above", "moves"):
        return SpeedDetector(trigger)
    if kind in ("rises_above", "falls_below"):
        return HeightDetector(trigger)
    if kind == "hand":
        return HandDetector(trigger)
    if kind == "step":
        return GaitStepDetector(trigger) if trigger.gait else StepDetector(trigger)
    if kind in ("appears", "disappears"):
        return PresenceDetector(trigger)
    return ClockDetector(trigger)
