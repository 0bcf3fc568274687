"""Northwestern-UCLA multiview action 3D (N-UCLA) skeletons in their JSON form.

Written from the published description of the JSON files (one file per
action sample and camera view, e.g. ``a01_s01_e00_v01.json``)::

    {"file_name": "a01_s01_e00_v01", "skeletons": [frame][20][x, y, z], "label": 1}

The skeletons are Kinect v1's 20 joints in Kinect camera space (metres):
HipCenter, Spine, ShoulderCenter, Head, ShoulderLeft, ElbowLeft, WristLeft,
HandLeft, ShoulderRight, ElbowRight, WristRight, HandRight, HipLeft,
KneeLeft, AnkleLeft, FootLeft, HipRight, KneeRight, AnkleRight, FootRight.
They map onto the Kinect v2 names (HipCenter -> SpineBase, Spine -> SpineMid,
ShoulderCenter -> SpineShoulder, the rest by name); Neck, the hand tips and
the thumbs do not exist in Kinect v1 and are sent with confidence 0. A
joint written as (0, 0, 0) is missing: confidence 0. There are no tracking
states or hand states in these files: joints present count as tracked.

The three views (v01-v03) of one sample were cut separately, so their frame
counts differ and frame k of one view is not frame k of another: each view
starts at 0 s at ``fps`` (default 30), or with ``align='stretch'`` each is
stretched to the longest view's duration (start and end of the action then
coincide).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from ..clients.osc import BodyFrame
from ...errors import ConfigError
from ...joints import JOINT_INDEX, N_JOINTS
from .common import Frame, Take, write_takes

KINECT1_JOINTS = ("HipCenter", "Spine", "ShoulderCenter", "Head", "ShoulderLeft", "ElbowLeft",
                  "WristLeft", "HandLeft", "ShoulderRight", "ElbowRight", "WristRight",
                  "HandRight", "HipLeft", "KneeLeft", "AnkleLeft", "FootLeft", "HipRight",
                  "KneeRight", "AnkleRight", "FootRight")
_RENAME = {"HipCenter": "SpineBase", "Spine": "SpineMid", "ShoulderCenter": "SpineShoulder"}
#: Kinect v1 index -> Kinect v2 index
V1_TO_V2 = np.array([JOINT_INDEX[_RENAME.get(n, n)] for n in KINECT1_JOINTS])
_VIEW = re.compile(r"^(?P<sample>.*)_v(?P<view>\d+)$")


def read_nucla_json(path: str | os.PathLike) -> tuple[str, np.ndarray, object]:
    """(file_name, skeletons (T, 20, 3) metres, label) of one view's file."""
    path = str(path)
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("no such file", path=path) from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"not JSON: {exc.msg}", path=path, line=exc.lineno,
                          column=exc.colno) from None
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", path=path) from None
    if not isinstance(data, dict) or "skeletons" not in data:
        raise ConfigError("expected a JSON object with 'skeletons' (frames x 20 joints x 3)",
                          path=path)
    try:
        skel = np.asarray(data["skeletons"], dtype=float)
    except (TypeError, ValueError):
        raise ConfigError("'skeletons' must be frames x 20 joints x [x, y, z] numbers",
                          path=path) from None
    if skel.ndim == 2 and skel.shape[1] == 60:
        skel = skel.reshape(len(skel), 20, 3)
    if skel.ndim != 3 or skel.shape[1:] != (20, 3):
        raise ConfigError(f"'skeletons' must be frames x 20 x 3, got shape {skel.shape}",
                          path=path)
    if not np.isfinite(skel).all():
        raise ConfigError("'skeletons' holds NaN or infinite values", path=path)
    name = str(data.get("file_name", Path(path).stem))
    return name, skel, data.get("label")


def write_nucla_json(path: str | os.PathLike, file_name: str, skeletons: np.ndarray,
                     label: int = 1) -> None:
    """Write one view in the same JSON form (for tests and sample files)."""
    Path(path).write_text(json.dumps({"file_name": file_name,
                                      "skeletons": np.asarray(skeletons).tolist(),
                                      "label": label}), encoding="utf-8")


def to_kinect2(skeleton: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(20, 3) Kinect v1 joints -> ((25, 3) Kinect v2 joints, (25,) confidence)."""
    joints = np.zeros((N_JOINTS, 3))
    conf = np.zeros(N_JOINTS)
    joints[V1_TO_V2] = skeleton
    present = np.any(skeleton != 0.0, axis=1)
    conf[V1_TO_V2] = np.where(present, 1.0, 0.0)
    return joints, conf


def import_nucla(paths: list[str], out: str, fps: float = 30.0, align: str = "start") -> int:
    """Import the views of one sample into one recording; returns datagrams written."""
    if align not in ("start", "stretch"):
        raise ConfigError(f"align must be 'start' or 'stretch', got '{align}'")
    views = []
    samples = set()
    for path in paths:
        name, skel, label = read_nucla_json(path)
        m = _VIEW.match(name)
        samples.add(m.group("sample") if m else name)
        sensor = f"nucla-v{int(m.group('view'))}" if m else f"nucla-{name}"
        if any(v[0] == sensor for v in views):
            raise ConfigError(f"two files for view {sensor}", path=path)
        views.append((sensor, skel, label, path))
    if len(samples) > 1:
        raise ConfigError("the files are from different samples (" + ", ".join(sorted(samples)) +
                          "): import the views (v01-v03) of one sample at a time")
    longest = max((len(v[1]) - 1) / fps for v in views)
    takes = []
    for sensor, skel, _, _ in views:
        n = len(skel)
        step = 1.0 / fps
        if align == "stretch" and n > 1:
            step = longest / (n - 1)
        frames = []
        for k, s in enumerate(skel):
            joints, conf = to_kinect2(s)
            bodies = [BodyFrame(0, joints, conf, None)] if conf.any() else []
            frames.append(Frame(k * step, bodies))
        takes.append(Take(sensor, "kinect1", frames))
    meta = {"source": "stage import nucla", "files": [os.path.basename(p) for p in paths],
            "sample": samples.pop() if samples else None, "fps": fps, "align": align,
            "labels": [v[2] for v in views],
            "note": "Kinect v1 (20 joints): Neck, hand tips and thumbs are sent with "
                    "confidence 0; views are not calibrated to each other"}
    return write_takes(out, takes, meta)
