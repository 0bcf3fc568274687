"""Scenario files: the virtual rig, the performers' choreography, and events.

The format is documented, with examples, in docs/sources.md; the built-in
scenarios in ``stage/sensors/sim/scenarios/`` are examples too. Errors name
``file:line:column`` and say what was expected.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import ConfigError
from ...joints import HandState, parse_hand_state
from ...yamlio import MarkedDict, Where, load_marked
from ..kinds import HAND_READING_FRAMES
from .kinect import PRESETS, KinectModel, VirtualPose, ring_poses
from .performer import Clip, Performer, Step, describe_step

BUILTIN = "stage.sensors.sim.scenarios"

#: verb -> (allowed options, what the value must be)
VERBS: dict[str, tuple[tuple[str, ...], str]] = {
    "walk": (("speed", "over", "facing"), "a point [x, z] or a list of points"),
    "circle": (("turns", "speed", "over", "facing"), "the centre [x, z]"),
    "step": (("size", "over"), "forward, back, left, right or [dx, dz] in the performer's frame"),
    "turn": (("over",), "degrees (positive turns left)"),
    "face": (("over",), "degrees, a point [x, z] or a sensor id"),
    "raise": (("to", "plane", "elbow", "over"), "left, right or both"),
    "lower": (("over",), "left, right or both"),
    "reach": (("to", "over"), "left, right or both"),
    "point": (("to", "over"), "left, right or both"),
    "hands": ((), "a hand state, or {left: state, right: state}"),
    "open": ((), "left, right or both"),
    "close": ((), "left, right or both"),
    "lasso": ((), "left, right or both"),
    "crouch": (("over",), "metres the hips go down (0-0.8)"),
    "stand": (("over",), "true"),
    "jump": (("over",), "height in metres, or true for 0.3"),
    "wait": ((), "seconds"),
    "enter": (("facing",), "true, or the point [x, z] where the performer appears"),
    "leave": ((), "true"),
    "bvh": (("from", "to", "speed", "repeat", "facing"), "a BVH file (path relative to the scenario)"),
    "gait": (("length", "width", "cadence", "first", "lead", "facing"),
             "the number of steps of a straight walk with planted feet"),
}
TIMING = ("at", "with", "after")
SIDES = ("left", "right", "both")


@dataclass
class SensorSpec:
    id: str
    pose: VirtualPose
    model: KinectModel = field(default_factory=KinectModel)
    type: str = "kinect2"
    clock_offset: float | None = None     # seconds; None: drawn from the seed (+-2 s)
    clock_drift_ppm: float | None = None  # None: drawn from the seed (+-20 ppm)
    latency: float | None = None          # seconds; None: drawn from the seed (60-80 ms)
    phase: float | None = None            # seconds into the frame period of its first frame;
                                          # None: drawn from the seed (free-running sensors)


@dataclass
class Event:
    at: float
    kind: str                     # bump, unplug, replug, enter, leave
    target: str
    yaw: float = 0.0              # radians (bump)
    pitch: float = 0.0
    roll: float = 0.0
    move: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class Scenario:
    name: str
    sensors: list[SensorSpec]
    performers: list[Performer]
    events: list[Event] = field(default_factory=list)
    reference: str | None = None
    duration: float | None = None
    description: str = ""
    path: str | None = None
    network_jitter_s: float = 0.0005
    latency_range: tuple[float, float] = (0.060, 0.080)   # seed 004: 60-80 ms


def looks_like_scenario(path: str | os.PathLike) -> bool:
    """Whether a YAML file is a scenario rather than a piece: it has 'performers' or
    'sensors' at the top and no 'piece' (rehearsals live beside the pieces they rehearse)."""
    try:
        data = load_marked(path)
    except ConfigError:
        return False
    return isinstance(data, dict) and "piece" not in data and (
        "performers" in data or "sensors" in data)


def describe(scenario: Scenario) -> list[str]:
    """A scenario in words: its sensors, then each performer's choreography with the time
    every step begins and ends (seconds from the start), as ``stage check`` prints it."""
    out = [f"{len(scenario.sensors)} sensor(s) ({', '.join(s.id for s in scenario.sensors)}), "
           f"{len(scenario.performers)} performer(s)"
           + (f", {scenario.duration:g} s" if scenario.duration else "")]
    for p in scenario.performers:
        loop = f", repeating every {p.period:.1f} s" if p.period else ""
        out.append(f"  {p.name}: {p.props.height:.2f} m tall, {p.length:.1f} s of "
                   f"choreography{loop}")
        for start, duration, step in p.schedule:
            span = f"{start:5.1f}-{start + duration:5.1f} s" if duration > 0 else \
                f"{start:5.1f}        "
            out.append(f"    {span}  {describe_step(step)}")
    for e in scenario.events:
        out.append(f"  at {e.at:g} s: {e.kind} {e.target}")
    return out


def builtin_names() -> list[str]:
    return sorted(p.name[:-5] for p in resources.files(BUILTIN).iterdir()
                  if p.name.endswith(".yaml"))


def load_scenario(name_or_path: str | os.PathLike | None = None) -> Scenario:
    """A built-in scenario by name (None or 'default': three sensors, one dancer) or a file."""
    name = "default" if name_or_path is None else str(name_or_path)
    if os.sep not in name and "/" not in name and not name.endswith((".yaml", ".yml")) \
            and not Path(name).exists():
        if name not in builtin_names():
            raise ConfigError(f"no built-in scenario '{name}' (built-in: "
                              f"{', '.join(builtin_names())}); or give a .yaml file")
        with resources.as_file(resources.files(BUILTIN) / f"{name}.yaml") as p:
            return parse_scenario(load_marked(p), str(p))
    return parse_scenario(load_marked(name), name)


def default_scenario(sensors: int = 3, radius: float = 2.5, height: float = 0.8) -> Scenario:
    """The default scenario with ``sensors`` virtual Kinects on a ring of its own size."""
    return builtin_with_ring("default", count=sensors, radius=radius, height=height)


def demo_scenario(n_sensors: int = 3) -> Scenario:
    """The ``demo`` scenario with ``n_sensors`` virtual Kinects on its ring (`stage demo`)."""
    return builtin_with_ring("demo", count=n_sensors)


def builtin_with_ring(name: str, **ring: Any) -> Scenario:
    """A built-in scenario whose ``ring:`` keys (count, radius, ...) are replaced by ``ring``.

    The file is parsed again with the new ring, so sensor ids, the reference
    and the places performers face or point at follow the new sensors.
    """
    if name not in builtin_names():
        raise ConfigError(f"no built-in scenario '{name}' (built-in: {', '.join(builtin_names())})")
    with resources.as_file(resources.files(BUILTIN) / f"{name}.yaml") as p:
        data = load_marked(p)
        sensors = data.get("sensors") if isinstance(data, dict) else None
        if not isinstance(sensors, dict) or not isinstance(sensors.get("ring"), dict):
            raise ConfigError(f"the built-in scenario '{name}' has no sensor ring", path=str(p))
        sensors["ring"].update(ring)
        return parse_scenario(data, str(p))


def parse_scenario(data: Any, path: str) -> Scenario:
    where = Where(path)
    data = where.mapping(data, "the scenario")
    where.check_keys(data, ("name", "description", "duration", "reference", "sensors", "kinect",
                            "network", "performers", "events"), "the scenario")
    base_model = _model(where, data.get("kinect"), KinectModel(), "'kinect'")
    sensors = _sensors(where, data, base_model)
    ids = [s.id for s in sensors]
    reference = data.get("reference", ids[0])
    if reference not in ids:
        raise where.at_key(data, "reference", f"reference '{reference}' is not one of the "
                           f"sensors: {', '.join(ids)}")
    network = where.mapping(data.get("network"), "'network'")
    where.check_keys(network, ("jitter_s", "latency"), "'network'")
    jitter = where.number(network, "jitter_s", 0.0005, minimum=0.0)
    latency = network.get("latency", [0.060, 0.080])
    lat = _numbers(where, network, "latency", latency, (1, 2), minimum=0.0)
    duration = None
    if data.get("duration") is not None:
        duration = where.number(data, "duration", 0.0, exclusive_minimum=0.0)
    places = {s.id: s.pose.position for s in sensors}
    performers = _performers(where, data, places, path)
    events = _events(where, data, ids, {p.name: p for p in performers})
    return Scenario(str(data.get("name", Path(path).stem)), sensors, performers, events,
                    str(reference), duration, str(data.get("description", "")), path, jitter,
                    (lat[0], lat[-1]))


def _numbers(where: Where, mapping: dict, key: str, value: Any, sizes: tuple[int, ...],
             minimum: float | None = None) -> list[float]:
    items = value if isinstance(value, list) else [value]
    ok = len(items) in sizes and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                     and math.isfinite(v) for v in items)
    if ok and minimum is not None:
        ok = all(v >= minimum for v in items)
    if not ok:
        want = " or ".join(str(n) for n in sizes)
        raise where.at_key(mapping, key, f"'{key}' must be {want} number(s)"
                           + (f" >= {minimum:g}" if minimum is not None else "")
                           + f", got {value!r}")
    return [float(v) for v in items]


def _model(where: Where, section: Any, base: KinectModel, what: str) -> KinectModel:
    section = where.mapping(section, what)
    where.check_keys(section, (*KinectModel.keys(), "preset"), what)
    values: dict[str, Any] = {}
    if "preset" in section:  # a named model first, then this section's keys over it
        name = section["preset"]
        if name not in PRESETS:
            raise where.at_key(section, "preset", f"'preset' must be one of "
                               f"{', '.join(PRESETS)}, got {name!r}")
        base = replace(base, **PRESETS[name])
    for key in section:
        if key == "preset":
            continue
        default = getattr(base, key)
        if isinstance(default, tuple):
            values[key] = tuple(_numbers(where, section, key, section[key], (2,), minimum=0.0))
            if values[key][0] > values[key][1]:
                raise where.at_key(section, key, f"'{key}' must be [low, high] with low <= high")
        elif isinstance(default, bool):
            if not isinstance(section[key], bool):
                raise where.at_key(section, key, f"'{key}' must be true or false")
            values[key] = section[key]
        elif isinstance(default, int):
            values[key] = int(where.number(section, key, default, minimum=1))
        else:
            values[key] = where.number(section, key, default, minimum=0.0)
    for key in ("drop_p", "hand_misread_p", "nan_p", "glitch_p", "noise_correlation"):
        if values.get(key, 0.0) >= 1.0:
            raise where.at_key(section, key, f"'{key}' must be below 1")
    model = replace(base, **values)
    if not 0 < model.near < model.far:
        raise where.error("'near' must be above 0 and below 'far'", section.mark
                          if isinstance(section, MarkedDict) else None)
    return model


def _point(where: Where, mapping: dict, key: str, sizes: tuple[int, ...] = (2,)) -> np.ndarray:
    return np.array(_numbers(where, mapping, key, mapping[key], sizes))


def _sensors(where: Where, data: dict, base: KinectModel) -> list[SensorSpec]:
    section = data.get("sensors")
    if section is None:
        section = MarkedDict({"ring": MarkedDict()})
    section = where.mapping(section, "'sensors'")
    out: list[SensorSpec] = []
    for sid, entry in section.items():
        entry = where.mapping(entry, f"sensor '{sid}'",
                              getattr(section, "value_marks", {}).get(sid))
        if sid == "ring":
            out.extend(_ring(where, entry, base))
            continue
        keys = ("position", "look_at", "yaw", "pitch", "roll", "type", "clock_offset",
                "clock_drift_ppm", "latency", "phase", "kinect")
        where.check_keys(entry, keys, f"sensor '{sid}'")
        if "position" not in entry:
            raise where.error(f"sensor '{sid}' needs a 'position' [x, y, z] in metres",
                              getattr(entry, "mark", None))
        position = _point(where, entry, "position", (3,))
        roll = math.radians(where.number(entry, "roll", 0.0))
        if "look_at" in entry:
            if "yaw" in entry or "pitch" in entry:
                raise where.at_key(entry, "look_at", "give either 'look_at' or 'yaw'/'pitch'")
            pose = VirtualPose.looking_at(position, _point(where, entry, "look_at", (3,)), roll)
        else:
            pose = VirtualPose(position, math.radians(where.number(entry, "yaw", 0.0)),
                               math.radians(where.number(entry, "pitch", 0.0)), roll)
        kind = str(entry.get("type", "kinect2"))
        model = _model(where, entry.get("kinect"), base, f"kinect of '{sid}'")
        if HAND_READING_FRAMES.get(kind) == 1 and not any(
                isinstance(given, dict) and "hand_update_frames" in given
                for given in (data.get("kinect"), entry.get("kinect"))):
            # a client of that type reads hand states every frame (the engine counts its
            # readings so), unless the scenario says otherwise; others repeat each reading
            # over ``hand_update_frames``, 2 by default, as a Kinect v2 does
            model = replace(model, hand_update_frames=1)
        out.append(SensorSpec(
            str(sid), pose, model, kind,
            _optional(where, entry, "clock_offset"),
            _optional(where, entry, "clock_drift_ppm"),
            _optional(where, entry, "latency", minimum=0.0),
            _optional(where, entry, "phase", minimum=0.0)))
    if not out:
        raise where.at_key(data, "sensors", "a scenario needs at least one sensor")
    ids = [s.id for s in out]
    if len(set(ids)) != len(ids):
        raise where.at_key(data, "sensors", f"sensor ids must be unique: {', '.join(ids)}")
    return out


def _optional(where: Where, entry: dict, key: str, minimum: float | None = None) -> float | None:
    if entry.get(key) is None:
        return None
    return where.number(entry, key, 0.0, minimum=minimum)


def _ring(where: Where, entry: dict, base: KinectModel) -> list[SensorSpec]:
    where.check_keys(entry, ("count", "radius", "height", "centre", "prefix", "start_angle",
                             "tilt", "aim_height", "kinect"), "'ring'")
    count = int(where.number(entry, "count", 3, minimum=1))
    radius = where.number(entry, "radius", 2.5, exclusive_minimum=0.0)
    height = where.number(entry, "height", 0.8, minimum=0.0)
    aim = where.number(entry, "aim_height", height, minimum=0.0)
    centre = _point(where, entry, "centre") if "centre" in entry else np.zeros(2)
    start = math.radians(where.number(entry, "start_angle", 0.0))
    prefix = str(entry.get("prefix", "kinect-"))
    model = _model(where, entry.get("kinect"), base, "kinect of 'ring'")
    poses = ring_poses(count, radius, height, (centre[0], centre[1]), start, aim)
    return [SensorSpec(prefix + (chr(ord("a") + k) if count <= 26 else str(k + 1)), pose, model)
            for k, pose in enumerate(poses)]


def _performers(where: Where, data: dict, places: dict, path: str) -> list[Performer]:
    items = data.get("performers") or []
    if not isinstance(items, list):
        raise where.at_key(data, "performers", "'performers' must be a list")
    if len(items) > 6:
        raise where.at_key(data, "performers", "at most 6 performers (a Kinect tracks six people)")
    out: list[Performer] = []
    marks = getattr(items, "marks", [None] * len(items))
    for k, entry in enumerate(items):
        entry = where.mapping(entry, "a performer", marks[k])
        where.check_keys(entry, ("name", "height", "position", "facing", "present", "hands",
                                 "loop", "timeline", "motion", "joint_map"), "a performer")
        name = str(entry.get("name", f"performer-{k + 1}"))
        if any(p.name == name for p in out):
            raise where.at_key(entry, "name", f"two performers are called '{name}'")
        height = where.number(entry, "height", 1.75, exclusive_minimum=0.5)
        position = _point(where, entry, "position") if "position" in entry else np.zeros(2)
        facing = entry.get("facing", 0.0)
        if isinstance(facing, str) and facing in places:
            d = places[facing][[0, 2]] - position
            facing_rad = math.atan2(d[0], d[1])
        else:
            facing_rad = math.radians(where.number(entry, "facing", 0.0))
        present = entry.get("present", True)
        if not isinstance(present, bool):
            raise where.at_key(entry, "present", "'present' must be true or false")
        hands = _hand_state(where, entry, "hands", entry.get("hands", "open"))
        loop = entry.get("loop", False)
        if not isinstance(loop, bool):
            loop = where.number(entry, "loop", 0.0, exclusive_minimum=0.0)
        joint_map = where.mapping(entry.get("joint_map"), "'joint_map'")
        timeline = entry.get("timeline") or []
        if "motion" in entry:
            if timeline:
                raise where.at_key(entry, "motion", "give either 'motion' or 'timeline'")
            timeline = [MarkedDict({"bvh": entry["motion"]})]
            timeline[0].mark = entry.value_marks.get("motion", entry.mark)
            timeline[0].marks = {"bvh": timeline[0].mark}
            timeline[0].value_marks = {"bvh": timeline[0].mark}
            if "loop" not in entry:
                loop = True
        if not isinstance(timeline, list):
            raise where.at_key(entry, "timeline", "'timeline' must be a list of steps")
        steps, clips = _steps(where, timeline, places, path, height,
                              {str(k): str(v) for k, v in joint_map.items()})
        try:
            out.append(Performer(name, steps, height=height, position=(position[0], position[1]),
                                 facing=facing_rad, present=present, hands=(hands, hands),
                                 loop=loop, clips=clips, places=places, source=path))
        except ConfigError:
            raise
        except Exception as exc:  # a bug in a step's maths must still name the performer
            raise where.error(f"performer '{name}': {exc}", entry.mark) from None
    return out


def _hand_state(where: Where, mapping: dict, key: str, value: Any) -> HandState:
    state = parse_hand_state(value)
    if state is None:
        raise where.at_key(mapping, key, f"'{value}' is not a hand state (open, closed, lasso, "
                           f"unknown, notTracked)")
    return state


def _steps(where: Where, timeline: list, places: dict, path: str, height: float,
           joint_map: dict) -> tuple[list[Step], dict[str, Clip]]:
    steps: list[Step] = []
    clips: dict[str, Clip] = {}
    marks = getattr(timeline, "marks", [None] * len(timeline))
    for k, entry in enumerate(timeline):
        entry = where.mapping(entry, "a timeline step", marks[k])
        verbs = [key for key in entry if key in VERBS]
        if len(verbs) != 1:
            unknown = [key for key in entry if key not in TIMING and key not in VERBS]
            if unknown and not verbs:
                where.check_keys(entry, (*VERBS, *TIMING), "a timeline step")
            raise where.error("a step needs exactly one action (" + ", ".join(VERBS) + ")",
                              getattr(entry, "mark", marks[k]))
        verb = verbs[0]
        allowed, what = VERBS[verb]
        where.check_keys(entry, (verb, *allowed, *TIMING), f"a '{verb}' step")
        step = Step(verb, entry[verb], {}, mark=entry.marks.get(verb, entry.mark))
        if "at" in entry:
            step.at = where.number(entry, "at", 0.0, minimum=0.0)
        if "with" in entry:
            if entry["with"] != "previous":
                raise where.at_key(entry, "with", "'with' can only be 'previous'")
            step.with_previous = True
        if "after" in entry:
            step.after = where.number(entry, "after", 0.0, minimum=0.0)
        step.value = _step_value(where, entry, verb, what, places)
        for key in allowed:
            if key in entry:
                step.opts[key] = _step_option(where, entry, verb, key, places)
        if verb == "bvh":
            clips[step.value] = _clip(where, entry, step.value, path, height, joint_map)
        steps.append(step)
    return steps, clips


def _step_value(where: Where, entry: dict, verb: str, what: str, places: dict) -> Any:
    value = entry[verb]
    bad = where.at_key(entry, verb, f"'{verb}' takes {what}, got {value!r}")
    if verb in ("raise", "lower", "reach", "point", "open", "close", "lasso"):
        if not isinstance(value, str) or value not in SIDES:
            raise bad
        return value
    if verb == "walk":
        points = value if isinstance(value, list) and value and isinstance(value[0], list) \
            else [value]
        for p in points:
            if not (isinstance(p, list) and len(p) == 2 and all(_num(v) for v in p)):
                raise bad
        return [[float(v) for v in p] for p in points]
    if verb == "circle":
        if not (isinstance(value, list) and len(value) == 2 and all(_num(v) for v in value)):
            raise bad
        return [float(v) for v in value]
    if verb == "step":
        if isinstance(value, str) and value in ("forward", "back", "left", "right"):
            return value
        if isinstance(value, list) and len(value) == 2 and all(_num(v) for v in value):
            return [float(v) for v in value]
        raise bad
    if verb in ("turn", "wait"):
        if not _num(value) or (verb == "wait" and value < 0):
            raise bad
        return float(value)
    if verb == "face":
        if _num(value) or (isinstance(value, str) and value in places) or (isinstance(value, list) and len(value) == 2
                                               and all(_num(v) for v in value)):
            return value
        raise where.at_key(entry, verb, f"'face' takes {what}; '{value}' is not a sensor "
                           f"({', '.join(places)})")
    if verb == "hands":
        if isinstance(value, dict):
            where.check_keys(value, SIDES, "'hands'")
            return {side: _hand_state(where, value, side, v) for side, v in value.items()}
        return _hand_state(where, entry, verb, value)
    if verb == "crouch":
        if not _num(value) or not 0 <= value <= 0.8:
            raise bad
        return float(value)
    if verb in ("stand", "leave"):
        if value is not True:
            raise bad
        return True
    if verb == "jump":
        value = 0.3 if value is True else value
        if not _num(value) or not 0 < value <= 1.0:
            raise where.at_key(entry, verb, f"'jump' takes a height in metres (0-1) or true, "
                               f"got {entry[verb]!r}")
        return float(value)
    if verb == "enter":
        if value is True:
            return True
        if isinstance(value, list) and len(value) == 2 and all(_num(v) for v in value):
            return [float(v) for v in value]
        raise bad
    if verb == "bvh":
        if not isinstance(value, str) or not value:
            raise bad
        return value
    if verb == "gait":
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise bad
        return value
    raise bad  # pragma: no cover - every verb is handled above


def _num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _step_option(where: Where, entry: dict, verb: str, key: str, places: dict) -> Any:
    value = entry[key]
    if key == "facing":
        if (isinstance(value, str) and (value in ("travel", "keep", "backwards") or value in places)) or _num(value) or (
                isinstance(value, list) and len(value) == 2 and all(_num(v) for v in value)):
            return value
        raise where.at_key(entry, key, "'facing' takes travel, backwards, keep, degrees, a "
                           "point [x, z] or a sensor id")
    if key == "plane":
        if (isinstance(value, str) and value in ("side", "front", "diagonal")) or _num(value):
            return value
        raise where.at_key(entry, key, "'plane' takes side, front, diagonal or degrees "
                           "(0 side, 90 front)")
    if key == "to" and verb in ("reach", "point"):
        if isinstance(value, str) and value in places:
            return value
        if isinstance(value, list) and len(value) == 3 and all(_num(v) for v in value):
            return [float(v) for v in value]
        raise where.at_key(entry, key, "'to' takes a point [x, y, z] in metres or a sensor id")
    if key == "lead":
        if value not in ("left", "right"):
            raise where.at_key(entry, key, "'lead' is the foot that starts: left or right")
        return value
    if key == "repeat":
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise where.at_key(entry, key, "'repeat' must be a whole number >= 1")
        return value
    if key in ("over", "speed"):
        return where.number(entry, key, 0.0, exclusive_minimum=0.0)
    if key in ("turns", "to", "elbow"):
        return where.number(entry, key, 0.0)
    return where.number(entry, key, 0.0, minimum=0.0)


def _clip(where: Where, entry: dict, file: str, path: str, height: float,
          joint_map: dict) -> Clip:
    from ..importers.bvh import BvhMotion, load_bvh
    full = Path(file) if Path(file).is_absolute() else Path(path).parent / file
    if not full.exists():
        raise where.at_key(entry, "bvh", f"BVH file '{file}' not found (looked for {full})")
    try:
        return BvhMotion(load_bvh(full), height, joint_map or None)
    except ConfigError as exc:
        if exc.path is not None:
            raise
        raise where.at_key(entry, "bvh", exc.bare_message) from None


def _events(where: Where, data: dict, sensors: list[str], performers: dict[str, Performer],
            ) -> list[Event]:
    items = data.get("events") or []
    if not isinstance(items, list):
        raise where.at_key(data, "events", "'events' must be a list")
    out: list[Event] = []
    marks = getattr(items, "marks", [None] * len(items))
    kinds = ("bump", "unplug", "replug", "enter", "leave")
    for k, entry in enumerate(items):
        entry = where.mapping(entry, "an event", marks[k])
        found = [key for key in kinds if key in entry]
        if len(found) != 1:
            where.check_keys(entry, (*kinds, "at", "yaw", "pitch", "roll", "move", "position"),
                             "an event")
            raise where.error("an event needs exactly one of: " + ", ".join(kinds),
                              getattr(entry, "mark", marks[k]))
        kind = found[0]
        allowed = {"bump": ("yaw", "pitch", "roll", "move"), "enter": ("position",)}.get(kind, ())
        where.check_keys(entry, (kind, "at", *allowed), f"a '{kind}' event")
        if "at" not in entry:
            raise where.error(f"the '{kind}' event needs 'at' (seconds)", entry.mark)
        at = where.number(entry, "at", 0.0, minimum=0.0)
        target = str(entry[kind])
        names = sensors if kind in ("bump", "unplug", "replug") else list(performers)
        if target not in names:
            raise where.at_key(entry, kind, f"'{target}' is not a "
                               f"{'sensor' if names is sensors else 'performer'} "
                               f"({', '.join(names)})")
        event = Event(at, kind, target)
        if kind == "bump":
            event.yaw = math.radians(where.number(entry, "yaw", 0.0))
            event.pitch = math.radians(where.number(entry, "pitch", 0.0))
            event.roll = math.radians(where.number(entry, "roll", 0.0))
            if "move" in entry:
                event.move = _point(where, entry, "move", (3,))
        if kind in ("enter", "leave"):
            performer = performers[target]
            if kind == "enter" and "position" in entry:
                from .channels import Still
                here = performer.pos.segment_at(at)
                performer.pos.add(Still(at, _point(where, entry, "position"),
                                        here.distance(at) if here else 0.0))
            performer.overrides.append((at, kind == "enter"))
            performer.overrides.sort(key=lambda o: o[0])
        out.append(event)
    out.sort(key=lambda e: e.at)
    return out
