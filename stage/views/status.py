"""The installer's digest of the engine's state: which sensor is fine and why not.

``StatusCollector.collect`` runs on the engine thread (it reads engine state);
``sensor_health`` is the pure rule, tested on its own.
"""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

from .base import SensorStatus, Status

if TYPE_CHECKING:  # the engine is duck-typed here: views import no engine code
    from ..engine import Engine

#: Calibration states that mean "fine". The live calibrator (stage.calibration)
#: writes ok | suspect | recalibrating | uncalibrated with a reason; anything
#: but "ok" is shown red with that reason.
OK_STATES = frozenset({"", "ok", "good", "calibrated", "reference"})
#: With no state from a live calibrator (a fitness from the rig file only), a
#: fitness below this is shown red: the live calibrator's own "suspect" line
#: (0.5: joints 10 cm apart on average).
LOW_FITNESS = 0.5


def sensor_health(client: dict[str, Any], low_fitness: float = LOW_FITNESS,
                  rig_fitness: float | None = None) -> tuple[bool, str, float | None, str]:
    """(ok, reason, fitness, state) for one client of ``Engine.stats()["clients"]``.

    Silence comes first (a silent sensor's calibration cannot be judged), then
    a missing calibration, then what the live calibrator says of it (its state
    rules), then the fitness (the calibrator's, else the rig file's).
    """
    note = client.get("calibration") or {}
    fitness = note.get("fitness", rig_fitness)
    fitness = float(fitness) if isinstance(fitness, (int, float)) and not isinstance(
        fitness, bool) else None
    state = str(note.get("state") or "")
    if not client.get("active", True):
        return False, f"lost tracking: silent for {client.get('silent_s', 0):.1f} s", fitness, state
    if not client.get("calibrated", True) and state.lower() in OK_STATES:
        return False, "not calibrated: its frames are not fused", fitness, state
    reason = str(note.get("reason") or "")
    if note.get("progress"):
        reason = f"{reason} ({note['progress']})" if reason else str(note["progress"])
    if state.lower() not in OK_STATES:
        return False, f"calibration {state}" + (f": {reason}" if reason else ""), fitness, state
    if not state and fitness is not None and fitness < low_fitness:
        return (False, f"calibration fitness {fitness:.2f} below {low_fitness:.2f}"
                + (f": {reason}" if reason else ""), fitness, state)
    return True, "", fitness, state


class StatusCollector:
    """Builds ``Status`` from an engine; remembers frame counts to give rates."""

    def __init__(self, low_fitness: float = LOW_FITNESS) -> None:
        self.low_fitness = low_fitness
        self._last: tuple[float, dict[str, int]] | None = None

    def collect(self, engine: Engine, views: dict[str, dict[str, Any]] | None = None,
                health: dict[str, Any] | None = None) -> Status:
        """Call on the engine thread only (reads the engine's live state)."""
        stats = engine.stats()
        now = engine.clock.now()
        frames = {cid: int(c.get("frames", 0)) for cid, c in stats["clients"].items()}
        previous = self._last
        self._last = (now, frames)
        sensors: dict[str, SensorStatus] = {}
        for cid, client in stats["clients"].items():
            fps = 0.0
            if previous is not None and now > previous[0]:
                before = previous[1].get(cid, frames[cid])
                fps = max(0.0, (frames[cid] - before) / (now - previous[0]))
            # the transform in use (the rig's, or one set live by calibration, or the
            # identity of a reference chosen at run time); the rig's as a fallback
            transform = getattr(engine.clients.get(cid), "transform", None)
            if transform is None:
                transform = engine.rig.transform_for(cid)
            position = None if transform is None else tuple(
                round(float(v), 4) for v in transform[:3, 3])
            config = engine.rig.sensors.get(cid)
            rig_fitness = None if config is None or config.calibration is None else (
                config.calibration.fitness)
            ok, reason, fitness, state = sensor_health(client, self.low_fitness, rig_fitness)
            drops = sum(client.get("drops", {}).values())
            sensors[cid] = SensorStatus(cid, position, round(fps, 2), bool(client.get("active")),
                                        bool(client.get("calibrated")), fitness, state, ok,
                                        reason, drops)
        for sid in engine.rig.sensors:  # listed by the installer, never heard from
            if sid not in sensors:
                transform = engine.rig.transform_for(sid)
                position = None if transform is None else tuple(
                    round(float(v), 4) for v in transform[:3, 3])
                sensors[sid] = SensorStatus(sid, position, 0.0, False, transform is not None,
                                            None, "", False, "in the rig but not connected")
        return Status(now, stats, sensors, views or {}, tuple(engine.views), health or {})
