"""Forecasts: each fused body predicted ahead of its capture time, bounded, with its uncertainty.

A skeleton reaches the engine some 60 ms after the movement it shows (the
sensor's pipeline; docs/anticipation.md). The filter knows each joint's
velocity, so it can say where the joint will be ``h`` seconds after the
body's capture time: the IMM prediction (``kalman.mix``, ``predict``,
``combine``), whose mean is the estimate plus ``h`` times the velocity and
whose covariance grows with ``h``. Two bounds keep a prediction a body:

- **speed**: a joint moves at most its group's speed limit times the
  horizon (``ForecastSettings``: torso, limbs, extremities), so a velocity
  spoilt by a glitch cannot throw a hand across the stage;
- **bones**: walking the skeleton from SpineBase outwards, each predicted
  bone keeps its length at capture time within ``bone_tolerance``: a child
  too far from (or too near to) its parent is moved along the bone.

The uncertainty given with a forecast is each joint's position s.d. (m): the
square root of the mean of its three axes' predicted variances.

A foot's vertical velocity does not last: a foot that rises fast in a step stops
10-20 cm up. Where the rig gives a joint group a velocity memory
(``foot_velocity_memory_s``, ``hand_velocity_memory_s``: the s.d. of a Gaussian fitted
to the vertical velocity's autocorrelation in motion capture,
bench/bench_motion_memory.py), the vertical axis of those joints is carried by the same
IMM prediction over the *effective horizon* (``effective_horizon``: the least-squares
linear prediction of the displacement from the present velocity) instead of ``h``;
their mean and covariance both come from it, so the s.d. stays the filter's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..joints import JOINT_INDEX, JOINTS, N_JOINTS
from ..settings import ForecastSettings, KalmanSettings
from . import jit
from .kalman import FilterState, combine, mix, predict, transition

#: (parent, child) of every bone, parents before children (Kinect v2's joint tree)
BONES: tuple[tuple[int, int], ...] = tuple((JOINT_INDEX[a], JOINT_INDEX[b]) for a, b in (
    ("SpineBase", "SpineMid"), ("SpineMid", "SpineShoulder"), ("SpineShoulder", "Neck"),
    ("Neck", "Head"),
    ("SpineShoulder", "ShoulderLeft"), ("ShoulderLeft", "ElbowLeft"), ("ElbowLeft", "WristLeft"),
    ("WristLeft", "HandLeft"), ("HandLeft", "HandTipLeft"), ("WristLeft", "ThumbLeft"),
    ("SpineShoulder", "ShoulderRight"), ("ShoulderRight", "ElbowRight"),
    ("ElbowRight", "WristRight"), ("WristRight", "HandRight"), ("HandRight", "HandTipRight"),
    ("WristRight", "ThumbRight"),
    ("SpineBase", "HipLeft"), ("HipLeft", "KneeLeft"), ("KneeLeft", "AnkleLeft"),
    ("AnkleLeft", "FootLeft"),
    ("SpineBase", "HipRight"), ("HipRight", "KneeRight"), ("KneeRight", "AnkleRight"),
    ("AnkleRight", "FootRight"),
))

_LIMB = {"ElbowLeft", "ElbowRight", "KneeLeft", "KneeRight"}
_EXTREMITY = {"WristLeft", "WristRight", "HandLeft", "HandRight", "HandTipLeft", "HandTipRight",
              "ThumbLeft", "ThumbRight", "AnkleLeft", "AnkleRight", "FootLeft", "FootRight"}


_FOOT = {"AnkleLeft", "AnkleRight", "FootLeft", "FootRight"}
_HAND = _EXTREMITY - _FOOT
UP = 1  # the vertical axis


def memories(s: ForecastSettings) -> np.ndarray:
    """(25,) how long each joint's vertical velocity is remembered, s (0: for ever, i.e.
    constant velocity)."""
    return np.array([s.foot_velocity_memory_s if n in _FOOT else
                     s.hand_velocity_memory_s if n in _HAND else 0.0 for n in JOINTS])


def effective_horizon(dt: np.ndarray, memory: np.ndarray) -> np.ndarray:
    """How far ahead (s) the velocity carries a joint in ``dt`` (s): the integral over
    ``dt`` of the velocity's autocorrelation, a Gaussian of s.d. ``memory`` (s; 0: constant
    velocity, the integral is ``dt``). This is the least-squares linear prediction of the
    displacement from the present velocity: ``sigma sqrt(pi/2) erf(dt / (sigma sqrt 2))``,
    about ``dt`` for ``dt`` much shorter than ``sigma``, at most ``1.25 sigma``."""
    dt = np.asarray(dt, dtype=float)
    memory = np.broadcast_to(np.asarray(memory, dtype=float), dt.shape)
    out = dt.copy()
    m = memory > 0
    if m.any():
        sig = memory[m]
        out[m] = sig * _SQRT_HALF_PI * _erf(dt[m] / (sig * _SQRT2))
    return out


_SQRT2 = float(np.sqrt(2.0))
_SQRT_HALF_PI = float(np.sqrt(np.pi / 2.0))
_erf = np.vectorize(math.erf, otypes=[float])


def speed_limits(s: ForecastSettings) -> np.ndarray:
    """(25,) the fastest each joint may be predicted to move, m/s."""
    return np.array([s.extremity_speed_m_s if n in _EXTREMITY else
                     s.limb_speed_m_s if n in _LIMB else s.torso_speed_m_s for n in JOINTS])


@dataclass
class Forecast:
    """One person's body ``horizon`` s after ``t`` (its capture time)."""

    t: float                  # capture time the forecast starts from, engine clock
    horizon: float            # seconds ahead of ``t``
    joints: np.ndarray        # (25, 3) metres
    velocity: np.ndarray      # (25, 3) m/s, the filter's (not faded by a velocity memory)
    sd: np.ndarray            # (25,) position s.d., m (NaN for joints never measured)
    speed_capped: int = 0     # joints whose predicted move was cut to their speed limit
    bones_fixed: int = 0      # joints moved to keep a bone's length


class Forecaster:
    """Predicts bodies ahead (engine thread; pure but for its counters)."""

    def __init__(self, smoothing: KalmanSettings, settings: ForecastSettings) -> None:
        self.smoothing, self.settings = smoothing, settings
        self.limits = speed_limits(settings)
        self.memory = memories(settings)
        self._remembers = self.memory > 0
        self._q = np.array([smoothing.quiet_noise, smoothing.fast_noise])
        # the compiled kernel's constants (writable, C-ordered: what it takes)
        self._rates = -np.array([smoothing.quiet_to_fast_per_s, smoothing.fast_to_quiet_per_s])
        self._bones = np.array(BONES, dtype=np.int64)
        self.made = 0
        self.speed_capped = 0
        self.bones_fixed = 0
        #: the latest forecast's mean s.d. over seen joints, m, per horizon (for stats)
        self.last_sd: dict[float, float] = {}

    def predict(self, state: FilterState, t: float, joints: np.ndarray, seen: np.ndarray,
                horizon: float) -> Forecast:
        """The body whose filter is ``state`` and whose output at capture time ``t`` is
        ``joints`` (25, 3), predicted ``horizon`` s past ``t``; ``seen`` (25,) bool: the
        joints that are predicted (others stay where ``joints`` has them, s.d. NaN).
        Compiled (``jit._forecast``, the same floats) when the kernels are used: in numpy a
        body's forecast cost some 0.5 ms (a 6x6 datagram's CPU, 597 us without forecasts,
        was 4129 us with them; issue 10, stop 53)."""
        if jit.ready():
            return self._predict_compiled(state.stacked(), state.t, t, joints, seen, horizon)
        target = t + horizon
        dt = np.maximum(target - state.t, 0.0)
        dt = np.where(np.isnan(dt), 0.0, dt)
        s = self.smoothing
        with np.errstate(invalid="ignore", divide="ignore"):
            x0, P0, cbar = mix(state.x, state.P, state.mu, *transition(dt, s))
            xp, Pp = predict(x0, P0, dt, self._q)
            xm, Pm = combine(xp, Pp, cbar)
            if self._remembers.any():
                # the vertical axis of joints whose velocity fades: the same IMM prediction
                # over the effective horizon (the modes still switch over ``dt``)
                r = self._remembers
                xk, Pk = predict(x0[:, :, r], P0[:, :, r], effective_horizon(dt[r],
                                 self.memory[r]), self._q)
                xk, Pk = combine(xk, Pk, cbar[:, r])
                xm[:, r, UP] = xk[:, :, UP]
                Pm[:, r, UP] = Pk[:, :, UP]
        pos, vel = xm[0], xm[1]
        sd = np.sqrt(Pm[0].mean(axis=1))
        ok = seen & np.isfinite(pos).all(axis=1)
        # speed: the move from the body at capture time, at most limit * horizon
        move = np.where(ok[:, None], pos - joints, 0.0)
        dist = np.sqrt((move * move).sum(axis=1))
        cap = self.limits * horizon
        over = ok & (dist > cap)
        if over.any():
            move[over] *= (cap[over] / dist[over])[:, None]
        out = joints + move
        fixed = _keep_bones(out, joints, ok, self.settings.bone_tolerance, sd)
        self.made += 1
        n_over = int(over.sum())
        self.speed_capped += n_over
        self.bones_fixed += fixed
        if ok.any():
            self.last_sd[horizon] = float(np.nanmean(sd[ok]))
        vel = np.where(ok[:, None] & np.isfinite(vel), vel, 0.0)
        return Forecast(t, horizon, out, vel, np.where(ok, sd, np.nan), n_over, fixed)

    def predict_block(self, block: np.ndarray, row_t: np.ndarray, t: float, joints: np.ndarray,
                      seen: np.ndarray, horizon: float) -> Forecast:
        """``predict`` of the state given as its (6, 2, N, 3) block [x; P; mu] and row times
        (``fuser.BodyFilter.peek``: read at once, no copy made)."""
        if jit.ready():
            return self._predict_compiled(block, row_t, t, joints, seen, horizon)
        n = len(row_t)
        return self.predict(FilterState.of_block(block, row_t, np.full((n, 3), np.nan),
                                                 np.full(n, np.nan)), t, joints, seen, horizon)

    def _predict_compiled(self, block: np.ndarray, row_t: np.ndarray, t: float,
                          joints: np.ndarray, seen: np.ndarray, horizon: float) -> Forecast:
        out, vel, sd, counts = jit.forecast(
            block, row_t, t + horizon, horizon, self._q, self._rates, self.memory,
            self.limits, np.asarray(joints, dtype=float), np.asarray(seen, dtype=np.bool_),
            self.settings.bone_tolerance, self._bones)
        n_over, fixed = int(counts[0]), int(counts[1])
        self.made += 1
        self.speed_capped += n_over
        self.bones_fixed += fixed
        if counts[3] > 0:
            self.last_sd[horizon] = float(counts[2] / counts[3])
        return Forecast(t, horizon, out, vel, sd, n_over, fixed)

    def predict_many(self, blocks: np.ndarray, row_t: np.ndarray, t: np.ndarray,
                     joints: np.ndarray, seen: np.ndarray, horizon: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``predict_block`` of B bodies in one compiled call (``jit.forecast_many``):
        blocks (B, 6, 2, N, 3), row_t (B, N), capture times t (B,), joints (B, N, 3), seen
        (B, N); returns (joints (B, N, 3), velocity (B, N, 3), s.d. (B, N)), each body's the
        floats ``predict_block`` gives it, and counts them as it would, in order. Needs the
        kernels (``jit.ready()``)."""
        out, vel, sd, counts = jit.forecast_many(
            blocks, row_t, t + horizon, horizon, self._q, self._rates, self.memory,
            self.limits, joints, seen, self.settings.bone_tolerance, self._bones)
        last = None
        for capped, fixed, total, n in counts.tolist():
            self.speed_capped += int(capped)
            self.bones_fixed += int(fixed)
            if n > 0:
                last = total / n     # (the last body with a predicted joint's, as one by one)
        self.made += len(counts)
        if last is not None:
            self.last_sd[horizon] = last
        return out, vel, sd

    def stats(self) -> dict:
        return {"made": self.made, "speed_capped": self.speed_capped,
                "bones_fixed": self.bones_fixed,
                "sd_mm": {f"{h:g}": round(v * 1000.0, 1) for h, v in sorted(self.last_sd.items())}}


def _keep_bones(pred: np.ndarray, now: np.ndarray, ok: np.ndarray, tol: float,
                sd: np.ndarray | None = None) -> int:
    """Move predicted joints (in place) so that every bone whose two ends are predicted keeps
    its length in ``now`` within ``tol`` (a fraction); returns how many joints moved.

    A bone is mended by moving its less certain end: first, walking inwards, a parent whose
    predicted s.d. (``sd``, (25,) m) is larger than its child's is moved towards or away from
    the child; then, walking outwards, every child still out of range is moved. Without the
    inward walk a noisy knee predicted high would drag its ankle and foot up with it (seen in
    bench/bench_anticipation.py: a foot predicted 16 cm over its own prediction by its knee)."""
    fixed = 0
    if sd is not None:
        for parent, child in reversed(BONES):
            if ok[parent] and ok[child] and sd[parent] > sd[child]:
                fixed += _mend(pred, now, parent, child, tol, move_child=False)
    for parent, child in BONES:
        if ok[parent] and ok[child]:
            fixed += _mend(pred, now, parent, child, tol, move_child=True)
    return fixed


def _mend(pred: np.ndarray, now: np.ndarray, parent: int, child: int, tol: float,
          move_child: bool) -> int:
    """Bring the bone parent-child of ``pred`` within ``tol`` of its length in ``now`` by
    moving one end along the bone (the child, or the parent); 1 if it moved, else 0."""
    ref = now[child] - now[parent]
    length = math.sqrt((ref * ref).sum())       # (summed in order, as the kernel sums)
    if length <= 0.0:
        return 0
    bone = pred[child] - pred[parent]
    got = math.sqrt((bone * bone).sum())
    lo, hi = length * (1.0 - tol), length * (1.0 + tol)
    if lo <= got <= hi:
        return 0
    # along the predicted bone (or the bone at capture time if the two ends meet)
    direction = bone / got if got > 1e-9 else ref / length
    if move_child:
        pred[child] = pred[parent] + direction * min(max(got, lo), hi)
    else:
        pred[parent] = pred[child] - direction * min(max(got, lo), hi)
    return 1


__all__ = ["BONES", "Forecast", "Forecaster", "effective_horizon", "memories", "speed_limits",
           "N_JOINTS"]
