"""Importers: sample files in each format round-trip into recordings, errors are one line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stage.cli.main import main
from stage.errors import ConfigError
from stage.sensors.importers.bvh import (BvhMotion, forward_kinematics, kinect_joints, load_bvh,
                                         parse_bvh, resolve_mapping)
from stage.sensors.importers.ntu import import_ntu, read_skeleton_file, write_skeleton_file
from stage.sensors.importers.nucla import V1_TO_V2, import_nucla, read_nucla_json
from stage.joints import JOINT_INDEX as J
from stage.joints import JOINTS
from stage.sensors.protocol import (HandStateMsg, JointCoordinates, LostUser, NewUser,
                                    RegisterDevice, decode_datagram)
from stage.sensors.recording import read_recording

DATA = Path(__file__).parent / "data"
NTU = sorted(DATA.glob("S001C00*P001R001A001.skeleton"))
NUCLA = sorted(DATA.glob("a01_s01_e00_v0*.json"))


def messages(path) -> dict[str, list[tuple[float, object]]]:
    """Per client: (arrival, message) in order, decoded from a recording."""
    out: dict[str, list] = {}
    for rec in read_recording(path):
        decoded = decode_datagram(rec.data)
        assert not decoded.drops
        for msg, _ in decoded.messages:
            out.setdefault(msg.client, []).append((rec.arrival, msg))
    return out


# ---------------------------------------------------------------- NTU RGB+D

def test_ntu_files_write_and_read_back_identically(tmp_path):
    for path in NTU:
        frames = read_skeleton_file(path)
        copy = tmp_path / path.name
        write_skeleton_file(copy, frames)
        assert copy.read_text() == path.read_text()


def test_ntu_performance_imports_as_one_multi_sensor_recording(tmp_path):
    out = tmp_path / "ntu.rec"
    import_ntu([str(p) for p in NTU], str(out))
    got = messages(out)
    assert set(got) == {"ntu-c1", "ntu-c2", "ntu-c3"}
    for cam, path in enumerate(NTU, 1):
        frames = read_skeleton_file(path)
        msgs = got[f"ntu-c{cam}"]
        assert isinstance(msgs[0][1], RegisterDevice) and msgs[0][1].sensor_type == "kinect2"
        skeletons = [(t, m) for t, m in msgs if isinstance(m, JointCoordinates)]
        assert len(skeletons) == sum(len(b) for b in frames)
        ids: dict[int, int] = {}
        k = 0
        for f, bodies in enumerate(frames):
            for body in bodies:
                t, msg = skeletons[k]
                k += 1
                assert t == pytest.approx(f / 30)
                uid = ids.setdefault(body.body_id, msg.user)
                assert msg.user == uid
                np.testing.assert_allclose(msg.joints, body.joints[:, :3], rtol=1e-6, atol=1e-6)
                expected = np.array([{0: 0.0, 1: 0.5, 2: 1.0}[int(s)] for s in body.joints[:, 11]])
                np.testing.assert_array_equal(msg.conf, expected)
        hands = [(m.hand, int(m.state)) for _, m in msgs if isinstance(m, HandStateMsg)]
        assert hands[:2] == [(0, frames[0][0].hand_left_state), (1, frames[0][0].hand_right_state)]
    # the second person on camera 1 gets user id 1, arrives at frame 5, leaves after frame 9
    c1 = got["ntu-c1"]
    new = [(round(t * 30), m.user) for t, m in c1 if isinstance(m, NewUser)]
    lost = [(round(t * 30), m.user) for t, m in c1 if isinstance(m, LostUser)]
    assert new == [(0, 0), (4, 1)]
    assert (9, 1) in lost and lost[-1][1] == 0  # and everybody leaves when the take ends


def test_ntu_errors_name_the_line(tmp_path):
    text = NTU[0].read_text().splitlines()
    cut = tmp_path / "S001C001P001R001A001.skeleton"
    cut.write_text("\n".join(text[:40]) + "\n")
    with pytest.raises(ConfigError, match=r"S001C001P001R001A001.skeleton:\d+: file ends"):
        read_skeleton_file(cut)
    bad = tmp_path / "S001C002P001R001A001.skeleton"
    text[4] = text[4].replace(" ", " x ", 1)
    bad.write_text("\n".join(text) + "\n")
    with pytest.raises(ConfigError, match=r":5: a joint line: expected 12 value"):
        read_skeleton_file(bad)
    other = tmp_path / "S002C003P001R001A001.skeleton"
    other.write_text(NTU[2].read_text())
    with pytest.raises(ConfigError, match="different performances"):
        import_ntu([str(NTU[0]), str(other)], str(tmp_path / "x.rec"))


# ---------------------------------------------------------------- N-UCLA

def test_nucla_views_import_with_kinect1_joints_mapped(tmp_path):
    out = tmp_path / "nucla.rec"
    import_nucla([str(p) for p in NUCLA], str(out))
    got = messages(out)
    assert set(got) == {"nucla-v1", "nucla-v2", "nucla-v3"}
    missing = [J[n] for n in ("Neck", "HandTipLeft", "ThumbLeft", "HandTipRight", "ThumbRight")]
    lengths = []
    for view, path in enumerate(NUCLA, 1):
        _, skel, _ = read_nucla_json(path)
        skeletons = [(t, m) for t, m in got[f"nucla-v{view}"] if isinstance(m, JointCoordinates)]
        lengths.append(len(skeletons))
        assert len(skeletons) == len(skel)
        for k, (t, msg) in enumerate(skeletons):
            assert t == pytest.approx(k / 30)
            np.testing.assert_allclose(msg.joints[V1_TO_V2], skel[k], atol=1e-6)
            assert (msg.conf[missing] == 0).all()
            present = np.any(skel[k] != 0, axis=1)
            np.testing.assert_array_equal(msg.conf[V1_TO_V2], present.astype(float))
        assert not [m for _, m in got[f"nucla-v{view}"] if isinstance(m, HandStateMsg)]
    assert len(set(lengths)) == 3  # the views are not aligned frame for frame
    # the sample has one joint missing in view 2 (FootLeft, frames 4-5)
    v2 = [m for _, m in got["nucla-v2"] if isinstance(m, JointCoordinates)]
    assert v2[3].conf[J["FootLeft"]] == 0 and v2[2].conf[J["FootLeft"]] == 1


def test_nucla_stretch_aligns_the_ends(tmp_path):
    out = tmp_path / "nucla.rec"
    import_nucla([str(p) for p in NUCLA], str(out), align="stretch")
    got = messages(out)
    ends = [max(t for t, m in msgs if isinstance(m, JointCoordinates)) for msgs in got.values()]
    assert max(ends) - min(ends) < 1e-9


def test_nucla_errors(tmp_path):
    bad = tmp_path / "a01_s01_e00_v01.json"
    bad.write_text('{"file_name": "a01_s01_e00_v01", "skeletons": [[[0, 1]]]}')
    with pytest.raises(ConfigError, match="frames x 20 x 3"):
        read_nucla_json(bad)
    bad.write_text('{"skeletons": [}')
    with pytest.raises(ConfigError, match=r"a01_s01_e00_v01.json:1:\d+: not JSON"):
        read_nucla_json(bad)
    other = tmp_path / "a02_s01_e00_v02.json"
    other.write_text(NUCLA[1].read_text().replace("a01_", "a02_"))
    with pytest.raises(ConfigError, match="different samples"):
        import_nucla([str(NUCLA[0]), str(other)], str(tmp_path / "x.rec"))


# ---------------------------------------------------------------- BVH

def _fk_by_hand(bvh, frame: int) -> dict[str, np.ndarray]:
    """An independent forward kinematics with scipy, joint by joint, for one frame."""
    values = list(bvh.frames[frame])
    world: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    out = {}
    for k, joint in enumerate(bvh.joints):
        chans = {}
        order = ""
        for ch in joint.channels:
            chans[ch] = values.pop(0)
            if ch.endswith("rotation"):
                order += ch[0].upper()
        angles = [chans[a.lower() + "rotation"] for a in order]
        r = Rotation.from_euler(order, angles, degrees=True).as_matrix() if order else np.eye(3)
        t = np.array([chans.get(a + "position", joint.offset[i]) for i, a in enumerate("xyz")])
        if joint.parent < 0:
            world[k] = (r, t)
        else:
            pr, pp = world[joint.parent]
            world[k] = (pr @ r, pp + pr @ t)
        out[joint.name] = world[k][1]
        if joint.end_site is not None:
            out[joint.name + "/end"] = world[k][1] + world[k][0] @ joint.end_site
    return out


def test_bvh_forward_kinematics_agrees_with_an_independent_computation():
    bvh = load_bvh(DATA / "march.bvh")
    fk = forward_kinematics(bvh)
    for frame in (0, 13, 40):
        expected = _fk_by_hand(bvh, frame)
        for name, pos in expected.items():
            np.testing.assert_allclose(fk[name][frame], pos, atol=1e-9, err_msg=name)


def test_bvh_imports_as_clean_mocap_at_30_hz(tmp_path):
    out = tmp_path / "march.rec"
    assert main(["import", "bvh", str(DATA / "march.bvh"), "--out", str(out),
                 "--height", "1.82"]) == 0
    rec = read_recording(out)
    assert rec.meta["rig"]["reference"] == "bvh"
    skeletons = [m for msgs in messages(out).values() for _, m in msgs
                 if isinstance(m, JointCoordinates)]
    assert len(skeletons) == 31  # 1 s at 30 Hz, both ends included
    frames, conf = kinect_joints(load_bvh(DATA / "march.bvh"), 1.82)
    np.testing.assert_allclose(skeletons[0].joints, frames[0] * (conf > 0)[:, None], atol=1e-6)
    np.testing.assert_allclose(skeletons[-1].joints, frames[-1] * (conf > 0)[:, None], atol=1e-6)
    assert conf[J["HandTipLeft"]] == 1 and conf[J["ThumbLeft"]] == 0  # the file has no thumbs
    assert rec.meta["joints_missing"] == ["ThumbLeft", "ThumbRight"]


def test_bvh_naming_conventions_map_to_the_right_joints():
    cmu = ["Hips", "LHipJoint", "LeftHip", "LeftKnee", "LeftAnkle", "LeftToe", "LeftCollar",
           "LeftShoulder", "LeftElbow", "LeftWrist", "lhand", "LFingers", "LFingers/end",
           "LThumb/end", "Neck", "Head"]
    m = resolve_mapping(cmu)
    assert (m["ShoulderLeft"], m["ElbowLeft"], m["WristLeft"], m["HandLeft"], m["HipLeft"],
            m["FootLeft"], m["HandTipLeft"]) == ("LeftShoulder", "LeftElbow", "LeftWrist",
                                                  "LFingers", "LeftHip", "LeftToe",
                                                  "LFingers/end")
    mixamo = ["Hips", "Spine", "Spine1", "Spine2", "Neck", "Head", "LeftShoulder", "LeftArm",
              "LeftForeArm", "LeftHand", "LeftHandMiddle1", "RightShoulder", "RightArm",
              "RightForeArm", "RightHand", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"]
    m = resolve_mapping(mixamo)
    assert (m["ShoulderLeft"], m["ElbowLeft"], m["WristLeft"], m["HandLeft"], m["KneeLeft"],
            m["ShoulderRight"]) == ("LeftArm", "LeftForeArm", "LeftHand", "LeftHandMiddle1",
                                    "LeftLeg", "RightArm")
    with pytest.raises(ConfigError, match="no joint 'Nope'"):
        resolve_mapping(mixamo, {"HandLeft": "Nope"})


def test_bvh_errors_name_the_line(tmp_path):
    text = (DATA / "march.bvh").read_text()
    with pytest.raises(ConfigError, match=r"x.bvh:\d+: frame 2 has 20 values"):
        parse_bvh(text.replace("\n0 95 1.6667", "\n0 95", 1), "x.bvh")
    with pytest.raises(ConfigError, match=r"x.bvh:\d+: the file has 30 frames"):
        parse_bvh("\n".join(text.splitlines()[:-31]) + "\n", "x.bvh")
    with pytest.raises(ConfigError, match=r"x.bvh:5: unknown channel 'Wrotation'"):
        parse_bvh(text.replace("Zrotation Yrotation Xrotation", "Wrotation Yrotation Xrotation",
                               1), "x.bvh")
    with pytest.raises(ConfigError, match=r"x.bvh:1: expected 'HIERARCHY'"):
        parse_bvh("MOTION\n", "x.bvh")


def test_bvh_motion_interpolates_and_finds_the_heading():
    motion = BvhMotion(load_bvh(DATA / "march.bvh"), 1.82)
    assert motion.duration == pytest.approx(1.0)
    assert motion.heading(0.5) == pytest.approx(0.0, abs=0.1)  # marching along +z
    a, b = motion.joints(0.0), motion.joints(1 / 60)
    np.testing.assert_allclose(motion.joints(1 / 120), (a + b) / 2, atol=1e-12)
    # 100 units in a second; the 182-unit skeleton scaled to 1.82 m (stance height from the
    # motion itself, so within a percent)
    assert motion.root(1.0)[1] - motion.root(0.0)[1] == pytest.approx(1.0, abs=0.01)
    assert math.isfinite(motion.heading(2.0))  # past the end: the last frame


def test_import_command_reports_one_line_errors(tmp_path, capsys):
    assert main(["import", "ntu", str(tmp_path / "missing.skeleton"), "--out",
                 str(tmp_path / "x.rec")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stage: ") and "missing.skeleton: no such file" in err
    assert "\n" not in err
    assert main(["import", "nucla", *map(str, NUCLA), "--out", str(tmp_path / "n.rec")]) == 0
    assert "3 sensor(s)" in capsys.readouterr().out
    assert json.loads(json.dumps(read_recording(tmp_path / "n.rec").meta))["labels"] == [1, 1, 1]
    assert JOINTS  # (imported for the joint names used above)
