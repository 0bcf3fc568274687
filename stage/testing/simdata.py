"""Simulated sensor streams with known calibrations, for calibration tests and benchmarks.

Everything comes from the simulator: the scenarios are built here (as YAML,
like any scenario file), ``Simulator`` runs them, and the datagrams are
decoded by ``streams_from_datagrams``, as a recording's would be. The true
transforms are the simulator's exact rig. Clocks are fixed (no offset, no
drift, frames at the start of each period) unless a scenario asks otherwise,
so streams line up sensor against sensor as the tests expect; the Kinect model
is the simulator's default, tuned on real recordings (heavy-tailed joints:
view-dependent bias, limb swaps, guessed inferred joints; docs/sources.md),
unless a test asks for ``CLEAN_KINECT`` and says why; everything else (field of
view, occlusion, acquisition, frame jitter, drops, NaN frames) is the model's,
seeded.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import yaml

from ..calibration.streams import Stream, streams_from_datagrams
from ..sensors.sim import KinectModel, Scenario, Simulator, parse_scenario
from ..yamlio import loads_marked

#: a Kinect that reports the truth: no noise, fit error, occlusion bias, heavy tails, jitter,
#: drops or NaN (its pipeline delay stays, without jitter: every sensor shows the same
#: instant for the same capture stamp, so paired frames are exact)
IDEAL_KINECT = {"noise_m": 0.0, "noise_per_m": 0.0, "fit_bias_m": 0.0, "occlusion_bias_m": 0.0,
                "frame_jitter_s": 0.0, "pipeline_jitter_s": 0.0, "drop_p": 0.0, "nan_p": 0.0,
                "preset": "clean"}
#: the error budget the methods' maths are stated for (docs/calibration.md), with none of
#: the heavy tails real skeletons have: 1 cm of white noise per axis on every joint, hidden
#: joints inferred and pulled 3 cm towards the sensor, no fit error, no view-dependent bias,
#: limb swaps or guessed joints. NOT the default (that is the realistic model): a test that
#: checks a method's precision asks for it (``kinect=CLEAN_KINECT``) and says why.
CLEAN_KINECT = {"preset": "clean", "noise_m": 0.01, "noise_per_m": 0.0,
                "noise_correlation": 0.0, "feet_noise": 1.0, "hands_noise": 1.0,
                "inferred_noise": 1.0, "fit_bias_m": 0.0, "occlusion_bias_m": 0.03}
#: what fixes a sensor's clock: offset, drift and frame phase (the seed would draw them)
_CLOCK = {"clock_offset": 0.0, "clock_drift_ppm": 0.0, "phase": 0.0}


def kinect_model(**keys: Any) -> KinectModel:
    """The simulator's Kinect model (its realistic defaults) with a scenario's ``kinect:``
    keys over it (``preset`` included), for ``VirtualKinect`` in tests and benchmarks."""
    preset = keys.pop("preset", "real")
    return replace(KinectModel.preset(preset), **keys)


def wander(period_s: float = 20.0, points: int = 24) -> dict[str, Any]:
    """A performer walking a 2.4 m x 1.6 m figure of eight round the origin (one lap per
    ``period_s``), raising the arms in turn every 3 s; looping."""
    w = 2 * math.pi / period_s
    path = [[round(1.2 * math.sin(w * t), 4), round(0.8 * math.sin(2 * w * t), 4)]
            for t in np.linspace(0.0, period_s, points + 1)[1:]]
    arms: list[dict[str, Any]] = [{"raise": "left", "to": 170, "over": 3, "at": 0}]
    up, t = "left", 3.0
    while t < period_s - 1e-9:
        down, up = up, "right" if up == "left" else "left"
        over = min(3.0, period_s - t)
        arms.append({"lower": down, "over": over, "at": t})
        if t + 3.0 < period_s - 1e-9:   # the lap ends with both arms down, as it started
            arms.append({"raise": up, "to": 170, "over": 3, "at": t})
        t += 3.0
    return {"name": "walker", "position": [0, 0], "facing": math.degrees(math.atan2(1.2, 1.6)),
            "loop": True, "timeline": [{"walk": path, "over": period_s}] + arms}


def standing_still() -> dict[str, Any]:
    """A performer standing at the origin (where ``wander`` starts), arms out to the sides."""
    return {"name": "walker", "position": [0, 0], "facing": math.degrees(math.atan2(1.2, 1.6)),
            "timeline": [{"raise": "both", "to": 90, "over": 0.5}]}


def walk_line(start: tuple[float, float], end: tuple[float, float], period_s: float = 24.0,
              ) -> dict[str, Any]:
    """A performer walking from ``start`` to ``end`` and back ((x, z) metres) once per
    ``period_s``, the left arm rising and falling every 2.5 s, the right every 3.5 s."""
    half = period_s / 2
    steps: list[tuple[float, dict[str, Any]]] = [
        (0.0, {"walk": list(end), "over": half}), (half, {"walk": list(start), "over": half})]
    for side, every in (("left", 2.5), ("right", 3.5)):
        raised, t = False, 0.0
        while t + every <= period_s + 1e-9:
            step: dict[str, Any] = {"lower": side} if raised else {"raise": side, "to": 170}
            steps.append((t, {**step, "over": every}))
            raised, t = not raised, t + every
    steps.sort(key=lambda s: s[0])  # stable: the walks stay before the arms at the same time
    return {"name": "walker", "position": list(start), "loop": True,
            "timeline": [{**step, "at": t} for t, step in steps]}


def scenario(sensors: dict[str, dict], performer: dict[str, Any], *,
             kinect: dict[str, float] | None = None,
             noise: dict[str, float] | None = None,
             name: str = "calibration-test") -> Scenario:
    """A scenario of these ``sensors`` (id -> the scenario file's sensor keys; clocks fixed
    unless given) watching one ``performer`` (a performer entry of a scenario file). The
    Kinect model: its realistic defaults, then ``noise``, then ``kinect`` (both: a
    scenario's ``kinect:`` keys, e.g. ``CLEAN_KINECT``)."""
    data: dict[str, Any] = {"name": name,
                            "sensors": {sid: {**_CLOCK, **spec} for sid, spec in sensors.items()},
                            "performers": [performer],
                            "kinect": {**(noise or {}), **(kinect or {})}}
    return parse_scenario(loads_marked(yaml.safe_dump(data, sort_keys=False)), f"<{name}>")


def two_sensors(tilt_deg: float = 8.0, roll_deg: float = 0.0, *, offset_s: float = 0.0,
                phase_s: float = 0.0, performer: dict[str, Any] | None = None,
                kinect: dict[str, float] | None = None) -> Scenario:
    """Two sensors 100 degrees apart round a 3.2 m circle: kinect-a (the reference) 0.8 m
    high and level at z = -3.2 looking along +z, kinect-b 1.5 m high tilted down
    ``tilt_deg`` and rolled ``roll_deg``; kinect-b's clock is ``offset_s`` ahead and its
    frames come ``phase_s`` into each frame period. Default performer: ``wander()``."""
    angle = math.radians(100.0)
    b = [3.2 * math.sin(angle), 1.5, -3.2 * math.cos(angle)]
    sensors = {"kinect-a": {"position": [0.0, 0.8, -3.2], "look_at": [0.0, 0.8, 0.0]},
               "kinect-b": {"position": b, "yaw": -100.0, "pitch": tilt_deg, "roll": roll_deg,
                            "clock_offset": offset_s, "phase": phase_s}}
    return scenario(sensors, performer or wander(), kinect=kinect)


def row_of_sensors(n: int, spacing: float, kinect: dict[str, Any] | None = None) -> Scenario:
    """``n`` sensors ``spacing`` metres apart along a wall (k0, k1, ...: x = 0, spacing, ...;
    1 m high, looking across the room at 0.8 m), and a performer walking along the far
    side, 2.5 m from the wall, from 1 m before the first to 1 m past the last and back in
    40 s. Each sensor sees its neighbours' part of the walk only where their views overlap."""
    sensors = {f"k{i}": {"position": [i * spacing, 1.0, 0.0], "look_at": [i * spacing, 0.8, 3.0]}
               for i in range(n)}
    return scenario(sensors, walk_line((-1.0, 2.5), ((n - 1) * spacing + 1.0, 2.5), 40.0),
                    kinect=kinect)


def streams(sim: Simulator, duration: float, clocks: str = "capture") -> dict[str, Stream]:
    """Each sensor's stream for ``duration`` simulated seconds, decoded from its datagrams.

    clocks: 'capture' -- frame times are the true capture times (simulation
    seconds), as in the simulator's recordings; 'sensor' -- the sensors' own
    clocks (their bundles' timetags, counted from 0 plus the sensor's
    clock offset), as a recording made without capture times has them.
    """
    if clocks not in ("capture", "sensor"):
        raise ValueError(f"clocks must be 'capture' or 'sensor', not {clocks!r}")
    records = ((capture, data, capture if clocks == "capture" else None)
               for capture, _, data in sim.datagrams(duration, epoch=0.0))
    return streams_from_datagrams(records)[0]


def true_transform(sim: Simulator, sensor: str) -> np.ndarray:
    """(4, 4) the exact calibration of ``sensor``: its space -> the reference sensor's."""
    rig = sim.rig()
    if sensor == rig.reference:
        return np.eye(4)
    return rig.sensors[sensor].calibration.matrix.copy()
