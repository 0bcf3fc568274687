"""Per-sensor skeleton streams for offline calibration (recordings, simulations).

A ``Stream`` is one sensor's frames in its own space, sorted by time. It is
built from raw OSC datagrams (``streams_from_datagrams``), the way a
recording or the simulator gives them.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ..errors import StageError
from ..joints import N_JOINTS
from ..sensors.protocol import FloorPlane, JointCoordinates, decode_records

log = logging.getLogger("stage.calibration")


@dataclass
class Stream:
    """One sensor's skeletons over time.

    t: (M,) seconds, ascending, on this sensor's clock as recorded.
    user: (M,) int user ids. joints: (M, 25, 3) metres, the sensor's own space.
    conf: (M, 25) in [0, 1]. floor: (4,) the floor plane it reported
    (a, b, c, d; median over the recording) or None.
    """

    sensor: str
    t: np.ndarray
    user: np.ndarray
    joints: np.ndarray
    conf: np.ndarray
    floor: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def from_frames(cls, sensor: str, frames: list[tuple[float, int, np.ndarray, np.ndarray]],
                    floors: list[np.ndarray] | None = None) -> "Stream":
        frames = sorted(frames, key=lambda f: f[0])
        if frames:
            t = np.array([f[0] for f in frames], dtype=float)
            user = np.array([f[1] for f in frames], dtype=int)
            joints = np.stack([np.asarray(f[2], dtype=float) for f in frames])
            conf = np.stack([np.asarray(f[3], dtype=float) for f in frames])
        else:
            t, user = np.zeros(0), np.zeros(0, dtype=int)
            joints, conf = np.zeros((0, N_JOINTS, 3)), np.zeros((0, N_JOINTS))
        floor = None
        if floors:
            floor = np.median(np.stack(floors), axis=0)
            floor = floor / np.linalg.norm(floor[:3])
        return cls(sensor, t, user, joints, conf, floor)

    def subset(self, index: np.ndarray) -> "Stream":
        return Stream(self.sensor, self.t[index], self.user[index], self.joints[index],
                      self.conf[index], self.floor)

    def shifted(self, dt: float) -> "Stream":
        """The same stream with every time moved by ``dt`` seconds."""
        return Stream(self.sensor, self.t + dt, self.user, self.joints, self.conf, self.floor)

    def finite(self) -> np.ndarray:
        """(M,) bool: frames without NaN or inf anywhere (a NaN frame is dropped whole)."""
        return (np.isfinite(self.joints).all(axis=(1, 2)) & np.isfinite(self.conf).all(axis=1))

    def single_user(self, window_s: float = 0.5) -> np.ndarray:
        """(M,) bool: no other user has a frame within ``window_s / 2`` of this one."""
        out = np.ones(len(self.t), dtype=bool)
        users = np.unique(self.user)
        if len(users) <= 1:
            return out
        half = window_s / 2.0
        for u in users:
            times = self.t[self.user == u]
            others = self.user != u
            idx = np.searchsorted(times, self.t[others])
            near = np.full(others.sum(), np.inf)
            ok = idx < len(times)
            near[ok] = np.abs(times[idx[ok]] - self.t[others][ok])
            ok = idx > 0
            near[ok] = np.minimum(near[ok], np.abs(self.t[others][ok] - times[idx[ok] - 1]))
            bad = np.flatnonzero(others)[near <= half]
            out[bad] = False
        return out

    def smoothed(self, frames: int = 5, max_gap: float = 0.1) -> "Stream":
        """A centred moving average over ``frames`` frames of each user's runs.

        For the lag search: a smoothed stream's noise is already averaged, so
        interpolating it at a sub-frame lag cannot lower the residual by
        averaging noise (which would bias the search towards half-frame lags).
        A joint's confidence is the smallest within the window.
        """
        if frames <= 1 or len(self) == 0:
            return self
        joints, conf = self.joints.copy(), self.conf.copy()
        half = frames // 2
        for u in np.unique(self.user):
            idx = np.flatnonzero(self.user == u)
            breaks = np.flatnonzero(np.diff(self.t[idx]) > max_gap) + 1
            for run in np.split(idx, breaks):
                n = len(run)
                if n < 2:
                    continue
                csum = np.concatenate([np.zeros((1,) + joints.shape[1:]),
                                       np.cumsum(self.joints[run], axis=0)])
                lo = np.clip(np.arange(n) - half, 0, n)
                hi = np.clip(np.arange(n) + half + 1, 0, n)
                joints[run] = (csum[hi] - csum[lo]) / (hi - lo)[:, None, None]
                c = self.conf[run]
                conf[run] = np.stack([c[a:b].min(axis=0) for a, b in zip(lo, hi)])
        return Stream(self.sensor, self.t, self.user, joints, conf, self.floor)

    def frame_interval(self) -> float:
        """Median time between frames of one user (s); 1/30 when unknown."""
        gaps = []
        for u in np.unique(self.user):
            d = np.diff(self.t[self.user == u])
            gaps.extend(d[d > 0])
        return float(np.median(gaps)) if gaps else 1.0 / 30.0


def streams_from_datagrams(records: Iterable[tuple[float, bytes, float | None]],
                           ) -> tuple[dict[str, Stream], dict[str, int]]:
    """Decode raw OSC datagrams into one ``Stream`` per sensor.

    ``records``: (arrival s, datagram bytes, capture s or None). A frame's
    time is, in order of preference: the recorded capture time, the OSC
    bundle timetag (the client's clock), the arrival time. Clocks of
    different clients may differ; ``pairs.find_lag`` finds the offset.
    Returns the streams and the drop counts by reason (bad datagrams are
    counted, never fatal).
    """
    frames: dict[str, list] = {}
    floors: dict[str, list] = {}
    drops: dict[str, int] = {}
    for arrival, capture, msg, timetag in decode_records(records, drops):
        if isinstance(msg, JointCoordinates):
            t = capture if capture is not None else timetag if timetag is not None else arrival
            frames.setdefault(msg.client, []).append((float(t), msg.user, msg.joints, msg.conf))
        elif isinstance(msg, FloorPlane):
            floors.setdefault(msg.client, []).append(msg.plane)
    streams = {sid: Stream.from_frames(sid, f, floors.get(sid)) for sid, f in frames.items()}
    return streams, drops


def load_recording(path: str) -> tuple[dict[str, Stream], dict[str, int]]:
    """A recording file (``stage.sensors.recording`` format) -> streams and drop counts."""
    try:
        from ..sensors.recording import read_recording  # type: ignore[attr-defined]
    except ImportError:
        raise StageError("cannot read recordings: the stage.sensors.recording module is not "
                         "available in this installation") from None
    try:
        records = ((r.arrival, r.data, getattr(r, "capture", None)) for r in read_recording(path))
        return streams_from_datagrams(records)
    except FileNotFoundError:
        raise StageError(f"{path}: no such file") from None
    except OSError as exc:
        raise StageError(f"{path}: cannot read: {exc.strerror or exc}") from None


def find_identical_streams(streams: dict[str, Stream], min_frames: int = 5,
                           ) -> list[tuple[str, str, int]]:
    """Pairs of sensors that sent bit-identical skeletons (a copied stream).

    Two real sensors never agree to the last bit (noise, different
    viewpoints), so ``min_frames`` identical frames mean one stream is a
    copy, which would otherwise look like a perfect calibration. Returns
    (sensor a, sensor b, identical frame count), a before b in input order.
    """
    seen: dict[bytes, str] = {}
    counts: dict[tuple[str, str], int] = {}
    order = list(streams)
    for sid in order:
        s = streams[sid]
        for k in range(len(s)):
            if not (s.conf[k] > 0).any():
                continue
            key = hashlib.blake2b(s.joints[k].tobytes() + s.conf[k].tobytes(),
                                  digest_size=16).digest()
            first = seen.setdefault(key, sid)
            if first != sid:
                pair = (first, sid)
                counts[pair] = counts.get(pair, 0) + 1
    return [(a, b, n) for (a, b), n in counts.items() if n >= min_frames]
