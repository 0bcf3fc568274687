"""What the monitor page is sent, as JSON-ready dicts (pure functions).

Message kinds on the event stream (server-sent events, ``event: <kind>``):

- ``frame``  {t, fps, bodies: [{id, joints (25 x [x, y, z]) m, conf (25), hands [l, r],
             position [x, y, z], sensors [...]}]}  at most 30 times a second;
- ``status`` {t, sensors: [...], engine: {...}, views: {...}}  about twice a second;
- ``scene``  {zones: [normalised zones], sections: [...]}  when the piece is set;
- ``piece``  {section, index, zones: {name: [persons]} (occupied ones), mappings: {name: value},
             outputs: {"output address": "latest args"} (OscOut and control changes, which
             mappings send continuously)};
- ``events`` [{seq, t (s since the monitor started), type, text, event}]  new discrete
             events (notes, programs, all-notes-off, sections, triggers, zones).
"""

from __future__ import annotations

import math
from typing import Any, Iterable

import numpy as np

from stage.frames import Body, FusedFrame
from stage.events import (AllNotesOff, ControlChange, Event, MappingValue, Note, OscOut,
                          ProgramChange, SectionChange, TriggerFired, ZoneState)
from stage.joints import JOINTS
from stage.views import Status

#: Default height of a cylinder zone when the piece gives none (m): the piece language's
CYLINDER_HEIGHT_M = 3.0


def frame_json(frame: FusedFrame, fps: float) -> dict[str, Any]:
    return {"t": round(frame.t, 4), "fps": round(fps, 1),
            "bodies": [body_json(b) for _, b in sorted(frame.bodies.items())]}


def body_json(body: Body) -> dict[str, Any]:
    joints = np.nan_to_num(np.asarray(body.joints, dtype=float)).round(3)
    return {"id": int(body.id), "joints": joints.tolist(),
            "conf": np.asarray(body.conf, dtype=float).round(2).tolist(),
            "hands": [h.wire_name for h in body.hands],
            "position": np.nan_to_num(np.asarray(body.position, dtype=float)).round(3).tolist(),
            "sensors": list(body.sensors)}


def status_json(status: Status) -> dict[str, Any]:
    engine = status.engine
    reasons: dict[str, int] = {}
    for per_client in engine.get("drops", {}).values():
        for reason, n in per_client.items():
            reasons[reason] = reasons.get(reason, 0) + n
    views = {name: {"state": v.get("state"), "error": v.get("error"),
                    "frames_dropped": v.get("frames_dropped", 0),
                    "events_dropped": v.get("events_dropped", 0)}
             for name, v in status.views.items()}
    return {
        "t": round(status.t, 3),
        "sensors": [{"id": s.id, "position": s.position, "fps": s.fps, "active": s.active,
                     "calibrated": s.calibrated, "fitness": s.fitness, "state": s.state,
                     "ok": s.ok, "reason": s.reason, "drops": s.drops}
                    for s in sorted(status.sensors.values(), key=lambda s: s.id)],
        "engine": {"uptime_s": engine.get("uptime_s"), "reference": engine.get("reference"),
                   "persons": len(engine.get("persons", {})),
                   "drops_total": engine.get("drops_total", 0), "drops": reasons,
                   "latency_ms": engine.get("latency_ms", {}),
                   "counts": engine.get("counts", {}),
                   # bodies predicted ahead (docs/anticipation.md): horizons and their s.d.
                   "forecast": {k: engine.get("forecast", {}).get(k) for k in
                                ("horizons_s", "views_s", "sd_mm", "speed_capped",
                                 "bones_fixed")}},
        "views": views,
        "view_drops": sum(v["frames_dropped"] + v["events_dropped"] for v in views.values()),
        "health": health_json(status.health),
    }


def health_json(health: dict[str, Any]) -> dict[str, Any] | None:
    """The show's health for the page: ok, the problems, the engine's figures."""
    if not health:
        return None
    engine = health.get("engine", {})
    return {"ok": bool(health.get("ok")), "problems": list(health.get("problems", []))[:20],
            "time": health.get("time"),
            "engine": {k: engine.get(k) for k in ("frame_ms_p99", "rss_mb", "cpu_percent",
                                                  "kernel_drops", "uptime_s")},
            "synths": {name: {"connected": p.get("connected"), "reason": p.get("reason")}
                       for name, p in health.get("synths", {}).items()},
            "calibrator": health.get("calibrator", {})}


def _vec(value: Any, n: int | tuple[int, ...]) -> list[float] | None:
    sizes = (n,) if isinstance(n, int) else n
    if isinstance(value, (int, float)) and not isinstance(value, bool) and 1 in sizes:
        return [float(value)]
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        return None
    return out if len(out) in sizes and all(math.isfinite(v) for v in out) else None


def _num(zone: dict, *keys: str, default: float | None = None) -> float | None:
    for key in keys:
        value = zone.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    return default


def normalise_zone(zone: dict[str, Any]) -> dict[str, Any]:
    """One zone in the page's terms; what cannot be drawn gets ``shape: "unknown"``.

    box: ``min``/``max`` [x, y, z], or ``centre`` (``center``) with ``size`` [w, h, d]
    (a floor-only centre [x, z] stands on y = 0); cylinder: ``centre`` [x, z] or [x, y, z]
    (the base), ``radius``, ``bottom`` (default: the centre's y) with ``height`` or ``top``
    (or ``y``: [bottom, top]); sphere: ``centre``
    [x, y, z], ``radius``. Stage metres.
    """
    name = str(zone.get("name", "?"))
    shape = str(zone.get("shape", "")).lower()
    centre = _vec(zone.get("centre", zone.get("center", zone.get("position"))), (2, 3))
    if centre is not None and len(centre) == 2:
        centre = [centre[0], 0.0, centre[1]]
    if shape == "box":
        lo, hi = _vec(zone.get("min"), 3), _vec(zone.get("max"), 3)
        size = _vec(zone.get("size"), (1, 2, 3))
        if (lo is None or hi is None) and centre is not None and size is not None:
            if len(size) == 1:
                size = size * 3
            elif len(size) == 2:     # [width, depth] on the floor
                size = [size[0], CYLINDER_HEIGHT_M, size[1]]
            lo = [centre[0] - size[0] / 2, centre[1], centre[2] - size[2] / 2]
            hi = [centre[0] + size[0] / 2, centre[1] + size[1], centre[2] + size[2] / 2]
        if lo is not None and hi is not None:
            return {"name": name, "shape": "box", "min": [min(a, b) for a, b in zip(lo, hi)],
                    "max": [max(a, b) for a, b in zip(lo, hi)]}
    elif shape == "cylinder":
        radius = _num(zone, "radius", "r")
        if centre is not None and radius is not None and radius > 0:
            span = _vec(zone.get("y"), 2)
            if span is None:
                bottom = _num(zone, "bottom", default=centre[1])
                top = _num(zone, "top")
                height = _num(zone, "height", "h", default=CYLINDER_HEIGHT_M)
                span = [bottom, top if top is not None else bottom + height]
            return {"name": name, "shape": "cylinder", "centre": centre, "radius": radius,
                    "y0": min(span), "y1": max(span)}
    elif shape == "sphere":
        radius = _num(zone, "radius", "r")
        if centre is not None and radius is not None and radius > 0:
            return {"name": name, "shape": "sphere", "centre": centre, "radius": radius}
    return {"name": name, "shape": "unknown"}


def scene_json(zones: Iterable[dict[str, Any]], sections: Iterable[str]) -> dict[str, Any]:
    return {"zones": [normalise_zone(z) for z in zones], "sections": list(sections)}


def event_text(event: Event) -> str:
    """One short line for the page's event list."""
    if isinstance(event, Note):
        return (f"note {event.note} vel {event.velocity} ch {event.channel + 1} "
                f"{event.duration:.2f} s -> {event.output}")
    if isinstance(event, ControlChange):
        return f"cc {event.control} = {event.value} ch {event.channel + 1} -> {event.output}"
    if isinstance(event, ProgramChange):
        return f"program {event.program} ch {event.channel + 1} -> {event.output}"
    if isinstance(event, AllNotesOff):
        where = event.output or "all outputs"
        return f"all notes off {where}" + ("" if event.channel is None
                                           else f" ch {event.channel + 1}")
    if isinstance(event, OscOut):
        return f"osc {event.address} {' '.join(map(str, event.args))} -> {event.output}".strip()
    if isinstance(event, SectionChange):
        return f"section {event.section}" + (f" (from {event.previous})" if event.previous else "") \
            + (f" by {event.cause}" if event.cause else "")
    if isinstance(event, TriggerFired):
        who = "" if event.person is None else f" person {event.person}"
        joint = f" {event.joint}" if event.joint else ""
        return f"trigger {event.trigger}{who}{joint}"
    if isinstance(event, ZoneState):
        people = ", ".join(map(str, event.persons))
        return f"zone {event.zone} " + (f"occupied by {people}" if event.occupied else "empty")
    if isinstance(event, MappingValue):
        return f"mapping {event.mapping} = {event.value:.3f}"
    return type(event).__name__


JOINT_NAMES = list(JOINTS)
