"""Foot placements and gait parameters, seed 003's way, offline and live.

Seed 003 identifies foot placements by "the events when one foot passes
the other in walking direction ... the intersections of the ankle
trajectories" (Figure 7); step length and time are "the time passed, and
the distance between the two feet in walking direction", step width "the
lateral distance between the feet", a stride "the distance between
subsequent foot placements of the same foot", walking speed the sum of step
lengths over the sum of step times, and a step belongs to the foot placed
last (Figure 6). Here, with the walking direction taken from the pelvis's
smoothed horizontal velocity:

* ``foot_events`` (offline): the ankles cross where the left ankle's lead
  over the right one changes sign (with a 2 cm hysteresis against noise).
  At a crossing one foot swings past the other, which stands where it was
  put down, half-way through its stance: its placement is the median of
  its ankle's position over the middle of the stance (a steadier measure
  than any single frame). A step joins two successive placements (of
  alternate feet): its length and width are their distance along and
  across the walking direction, its time the time between the crossings.
  The first placement of a walk has no step before it: that is the first
  step seed 003 leaves out. The trajectory is gap-filled and filtered (zero
  phase) first, as seed 003 filters its trajectories.
* ``LiveSteps`` (frame by frame, for pieces): a step is reported when the
  foot that has just passed the other lands, i.e. once its lead has stopped
  growing for ``settle_s`` (about a tenth of a second after touch-down),
  with the distance between the two ankles then.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np

from ..joints import JOINT_INDEX as J
from .trajectory import Trajectory, fill, smooth

_AL, _AR = J["AnkleLeft"], J["AnkleRight"]
_PELVIS = (J["SpineBase"], J["HipLeft"], J["HipRight"])
HYSTERESIS_M = 0.02


@dataclass
class Step:
    """One foot placement and the step it ends.

    t: seconds (offline: when the other foot passed this one; live: when it
    landed); side: the foot placed ("left"/"right"); length, width: metres
    from the previous placement along and across the walking direction, time:
    seconds since it (all None for a walk's first placement); stride: metres
    from this foot's previous placement (None if unknown); x, z: where the
    ankle stands (stage metres); bout: which walk (a pause longer than
    ``bout_gap_s`` starts a new one); index: its place in the bout.
    """

    t: float
    side: str
    length: float | None
    width: float | None
    time: float | None
    stride: float | None
    x: float
    z: float
    bout: int = 0
    index: int = 0

    @property
    def first(self) -> bool:
        return self.index == 0

    def as_json(self) -> dict:
        return {k: (round(v, 5) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def _pelvis(joints: np.ndarray) -> np.ndarray:
    """(N, 3) pelvis: SpineBase, else the middle of the hips."""
    base = joints[:, _PELVIS[0]]
    hips = 0.5 * (joints[:, _PELVIS[1]] + joints[:, _PELVIS[2]])
    return np.where(np.isfinite(base), base, hips)


def walking_direction(traj: Trajectory, sigma_s: float = 0.3,
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(unit horizontal walking direction (N, 2) as (x, z), pelvis speed (N,) m/s).

    From the pelvis smoothed over ``sigma_s`` seconds; NaN where unknown.
    """
    if len(traj) < 3:
        return np.full((len(traj), 2), np.nan), np.full(len(traj), np.nan)
    pelvis = smooth(fill(traj.t, _pelvis(traj.joints), 0.25), sigma_s * traj.rate)
    v = np.gradient(pelvis[:, [0, 2]], traj.t, axis=0)
    speed = np.linalg.norm(v, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / speed[:, None], speed


def foot_events(traj: Trajectory, *, min_speed: float = 0.2, min_lead: float = 0.10,
                standing_s: float = 0.8, fill_s: float = 0.25, smooth_s: float = 0.05,
                bout_gap_s: float = 1.5) -> list[Step]:
    """Every foot placement of a trajectory (seed 003), in time order.

    ``fill_s``: gaps up to this long are interpolated first; ``smooth_s``:
    the zero-phase low-pass (s.d., seconds); ``min_speed``: the pelvis must
    move at least this fast (m/s) for the body to be walking; ``min_lead``:
    a foot counts as passed only if the other one had been at least this far
    ahead and then gets at least this far ahead itself (metres: feet side by
    side, or a foot closing beside the other, never make a placement, however
    noisy the data); ``standing_s``: a foot passed after standing still this
    long was stood on before the walk began, not put down in it (so the step
    from standing, seed 003's excluded first step, is never measured, whether
    or not the feet happened to be staggered when the walk began).
    """
    if len(traj) < 5:
        return []
    tr = traj.filled(fill_s).smoothed(smooth_s)
    t = tr.t
    d, speed = walking_direction(traj)
    ankles = {"left": tr.joints[:, _AL][:, [0, 2]], "right": tr.joints[:, _AR][:, [0, 2]]}
    rel = ankles["left"] - ankles["right"]
    lead = rel[:, 0] * d[:, 0] + rel[:, 1] * d[:, 1]
    walking = np.isfinite(lead) & (speed >= min_speed)
    idx = np.flatnonzero(walking)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if len(idx) else []
    steps: list[Step] = []
    for run in runs:
        state, most = 0, 0.0
        pending: tuple[float, str] | None = None  # a crossing waiting to be confirmed
        for k, i in enumerate(run):
            new = 1 if lead[i] > HYSTERESIS_M else -1 if lead[i] < -HYSTERESIS_M else state
            if new != state:
                pending = None
                if state and most >= min_lead:
                    # where the lead changed sign, between two samples of this run
                    j = k
                    while j > 1 and np.sign(lead[run[j - 1]]) != np.sign(state):
                        j -= 1
                    a, b = run[j - 1], run[j]
                    u = lead[a] / (lead[a] - lead[b]) if lead[a] != lead[b] else 0.0
                    # the foot that was ahead is the one standing
                    pending = (float(t[a] + u * (t[b] - t[a])), "left" if state > 0 else "right")
                state, most = new, 0.0
            most = max(most, abs(float(lead[i])))
            if pending is not None and most >= min_lead:
                # the passing foot got well ahead: a step, not a foot closing beside the other;
                # and the foot passed was put down in this walk, not stood on before it
                if not _stood(pending[0], ankles[pending[1]], t, standing_s):
                    steps.append(_placement(pending[0], pending[1], ankles[pending[1]], t))
                pending = None
    return _link(steps, bout_gap_s, t, d)


STOOD_M = 0.10


def _stood(tc: float, ankle: np.ndarray, t: np.ndarray, standing_s: float) -> bool:
    """Whether the ankle stood where it is for ``standing_s`` before ``tc``: its median
    positions over 0.15 s at both ends of that time are less than 10 cm apart (medians, so
    a noisy far-away ankle does not seem to move)."""
    early = (t >= tc - standing_s) & (t <= tc - standing_s + 0.15)
    late = (t >= tc - 0.15) & (t <= tc)
    a, b = ankle[early], ankle[late]
    a, b = a[np.isfinite(a).all(axis=1)], b[np.isfinite(b).all(axis=1)]
    if not len(a) or not len(b):
        return False
    return float(np.hypot(*(np.median(a, axis=0) - np.median(b, axis=0)))) < STOOD_M


def _placement(tc: float, side: str, ankle: np.ndarray, t: np.ndarray) -> Step:
    """The standing foot's placement: its median position over +-0.15 s around ``tc``."""
    near = np.abs(t - tc) <= 0.15
    pos = ankle[near & np.isfinite(ankle).all(axis=1)]
    x, z = (np.median(pos, axis=0) if len(pos) else (np.nan, np.nan))
    return Step(tc, side, None, None, None, None, float(x), float(z))


def _link(steps: list[Step], bout_gap_s: float, t: np.ndarray | None = None,
          d: np.ndarray | None = None) -> list[Step]:
    """Bouts, step lengths, widths, times and strides of placements in time order.

    ``t``/``d``: the trajectory's times and walking directions, to measure
    each step along the direction walked between its two placements.
    """
    bout = -1
    previous: Step | None = None
    last_by_side: dict[str, Step] = {}
    for s in steps:
        # a placement missed (the same foot twice) or a pause starts a new walk; a short
        # loss of data between two placements does not
        if previous is None or s.t - previous.t > bout_gap_s or s.side == previous.side \
                or not np.isfinite(s.x):
            bout += 1
            s.index = 0
            last_by_side = {}
        else:
            s.index = previous.index + 1
            s.time = s.t - previous.t
            if t is not None and d is not None:
                # over one stride centred on the step: the pelvis sways towards each standing
                # foot in turn, and a whole sway cycle cancels out of the direction
                half = 0.5 * (s.t - previous.t)
                span = (t >= previous.t - half) & (t <= s.t + half)
                known = span & np.isfinite(d).all(axis=1)
                way = d[known].mean(axis=0) if known.any() else np.full(2, np.nan)
                n = float(np.hypot(*way))
                if n > 1e-6:
                    way = way / n
                    dx, dz = s.x - previous.x, s.z - previous.z
                    s.length = float(dx * way[0] + dz * way[1])
                    s.width = float(abs(dx * way[1] - dz * way[0]))
        s.bout = bout
        before = last_by_side.get(s.side)
        if before is not None and before.index == s.index - 2:
            s.stride = math.hypot(s.x - before.x, s.z - before.z)
        last_by_side[s.side] = s
        previous = s
    return steps


class LiveSteps:
    """Foot placements of one body as its frames arrive (for pieces): ``foot_events`` live.

    ``update(t, joints)`` with stage-space joints (25, 3), NaN where unseen,
    returns the ``Step`` found at this frame, or None. As offline, a foot
    event is where one foot passes the other (reported as soon as the passing
    foot is ``min_lead`` ahead, a few hundredths of a second later); the step
    is the one the standing foot ended, measured from its position over the
    last ``window_s`` seconds (it has been standing for a while, so a
    smoother's overshoot at touch-down has died away) to the previous
    placement, along the direction the pelvis moved over the last stride.
    """

    def __init__(self, min_lead: float = 0.10, min_speed: float = 0.2, window_s: float = 0.15,
                 heading_tau_s: float = 0.3, bout_gap_s: float = 1.5,
                 standing_s: float = 0.8) -> None:
        self.min_lead, self.min_speed, self.window_s = min_lead, min_speed, window_s
        self.standing_s = standing_s
        self.tau, self.bout_gap_s = heading_tau_s, bout_gap_s
        self._t: float | None = None
        self._pelvis: np.ndarray | None = None
        self._vel = np.zeros(2)
        self._history: deque[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._state, self._most = 0, 0.0
        self._pending: tuple[float, str] | None = None
        self._steps: list[Step] = []


    def update(self, t: float, joints: np.ndarray) -> Step | None:
        joints = np.asarray(joints, float)
        pelvis = _pelvis(joints[None])[0][[0, 2]]
        if np.isfinite(pelvis).all():
            if self._t is not None and self._pelvis is not None and t > self._t:
                dt = t - self._t
                self._vel += (1.0 - math.exp(-dt / self.tau)) * ((pelvis - self._pelvis) / dt
                                                                 - self._vel)
            self._t, self._pelvis = t, pelvis
        al, ar = joints[_AL, [0, 2]], joints[_AR, [0, 2]]
        speed = float(np.hypot(*self._vel))
        if speed < self.min_speed or not (np.isfinite(al).all() and np.isfinite(ar).all()
                                          and np.isfinite(pelvis).all()):
            self._state, self._most, self._pending = 0, 0.0, None
            return None
        self._history.append((t, pelvis, al, ar))
        while self._history and self._history[0][0] < t - 2.5:
            self._history.popleft()
        lead = float((al - ar) @ (self._vel / speed))
        new = 1 if lead > HYSTERESIS_M else -1 if lead < -HYSTERESIS_M else self._state
        if new != self._state:
            self._pending = None
            if self._state and self._most >= self.min_lead:
                self._pending = (t, "left" if self._state > 0 else "right")
            self._state, self._most = new, 0.0
        self._most = max(self._most, abs(lead))
        if self._pending is not None and self._most >= self.min_lead:
            tc, side = self._pending
            self._pending = None
            k = 2 if side == "left" else 3
            t_hist = np.array([h[0] for h in self._history])
            ankle = np.array([h[k] for h in self._history])
            if not _stood(tc, ankle, t_hist, self.standing_s):
                return self._place(tc, side, now=t)
        return None

    def _place(self, tc: float, side: str, now: float) -> Step:
        k = 2 if side == "left" else 3
        pos = np.array([h[k] for h in self._history if h[0] >= tc - self.window_s])
        x, z = np.median(pos, axis=0)
        step = Step(float(tc), side, None, None, None, None, float(x), float(z))
        last = self._steps[-1] if self._steps else None
        if last is None or tc - last.t > self.bout_gap_s or last.side == side:
            step.bout = last.bout + 1 if last is not None else 0
            self._steps = [step]
            return step
        step.bout, step.index, step.time = last.bout, last.index + 1, float(tc) - last.t
        # the direction walked over about one stride (a whole pelvis sway) up to now
        back = [h for h in self._history if h[0] >= now - 2.0 * step.time]
        way = back[-1][1] - back[0][1] if len(back) > 1 else self._vel
        n = float(np.hypot(*way))
        way = way / n if n > 1e-6 else self._vel / float(np.hypot(*self._vel))
        dx, dz = step.x - last.x, step.z - last.z
        step.length = float(dx * way[0] + dz * way[1])
        step.width = float(abs(dx * way[1] - dz * way[0]))
        if len(self._steps) >= 2 and self._steps[-2].side == side:
            before = self._steps[-2]
            step.stride = math.hypot(step.x - before.x, step.z - before.z)
        self._steps = self._steps[-1:] + [step]
        return step


# ---------------------------------------------------------------- gait parameters
PARAMETERS = ("step_length", "step_width", "step_time", "stride_length")
_FIELD = {"step_length": "length", "step_width": "width", "step_time": "time",
          "stride_length": "stride"}


def included(steps: list[Step], exclude_first: bool = True) -> list[Step]:
    """The steps gait parameters are computed from: each bout's first step left out (seed 003)."""
    return [s for s in steps if not (exclude_first and s.first)]


def values(steps: list[Step], parameter: str, side: str | None = None) -> np.ndarray:
    """The known values of ``parameter`` (a PARAMETERS name) over ``steps`` of one side or both."""
    field = _FIELD[parameter]
    return np.array([getattr(s, field) for s in steps
                     if (side is None or s.side == side) and getattr(s, field) is not None],
                    dtype=float)


def summary(steps: list[Step], exclude_first: bool = True) -> dict:
    """Gait parameters (seed 003): per parameter and side (left, right, all), n / mean / sd;
    walking speed (m/s) and cadence (steps per minute)."""
    use = included(steps, exclude_first)
    out: dict = {"steps": len(steps), "used": len(use), "bouts": len({s.bout for s in steps})}
    for p in PARAMETERS:
        out[p] = {}
        for side in ("left", "right", None):
            v = values(use, p, side)
            out[p][side or "all"] = {"n": int(len(v)),
                                     "mean": float(v.mean()) if len(v) else math.nan,
                                     "sd": float(v.std(ddof=1)) if len(v) > 1 else math.nan}
    timed = [s for s in use if s.time is not None]
    total_t = sum(s.time for s in timed)  # type: ignore[misc]
    out["speed"] = sum(s.length for s in timed) / total_t if total_t > 0 else math.nan
    mean_t = out["step_time"]["all"]["mean"]
    out["cadence"] = 60.0 / mean_t if mean_t and math.isfinite(mean_t) else math.nan
    return out


def match_steps(measured: list[Step], truth: list[Step], max_dt: float = 0.25,
                ) -> list[tuple[Step, Step]]:
    """Pairs (measured, true) of the same foot placed within ``max_dt`` seconds, closest first."""
    pairs = sorted(((abs(m.t - r.t), a, b) for a, m in enumerate(measured)
                    for b, r in enumerate(truth) if m.side == r.side and abs(m.t - r.t) <= max_dt))
    used_m, used_t, out = set(), set(), []
    for _, a, b in pairs:
        if a not in used_m and b not in used_t:
            used_m.add(a)
            used_t.add(b)
            out.append((measured[a], truth[b]))
    return sorted(out, key=lambda p: p[1].t)


def same_steps(measured: list[Step], truth: list[Step], max_dt: float = 0.25,
               ) -> list[tuple[Step, Step]]:
    """Paired placements whose steps are the same step: the placements before them (in their
    walks) are paired with each other too. A missed or extra placement would otherwise set a
    step against half or twice of another."""
    pairs = match_steps(measured, truth, max_dt)
    partner = {id(m): t for m, t in pairs}

    def before(steps: list[Step]) -> dict[int, Step]:
        return {id(b): a for a, b in zip(steps, steps[1:]) if b.index == a.index + 1}
    prev_m, prev_t = before(measured), before(truth)
    return [(m, t) for m, t in pairs
            if id(m) in prev_m and id(t) in prev_t and partner.get(id(prev_m[id(m)])) is
            prev_t[id(t)]]
