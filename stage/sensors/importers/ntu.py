"""NTU RGB+D ``.skeleton`` files (Kinect v2, 25 joints): read, write, import.

Written from the dataset's published description of the text format::

    <frame count>
    per frame:
      <body count>
      per body:
        <bodyID> <clippedEdges> <handLeftConfidence> <handLeftState>
            <handRightConfidence> <handRightState> <isRestricted> <leanX> <leanY>
            <trackingState>
        <joint count = 25>
        per joint (Kinect v2 JointType order):
          <x> <y> <z> <depthX> <depthY> <colorX> <colorY>
          <orientationW> <orientationX> <orientationY> <orientationZ> <trackingState>

x y z are Kinect camera space (metres); joint trackingState is 0 not
tracked, 1 inferred, 2 tracked; hand states are the Kinect codes 0-4. Files
are named ``SsssCcccPpppRrrrAaaa`` (setup, camera, performer, replication,
action): the three cameras (C001-C003) of one performance become the three
sensors of one recording. Frames are 30 Hz.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..clients.osc import BodyFrame
from ...errors import ConfigError
from ...joints import N_JOINTS, HandState
from .common import Frame, Take, write_takes

FPS = 30.0
_NAME = re.compile(r"S(\d{3})C(\d{3})P(\d{3})R(\d{3})A(\d{3})", re.IGNORECASE)
_CONF = {0: 0.0, 1: 0.5, 2: 1.0}


@dataclass
class NtuBody:
    body_id: int
    clipped_edges: int
    hand_left_confidence: int
    hand_left_state: int
    hand_right_confidence: int
    hand_right_state: int
    restricted: int
    lean: tuple[float, float]
    tracking_state: int
    joints: np.ndarray          # (25, 12) as in the file


def read_skeleton_file(path: str | os.PathLike) -> list[list[NtuBody]]:
    """Frames of bodies; errors are ConfigError naming ``path:line``."""
    path = str(path)
    try:
        lines = Path(path).read_text(encoding="ascii", errors="replace").splitlines()
    except FileNotFoundError:
        raise ConfigError("no such file", path=path) from None
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", path=path) from None
    rows = [(k + 1, line.split()) for k, line in enumerate(lines) if line.strip()]
    pos = 0

    def row(count: int | None, what: str) -> tuple[int, list[str]]:
        nonlocal pos
        if pos >= len(rows):
            raise ConfigError(f"file ends where {what} was expected (truncated?)", path=path,
                              line=len(lines))
        line_no, parts = rows[pos]
        pos += 1
        if count is not None and len(parts) != count:
            raise ConfigError(f"{what}: expected {count} value(s), found {len(parts)}",
                              path=path, line=line_no)
        return line_no, parts

    def integer(text: str, line_no: int, what: str) -> int:
        try:
            return int(text)
        except ValueError:
            raise ConfigError(f"{what} must be a whole number, found {text!r}", path=path,
                              line=line_no) from None

    line_no, parts = row(1, "the frame count")
    n_frames = integer(parts[0], line_no, "the frame count")
    frames: list[list[NtuBody]] = []
    for _ in range(n_frames):
        line_no, parts = row(1, "a body count")
        bodies = []
        for _ in range(integer(parts[0], line_no, "the body count")):
            line_no, info = row(10, "a body line")
            try:
                ints = [int(v) for v in info[:7]] + [int(info[9])]
                lean = (float(info[7]), float(info[8]))
            except ValueError:
                raise ConfigError("a body line must be: bodyID, 6 integers, leanX, leanY, "
                                  "trackingState", path=path, line=line_no) from None
            line_no, parts = row(1, "the joint count")
            n_joints = integer(parts[0], line_no, "the joint count")
            if n_joints != N_JOINTS:
                raise ConfigError(f"joint count must be 25 (Kinect v2), found {n_joints}",
                                  path=path, line=line_no)
            joints = np.empty((N_JOINTS, 12))
            for j in range(N_JOINTS):
                line_no, values = row(12, "a joint line")
                try:
                    joints[j] = [float(v) for v in values]
                except ValueError:
                    raise ConfigError("a joint line must be 12 numbers", path=path,
                                      line=line_no) from None
            bodies.append(NtuBody(ints[0], ints[1], ints[2], ints[3], ints[4], ints[5], ints[6],
                                  lean, ints[7], joints))
        frames.append(bodies)
    return frames


def write_skeleton_file(path: str | os.PathLike, frames: list[list[NtuBody]]) -> None:
    """Write frames in the same text format (for tests and sample files)."""
    out = [str(len(frames))]
    for bodies in frames:
        out.append(str(len(bodies)))
        for b in bodies:
            out.append(f"{b.body_id} {b.clipped_edges} {b.hand_left_confidence} "
                       f"{b.hand_left_state} {b.hand_right_confidence} {b.hand_right_state} "
                       f"{b.restricted} {b.lean[0]:.7g} {b.lean[1]:.7g} {b.tracking_state}")
            out.append(str(N_JOINTS))
            for j in b.joints:
                out.append(" ".join(f"{v:.7g}" for v in j[:11]) + f" {int(j[11])}")
    Path(path).write_text("\n".join(out) + "\n", encoding="ascii")


def body_frame(body: NtuBody) -> BodyFrame:
    """One NTU body as the client would send it (camera space, confidences, hand states)."""
    conf = np.array([_CONF.get(int(s), 0.0) for s in body.joints[:, 11]])
    hands = (_hand(body.hand_left_state), _hand(body.hand_right_state))
    return BodyFrame(body.body_id, body.joints[:, :3].copy(), conf, hands)


def _hand(code: int) -> HandState:
    return HandState(code) if 0 <= code <= 4 else HandState.UNKNOWN


def camera_of(path: str) -> tuple[str, int | None]:
    """(performance key, camera number) from an NTU file name; (stem, None) otherwise."""
    stem = Path(path).name.split(".")[0]
    m = _NAME.search(stem)
    if m is None:
        return stem, None
    s, c, p, r, a = (int(g) for g in m.groups())
    return f"S{s:03d}P{p:03d}R{r:03d}A{a:03d}", c


def import_ntu(paths: list[str], out: str, fps: float = FPS) -> int:
    """Import one performance's camera files into one recording; returns datagrams written."""
    keys = {}
    takes = []
    for path in paths:
        key, camera = camera_of(path)
        keys.setdefault(key, []).append(path)
        sensor = f"ntu-c{camera}" if camera is not None else f"ntu-{key}"
        if any(t.sensor == sensor for t in takes):
            raise ConfigError(f"two files for camera {sensor}", path=path)
        frames = [Frame(k / fps, [body_frame(b) for b in bodies])
                  for k, bodies in enumerate(read_skeleton_file(path))]
        takes.append(Take(sensor, "kinect2", frames))
    if len([k for k, v in keys.items() if _NAME.search(v[0])]) > 1:
        raise ConfigError("the files are from different performances (" + ", ".join(keys) +
                          "): import one performance (same S, P, R, A; cameras C001-C003) at "
                          "a time")
    meta = {"source": "stage import ntu", "files": [os.path.basename(p) for p in paths],
            "performance": next(iter(keys)), "fps": fps,
            "note": "NTU RGB+D cameras are not calibrated to each other: calibrate before fusing"}
    return write_takes(out, takes, meta)
