"""Anticipating triggers (docs/anticipation.md): firings on a crossing the filter predicts.

A trigger with ``anticipate`` keeps a second detector that watches each body as the
engine predicts it ``ahead`` s past its capture time (``FusedFrame.forecasts``). A
predicted crossing fires when that joint's predicted s.d. is at most ``max_sd``
(else it is ``unsure`` and the measurements decide); the measured crossing then only
confirms it (the runtime drops that firing); one the measurements have not made
``within`` s after the predicted moment is contradicted: counted, told as a
``TriggerContradicted`` event, and its notes cut short where the trigger asks.
These functions run on the runtime's thread, as part of ``PieceRuntime``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..events import TriggerContradicted
from .model import BODY, joint_label
from .triggers import Firing, Person

if TYPE_CHECKING:
    from .runtime import PieceRuntime, _TriggerRun


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


def anticipate(rt: PieceRuntime, run: _TriggerRun, t: float, chosen: list[Person]) -> None:
    """Fire ``run`` on crossings predicted ahead whose uncertainty is small enough."""
    a = run.trigger.anticipate
    ahead = persons_ahead(rt, a.ahead)
    predicted: list[Firing] = []
    run.ahead.frame(t, [ahead[p.id] for p in chosen if p.id in ahead], predicted)
    for f in predicted:
        key = (f.person, f.joint)
        if key in run.pending:
            continue
        sd = ahead[f.person].body.sd
        # the torso centre moves like SpineMid (as its velocity does)
        s = float(sd[1 if f.joint == BODY else f.joint]) if sd is not None else float("inf")
        if not s <= a.max_sd:
            rt.counts["unsure"] += 1     # the measurements will fire it, if they cross
            continue
        if rt._consider(run, f, t, a.ahead):
            rt.counts["anticipated"] += 1
            run.pending[key] = (t, t + a.ahead + a.within, rt._firings)


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
