"""BVH for any skeleton: the built-in naming schemes, joint-map files, units, channel orders.

Each built-in scheme gets a small file written here in its own names,
hierarchy, unit and channel layout (``bvh_schemes``); all four move the same
body the same way, so the imported joints are checked against positions
computed without any BVH.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from bvh_schemes import DIRECT, N_FRAMES, expected, write
from scipy.spatial.transform import Rotation

from stage.cli.main import main
from stage.errors import ConfigError
from stage.joints import JOINT_INDEX as J
from stage.sensors.importers.bvh import forward_kinematics, load_bvh, parse_bvh, to_kinect
from stage.sensors.importers.bvh_maps import SCHEMES, detect, detect_units, load_joint_map
from stage.sensors.recording import read_recording

UNIT = {"cmu": "cmu", "bandai-namco": "cm", "mixamo": "cm", "lafan": "cm"}


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_each_built_in_scheme_is_recognised_and_read_in_its_own_units(tmp_path, scheme):
    path = tmp_path / f"{scheme}.bvh"
    write(scheme, path)
    take = to_kinect(load_bvh(path))
    assert take.scheme == scheme and take.units == UNIT[scheme]
    for k in range(N_FRAMES):
        for joint in DIRECT:
            np.testing.assert_allclose(take.frames[k, J[joint]], expected(joint, k), atol=1e-4,
                                       err_msg=f"{scheme} {joint} frame {k}")
    # a rigid skeleton: every bone keeps its length through the motion
    for a, b in (("ShoulderLeft", "ElbowLeft"), ("ElbowLeft", "WristLeft"),
                 ("HipLeft", "KneeLeft"), ("KneeLeft", "AnkleLeft"), ("SpineBase", "Neck")):
        lengths = np.linalg.norm(take.frames[:, J[a]] - take.frames[:, J[b]], axis=1)
        assert np.ptp(lengths) < 1e-5, (scheme, a, b)
    assert take.frames[:, :, 1].min() == pytest.approx(0.0, abs=1e-9)   # on the floor
    fingers = scheme in ("cmu", "mixamo")
    assert take.conf[J["HandTipLeft"]] == (1.0 if fingers else 0.0)
    assert take.conf[J["ThumbRight"]] == (1.0 if fingers else 0.0)
    # no hand joint (Bandai Namco, LAFAN): the palm continues the forearm, as a guess
    assert take.conf[J["HandLeft"]] == (1.0 if fingers else 0.5)


def test_schemes_are_told_apart_by_their_names():
    assert detect(["Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase", "Spine", "Spine1",
                   "Neck", "Neck1", "Head", "LHipJoint", "RHipJoint", "LeftForeArm"]).name == "cmu"
    assert detect(["mixamorig1:Hips", "mixamorig1:Spine1", "mixamorig1:Spine2",
                   "mixamorig1:LeftUpLeg", "mixamorig1:LeftToeBase", "mixamorig1:LeftForeArm",
                   "mixamorig1:HeadTop_End"]).name == "mixamo"
    assert detect(["Hips", "Chest", "LeftHip", "LeftShoulder"]) is None


def test_units_are_detected_from_the_performers_size():
    assert [detect_units(h) for h in (1.7, 170, 1750, 67, 30.5)] == ["m", "cm", "mm", "in",
                                                                       "cmu"]
    with pytest.raises(ConfigError, match="give --units or --height"):
        detect_units(8.0)


def test_the_import_command_takes_a_joint_map_and_units(tmp_path, capsys):
    path = tmp_path / "lafan.bvh"
    write("lafan", path)
    out = tmp_path / "take.rec"
    assert main(["import", "bvh", str(path), "--out", str(out)]) == 0
    assert "bvh naming: lafan; lengths: cm (detected)" in capsys.readouterr().out
    assert read_recording(out).meta["scheme"] == "lafan"
    # the palm from the End Site beyond the hand, and the hand tip too
    joint_map = tmp_path / "map.yaml"
    joint_map.write_text("HandLeft: LeftHand/end\nHandTipLeft: LeftHand/end\n")
    assert main(["import", "bvh", str(path), "--out", str(tmp_path / "b.rec"), "--joint-map",
                 str(joint_map), "--units", "cm"]) == 0
    assert "lafan + " in capsys.readouterr().out
    assert "HandTipLeft" not in read_recording(tmp_path / "b.rec").meta["joints_missing"]
    take = to_kinect(load_bvh(path), joint_map=load_joint_map(joint_map))
    assert take.conf[J["HandLeft"]] == 1.0
    # a map for a file no scheme knows
    generic = tmp_path / "generic.bvh"
    generic.write_text(path.read_text().replace("Hips", "pelvis_root").replace(
        "UpLeg", "Thigh"))
    with pytest.raises(ConfigError, match="give a joint map"):
        to_kinect(load_bvh(generic))
    joint_map.write_text("SpineBase: pelvis_root\nHipLeft: LeftThigh\nHipRight: RightThigh\n")
    assert to_kinect(load_bvh(generic), joint_map=load_joint_map(joint_map)).units == "cm"
    # mistakes are one line naming the file and line
    joint_map.write_text("SpineBase: pelvis_root\nHandLeftt: LeftHand\n")
    assert main(["import", "bvh", str(generic), "--out", str(tmp_path / "c.rec"),
                 "--joint-map", str(joint_map)]) == 2
    err = capsys.readouterr().err.strip()
    assert "map.yaml:2" in err and "'HandLeftt' is not one of the 25 joint names" in err
    joint_map.write_text("SpineBase: nowhere\n")
    with pytest.raises(ConfigError, match="no joint 'nowhere'"):
        to_kinect(load_bvh(generic), joint_map=load_joint_map(joint_map))


ORDERS = ["".join(p) for p in itertools.permutations("XYZ")]


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("positions_first", [True, False])
def test_every_channel_order(order, positions_first):
    """Rotation channels apply in the order listed, wherever the position channels are."""
    rng = np.random.default_rng(sum(map(ord, order)) + positions_first)
    angles = rng.uniform(-80, 80, size=(2, 3))
    rotations = [f"{a}rotation" for a in order]
    positions = ["Xposition", "Yposition", "Zposition"]
    channels = positions + rotations if positions_first else rotations + positions
    values = []
    for k in range(2):   # root: at (1, 2, 3) turned by frame k's angles; child 10 units along x
        by_name = dict(zip(rotations, angles[k]))
        by_name.update(zip(positions, (1.0, 2.0, 3.0)))
        values.append(" ".join(f"{by_name[c]:.9f}" for c in channels) + " 0 0 0")
    text = (f"HIERARCHY\nROOT root\n{{\n OFFSET 0 0 0\n CHANNELS 6 {' '.join(channels)}\n"
            " JOINT child\n {\n  OFFSET 10 0 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n"
            "  End Site\n  {\n   OFFSET 0 5 0\n  }\n }\n}\nMOTION\nFrames: 2\n"
            "Frame Time: 0.01\n" + "\n".join(values) + "\n")
    world = forward_kinematics(parse_bvh(text))
    for k in range(2):
        r = Rotation.from_euler(order, angles[k], degrees=True).as_matrix()  # intrinsic
        np.testing.assert_allclose(world["root"][k], [1, 2, 3], atol=1e-9)
        np.testing.assert_allclose(world["child"][k], [1, 2, 3] + r @ [10, 0, 0], atol=1e-6)
        np.testing.assert_allclose(world["child/end"][k], [1, 2, 3] + r @ [10, 5, 0],
                                   atol=1e-6)
