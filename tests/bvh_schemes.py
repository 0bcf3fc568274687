"""Small BVH files in the four built-in naming schemes, all moving the same body the same way.

A plain helper module for the tests (``from bvh_schemes import ...``). One
body (metres, y up, facing +z, the performer's left on +x, toes on the floor,
toes below the knees so that bending a knee never lowers a foot) is written in
each scheme's own joint names, hierarchy, length unit and channel layout, as
the published files of that scheme are:

- ``cmu``: ASF-style names (``LHipJoint``, ``LeftHip``, ``LeftCollar``, ``lhand``,
  ``LFingers``, ``LThumb``), the CMU unit (1/0.45 inch), ``Zrotation Yrotation
  Xrotation`` on every joint, End Sites on the limbs;
- ``bandai-namco``: ``joint_Root`` on the floor, ``Hips``, ``UpperArm_L``,
  ``LowerLeg_R``, ``Toes_L``...; centimetres; six channels on every joint
  (``Xposition Yposition Zposition Zrotation Xrotation Yrotation``, positions
  equal to the offsets), End Sites with zero offsets;
- ``mixamo``: ``mixamorig:`` names with fingers and ``HeadTop_End``;
  centimetres; ``Zrotation Xrotation Yrotation``;
- ``lafan``: LAFAN1's 22 joints; centimetres; ``Zrotation Yrotation Xrotation``.

The motion: the root walks and turns, the left arm swings about all three
axes at the shoulder, the left knee bends. Every other joint keeps its rest
rotation, so the positions of the same body part agree across the four files
and ``expected`` computes them without any BVH (a check independent of the
importer's forward kinematics).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

N_FRAMES = 9
FRAME_TIME = 1 / 30

# the body, metres (left side; the right side mirrors x)
CENTRE = {"floor": (0, 0, 0), "hips": (0, 0.95, 0), "spine": (0, 1.05, 0), "chest": (0, 1.25, 0),
          "chest2": (0, 1.36, 0), "neck": (0, 1.50, 0), "head": (0, 1.60, 0),
          "head_top": (0, 1.75, 0)}
SIDE = {"clavicle": (0.03, 1.42, 0), "shoulder": (0.18, 1.42, 0), "elbow": (0.18, 1.14, 0),
        "wrist": (0.18, 0.88, 0), "palm": (0.18, 0.83, 0), "knuckle": (0.18, 0.80, 0),
        "finger_mid": (0.18, 0.75, 0), "fingertip": (0.18, 0.70, 0),
        "thumb": (0.16, 0.86, 0.02), "thumb_mid": (0.155, 0.83, 0.035),
        "thumb_tip": (0.15, 0.80, 0.05), "hip": (0.09, 0.92, 0), "knee": (0.09, 0.50, 0.12),
        "ankle": (0.09, 0.08, 0), "toe": (0.09, 0.0, 0.12), "toe_end": (0.09, 0.0, 0.18)}


def point(key: str) -> np.ndarray:
    if key in CENTRE:
        return np.array(CENTRE[key], float)
    side, part = key.split(".")
    p = np.array(SIDE[part], float)
    return p * [1 if side == "L" else -1, 1, 1]


# a scheme: (units -> metres per unit, root channels, joint channels, joints), joints being
# (name, parent or None, body point, end-site body point or None); "{S}" Left/Right, "{s}" L/R
SCHEMES = {
    "cmu": (0.0254 / 0.45, "Xposition Yposition Zposition Zrotation Yrotation Xrotation",
            "Zrotation Yrotation Xrotation", [
                ("Hips", None, "hips", None),
                ("{s}HipJoint", "Hips", "hips", None), ("{S}Hip", "{s}HipJoint", "{s}.hip", None),
                ("{S}Knee", "{S}Hip", "{s}.knee", None), ("{S}Ankle", "{S}Knee", "{s}.ankle", None),
                ("{S}Toe", "{S}Ankle", "{s}.toe", "{s}.toe_end"),
                ("lowerback", "Hips", "hips", None), ("Chest", "lowerback", "spine", None),
                ("Chest2", "Chest", "chest", None), ("lowerneck", "Chest2", "chest2", None),
                ("Neck", "lowerneck", "neck", None), ("Head", "Neck", "head", "head_top"),
                ("{S}Collar", "Chest2", "chest2", None),
                ("{S}Shoulder", "{S}Collar", "{s}.shoulder", None),
                ("{S}Elbow", "{S}Shoulder", "{s}.elbow", None),
                ("{S}Wrist", "{S}Elbow", "{s}.wrist", None),
                ("{l}hand", "{S}Wrist", "{s}.palm", None),
                ("{s}Fingers", "{l}hand", "{s}.knuckle", "{s}.fingertip"),
                ("{s}Thumb", "{S}Wrist", "{s}.thumb", "{s}.thumb_tip")]),
    "bandai-namco": (0.01, "Xposition Yposition Zposition Zrotation Xrotation Yrotation",
                     "Xposition Yposition Zposition Zrotation Xrotation Yrotation", [
                         ("joint_Root", None, "floor", None), ("Hips", "joint_Root", "hips", None),
                         ("Spine", "Hips", "spine", None), ("Chest", "Spine", "chest", None),
                         ("Neck", "Chest", "neck", None), ("Head", "Neck", "head", "head"),
                         ("Shoulder_{s}", "Chest", "{s}.clavicle", None),
                         ("UpperArm_{s}", "Shoulder_{s}", "{s}.shoulder", None),
                         ("LowerArm_{s}", "UpperArm_{s}", "{s}.elbow", None),
                         ("Hand_{s}", "LowerArm_{s}", "{s}.wrist", "{s}.wrist"),
                         ("UpperLeg_{s}", "Hips", "{s}.hip", None),
                         ("LowerLeg_{s}", "UpperLeg_{s}", "{s}.knee", None),
                         ("Foot_{s}", "LowerLeg_{s}", "{s}.ankle", None),
                         ("Toes_{s}", "Foot_{s}", "{s}.toe", "{s}.toe")]),
    "mixamo": (0.01, "Xposition Yposition Zposition Zrotation Xrotation Yrotation",
               "Zrotation Xrotation Yrotation", [
                   ("mixamorig:Hips", None, "hips", None),
                   ("mixamorig:Spine", "mixamorig:Hips", "spine", None),
                   ("mixamorig:Spine1", "mixamorig:Spine", "chest", None),
                   ("mixamorig:Spine2", "mixamorig:Spine1", "chest2", None),
                   ("mixamorig:Neck", "mixamorig:Spine2", "neck", None),
                   ("mixamorig:Head", "mixamorig:Neck", "head", None),
                   ("mixamorig:HeadTop_End", "mixamorig:Head", "head_top", "head_top"),
                   ("mixamorig:{S}Shoulder", "mixamorig:Spine2", "{s}.clavicle", None),
                   ("mixamorig:{S}Arm", "mixamorig:{S}Shoulder", "{s}.shoulder", None),
                   ("mixamorig:{S}ForeArm", "mixamorig:{S}Arm", "{s}.elbow", None),
                   ("mixamorig:{S}Hand", "mixamorig:{S}ForeArm", "{s}.wrist", None),
                   ("mixamorig:{S}HandMiddle1", "mixamorig:{S}Hand", "{s}.knuckle", None),
                   ("mixamorig:{S}HandMiddle2", "mixamorig:{S}HandMiddle1", "{s}.finger_mid",
                    None),
                   ("mixamorig:{S}HandMiddle4", "mixamorig:{S}HandMiddle2", "{s}.fingertip",
                    "{s}.fingertip"),
                   ("mixamorig:{S}HandThumb1", "mixamorig:{S}Hand", "{s}.thumb", None),
                   ("mixamorig:{S}HandThumb2", "mixamorig:{S}HandThumb1", "{s}.thumb_mid", None),
                   ("mixamorig:{S}HandThumb4", "mixamorig:{S}HandThumb2", "{s}.thumb_tip",
                    "{s}.thumb_tip"),
                   ("mixamorig:{S}UpLeg", "mixamorig:Hips", "{s}.hip", None),
                   ("mixamorig:{S}Leg", "mixamorig:{S}UpLeg", "{s}.knee", None),
                   ("mixamorig:{S}Foot", "mixamorig:{S}Leg", "{s}.ankle", None),
                   ("mixamorig:{S}ToeBase", "mixamorig:{S}Foot", "{s}.toe", None),
                   ("mixamorig:{S}Toe_End", "mixamorig:{S}ToeBase", "{s}.toe_end",
                    "{s}.toe_end")]),
    "lafan": (0.01, "Xposition Yposition Zposition Zrotation Yrotation Xrotation",
              "Zrotation Yrotation Xrotation", [
                  ("Hips", None, "hips", None),
                  ("{S}UpLeg", "Hips", "{s}.hip", None), ("{S}Leg", "{S}UpLeg", "{s}.knee", None),
                  ("{S}Foot", "{S}Leg", "{s}.ankle", None),
                  ("{S}Toe", "{S}Foot", "{s}.toe", "{s}.toe_end"),
                  ("Spine", "Hips", "spine", None), ("Spine1", "Spine", "chest", None),
                  ("Spine2", "Spine1", "chest2", None), ("Neck", "Spine2", "neck", None),
                  ("Head", "Neck", "head", "head_top"),
                  ("{S}Shoulder", "Spine2", "{s}.clavicle", None),
                  ("{S}Arm", "{S}Shoulder", "{s}.shoulder", None),
                  ("{S}ForeArm", "{S}Arm", "{s}.elbow", None),
                  ("{S}Hand", "{S}ForeArm", "{s}.wrist", "{s}.palm")]),
}


def _expand(joints):
    """Both sides of every {S}/{s}/{l} joint, parents before children, left before right."""
    out = []
    for name, parent, body, end in joints:
        sides = (("Left", "L", "l"), ("Right", "R", "r")) if "{" in name + body else ((None,) * 3,)
        for side, s, low in sides:
            def fill(text):
                if text is None or side is None:
                    return text
                return text.replace("{S}", side).replace("{s}", s).replace("{l}", low)
            out.append((fill(name), fill(parent), fill(body), fill(end)))
    return out


def motion(u: float) -> dict[str, object]:
    """The motion at phase u (0-1): root translation (m) and yaw, arm and knee rotations."""
    return {"translation": np.array([0.5 * u, 0.0, 0.3 * u]),
            "root": Rotation.from_euler("Y", 40 * u, degrees=True).as_matrix(),
            "arm": Rotation.from_euler("ZXY", [70 * u, 25 * u, -30 * u], degrees=True).as_matrix(),
            "knee": Rotation.from_euler("X", 60 * u, degrees=True).as_matrix()}


def _moving(body: str) -> str | None:
    """Which rotation a joint at this body point carries: the left shoulder and knee move."""
    return {"L.shoulder": "arm", "L.knee": "knee"}.get(body)


def write(scheme: str, path) -> None:
    """Write the scheme's file to ``path``."""
    unit, root_channels, channels, joints = SCHEMES[scheme]
    joints = _expand(joints)
    parents = {name: parent for name, parent, _, _ in joints}
    bodies = {name: body for name, _, body, _ in joints}
    root_body = "hips"
    lines = ["HIERARCHY"]

    def offset(name):
        parent = parents[name]
        base = point(bodies[parent]) if parent else np.zeros(3)
        return (point(bodies[name]) - base) / unit

    def block(name, depth):
        pad = "  " * depth
        kind = "ROOT" if parents[name] is None else "JOINT"
        chans = root_channels if parents[name] is None else channels
        lines.append(f"{pad}{kind} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(f'{v:.6f}' for v in offset(name))}")
        lines.append(f"{pad}  CHANNELS {len(chans.split())} {chans}")
        end = next(e for n, _, _, e in joints if n == name)
        for child, parent, _, _ in joints:
            if parent == name:
                block(child, depth + 1)
        if end is not None:
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            e = (point(end) - point(bodies[name])) / unit
            lines.append(f"{pad}    OFFSET {' '.join(f'{v:.6f}' for v in e)}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    root = next(n for n, p, _, _ in joints if p is None)
    block(root, 0)
    order = [n for n in _walk(root, joints)]
    lines += ["MOTION", f"Frames: {N_FRAMES}", f"Frame Time: {FRAME_TIME:.7f}"]
    for k in range(N_FRAMES):
        m = motion(k / (N_FRAMES - 1))
        values = []
        for name in order:
            chans = (root_channels if parents[name] is None else channels).split()
            rot = np.eye(3)
            pos = offset(name).copy()
            if bodies[name] == root_body and (parents[name] is None
                                              or bodies[parents[name]] == "floor"):
                rot = m["root"]
                pos = pos + m["translation"] / unit
            elif _moving(bodies[name]) and not any(
                    bodies[p] == bodies[name] for p in [parents[name]] if p):
                rot = m[_moving(bodies[name])]
            axes = "".join(c[0] for c in chans if c.endswith("rotation"))
            angles = dict(zip(axes, Rotation.from_matrix(rot).as_euler(axes.upper(),
                                                                        degrees=True)))
            for c in chans:
                values.append(angles[c[0]] if c.endswith("rotation") else pos["XYZ".index(c[0])])
        lines.append(" ".join(f"{v:.6f}" for v in values))
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def _walk(name, joints):
    yield name
    for child, parent, _, _ in joints:
        if parent == name:
            yield from _walk(child, joints)


#: Kinect joint -> body point, for the joints every scheme maps directly
DIRECT = {f"{k}{side}": f"{s}.{b}" for side, s in (("Left", "L"), ("Right", "R"))
          for k, b in (("Shoulder", "shoulder"), ("Elbow", "elbow"), ("Wrist", "wrist"),
                       ("Hip", "hip"), ("Knee", "knee"), ("Ankle", "ankle"), ("Foot", "toe"))}
DIRECT["Neck"] = "neck"


def expected(kinect_joint: str, k: int) -> np.ndarray:
    """Where the body point of ``kinect_joint`` is in frame ``k`` (metres), without any BVH."""
    m = motion(k / (N_FRAMES - 1))
    body = DIRECT[kinect_joint]
    p = point(body)
    arm = ("L.shoulder", "L.elbow", "L.wrist")
    leg = ("L.knee", "L.ankle", "L.toe")
    if body in arm:
        s = point("L.shoulder")
        p = s + m["arm"] @ (p - s)
    elif body in leg:
        s = point("L.knee")
        p = s + m["knee"] @ (p - s)
    hips = point("hips")
    return m["translation"] + hips + m["root"] @ (p - hips)
