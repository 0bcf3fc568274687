"""Anticipating triggers (docs/anticipation.md): firings on a crossing the filter predicts.

A trigger with ``anticipate`` keeps a second detector that watches each body as the
engine predicts it ``ahead`` s past its capture time (``FusedFrame.forecasts``). A
predicted crossing waits, re-checked each frame, until it is sure enough (``sure``:
the joint's predicted s.d. at most ``max_sd``, the Gaussian probability of being past
the border at least ``min_p``, the measured approach at least ``trend``; the last two
default by joint group, ``GROUP_DEFAULTS``) and the measured detector is armed for the
joint (one arming for both: one movement fires once), then fires; the measured crossing
then only confirms it (the runtime drops that firing); one the measurements have not made
``within`` s after the predicted moment is contradicted: counted, told as a
``TriggerContradicted`` event, and its notes cut short where the trigger asks.
These functions run on the runtime's thread, as part of ``PieceRuntime``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from ..engine.forecast import speed_limits
from ..events import TriggerContradicted
from ..settings import ForecastSettings
from .model import BODY, Anticipation, Trigger, Zone, joint_label
from .triggers import Firing, Person

if TYPE_CHECKING:
    from .runtime import PieceRuntime, _TriggerRun

SQRT2 = math.sqrt(2.0)

#: joint group -> (min_p, trend m/s or None) for an ``anticipate`` that does not say.
#: Chosen on bench/bench_anticipation.py's tuning seeds 1-3 (docs/anticipation.md): a foot
#: that lifts fast but not high is predicted past a height as often as one that goes on
#: rising, so feet wait for a nearly certain prediction (0.94; with the feet's velocity
#: memory in the forecast 0.86 gave more earliness on those seeds, but added false feet on
#: the check seeds 4-10 and over seeds 1-20 and 21-40, so it was not kept); a hand
#: hovering near a border is predicted across it by its jitter, so hands need a measured
#: approach, 1.5 m/s (1.0 until stop 24: a slow rise to just above the head, 1.3-1.5 m/s at
#: the firing, was predicted across 100-160 ms early; 1.5 was read off those events on
#: seeds 4-80 and kept because the seeds nobody had run, 81-100, confirmed it: 40 -> 38
#: false triggers against 35 without forecast, the same 30.5 ms earlier); the torso
#: (zones) moves smoothly and fires on the bare prediction.
GROUP_DEFAULTS: dict[str, tuple[float, float | None, int]] = {
    "legs": (0.94, None, 1), "arms": (0.0, 1.5, 1), "torso": (0.0, None, 1)}
_LEGS = {"KneeLeft", "KneeRight", "AnkleLeft", "AnkleRight", "FootLeft", "FootRight"}
_ARMS = {"ElbowLeft", "ElbowRight", "WristLeft", "WristRight", "HandLeft", "HandRight",
         "HandTipLeft", "HandTipRight", "ThumbLeft", "ThumbRight"}


#: how far (m) a measured joint may move between two frames beyond its speed limit (the
#: forecast's defaults) times the time between them; further is a jump -- one sensor's limb
#: swap, the tracker re-finding a person elsewhere -- and no prediction is trusted from it
JUMP_M = 0.25
_LIMITS = speed_limits(ForecastSettings()).tolist()


def group(j: int) -> str:
    """The joint group whose defaults ``j`` takes: legs, arms or torso (BODY: torso)."""
    name = joint_label(j)
    return "legs" if name in _LEGS else "arms" if name in _ARMS else "torso"


def rule(a: Anticipation, j: int) -> tuple[float, float | None, int]:
    """(min_p, trend, persist) for joint ``j``: the trigger's, else its group's defaults."""
    min_p, trend, persist = GROUP_DEFAULTS[group(j)]
    return (min_p if a.min_p is None else a.min_p, trend if a.trend is None else a.trend,
            persist if a.persist is None else a.persist)


def persons_ahead(rt: PieceRuntime, horizon: float) -> dict[int, Person]:
    """This frame's persons predicted ``horizon`` s ahead ({} if the engine sent none)."""
    out = rt._ahead.get(horizon)
    if out is None:
        bodies = rt._frame.forecasts.get(horizon)
        if bodies is None:
            rt.counts["forecast_missing"] += 1
            bodies = {}
        out = rt._ahead[horizon] = {
            pid: Person(b, rt.min_conf, rt.arrivals.get(pid, rt._frame.t))
            for pid, b in bodies.items()}
    return out


def depth(zone: Zone, x: float, y: float, z: float) -> float:
    """Signed metres inside ``zone``: the smallest slack to any border (> 0 inside, < 0
    outside; outside, at most the true distance)."""
    if zone.shape == "cylinder":
        dx, dz = x - zone.centre[0], z - zone.centre[1]
        return min(zone.radius - math.sqrt(dx * dx + dz * dz), y - zone.bottom, zone.top - y)
    if zone.shape == "sphere":
        dx, dy, dz = x - zone.centre[0], y - zone.centre[1], z - zone.centre[2]
        return zone.radius - math.sqrt(dx * dx + dy * dy + dz * dz)
    lo, hi = zone.low, zone.high
    return min(x - lo[0], hi[0] - x, y - lo[1], hi[1] - y, z - lo[2], hi[2] - z)


def margin(trig: Trigger, p: Person, j: int) -> tuple[float, float] | None:
    """How far (m) ``p``'s joint ``j`` is past ``trig``'s border in the firing direction
    (> 0: crossed), and how fast (m/s) it moves that way; None where unseen."""
    pos = p.xyz(j)
    if pos is None:
        return None
    v = p.vel(j)
    kind = trig.kind
    if kind in ("rises_above", "falls_below"):
        sign = 1.0 if kind == "rises_above" else -1.0
        level, vlevel = trig.threshold, 0.0
        if trig.threshold_joint is not None:
            r = p.xyz(trig.threshold_joint)
            if r is None:
                return None
            level, vlevel = r[1], p.vel(trig.threshold_joint)[1]
        return sign * (pos[1] - level), sign * (v[1] - vlevel)
    sign = 1.0 if kind == "enters" else -1.0
    d = depth(trig.zone, pos[0], pos[1], pos[2])
    # the depth's rate along the velocity (a 1 ms step: the depth is piecewise linear)
    ahead = depth(trig.zone, pos[0] + v[0] * 1e-3, pos[1] + v[1] * 1e-3, pos[2] + v[2] * 1e-3)
    return sign * d, sign * (ahead - d) * 1e3


def _sd(p: Person, trig: Trigger, j: int) -> float:
    """The predicted s.d. (m) of ``j``'s margin: the joint's, and the reference joint's too."""
    sd = p.body.sd
    if sd is None:
        return float("inf")
    # the torso centre moves like SpineMid (as its velocity does)
    s = float(sd[1 if j == BODY else j])
    if trig.threshold_joint is not None and trig.kind in ("rises_above", "falls_below"):
        s = math.hypot(s, float(sd[trig.threshold_joint]))
    return s if math.isfinite(s) else float("inf")


def sure(a: Anticipation, trig: Trigger, ahead: Person, now: Person | None, j: int) -> bool:
    """Whether a predicted crossing of ``j`` is sure enough to fire: its s.d. at most
    ``max_sd``, the probability that the joint is past the border at the predicted moment
    (Gaussian: margin over s.d.) at least ``min_p``, and, if ``trend`` is set, the measured
    joint moving towards the border at least that fast."""
    s = _sd(ahead, trig, j)
    if not s <= a.max_sd:
        return False
    min_p, trend, _ = rule(a, j)
    if min_p > 0.0:
        m = margin(trig, ahead, j)
        if m is None or 0.5 * (1.0 + math.erf(m[0] / (s * SQRT2))) < min_p:
            return False
    if trend is not None:
        m = margin(trig, now, j) if now is not None else None
        if m is None or m[1] < trend:
            return False
    return True


def jumped(now: Person | None, before: Person | None, j: int) -> bool:
    """Whether measured joint ``j`` jumped between the frame before (``before``) and this
    one (``now``): moved more than its speed limit allows, plus ``JUMP_M``."""
    if now is None or before is None:
        return False
    a, b = now.xyz(j), before.xyz(j)
    dt = now.body.t - before.body.t
    if a is None or b is None or not dt >= 0.0:
        return False
    d = math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)
    return d > _LIMITS[1 if j == BODY else j] * dt + JUMP_M


def anticipate(rt: PieceRuntime, run: _TriggerRun, t: float, chosen: list[Person]) -> None:
    """Fire ``run`` on crossings predicted ahead once they are sure enough (``sure``) and
    the measured detector is armed for the joint: a predicted crossing waits, re-checked
    each frame, until it is, until the prediction falls back behind the border by the
    hysteresis, or until the measurements fire it."""
    a, trig = run.trigger.anticipate, run.trigger
    ahead = persons_ahead(rt, a.ahead)
    predicted: list[Firing] = []
    run.ahead.frame(t, [ahead[p.id] for p in chosen if p.id in ahead], predicted)
    for f in predicted:
        key = (f.person, f.joint)
        if key not in run.pending:
            run.waiting.setdefault(key, [t, 0])   # first predicted at, sure on n frames in a row
    if not run.waiting:
        return
    now = {p.id: p for p in chosen}
    for key, wait in list(run.waiting.items()):
        pid, j = key
        p = ahead.get(pid)
        m = margin(trig, p, j) if p is not None else None
        if m is None:
            continue                     # not seen this frame: wait on
        if m[0] < -trig.hysteresis or t - wait[0] > a.ahead:
            # the prediction went back, or the measurements have had the time to catch up
            del run.waiting[key]
            continue
        if run.detector.armed(key) is False:
            # the measured joint is still past the border (or crossed in this very frame):
            # the predicted crossing is the movement the measurements have, not a new one
            continue
        if not sure(a, trig, p, now.get(pid), j) or jumped(now.get(pid), rt.before.get(pid), j):
            if wait[0] == t:
                rt.counts["unsure"] += 1     # counted once per predicted crossing
            wait[1] = 0
            continue
        wait[1] += 1
        if wait[1] < rule(a, j)[2]:
            continue                     # sure, but not yet on enough frames in a row
        del run.waiting[key]
        f = Firing(pid, j, p.xyz(j)[1] if j != BODY and trig.kind in ("rises_above",
                                                                     "falls_below") else None,
                   p.speed(j))
        if rt._consider(run, f, t, a.ahead):
            rt.counts["anticipated"] += 1
            run.pending[key] = (t, t + a.ahead + a.within, rt._firings)


def confirmed(rt: PieceRuntime, run: _TriggerRun, f: Firing, t: float) -> None:
    """The measurements made the crossing ``run`` fired on a prediction: no second firing,
    and the trigger's cooldown runs from now, as it would have without anticipation (a
    glitch just after the measured crossing must not fire where the measured trigger would
    have been cooling down)."""
    rt.counts["confirmed"] += 1
    key = run.cooldown_key(f)
    run.last[key] = max(run.last.get(key, t), t)


def contradicted(rt: PieceRuntime, t: float) -> None:
    """Predicted crossings the measurements have not made in time: counted, told, and
    their notes cut short where the trigger asks."""
    for run in rt._all_runs():
        if not run.pending:
            continue
        trig = run.trigger
        for key, (fired, deadline, firing) in list(run.pending.items()):
            if t < deadline:
                continue
            del run.pending[key]
            rt.counts["contradicted"] += 1
            cut = trig.anticipate.cut and rt.voices.retract(
                t, trig.name, firing, "contradicted") > 0
            joint = None if key[1] is None else joint_label(key[1])
            rt._out.append(TriggerContradicted(t, rt.section.name, trig.name, key[0],
                                               joint, fired, cut))
            rt._narrate(t, f"[{rt.section.index + 1}] {trig.name}: predicted at "
                           f"{fired:.3f}, not measured" + ("; cut short" if cut else ""))
