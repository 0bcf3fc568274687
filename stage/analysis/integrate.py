"""Seed 003's integration of several sensors' skeletons into one, from a recording.

"We resampled the recordings with a fixed sampling rate of 30 Hz using
linear interpolation ... we weighted all sensors equally and calculated the
average across all skeletons tracked by the different sensors for every
sample. Untracked or inferred joint positions were considered as missing
values." (seed 003, "Integrating the information gathered by different
Kinect sensors"). This module does exactly that, independently of the live
engine's fusion: each sensor's frames are put into stage space with the
rig's calibrations, resampled onto one 30 Hz grid (never across a gap
longer than ``max_gap_s``), and averaged joint by joint over the sensors
that tracked the joint. Choosing a subset of sensors (seed 003's one-sided
analysis) is a parameter.

Times: a frame's capture time when the recording knows it (the simulator
writes it); otherwise the bundle timetag on the sensor's own clock, moved
onto the recording's clock by the smallest ``arrival - timetag`` seen (the
same one-way estimate the engine makes); otherwise the arrival time.

One walker: when a sensor reports several users at once, the one nearest to
the walker followed so far is used and the others are counted as ignored.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ..errors import ConfigError
from ..joints import N_JOINTS, TORSO
from ..rig import Rig
from ..sensors.protocol import JointCoordinates, decode_records
from .trajectory import Trajectory

log = logging.getLogger("stage.analysis")

#: a user of one sensor belongs to the walker when its torso is this close (m)
SAME_PERSON_M = 0.6


@dataclass
class SensorFrames:
    """One sensor's skeletons: t (M,) s on the recording's clock, user (M,), joints
    (M, 25, 3) metres in the sensor's own space, conf (M, 25)."""

    sensor: str
    t: np.ndarray
    user: np.ndarray
    joints: np.ndarray
    conf: np.ndarray
    timing: str = "capture"          # capture | timetag | arrival

    def __len__(self) -> int:
        return len(self.t)


def read_frames(records: Iterable[tuple[float, bytes, float | None]],
                ) -> tuple[dict[str, SensorFrames], dict[str, int]]:
    """Decode (arrival s, datagram, capture s or None) records into frames per sensor.

    Returns the frames and drop counts by reason (bad datagrams and frames
    with NaN coordinates are counted, never fatal).
    """
    raw: dict[str, list] = {}
    drops: dict[str, int] = {}
    for arrival, capture, msg, timetag in decode_records(records, drops):
        client = getattr(msg, "client", None)
        if isinstance(client, str):
            raw.setdefault(client, [])        # a sensor that never saw anyone is still one
        if isinstance(msg, JointCoordinates):
            if not (np.isfinite(msg.joints).all() and np.isfinite(msg.conf).all()):
                drops["non_finite"] = drops.get("non_finite", 0) + 1
                continue
            raw.setdefault(msg.client, []).append(
                (arrival, timetag, capture, msg.user, msg.joints, msg.conf))
    out: dict[str, SensorFrames] = {}
    for sid, items in raw.items():
        if not items:
            out[sid] = SensorFrames(sid, np.zeros(0), np.zeros(0, int),
                                    np.zeros((0, N_JOINTS, 3)), np.zeros((0, N_JOINTS)), "none")
            continue
        arrival = np.array([i[0] for i in items])
        if all(i[2] is not None and np.isfinite(i[2]) for i in items):
            t, timing = np.array([i[2] for i in items], float), "capture"
        elif all(i[1] is not None for i in items):
            tag = np.array([i[1] for i in items], float)
            t, timing = tag + float(np.min(arrival - tag)), "timetag"
        else:
            t, timing = arrival, "arrival"
        order = np.argsort(t, kind="stable")
        out[sid] = SensorFrames(sid, t[order], np.array([i[3] for i in items])[order],
                                np.stack([i[4] for i in items])[order],
                                np.stack([i[5] for i in items])[order], timing)
    return out, drops


def read_recording_frames(path: str) -> tuple[dict[str, SensorFrames], dict[str, int], dict]:
    """A recording file -> (frames per sensor, drops, the recording's meta)."""
    from ..sensors.recording import Recording
    rec = Recording(path)
    frames, drops = read_frames((r.arrival, r.data, r.capture) for r in rec)
    return frames, drops, rec.meta


def integrate(frames: dict[str, SensorFrames], rig: Rig, sensors: Iterable[str] | None = None,
              *, rate: float = 30.0, keep_inferred: bool = False, max_gap_s: float = 0.1,
              label: str = "") -> Trajectory:
    """Seed 003's averaged skeleton of the walker from ``sensors`` (default: all calibrated).

    ``keep_inferred``: average inferred joints too (seed 003 leaves them out).
    ``max_gap_s``: a sensor's joint is interpolated between two of its frames
    at most this far apart (a dropped frame is bridged, a longer loss is not).
    The trajectory's ``count`` says how many sensors each joint averages;
    ``meta`` lists the sensors used, those left out for want of a
    calibration, and the users ignored.
    """
    wanted = sorted(frames) if sensors is None else list(sensors)
    unknown = [s for s in wanted if s not in frames]
    if unknown:
        raise ConfigError(f"no frames from sensor(s) {', '.join(unknown)} in the recording "
                          f"(it has: {', '.join(sorted(frames)) or 'none'})")
    used, uncalibrated = [], []
    for sid in wanted:
        (used if rig.transform_for(sid) is not None else uncalibrated).append(sid)
    if uncalibrated:
        log.warning("sensor(s) %s have no calibration in the rig: left out",
                    ", ".join(uncalibrated))
    tracks = []  # (sensor, resampled joints (G, 25, 3)) per (sensor, user)
    if not used:
        raise ConfigError(f"none of the sensors ({', '.join(wanted) or 'none'}) has a "
                          "calibration in the rig: give --rig, or calibrate: stage calibrate "
                          "RECORDING --rig RIG")
    if not any(len(frames[s]) for s in used):
        raise ConfigError(f"no skeletons from {', '.join(used)}: nobody was seen")
    t0 = min(frames[s].t[0] for s in used if len(frames[s]))
    t1 = max(frames[s].t[-1] for s in used if len(frames[s]))
    grid = np.arange(t0, t1 + 1e-9, 1.0 / rate)
    threshold = 0.25 if keep_inferred else 0.75
    for sid in used:
        f = frames[sid]
        m = rig.transform_for(sid)
        stage = f.joints @ m[:3, :3].T + m[:3, 3]
        valid = f.conf >= threshold
        for user in np.unique(f.user):
            k = f.user == user
            tracks.append((sid, _resample(f.t[k], stage[k], valid[k], grid, max_gap_s)))
    chosen, ignored = _follow_walker(tracks, len(grid), max(1, int(round(0.3 * rate))))
    total = np.zeros((len(grid), N_JOINTS, 3))
    count = np.zeros((len(grid), N_JOINTS), dtype=int)
    for (sid, values), pick in zip(tracks, chosen):
        ok = pick[:, None] & np.isfinite(values[..., 0])
        total += np.where(ok[..., None], values, 0.0)
        count += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count[..., None] > 0, total / np.maximum(count, 1)[..., None], np.nan)
    meta = {"sensors": used, "uncalibrated": uncalibrated, "ignored_user_samples": ignored,
            "rate": rate, "keep_inferred": keep_inferred,
            "timing": {s: frames[s].timing for s in used}}
    return Trajectory(grid, mean, count, label or ",".join(used), meta)


def _resample(t: np.ndarray, joints: np.ndarray, valid: np.ndarray, grid: np.ndarray,
              max_gap_s: float) -> np.ndarray:
    """(G, 25, 3): linear interpolation between neighbouring frames where both have the joint."""
    out = np.full((len(grid), N_JOINTS, 3), np.nan)
    if len(t) == 0:
        return out
    if len(t) == 1:
        hit = np.isclose(grid, t[0], atol=1e-9)
        out[hit] = np.where(valid[0][:, None], joints[0], np.nan)
        return out
    inside = (grid >= t[0] - 1e-9) & (grid <= t[-1] + 1e-9)
    g = grid[inside]
    i = np.clip(np.searchsorted(t, g, side="right") - 1, 0, len(t) - 2)
    span = t[i + 1] - t[i]
    u = np.clip((g - t[i]) / np.maximum(span, 1e-12), 0.0, 1.0)
    at_i = u <= 1e-9
    at_j = u >= 1.0 - 1e-9
    ok = np.where(at_i[:, None], valid[i], np.where(at_j[:, None], valid[i + 1],
                                                     valid[i] & valid[i + 1]))
    ok &= ((span <= max_gap_s + 1e-9) | at_i | at_j)[:, None]
    value = joints[i] * (1.0 - u)[:, None, None] + joints[i + 1] * u[:, None, None]
    out[inside] = np.where(ok[..., None], value, np.nan)
    return out


def _follow_walker(tracks: list[tuple[str, np.ndarray]], n: int, patience: int,
                   ) -> tuple[list[np.ndarray], int]:
    """Per track, (G,) bool: the samples where it shows the walker; and how many user
    samples were ignored (another person in view). Lost for more than ``patience``
    samples, the walker is looked for afresh (they left and came back elsewhere)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # a frame without torso joints: NaN
        torso = [np.nanmean(v[:, TORSO], axis=1) if len(v) else v for _, v in tracks]
        torso = [np.where(np.isfinite(p).all(axis=1, keepdims=True), p, np.nan) for p in torso]
    chosen = [np.zeros(n, dtype=bool) for _ in tracks]
    anchor: np.ndarray | None = None
    lost = 0
    ignored = 0
    for g in range(n):
        cands = [(k, torso[k][g]) for k in range(len(tracks)) if np.isfinite(torso[k][g, 0])]
        if not cands:
            lost += 1
            if lost > patience:
                anchor = None
            continue
        if anchor is None:
            # start with the person most sensors agree on
            best = max(cands, key=lambda c: sum(np.linalg.norm(c[1] - o[1]) < SAME_PERSON_M
                                                for o in cands))
            anchor = best[1]
        by_sensor: dict[str, tuple[float, int]] = {}
        for k, p in cands:
            d = float(np.linalg.norm(p - anchor))
            sid = tracks[k][0]
            if d < SAME_PERSON_M and (sid not in by_sensor or d < by_sensor[sid][0]):
                by_sensor[sid] = (d, k)
        picked = [k for _, k in by_sensor.values()]
        ignored += len(cands) - len(picked)
        if not picked:
            lost += 1
            if lost > patience:
                anchor = None
            continue
        lost = 0
        for k in picked:
            chosen[k][g] = True
        anchor = np.mean([torso[k][g] for k in picked], axis=0)
    return chosen, ignored
