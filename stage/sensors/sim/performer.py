"""A performer: a choreography timeline turned into a moving 25-joint body.

The timeline is a list of ``Step``s (parsed from the scenario file). Steps
run one after another unless they say otherwise: ``at: S`` starts a step S
seconds into the performer's timeline, ``with: previous`` starts it together
with the step before it, ``after: S`` leaves a gap. Start times must not go
backwards in file order. A looping performer repeats the whole timeline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ...errors import ConfigError
from ...geometry import rot_y
from ...joints import JOINT_INDEX, HandState
from .channels import Arc, Channel, Ease, EaseTo, Hold, Motion, Polyline, Still, Travel, wrap_near
from .kinematics import (REST_POSE, STRIDE_M, ArmPose, BodyState, Proportions, reach_angles,
                         skeleton, upper_frame)

Mark = tuple[int, int]
G = 9.81


@dataclass
class Step:
    """One timeline entry as written in the scenario: ``verb: value`` plus options."""

    verb: str
    value: Any
    opts: dict = field(default_factory=dict)
    at: float | None = None
    with_previous: bool = False
    after: float = 0.0
    mark: Mark | None = None


class Clip:
    """What the performer needs from a motion-capture clip (see stage.importers.bvh.BvhMotion)."""

    duration: float

    def joints(self, t: float) -> np.ndarray: ...          # (25, 3) clip space, metres, feet on y=0
    def root(self, t: float) -> np.ndarray: ...            # (2,) x, z
    def heading(self, t: float) -> float: ...
    def conf(self) -> np.ndarray: ...                      # (25,) 1 where the clip has the joint


class _ClipSegment:
    def __init__(self, t0: float, t1: float, clip: Clip, start: float, length: float, speed: float,
                 rotation: np.ndarray, offset: np.ndarray) -> None:
        self.t0, self.t1, self.clip, self.start, self.length, self.speed = t0, t1, clip, start, \
            length, speed
        self.rotation, self.offset = rotation, offset

    def clip_time(self, t: float) -> float:
        local = (min(t, self.t1) - self.t0) * self.speed
        if self.length > 0 and local >= self.length:
            local = local % self.length if t < self.t1 else self.length
        return self.start + local

    def joints(self, t: float) -> np.ndarray:
        return self.clip.joints(self.clip_time(t)) @ self.rotation.T + self.offset


class Performer:
    """Evaluates a timeline: ``state(t)`` -> (joints (25,3) stage, hands) or None when offstage."""

    def __init__(self, name: str, steps: list[Step], *, height: float = 1.75,
                 position: tuple[float, float] = (0.0, 0.0), facing: float = 0.0,
                 present: bool = True, hands: tuple[HandState, HandState] = (HandState.OPEN,
                                                                           HandState.OPEN),
                 loop: bool | float = False, clips: dict[str, Clip] | None = None,
                 places: dict[str, np.ndarray] | None = None, source: str = "<scenario>") -> None:
        self.name = name
        self.props = Proportions(height)
        self.clips = clips or {}
        self.places = places or {}      # named points a step may face or point at (sensors)
        self.source = source
        self.pos = Channel(None)
        self.pos.add(Still(0.0, np.asarray(position, float), 0.0))
        self.heading = Channel(facing)
        self.arms = [Channel(ArmPose().as_array()), Channel(ArmPose().as_array())]
        self.hands = [Channel(hands[0]), Channel(hands[1])]
        self.crouch = Channel(0.0)
        self.present = Channel(present)
        self.jumps: list[tuple[float, float, float]] = []   # (t0, t1, height)
        self.clip_segments: list[_ClipSegment] = []
        self.overrides: list[tuple[float, bool]] = []       # scenario enter/leave, absolute time
        #: (start s, duration s, step) of each step as built: the choreography's times
        self.schedule: list[tuple[float, float, Step]] = []
        self.length = self._build(steps)
        if loop is True:
            self.period = self.length if self.length > 0 else None
        elif loop is False or loop is None:
            self.period = None
        else:
            self.period = float(loop)
        if self.period is not None and self.period <= 0:
            raise ConfigError(f"performer '{name}' loops but its timeline has no length",
                              path=source)

    # ------------------------------------------------------------ evaluation
    def local_time(self, t: float) -> float:
        if self.period is None or t < 0:
            return t
        return t % self.period

    def is_present(self, t: float) -> bool:
        for when, value in reversed(self.overrides):
            if when <= t:
                return value
        return bool(self.present.value(self.local_time(t)))

    def body_state(self, t: float, with_arms: bool = True) -> BodyState:
        """The body's pose parameters at local timeline time ``t``."""
        motion: Motion = self.pos.segment_at(t)  # type: ignore[assignment]
        position = motion.value(t)
        amp = 0.0
        if motion.moving(t):
            ramp = min(t - motion.t0, motion.t1 - t, 0.3) / 0.3
            amp = min(motion.speed / 1.0, 1.2) * max(ramp, 0.0)
        lift, tuck = 0.0, 0.0
        for t0, t1, h in self.jumps:
            if t0 <= t < t1:
                u = (t - t0) / (t1 - t0)
                lift, tuck = 4.0 * h * u * (1.0 - u), math.sin(math.pi * u)
        state = BodyState(position=position, heading=float(self.heading.value(t)),
                          crouch=float(self.crouch.value(t)), lift=lift, tuck=tuck,
                          stride_phase=motion.distance(t) / (STRIDE_M * self.props.s),
                          stride_amp=amp)
        if with_arms:
            state.arms = tuple(ArmPose(*map(float, ch.value(t))) for ch in self.arms)  # type: ignore[assignment]
        return state

    def state(self, t: float) -> tuple[np.ndarray, tuple[HandState, HandState]] | None:
        """(joints (25, 3) metres stage space, (left, right) hand states), None when offstage."""
        if not self.is_present(t):
            return None
        lt = self.local_time(t)
        hands = (self.hands[0].value(lt), self.hands[1].value(lt))
        for seg in self.clip_segments:
            if seg.t0 <= lt < seg.t1:
                return seg.joints(lt), hands
        return skeleton(self.body_state(lt), self.props), hands

    # ------------------------------------------------------------ building
    def _error(self, step: Step, message: str) -> ConfigError:
        line, col = step.mark if step.mark else (None, None)
        return ConfigError(message, path=self.source, line=line, column=col)

    def _build(self, steps: list[Step]) -> float:
        cursor = 0.0
        previous_start = 0.0
        for step in steps:
            if step.at is not None:
                start = step.at
            elif step.with_previous:
                start = previous_start
            else:
                start = cursor + step.after
            if start < previous_start - 1e-9:
                raise self._error(step, f"starts at {start:g} s, before the step above it "
                                  f"({previous_start:g} s): write steps in time order "
                                  f"(use 'with: previous' for steps at the same time)")
            handler: Callable[[Step, float], float] = getattr(self, "_do_" + step.verb)
            duration = handler(step, start)
            self.schedule.append((start, duration, step))
            previous_start = start
            cursor = max(cursor, start + duration)
        return cursor

    def _opt(self, step: Step, key: str, default: Any) -> Any:
        return step.opts.get(key, default)

    def _point(self, step: Step, value: Any) -> np.ndarray:
        """A place on the floor (x, z) or in space (x, y, z), or the name of a sensor."""
        if isinstance(value, str):
            if value not in self.places:
                raise self._error(step, f"'{value}' is not a sensor of this scenario "
                                  f"({', '.join(self.places) or 'none'})")
            return np.asarray(self.places[value], float)
        return np.asarray(value, float)

    def _motion(self, t: float) -> Motion:
        return self.pos.segment_at(t)  # type: ignore[return-value]

    def _add_motion(self, step: Step, start: float, make: Callable[[np.ndarray, float], Motion],
                    ) -> float:
        prev = self._motion(start)
        origin = prev.value(start)
        motion = self.pos.add(make(origin, prev.distance(start)))
        facing = self._opt(step, "facing", "travel")
        h0 = float(self.heading.value(start))
        if facing in ("travel", "backwards"):
            self.heading.add(Travel(motion, h0, backwards=facing == "backwards"))
        elif facing != "keep":
            goal = wrap_near(self._heading_of(step, facing, origin), h0)
            self.heading.add(Ease(start, start + min(0.5, motion.t1 - start), h0, goal))
        self.pos.add(Still(motion.t1, motion.value(motion.t1), motion.distance(motion.t1)))
        return motion.t1 - start

    def _heading_of(self, step: Step, value: Any, origin: np.ndarray) -> float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return math.radians(value)
        p = self._point(step, value)
        d = (p[[0, 2]] if p.shape == (3,) else p) - origin
        return math.atan2(float(d[0]), float(d[1]))

    def _do_walk(self, step: Step, start: float) -> float:
        points = np.asarray(step.value, float)
        points = points[None] if points.ndim == 1 else points

        def make(origin: np.ndarray, dist0: float) -> Motion:
            path = np.vstack([origin, points])
            length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
            over = self._opt(step, "over", None)
            duration = over if over is not None else length / self._opt(step, "speed", 1.0)
            return Polyline(start, start + duration, path, dist0)
        return self._add_motion(step, start, make)

    def _do_circle(self, step: Step, start: float) -> float:
        centre = np.asarray(step.value, float)

        def make(origin: np.ndarray, dist0: float) -> Motion:
            rel = origin - centre
            radius = float(np.linalg.norm(rel))
            if radius < 0.05:
                raise self._error(step, "the performer stands on the centre of the circle; "
                                  "walk away from it first")
            sweep = 2 * math.pi * float(self._opt(step, "turns", 1.0))
            over = self._opt(step, "over", None)
            duration = over if over is not None else abs(sweep) * radius / self._opt(
                step, "speed", 1.0)
            return Arc(start, start + duration, centre, radius,
                       math.atan2(float(rel[0]), float(rel[1])), sweep, dist0)
        return self._add_motion(step, start, make)

    def _do_step(self, step: Step, start: float) -> float:
        size = float(self._opt(step, "size", 0.6))
        named = {"forward": (0.0, 1.0), "back": (0.0, -1.0), "left": (1.0, 0.0),
                 "right": (-1.0, 0.0)}
        local = np.asarray(named[step.value], float) * size if isinstance(step.value, str) \
            else np.asarray(step.value, float)
        h = float(self.heading.value(start))
        r = rot_y(h)
        delta = (r @ np.array([local[0], 0.0, local[1]]))[[0, 2]]
        step.opts.setdefault("facing", "keep")

        def make(origin: np.ndarray, dist0: float) -> Motion:
            return Polyline(start, start + float(self._opt(step, "over", 0.6)),
                            np.vstack([origin, origin + delta]), dist0)
        return self._add_motion(step, start, make)

    def _do_turn(self, step: Step, start: float) -> float:
        h0 = float(self.heading.value(start))
        return self._turn_to(step, start, h0 + math.radians(float(step.value)))

    def _do_face(self, step: Step, start: float) -> float:
        h0 = float(self.heading.value(start))
        origin = self._motion(start).value(start)
        return self._turn_to(step, start, wrap_near(self._heading_of(step, step.value, origin), h0))

    def _turn_to(self, step: Step, start: float, goal: float) -> float:
        h0 = float(self.heading.value(start))
        over = self._opt(step, "over", None)
        duration = over if over is not None else max(0.3, abs(goal - h0) / math.pi)
        self.heading.add(Ease(start, start + duration, h0, goal))
        return duration

    def _sides(self, value: str) -> tuple[int, ...]:
        return {"left": (0,), "right": (1,), "both": (0, 1)}[value]

    def _arm_to(self, step: Step, start: float, side: int, goal: Any) -> float:
        duration = float(self._opt(step, "over", 0.6))
        current = np.asarray(self.arms[side].value(start), float)
        if callable(goal):
            self.arms[side].add(EaseTo(start, start + duration, current, goal, _blend_arm))
        else:
            a, b = _align_arm(current, np.asarray(goal, float))
            self.arms[side].add(Ease(start, start + duration, a, b))
        return duration

    def _do_raise(self, step: Step, start: float) -> float:
        plane = self._opt(step, "plane", "side")
        azimuth = {"side": 0.0, "front": 90.0, "diagonal": 45.0}.get(plane, plane)
        goal = (math.radians(float(self._opt(step, "to", 180.0))), math.radians(float(azimuth)),
                math.radians(float(self._opt(step, "elbow", 0.0))))
        return max(self._arm_to(step, start, s, goal) for s in self._sides(step.value))

    def _do_lower(self, step: Step, start: float) -> float:
        return max(self._arm_to(step, start, s, (0.0, 0.0, 0.0)) for s in self._sides(step.value))

    def _do_reach(self, step: Step, start: float, straight: bool = False) -> float:
        target = self._point(step, self._opt(step, "to", None))
        if target.shape != (3,):
            raise self._error(step, "'to' must be a point [x, y, z] in metres (or a sensor)")
        durations = []
        for side in self._sides(step.value):
            name = ("Left", "Right")[side]

            def goal(t: float, side_name: str = name) -> np.ndarray:
                rotation, translation, _ = upper_frame(self.body_state(t, with_arms=False),
                                                       self.props)
                local = rotation.T @ (target - translation)
                shoulder = REST_POSE[JOINT_INDEX["Shoulder" + side_name]] * self.props.s
                return reach_angles(local, shoulder, self.props, side_name, straight).as_array()
            durations.append(self._arm_to(step, start, side, goal))
        return max(durations)

    def _do_point(self, step: Step, start: float) -> float:
        return self._do_reach(step, start, straight=True)

    def _set_hands(self, start: float, sides: tuple[int, ...], state: HandState) -> float:
        for side in sides:
            self.hands[side].add(Hold(start, state))
        return 0.0

    def _do_hands(self, step: Step, start: float) -> float:
        if isinstance(step.value, dict):
            for key, state in step.value.items():
                self._set_hands(start, self._sides(key), state)
            return 0.0
        return self._set_hands(start, (0, 1), step.value)

    def _do_open(self, step: Step, start: float) -> float:
        return self._set_hands(start, self._sides(step.value), HandState.OPEN)

    def _do_close(self, step: Step, start: float) -> float:
        return self._set_hands(start, self._sides(step.value), HandState.CLOSED)

    def _do_lasso(self, step: Step, start: float) -> float:
        return self._set_hands(start, self._sides(step.value), HandState.LASSO)

    def _do_crouch(self, step: Step, start: float) -> float:
        duration = float(self._opt(step, "over", 0.8))
        self.crouch.add(Ease(start, start + duration, float(self.crouch.value(start)),
                             float(step.value)))
        return duration

    def _do_stand(self, step: Step, start: float) -> float:
        step.value = 0.0
        return self._do_crouch(step, start)

    def _do_jump(self, step: Step, start: float) -> float:
        height = float(step.value)
        duration = float(self._opt(step, "over", 2.0 * math.sqrt(2.0 * height / G)))
        self.jumps.append((start, start + duration, height))
        return duration

    def _do_wait(self, step: Step, start: float) -> float:
        return float(step.value)

    def _do_enter(self, step: Step, start: float) -> float:
        if step.value is not True:
            here = self._motion(start)
            self.pos.add(Still(start, self._point(step, step.value), here.distance(start)))
        if "facing" in step.opts:
            origin = self._motion(start).value(start)
            self.heading.add(Hold(start, self._heading_of(step, step.opts["facing"], origin)))
        self.present.add(Hold(start, True))
        return 0.0

    def _do_leave(self, step: Step, start: float) -> float:
        self.present.add(Hold(start, False))
        return 0.0

    def _do_bvh(self, step: Step, start: float) -> float:
        return self._play_clip(step, start, self.clips[step.value])

    def _do_gait(self, step: Step, start: float) -> float:
        from .gait import GaitClip
        o = step.opts
        try:
            clip = GaitClip(int(step.value), o.get("length", 0.70), o.get("width", 0.12),
                            o.get("cadence", 110.0), first_step=o.get("first"),
                            lead=o.get("lead", "left"), props=self.props)
        except ValueError as exc:
            raise self._error(step, str(exc)) from None
        self.clips[f"gait@{start:g}"] = clip
        step.opts = {k: v for k, v in o.items() if k == "facing"}
        return self._play_clip(step, start, clip)

    def _play_clip(self, step: Step, start: float, clip: Clip) -> float:
        begin = float(self._opt(step, "from", 0.0))
        end = float(self._opt(step, "to", clip.duration))
        if not 0 <= begin < end <= clip.duration + 1e-6:
            raise self._error(step, f"'from'/'to' must satisfy 0 <= from < to <= "
                              f"{clip.duration:.2f} s (the clip's length)")
        speed = float(self._opt(step, "speed", 1.0))
        repeat = int(self._opt(step, "repeat", 1))
        length = end - begin
        duration = length * repeat / speed
        here = self._motion(start)
        origin = here.value(start)
        h0 = float(self.heading.value(start))
        facing = self._opt(step, "facing", None)
        target_h = h0 if facing is None else self._heading_of(step, facing, origin)
        turn = target_h - clip.heading(begin)
        rotation = rot_y(turn)
        root = clip.root(begin)
        offset = np.array([origin[0], 0.0, origin[1]]) - rotation @ np.array([root[0], 0.0, root[1]])
        self.clip_segments.append(_ClipSegment(start, start + duration, clip, begin, length, speed,
                                               rotation, offset))
        # afterwards the procedural body carries on from where the clip left it
        last = clip.root(end)
        end_pos = (rotation @ np.array([last[0], 0.0, last[1]]) + offset)[[0, 2]]
        self.pos.add(Still(start + duration, end_pos if repeat == 1 else origin,
                           here.distance(start)))
        self.heading.add(Hold(start + duration, target_h + (clip.heading(end) - clip.heading(begin)
                                                            if repeat == 1 else 0.0)))
        return duration


def describe_step(step: Step) -> str:
    """A step in words, as a composer wrote it: 'raise left to 175 over 1'."""
    def word(v: Any) -> str:
        if isinstance(v, HandState):
            return v.wire_name
        if isinstance(v, np.ndarray):
            v = v.tolist()
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(word(x) for x in v) + "]"
        if isinstance(v, float):
            return f"{v:g}"
        if isinstance(v, dict):
            return ", ".join(f"{k} {word(x)}" for k, x in v.items())
        return str(v)
    value = "" if step.value is True or step.verb in ("wait", "stand") else " " + word(step.value)
    if step.verb == "wait":
        value = f" {word(step.value)} s"
    opts = "".join(f" {k} {word(v)}" for k, v in step.opts.items()
                   if not (k == "facing" and v == "keep"))
    return f"{step.verb}{value}{opts}"


def _align_arm(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arm angles made ready to interpolate: the azimuth of a hanging arm does not matter, so it
    takes the other end's (no sweep), and azimuths go the short way round."""
    a, b = a.copy(), b.copy()
    if a[0] < 0.05:
        a[1] = b[1]
    elif b[0] < 0.05:
        b[1] = a[1]
    b[1] = wrap_near(b[1], a[1])
    return a, b


def _blend_arm(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    a, b = _align_arm(np.asarray(a, float), np.asarray(b, float))
    return a + (b - a) * w
