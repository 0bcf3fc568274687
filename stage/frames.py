"""The frame types that cross layers: what the engine reads and what it hands on.

``SensorFrame`` is one sensor's skeleton as it arrived (calibration and tools
watch these); ``FusedFrame`` holds the fused ``Body`` of every person, and is
what the piece runtime and every view receive. Views and plugins import this
module, never the engine.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from .joints import HandState


@dataclass(slots=True)
class SensorFrame:
    """One sensor's skeleton as it arrived, before fusion (for calibration and monitors)."""

    sensor: str
    user: int
    t: float                        # capture time, engine clock
    joints: np.ndarray              # (25, 3) metres, the SENSOR's own space
    conf: np.ndarray                # (25,)
    transform: np.ndarray | None    # (4, 4) sensor -> stage in use now; None = not fused
    floor: np.ndarray | None = None  # (4,) the sensor's last /floorPlane (a, b, c, d), if any


@dataclass(slots=True)
class Body:
    """One fused person in one frame. Arrays are stage space, metres."""

    id: int
    joints: np.ndarray      # (25, 3) smoothed positions
    conf: np.ndarray        # (25,) 0 where no sensor saw the joint in this frame
    velocity: np.ndarray    # (25, 3) m/s, from the Kalman filter
    hands: tuple[HandState, HandState]
    position: np.ndarray    # (3,) torso centre
    sensors: tuple[str, ...]
    #: capture time (engine clock) the joints refer to, plus ``horizon``: a forecast body
    #: (``FusedFrame.forecasts``) is the filter's prediction ``horizon`` s past its capture
    t: float = float("nan")
    horizon: float = 0.0
    #: (25,) position s.d. per joint, m, of a forecast (None: a measured body)
    sd: np.ndarray | None = None


@dataclass(slots=True)
class FusedFrame:
    t: float
    bodies: dict[int, Body]  # every person currently tracked
    updated: tuple[int, ...]
    new: tuple[int, ...]
    lost: tuple[int, ...]
    #: horizon (s) -> every body of ``bodies`` predicted that far past its capture time,
    #: for the horizons pieces and views asked the engine for (docs/anticipation.md); a
    #: ``Forecasts`` where some were asked for only when read
    forecasts: Mapping[float, dict[int, Body]] = field(default_factory=dict)


class Forecasts(Mapping):
    """A frame's forecasts where some horizons are made only when read (``lazy``): the
    piece asks for its anticipating triggers' horizons so, and reads them on the engine
    thread while the engine calls it, only in the sections where such a trigger is active.
    ``seal`` (the engine, once its listeners have returned) forgets how to make them: a
    horizon nobody read is then not in the mapping, so a view thread holding the frame
    later never predicts from a filter that has moved on."""

    __slots__ = ("_made", "_lazy", "_make")

    def __init__(self, made: dict[float, dict[int, Body]], lazy: tuple[float, ...],
                 make: Callable[[float], dict[int, Body]]) -> None:
        self._made, self._lazy, self._make = made, lazy, make

    def __getitem__(self, horizon: float) -> dict[int, Body]:
        got = self._made.get(horizon)
        if got is None:
            if self._make is None or horizon not in self._lazy:
                raise KeyError(horizon)
            got = self._made[horizon] = self._make(horizon)
        return got

    def __contains__(self, horizon: object) -> bool:
        return horizon in self._made or (self._make is not None and horizon in self._lazy)

    def __iter__(self) -> Iterator[float]:
        if self._make is None:
            return iter(list(self._made))
        return iter(list(self._made) + [h for h in self._lazy if h not in self._made])

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def seal(self) -> None:
        self._make, self._lazy = None, ()


def fused_json(frame) -> dict:
    """A FusedFrame as plain JSON (floats kept exact: json writes the shortest repr)."""
    return {"t": frame.t, "updated": list(frame.updated), "new": list(frame.new),
            "lost": list(frame.lost),
            "bodies": {str(pid): {"joints": b.joints.tolist(), "conf": b.conf.tolist(),
                                  "hands": [int(b.hands[0]), int(b.hands[1])],
                                  "position": b.position.tolist(), "sensors": list(b.sensors)}
                       for pid, b in sorted(frame.bodies.items())}}
