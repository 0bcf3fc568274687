"""Which BVH joint is which Kinect joint: built-in naming schemes, joint-map files, units.

A BVH file names its joints however its studio likes. Four widely used
schemes are built in and recognised by their names (``detect``):

- ``cmu``: the CMU Graphics Lab database as converted to BVH, in both common
  namings (``LHipJoint``, ``LeftHip``/``LeftUpLeg``, ``LeftCollar``, ``lhand``,
  ``LFingers``, ``LThumb``, ...); lengths in the ASF's own unit (1/0.45 inch).
- ``bandai-namco``: the Bandai Namco Research Motion Dataset (``joint_Root``,
  ``Hips``, ``UpperArm_L``, ``LowerLeg_R``, ``Toes_L``, ...; centimetres, six
  channels on every joint). No finger joints: the palm is extrapolated.
- ``mixamo``: Adobe Mixamo characters (``mixamorig:Hips``, ``LeftUpLeg``,
  ``LeftHandIndex1``..., ``HeadTop_End``; any ``prefix:`` namespace).
- ``lafan``: Ubisoft La Forge's LAFAN1 (``Hips``, ``LeftUpLeg``, ``LeftToe``,
  ``Spine2``, no fingers; centimetres).

A scheme lists, per Kinect joint, candidate BVH names, best first (``X/end``
is joint X's End Site). A joint-map file (YAML, our 25 joint names to the
file's names) overrides or completes the detected scheme, or maps a file no
scheme knows. Joints not mapped are derived where the Kinect's proportions
allow (``bvh.kinect_joints``) and otherwise sent with confidence 0.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from ...errors import ConfigError
from ...joints import JOINT_INDEX


@dataclass(frozen=True)
class Scheme:
    name: str
    description: str
    signature: tuple[str, ...]              # names that identify the scheme
    joints: dict[str, tuple[str, ...]]      # Kinect joint -> candidate BVH names, best first


def _sided(template: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """Expand ``{S}`` (Left/Right), ``{s}`` (L/R) and ``{l}`` (l/r) for both sides."""
    out: dict[str, tuple[str, ...]] = {}
    for joint, names in template.items():
        if "{side}" not in joint:
            out[joint] = names
            continue
        for side, s, low in (("Left", "L", "l"), ("Right", "R", "r")):
            out[joint.replace("{side}", side)] = tuple(
                n.replace("{S}", side).replace("{s}", s).replace("{l}", low) for n in names)
    return out


SCHEMES: dict[str, Scheme] = {s.name: s for s in (
    Scheme("cmu", "CMU Graphics Lab motion capture database (BVH conversions)",
           ("LHipJoint", "RHipJoint", "Hips", "Head"),
           _sided({"SpineBase": ("Hips",), "Neck": ("Neck",), "Head": ("Head",),
                   "Shoulder{side}": ("{S}Arm", "{S}Shoulder"),
                   "Elbow{side}": ("{S}ForeArm", "{S}Elbow"),
                   "Wrist{side}": ("{S}Hand", "{S}Wrist"),
                   "Hand{side}": ("{s}Fingers", "{S}FingerBase", "{l}hand"),
                   "HandTip{side}": ("{s}Fingers/end", "{S}HandIndex1/end", "{S}FingerBase/end"),
                   "Thumb{side}": ("{s}Thumb/end",),
                   "Hip{side}": ("{S}UpLeg", "{S}Hip"), "Knee{side}": ("{S}Leg", "{S}Knee"),
                   "Ankle{side}": ("{S}Foot", "{S}Ankle"),
                   "Foot{side}": ("{S}ToeBase", "{S}Toe")})),
    Scheme("bandai-namco", "Bandai Namco Research Motion Dataset",
           ("joint_Root", "Hips", "UpperArm_L", "UpperArm_R", "LowerLeg_L", "Toes_R"),
           _sided({"SpineBase": ("Hips",), "Neck": ("Neck",), "Head": ("Head",),
                   "Shoulder{side}": ("UpperArm_{s}",), "Elbow{side}": ("LowerArm_{s}",),
                   "Wrist{side}": ("Hand_{s}",), "Hip{side}": ("UpperLeg_{s}",),
                   "Knee{side}": ("LowerLeg_{s}",), "Ankle{side}": ("Foot_{s}",),
                   "Foot{side}": ("Toes_{s}",)})),
    Scheme("mixamo", "Adobe Mixamo characters",
           ("Hips", "Spine1", "Spine2", "LeftUpLeg", "LeftToeBase", "LeftForeArm",
            "HeadTop_End"),
           _sided({"SpineBase": ("Hips",), "Neck": ("Neck",), "Head": ("Head",),
                   "Shoulder{side}": ("{S}Arm",), "Elbow{side}": ("{S}ForeArm",),
                   "Wrist{side}": ("{S}Hand",),
                   "Hand{side}": ("{S}HandMiddle1", "{S}HandIndex1"),
                   "HandTip{side}": ("{S}HandMiddle4", "{S}HandMiddle3/end", "{S}HandIndex4",
                                     "{S}HandIndex3/end"),
                   "Thumb{side}": ("{S}HandThumb4", "{S}HandThumb3/end"),
                   "Hip{side}": ("{S}UpLeg",), "Knee{side}": ("{S}Leg",),
                   "Ankle{side}": ("{S}Foot",), "Foot{side}": ("{S}ToeBase", "{S}Toe_End")})),
    Scheme("lafan", "Ubisoft La Forge LAFAN1",
           ("Hips", "Spine1", "Spine2", "LeftUpLeg", "LeftToe", "LeftForeArm", "Neck", "Head"),
           _sided({"SpineBase": ("Hips",), "Neck": ("Neck",), "Head": ("Head",),
                   "Shoulder{side}": ("{S}Arm",), "Elbow{side}": ("{S}ForeArm",),
                   "Wrist{side}": ("{S}Hand",), "Hip{side}": ("{S}UpLeg",),
                   "Knee{side}": ("{S}Leg",), "Ankle{side}": ("{S}Foot",),
                   "Foot{side}": ("{S}Toe",)})),
)}


def bare(name: str) -> str:
    """A joint name without its namespace and case: ``mixamorig:LeftArm`` -> ``leftarm``."""
    head, _, end = name.partition("/")
    return head.rsplit(":", 1)[-1].lower() + (("/" + end) if end else "")


def detect(names: list[str]) -> Scheme | None:
    """The built-in scheme whose signature the file's joint names match best (all of it or
    all but one name), or None."""
    present = {bare(n) for n in names}
    best, best_score = None, 0.0
    for scheme in SCHEMES.values():
        hits = sum(bare(n) in present for n in scheme.signature)
        score = hits / len(scheme.signature)
        if hits >= len(scheme.signature) - 1 and score > best_score:
            best, best_score = scheme, score
    return best


def scheme_mapping(scheme: Scheme, names: list[str]) -> dict[str, str]:
    """Kinect joint -> the file's position name ('Joint' or 'Joint/end'), for those found."""
    lookup = {bare(n): n for n in names}
    out = {}
    for kinect, candidates in scheme.joints.items():
        for candidate in candidates:
            if bare(candidate) in lookup:
                out[kinect] = lookup[bare(candidate)]
                break
    return out


def apply_overrides(mapping: dict[str, str], names: list[str], overrides: dict[str, str],
                    source: str = "joint_map") -> dict[str, str]:
    """The mapping with a joint map's entries put over it; errors name the bad entry."""
    lookup = {bare(n): n for n in names}
    out = dict(mapping)
    for kinect, name in overrides.items():
        if kinect not in JOINT_INDEX:
            raise ConfigError(f"{source}: '{kinect}' is not one of the 25 joint names "
                              "(SpineBase, HandLeft, ...)")
        if not isinstance(name, str) or bare(name) not in lookup:
            raise ConfigError(f"{source}: the BVH file has no joint '{name}' (for {kinect})")
        out[kinect] = lookup[bare(name)]
    return out


def load_joint_map(path: str | os.PathLike) -> dict[str, str]:
    """A joint-map YAML file: ``{HandLeft: LeftHandMiddle1, ...}`` (our name: the file's name)."""
    from ...yamlio import load_marked
    path = str(path)
    data = load_marked(path)
    if not isinstance(data, dict):
        raise ConfigError("a joint map is a mapping of our joint names to the BVH file's names",
                          path=path)
    out = {}
    for key, value in data.items():
        line = getattr(data, "marks", {}).get(key, (None, None))[0]
        if str(key) not in JOINT_INDEX:
            raise ConfigError(f"'{key}' is not one of the 25 joint names", path=path, line=line)
        if not isinstance(value, str):
            raise ConfigError(f"{key}: give the BVH joint's name (a string)", path=path,
                              line=line)
        out[str(key)] = value
    return out


#: metres per file unit
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "cmu": 0.0254 / 0.45}
#: standing heights (m) a unit may imply; the ranges of the units do not overlap
PLAUSIBLE_HEIGHT = (1.2, 2.3)


def detect_units(standing: float) -> str:
    """The unit in which a performer ``standing`` file units tall is 1.2-2.3 m tall."""
    fits = [(abs(math.log(standing * f / 1.7)), u) for u, f in UNITS.items()
            if PLAUSIBLE_HEIGHT[0] <= standing * f <= PLAUSIBLE_HEIGHT[1]]
    if not fits:
        raise ConfigError(f"cannot tell the file's length unit: the performer stands "
                          f"{standing:.4g} units tall, which is no adult in "
                          f"{', '.join(UNITS)}; give --units or --height")
    return min(fits)[1]
