"""Walks watched by seed 003's six-sensor walkway, for the gait tests and benchmark.

The sensors (and their Kinect model, spelled out in full in the built-in
``walkway`` scenario so a change of the simulator's defaults does not change
these results) come from that scenario; the walker is either the
simulator's planted-feet gait (``GaitClip``: step length, width and cadence
set exactly) or a motion-capture take (the CMU walks), optionally mirrored
left for right. ``simulate`` runs the simulator and decodes its datagrams as
a recording's would be; the truth is sampled from the same performer.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..analysis.integrate import SensorFrames, read_frames
from ..analysis.trajectory import Trajectory
from ..joints import JOINT_INDEX, JOINTS
from ..rig import Rig
from ..sensors.sim import Performer, Scenario, Simulator, Step, load_scenario
from ..sensors.sim.gait import GaitClip

#: the one-sided subset of seed 003: the sensors on the walker's left (+x, walking +z)
LEFT = ("kinect-l1", "kinect-l2", "kinect-l3")
RIGHT = ("kinect-r1", "kinect-r2", "kinect-r3")
_SWAP = np.arange(len(JOINTS))
for _name, _i in JOINT_INDEX.items():
    if _name.endswith("Left"):
        _SWAP[_i], _SWAP[JOINT_INDEX[_name[:-4] + "Right"]] = JOINT_INDEX[_name[:-4] + "Right"], _i


def cmu_file(name: str) -> Path | None:
    """The CMU take ``name`` (e.g. "131_01"): $STAGE_CMU_DIR, else a ``shared/data/cmu`` folder
    beside the checkout or any folder above it; None when absent."""
    folders = [Path(os.environ["STAGE_CMU_DIR"])] if os.environ.get("STAGE_CMU_DIR") else []
    here = Path(__file__).resolve()
    folders += [p / "shared" / "data" / "cmu" for p in here.parents]
    for folder in folders:
        path = folder / f"{name}.bvh"
        if path.exists():
            return path
    return None


class Mirrored:
    """A clip seen in a mirror: x negated, left and right swapped (a left-footed twin)."""

    def __init__(self, clip) -> None:
        self.clip = clip
        self.duration = clip.duration

    def joints(self, t: float) -> np.ndarray:
        j = self.clip.joints(t)[_SWAP].copy()
        j[:, 0] *= -1.0
        return j

    def root(self, t: float) -> np.ndarray:
        r = np.array(self.clip.root(t), float)
        r[0] *= -1.0
        return r

    def heading(self, t: float) -> float:
        return -self.clip.heading(t)

    def conf(self) -> np.ndarray:
        return self.clip.conf()[_SWAP]


def walker(clip, *, height: float, start: tuple[float, float] = (0.0, 0.3),
           name: str = "walker", rate: float | None = None) -> Performer:
    """A performer who stands still for 1 s, then plays ``clip`` so that its overall
    displacement runs along +z from ``start`` (x, z metres, where the clip's root begins)."""
    a = np.asarray(clip.root(0.0), float)
    b = np.asarray(clip.root(clip.duration), float)
    d = b - a
    travel = math.atan2(d[0], d[1]) if np.hypot(*d) > 0.2 else clip.heading(0.0)
    facing = math.degrees(clip.heading(0.0) - travel)
    steps = [Step("wait", 1.0), Step("bvh", "clip", {"facing": facing})]
    return Performer(name, steps, height=height, position=start, facing=0.0,
                     clips={"clip": clip})


def gait_walker(steps: int = 10, length: float = 0.70, width: float = 0.12,
                cadence: float = 110.0, *, height: float = 1.75,
                start: tuple[float, float] = (0.0, 0.3)) -> tuple[Performer, GaitClip]:
    """A performer walking along +z with a set gait, and the gait (for its truth)."""
    from ..sensors.sim.kinematics import proportions
    clip = GaitClip(steps, length, width, cadence, props=proportions(height))
    return walker(clip, height=height, start=start), clip


def cmu_walker(path: Path, *, height: float, mirrored: bool = False,
               start: tuple[float, float] = (0.0, 1.0)) -> Performer:
    """A CMU take scaled to ``height`` metres, walked along +z of the walkway."""
    from ..sensors.importers.bvh import BvhMotion, load_bvh
    clip = BvhMotion(load_bvh(path), height)
    return walker(Mirrored(clip) if mirrored else clip, height=height, start=start)


def walkway(performer: Performer, duration: float) -> Scenario:
    """Seed 003's walkway (the built-in ``walkway`` scenario's sensors) with this walker."""
    base = load_scenario("walkway")
    return Scenario("walkway", base.sensors, [performer], [], base.reference, duration,
                    "seed 003's walkway", None)


def simulate(scenario: Scenario, seed: int, duration: float | None = None,
             ) -> tuple[dict[str, SensorFrames], Rig, Simulator]:
    """Run ``scenario``; its frames per sensor (decoded as a recording's) and its exact rig."""
    sim = Simulator(scenario, seed)
    length = duration if duration is not None else scenario.duration
    frames, _ = read_frames((d.arrival, d.data, d.capture) for d in sim.stream(length))
    return frames, sim.rig(), sim


def truth(performer: Performer, duration: float, rate: float = 120.0) -> Trajectory:
    """The performer's true joints at ``rate`` Hz (motion capture's own rate by default)."""
    t = np.arange(0.0, duration, 1.0 / rate)
    joints = np.full((len(t), len(JOINTS), 3), np.nan)
    for k, tk in enumerate(t):
        state = performer.state(float(tk))
        if state is not None:
            joints[k] = state[0]
    return Trajectory(t, joints, None, "truth")
