"""BVH motion capture: parse, forward kinematics, and mapping onto the 25 Kinect joints.

Written from the published description of the Biovision Hierarchy format:
a ``HIERARCHY`` section (``ROOT``/``JOINT`` blocks with an ``OFFSET`` from the
parent and the ``CHANNELS`` they animate, ``End Site`` blocks with only an
offset) followed by a ``MOTION`` section (``Frames:``, ``Frame Time:`` and one
line of channel values per frame, in hierarchy order). Rotation channels are
degrees and apply in the order listed: ``Zrotation Yrotation Xrotation``
means R = Rz @ Ry @ Rx (each joint may list its own order). A joint's
position channels, when present, replace its offset.

Mapping: a built-in naming scheme (CMU, Bandai Namco, Mixamo, LAFAN;
``bvh_maps``) recognised by the file's joint names, else the first BVH joint
whose name is in each Kinect joint's alias list, compared case-insensitively;
a joint map (ours -> the file's names) goes over either. A few joints are
derived (SpineMid between the hips and the shoulder line, Head half-way up
the head segment, a palm beyond the wrist). Joints found nowhere get
confidence 0. Lengths are in the file's own unit, detected from the
performer's size or given, or scaled to a requested height.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ...errors import ConfigError
from ...geometry import axis_rotations
from ...joints import JOINT_INDEX, JOINTS, N_JOINTS
from .bvh_maps import UNITS, apply_overrides, detect, detect_units, scheme_mapping


@dataclass
class BvhJoint:
    name: str
    parent: int                 # index into Bvh.joints, -1 for the root
    offset: np.ndarray          # (3,) file units
    channels: list[str] = field(default_factory=list)
    end_site: np.ndarray | None = None   # (3,) offset of the End Site, if any


@dataclass
class Bvh:
    joints: list[BvhJoint]
    frame_time: float           # seconds
    frames: np.ndarray          # (T, total channels) as in the file
    path: str = "<bvh>"

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def duration(self) -> float:
        return len(self.frames) * self.frame_time


def _tokens(text: str):
    for line_no, line in enumerate(text.splitlines(), 1):
        for tok in line.split():
            yield tok, line_no


def parse_bvh(text: str, path: str = "<bvh>") -> Bvh:
    """Parse BVH text; errors are ConfigError naming ``path:line``."""
    toks = list(_tokens(text))
    pos = 0

    def fail(message: str, k: int | None = None) -> ConfigError:
        line = toks[min(k if k is not None else pos, len(toks) - 1)][1] if toks else None
        return ConfigError(message, path=path, line=line)

    def take(expected: str | None = None) -> str:
        nonlocal pos
        if pos >= len(toks):
            raise fail(f"unexpected end of file{f', expected {expected!r}' if expected else ''}")
        tok = toks[pos][0]
        if expected is not None and tok.upper() != expected.upper():
            raise fail(f"expected {expected!r}, found {tok!r}")
        pos += 1
        return tok

    def number() -> float:
        tok = take()
        try:
            return float(tok)
        except ValueError:
            raise fail(f"expected a number, found {tok!r}", pos - 1) from None

    joints: list[BvhJoint] = []

    def block(name: str, parent: int) -> None:
        take("{")
        take("OFFSET")
        offset = np.array([number(), number(), number()])
        index = len(joints)
        joint = BvhJoint(name, parent, offset)
        joints.append(joint)
        if pos < len(toks) and toks[pos][0].upper() == "CHANNELS":
            take()
            n_tok = take()
            if not n_tok.isdigit():
                raise fail(f"CHANNELS needs a count, found {n_tok!r}", pos - 1)
            for _ in range(int(n_tok)):
                ch = take()
                if ch.lower() not in ("xposition", "yposition", "zposition", "xrotation",
                                      "yrotation", "zrotation"):
                    raise fail(f"unknown channel {ch!r}", pos - 1)
                joint.channels.append(ch.lower())
        while True:
            tok = take().upper()
            if tok == "}":
                return
            if tok == "JOINT":
                block(take(), index)
            elif tok == "END":
                take("Site")
                take("{")
                take("OFFSET")
                joint.end_site = np.array([number(), number(), number()])
                take("}")
            else:
                raise fail(f"expected JOINT, End Site or '}}', found {toks[pos - 1][0]!r}", pos - 1)

    take("HIERARCHY")
    take("ROOT")
    block(take(), -1)
    take("MOTION")
    take("Frames:")
    n_tok = take()
    if not n_tok.isdigit():
        raise fail(f"'Frames:' needs a whole number, found {n_tok!r}", pos - 1)
    n_frames = int(n_tok)
    take("Frame")
    take("Time:")
    frame_time = number()
    if not frame_time > 0:
        raise fail("'Frame Time:' must be greater than 0", pos - 1)
    n_channels = sum(len(j.channels) for j in joints)
    # the motion is line based: one frame per line, one value per channel
    first_line = toks[pos][1] if pos < len(toks) else None
    lines = text.splitlines()
    rows = []
    if first_line is not None:
        for line_no in range(first_line, len(lines) + 1):
            parts = lines[line_no - 1].split()
            if not parts:
                continue
            if len(rows) == n_frames:
                break
            if len(parts) != n_channels:
                raise ConfigError(f"frame {len(rows) + 1} has {len(parts)} values; the hierarchy "
                                  f"has {n_channels} channels", path=path, line=line_no)
            try:
                rows.append([float(v) for v in parts])
            except ValueError:
                bad = next(v for v in parts if not _is_float(v))
                raise ConfigError(f"expected a number, found {bad!r}", path=path,
                                  line=line_no) from None
    if len(rows) < n_frames:
        raise ConfigError(f"the file has {len(rows)} frames, 'Frames:' says {n_frames} "
                          f"(truncated?)", path=path, line=len(lines))
    data = np.array(rows, dtype=float).reshape(n_frames, n_channels)
    return Bvh(joints, frame_time, data, path)


def _is_float(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def load_bvh(path: str | os.PathLike) -> Bvh:
    path = str(path)
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read()
    except FileNotFoundError:
        raise ConfigError("no such file", path=path) from None
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", path=path) from None
    return parse_bvh(text, path)


def forward_kinematics(bvh: Bvh, frames: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """World positions per joint name, (T, 3) file units; End Sites as ``'<joint>/end'``.

    ``frames``: (T, channels) values (default: the file's); pass zeros for the rest pose.
    """
    values = bvh.frames if frames is None else frames
    n = len(values)
    rotations: list[np.ndarray] = []
    positions: list[np.ndarray] = []
    out: dict[str, np.ndarray] = {}
    col = 0
    for joint in bvh.joints:
        local_r = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        translation = np.broadcast_to(joint.offset, (n, 3)).copy()
        moved = [False, False, False]
        for ch in joint.channels:
            axis, kind = ch[0], ch[1:]
            if kind == "rotation":
                local_r = local_r @ axis_rotations(axis, np.radians(values[:, col]))
            else:
                k = "xyz".index(axis)
                if not moved[k]:
                    translation[:, k] = 0.0 if joint.parent >= 0 else joint.offset[k]
                    moved[k] = True
                translation[:, k] += values[:, col]
            col += 1
        if joint.parent < 0:
            world_r, world_p = local_r, translation
        else:
            pr, pp = rotations[joint.parent], positions[joint.parent]
            world_r = pr @ local_r
            world_p = pp + np.einsum("nij,nj->ni", pr, translation)
        rotations.append(world_r)
        positions.append(world_p)
        out[joint.name] = world_p
        if joint.end_site is not None:
            out[joint.name + "/end"] = world_p + np.einsum("nij,j->ni", world_r, joint.end_site)
    return out


# Candidates per Kinect joint, best first. Left side; the right side is derived by name.
_ALIASES_LEFT: dict[str, tuple[str, ...]] = {
    "Shoulder": ("LeftArm", "LeftUpArm", "LeftUpperArm", "lhumerus", "LeftShoulder", "L_Shoulder",
                 "lShldr", "l_upperarm"),
    "Elbow": ("LeftForeArm", "LeftLowArm", "LeftLowerArm", "lradius", "LeftElbow", "lForeArm",
              "L_Elbow", "l_forearm"),
    "Wrist": ("LeftHand", "lwrist", "LeftWrist", "lHand", "L_Wrist", "l_hand"),
    "Hand": ("LFingers", "LeftHandMiddle1", "LeftHandIndex1", "lfingers", "LeftFingerBase",
             "lhand"),
    "HandTip": ("LFingers/end", "LeftHandMiddle4", "LeftHandMiddle3", "LeftHandIndex4",
                "LeftHandIndex3", "lfingers/end", "LeftHandMiddle1/end", "LeftHandIndex1/end",
                "LeftFingerBase/end", "lhand/end", "LeftHand/end", "LeftWrist/end", "lwrist/end"),
    "Thumb": ("LThumb/end", "LeftHandThumb3", "LeftHandThumb2", "lthumb/end", "lthumb",
              "LeftHandThumb1"),
    "Hip": ("LeftUpLeg", "LeftHip", "lfemur", "LeftThigh", "L_Hip", "lThigh", "l_thigh"),
    "Knee": ("LeftLeg", "LeftKnee", "ltibia", "LeftShin", "LeftLowLeg", "lShin", "L_Knee",
             "l_calf"),
    "Ankle": ("LeftFoot", "LeftAnkle", "lfoot", "L_Ankle", "lFoot", "l_foot"),
    "Foot": ("LeftToeBase", "LeftToe", "ltoes", "LeftToe_End", "L_Toe", "l_toe", "LeftFoot/end",
             "lfoot/end", "LeftAnkle/end"),
}
_ALIASES_CENTRE: dict[str, tuple[str, ...]] = {
    "SpineBase": ("Hips", "hip", "pelvis", "root", "Hip"),
    "Neck": ("Neck", "neck", "upperneck", "Neck1", "neck1"),
    "Head": ("Head", "head"),
}


def _right_name(name: str) -> str:
    for a, b in (("Left", "Right"), ("left", "right"), ("L_", "R_"), ("l_", "r_")):
        if a in name:
            return name.replace(a, b, 1)
    if name[:1] == "L" and name[1:2].isupper():   # LFingers, LThumb
        return "R" + name[1:]
    if name[:1] == "l":                             # ASF names: lhumerus, lwrist
        return "r" + name[1:]
    return name


def _aliases() -> dict[str, tuple[str, ...]]:
    out = dict(_ALIASES_CENTRE)
    for part, names in _ALIASES_LEFT.items():
        out[part + "Left"] = names
        out[part + "Right"] = tuple(_right_name(n) for n in names)
    return out


ALIASES = _aliases()


def resolve_mapping(available: list[str], overrides: dict[str, str] | None = None,
                    ) -> dict[str, str]:
    """Kinect joint name -> BVH position name ('Joint' or 'Joint/end') for the joints found."""
    lower = {name.lower(): name for name in available}
    mapping: dict[str, str] = {}
    for kinect, names in ALIASES.items():
        for candidate in names:
            if candidate.lower() in lower:
                mapping[kinect] = lower[candidate.lower()]
                break
    for kinect, name in (overrides or {}).items():
        if kinect not in JOINT_INDEX:
            raise ConfigError(f"'{kinect}' is not one of the 25 joint names")
        if name.lower() not in lower:
            raise ConfigError(f"joint_map: the BVH file has no joint '{name}'")
        mapping[kinect] = lower[name.lower()]
    return mapping


@dataclass
class KinectTake:
    """A BVH take as Kinect joints, and how it was read."""

    frames: np.ndarray          # (T, 25, 3) metres, y up, the lowest point of the take at y = 0
    conf: np.ndarray            # (25,) 1 mapped or derived, 0.5 extrapolated, 0 missing
    scheme: str | None          # the built-in naming scheme detected, if any
    units: str | None           # the length unit used (None: scaled to a height)
    scale: float                # metres per file unit
    mapping: dict[str, str]     # Kinect joint -> the file's joint ('X' or 'X/end')


def kinect_joints(bvh: Bvh, height: float | None = 1.75, joint_map: dict[str, str] | None = None,
                  units: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The file's motion as Kinect joints: ((T, 25, 3) metres, (25,) confidence); see ``to_kinect``."""
    take = to_kinect(bvh, height, joint_map, units)
    return take.frames, take.conf


def to_kinect(bvh: Bvh, height: float | None = None, joint_map: dict[str, str] | None = None,
              units: str | None = None) -> KinectTake:
    """The file's motion as Kinect joints (``KinectTake``).

    ``height``: scale so the performer, standing tallest, is that many metres
    from the lowest foot point to the top of the head. Else ``units`` (a key
    of ``bvh_maps.UNITS``; None: detected from the performer's size). y up as
    in the file; the lowest point of the take on y = 0.
    """
    world = forward_kinematics(bvh)
    names = list(world)
    scheme = detect([j.name for j in bvh.joints])
    mapping = scheme_mapping(scheme, names) if scheme is not None else resolve_mapping(names)
    mapping = apply_overrides(mapping, names, joint_map or {})
    for needed in ("SpineBase", "HipLeft", "HipRight"):
        if needed not in mapping:
            raise ConfigError(f"cannot find a joint for {needed} in the BVH file (names: "
                              f"{', '.join(j.name for j in bvh.joints[:12])}...); give a "
                              f"joint map (--joint-map FILE)", path=bvh.path)
    # standing height in the motion itself (rest poses often splay the legs): the top of the
    # head above the lowest foot point, taken where the performer stands tallest
    head_top = world.get(mapping.get("Head", "") + "/end", world.get(mapping.get("Head", ""),
                                                                   None))
    if head_top is None:
        head_top = np.max(np.stack([p[:, 1] for p in world.values()]), axis=0)[:, None] * [0, 1, 0]
    lowest = np.min(np.stack([p[:, 1] for p in world.values()]), axis=0)
    standing = float(np.percentile(head_top[:, 1] - lowest, 90))
    if height is not None:
        scale, units = height / max(standing, 1e-9), None
    else:
        if units is None:
            units = detect_units(standing)
        elif units not in UNITS:
            raise ConfigError(f"unknown unit '{units}' (known: {', '.join(UNITS)})")
        scale = UNITS[units]
    n = len(bvh.frames)
    out = np.zeros((n, N_JOINTS, 3))
    conf = np.zeros(N_JOINTS)
    for kinect, name in mapping.items():
        out[:, JOINT_INDEX[kinect]] = world[name]
        conf[JOINT_INDEX[kinect]] = 1.0
    shoulders = [mapping.get("ShoulderLeft"), mapping.get("ShoulderRight")]
    spine_shoulder = _branch_point(bvh, shoulders)
    if spine_shoulder is not None:
        out[:, JOINT_INDEX["SpineShoulder"]] = world[spine_shoulder]
        conf[JOINT_INDEX["SpineShoulder"]] = 1.0
        # Kinect proportions (the simulator's kinematics.REST_POSE): SpineBase 3 cm above the
        # hip joints, SpineMid 53 % of the way from SpineBase to SpineShoulder
        hips = 0.5 * (out[:, JOINT_INDEX["HipLeft"]] + out[:, JOINT_INDEX["HipRight"]])
        base = hips + 0.06 * (world[spine_shoulder] - hips)
        out[:, JOINT_INDEX["SpineBase"]] = base
        out[:, JOINT_INDEX["SpineMid"]] = base + 0.53 * (world[spine_shoulder] - base)
        conf[JOINT_INDEX["SpineMid"]] = 1.0
    for side in ("Left", "Right"):
        hand, wrist, tip = "Hand" + side, "Wrist" + side, "HandTip" + side
        elbow = "Elbow" + side
        if hand not in mapping and wrist in mapping and tip in mapping:
            # a skeleton without hand joints: the palm is half-way from the wrist to the tip
            out[:, JOINT_INDEX[hand]] = 0.5 * (world[mapping[wrist]] + world[mapping[tip]])
            conf[JOINT_INDEX[hand]] = 1.0
        elif hand not in mapping and wrist in mapping and elbow in mapping:
            # no hand joint and no tip (Bandai Namco, LAFAN): the palm centre continues the
            # forearm by 30 % of its length (8 cm on a 26 cm forearm); a guess, so "inferred"
            w, e = world[mapping[wrist]], world[mapping[elbow]]
            out[:, JOINT_INDEX[hand]] = w + 0.3 * (w - e)
            conf[JOINT_INDEX[hand]] = 0.5
    if "Head" in mapping and mapping["Head"] + "/end" in world:
        out[:, JOINT_INDEX["Head"]] = 0.5 * (world[mapping["Head"]] + world[mapping["Head"] + "/end"])
    if "Neck" not in mapping and "Head" in mapping and spine_shoulder is not None:
        out[:, JOINT_INDEX["Neck"]] = world[spine_shoulder] + 0.35 * (
            out[:, JOINT_INDEX["Head"]] - world[spine_shoulder])
        conf[JOINT_INDEX["Neck"]] = 1.0
    out *= scale
    seen = conf > 0
    floor = out[:, seen, 1].min()
    out[:, :, 1] -= floor
    out[:, ~seen] = 0.0
    return KinectTake(out, conf, scheme.name if scheme is not None else None, units, scale,
                      mapping)


def _branch_point(bvh: Bvh, shoulders: list[str | None]) -> str | None:
    """The joint where the two arm chains meet (the base of the neck)."""
    names = [j.name for j in bvh.joints]
    chains = []
    for s in shoulders:
        if s is None or s.split("/")[0] not in names:
            return None
        chain, k = [], names.index(s.split("/")[0])
        while k >= 0:
            chain.append(k)
            k = bvh.joints[k].parent
        chains.append(chain)
    common = [k for k in chains[0] if k in set(chains[1])]
    return names[common[0]] if common else None


class BvhMotion:
    """A BVH clip as the simulator uses it: joints at any time (linear interpolation)."""

    def __init__(self, bvh: Bvh, height: float = 1.75, joint_map: dict[str, str] | None = None
                 ) -> None:
        self.bvh = bvh
        self.frames, self._conf = kinect_joints(bvh, height, joint_map)
        self.frame_time = bvh.frame_time
        self.duration = max(len(self.frames) - 1, 0) * bvh.frame_time
        hips = self.frames[:, JOINT_INDEX["HipLeft"]] - self.frames[:, JOINT_INDEX["HipRight"]]
        # facing: the left-hip direction turned a quarter to the right (body frame x=left, z=fwd)
        self._headings = np.unwrap(np.arctan2(-hips[:, 2], hips[:, 0]))
        self._roots = self.frames[:, JOINT_INDEX["SpineBase"]][:, [0, 2]]

    def _at(self, series: np.ndarray, t: float) -> np.ndarray:
        x = min(max(t / self.frame_time, 0.0), len(series) - 1.0)
        i = min(int(x), len(series) - 2) if len(series) > 1 else 0
        f = x - i
        return series[i] if len(series) == 1 else series[i] * (1 - f) + series[i + 1] * f

    def joints(self, t: float) -> np.ndarray:
        return self._at(self.frames, t)

    def root(self, t: float) -> np.ndarray:
        return self._at(self._roots, t)

    def heading(self, t: float) -> float:
        return float(self._at(self._headings, t))

    def conf(self) -> np.ndarray:
        return self._conf.copy()


def resample(frames: np.ndarray, frame_time: float, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """(times (N,), frames (N, ...)) at ``fps`` by linear interpolation."""
    duration = (len(frames) - 1) * frame_time
    times = np.arange(0.0, duration + 1e-9, 1.0 / fps)
    x = times / frame_time
    i = np.minimum(x.astype(int), len(frames) - 2) if len(frames) > 1 else np.zeros(len(x), int)
    f = (x - i).reshape(-1, *([1] * (frames.ndim - 1)))
    if len(frames) == 1:
        return times, np.repeat(frames, len(times), axis=0)
    return times, frames[i] * (1 - f) + frames[i + 1] * f


def import_bvh(path: str, out: str, height: float | None = None, fps: float = 30.0,
               sensor: str = "bvh", joint_map: dict[str, str] | None = None,
               units: str | None = None) -> tuple[int, KinectTake]:
    """A BVH take as a one-sensor recording: clean motion capture at ``fps`` (default 30 Hz).

    The sensor's space is stage space (y up, feet on y = 0, metres), so the
    recording's rig makes it the reference with no calibration needed. Every
    mapped joint is tracked (confidence 1); BVH has no hand states. Lengths:
    ``height`` (scale to it) or ``units`` (None: detected). Returns
    (datagrams written, the take as read).
    """
    from ..clients.osc import BodyFrame
    from ...rig import Rig, SensorConfig
    from .common import Frame, Take, write_takes
    bvh = load_bvh(path)
    kinect = to_kinect(bvh, height, joint_map, units)
    frames, conf = kinect.frames, kinect.conf
    times, resampled = resample(frames, bvh.frame_time, fps)
    take = Take(sensor, "mocap", [Frame(float(t), [BodyFrame(0, j, conf, None)])
                                  for t, j in zip(times, resampled)])
    rig = Rig(reference=sensor)
    rig.sensors[sensor] = SensorConfig(sensor, "mocap")
    meta = {"source": "stage import bvh", "files": [os.path.basename(path)], "height_m": height,
            "units": kinect.units, "m_per_unit": kinect.scale, "scheme": kinect.scheme,
            "fps": fps, "file_fps": bvh.fps, "rig": rig.to_dict(),
            "joints_missing": [JOINTS[i] for i in range(N_JOINTS) if conf[i] == 0]}
    return write_takes(out, [take], meta), kinect


__all__ = ["Bvh", "BvhJoint", "BvhMotion", "KinectTake", "parse_bvh", "load_bvh",
           "forward_kinematics", "kinect_joints", "to_kinect", "resolve_mapping", "resample",
           "import_bvh", "ALIASES"]
