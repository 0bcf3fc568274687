"""Sensor clients: the shared OSC encoder and each sensor's mapping, on recorded arrays."""

from __future__ import annotations

import importlib
import math
import re
import sys
import time

import numpy as np
import pytest
from helpers import query_stats

from stage.errors import StageError
from stage.sensors.sim import standing_pose
from stage.sensors.clients.azure import AZURE_INDEX, K4ABT_JOINTS, azure_body
from stage.sensors.clients.kinect2 import RelativeClock, floor_plane, kinect2_body
from stage.sensors.clients.osc import BodyFrame, ClientEncoder, UdpSender, UserSlots
from stage.sensors.clients.webcam import L, Camera, confidence, hip_distance, landmarks_to_body
from stage.joints import JOINT_INDEX as J
from stage.joints import HandState
from stage.sensors.protocol import (FloorPlane, JointCoordinates, LostUser, NewUser,
                                    RegisterDevice, decode_datagram)
from stage.rig import Rig
from stage.app.server import Server


def body(key, x=0.0, z=3.0) -> BodyFrame:
    """A person 3 m in front of a sensor, facing it, in Kinect camera space."""
    j = standing_pose((x, z), math.pi)
    j[:, 1] -= 0.8  # the sensor is 0.8 m above the floor
    return BodyFrame(key, j, np.ones(25), (HandState.OPEN, HandState.LASSO))


def decode(data: bytes) -> list:
    decoded = decode_datagram(data)
    assert not decoded.drops, decoded.drops
    return [m for m, _ in decoded.messages]


def _stats_after(server: Server, frames: int, within_s: float = 5.0) -> dict:
    """The server's stats once it has counted ``frames`` frames (or after ``within_s``)."""
    deadline = time.monotonic() + within_s
    while True:
        stats = query_stats(server.address)
        if stats["counts"]["frames"] == frames or time.monotonic() > deadline:
            return stats
        time.sleep(0.02)


# ---------------------------------------------------------------- the shared encoder

def test_user_slots_take_the_lowest_free_id():
    slots = UserSlots(3)
    assert [slots.assign(k) for k in "abc"] == [0, 1, 2]
    assert slots.assign("d") is None
    assert slots.release("b") == 1
    assert slots.assign("d") == 1 and slots.assign("a") == 0


def test_encoder_speaks_the_paper_api_in_one_bundle_per_frame():
    enc = ClientEncoder("kin", "kinect2")
    assert decode(enc.register()) == [RegisterDevice("kin", "kinect2")]
    first = decode_datagram(enc.frame([body(901), body(902, x=1.0)], 1234.5,
                                      np.array([0, 1, 0, 0.8])))
    kinds = [type(m).__name__ for m, _ in first.messages]
    assert kinds == ["NewUser", "JointCoordinates", "HandStateMsg", "HandStateMsg", "NewUser",
                     "JointCoordinates", "HandStateMsg", "HandStateMsg", "FloorPlane"]
    assert all(tt == pytest.approx(1234.5) for _, tt in first.messages)
    msgs = [m for m, _ in first.messages]
    assert (msgs[0].user, msgs[4].user) == (0, 1)
    np.testing.assert_allclose(msgs[0].position, body(901).joints[J["SpineMid"]], atol=1e-6)
    assert msgs[2].state == HandState.OPEN and msgs[3].state == HandState.LASSO
    assert isinstance(msgs[8], FloorPlane)
    second = decode(enc.frame([body(902, x=1.0)], 1234.6))
    assert isinstance(second[0], LostUser) and second[0].user == 0
    assert isinstance(second[1], JointCoordinates) and second[1].user == 1
    third = decode(enc.frame([body(903), body(902, x=1.0)], 1234.7))
    assert isinstance(third[0], NewUser) and third[0].user == 0  # the freed id comes back
    assert enc.frame([], 1234.8) is not None  # both users lost
    assert enc.frame([], 1234.9) is None      # nothing to say


def test_encoder_sends_every_joint_with_its_confidence_and_nan_frames():
    enc = ClientEncoder("kin")
    b = body(1)
    b.conf[J["HandTipLeft"]] = 0.0
    b.conf[J["FootLeft"]] = 0.5
    msg = decode(enc.frame([b], None))[1]
    assert isinstance(msg, JointCoordinates)
    np.testing.assert_array_equal(msg.conf, b.conf)
    lean = ClientEncoder("kin", send_all_joints=False)
    data = lean.frame([b], None)
    assert data.count(b"HandTipLeft") == 0 and data.count(b"FootLeft") == 1
    broken = decode_datagram(enc.frame([b], None, nan_users=frozenset({1})))
    assert ("kin", "non_finite") in broken.drops


def test_seven_bodies_six_ids():
    enc = ClientEncoder("kin")
    msgs = decode(enc.frame([body(k, x=0.3 * k) for k in range(7)], None))
    assert sorted(m.user for m in msgs if isinstance(m, NewUser)) == [0, 1, 2, 3, 4, 5]
    assert enc.untracked == 1


@pytest.mark.integration
def test_a_client_reaches_a_real_server():
    with Server(Rig(port=0), host="127.0.0.1") as server:
        enc, sender = ClientEncoder("laptop", "webcam-mediapipe"), UdpSender(server.address)
        sender.send(enc.register())
        for k in range(10):
            sender.send(enc.frame([body("me")], time.time()))
        sender.close()
        stats = _stats_after(server, frames=10)
    assert stats["clients"]["laptop"]["type"] == "webcam-mediapipe"
    assert stats["counts"]["frames"] == 10 and stats["drops_total"] == 0
    assert len(stats["persons"]) == 1


# ---------------------------------------------------------------- webcam / MediaPipe

def _landmarks(kinect: np.ndarray, camera: Camera, visibility: float = 0.95):
    """What MediaPipe reports for a known skeleton (Kinect camera space, metres).

    world: hip-centred, image axes (x right, y down, z away); image: the
    pinhole projection, normalised; the ears either side of the head, the
    pinky beside the hand.
    """
    lm = np.tile(kinect[J["Head"]], (33, 1))  # eyes and mouth: near the head
    names = {"left_shoulder": "ShoulderLeft", "left_elbow": "ElbowLeft", "left_wrist": "WristLeft",
             "left_index": "HandTipLeft", "left_thumb": "ThumbLeft", "left_hip": "HipLeft",
             "left_knee": "KneeLeft", "left_ankle": "AnkleLeft", "left_foot_index": "FootLeft"}
    for mp_name, k_name in list(names.items()):
        names[mp_name.replace("left", "right")] = k_name.replace("Left", "Right")
    for mp_name, k_name in names.items():
        lm[L[mp_name]] = kinect[J[k_name]]
    for side, sign in (("left", -1.0), ("right", 1.0)):  # facing the camera: left is at -x
        hand = kinect[J["Hand" + side.title()]]
        tip = kinect[J["HandTip" + side.title()]]
        lm[L[f"{side}_pinky"]] = 3 * hand - kinect[J["Wrist" + side.title()]] - tip
        lm[L[f"{side}_ear"]] = kinect[J["Head"]] + [sign * 0.08, 0, 0]
        lm[L[f"{side}_heel"]] = kinect[J["Ankle" + side.title()]]
    lm[0] = kinect[J["Head"]] - [0, 0, 0.1]
    mp_space = lm * [-1, -1, 1]  # Kinect axes -> image axes
    hips = mp_space[[L["left_hip"], L["right_hip"]]].mean(axis=0)
    world = mp_space - hips
    f = camera.focal
    image = np.stack([(mp_space[:, 0] * f / mp_space[:, 2] + camera.width / 2) / camera.width,
                      (mp_space[:, 1] * f / mp_space[:, 2] + camera.height / 2) / camera.height,
                      np.zeros(33)], axis=1)
    return world, image, np.full(33, visibility)


def test_mediapipe_landmarks_map_onto_the_kinect_joints_in_camera_space():
    camera = Camera(1280, 720, 60.0)
    truth = body(1, x=0.4, z=3.2).joints
    got = landmarks_to_body(*_landmarks(truth, camera), camera=camera, key="me")
    direct = ["ShoulderLeft", "ElbowRight", "WristLeft", "HipRight", "KneeLeft", "AnkleRight",
              "FootLeft", "HandTipRight", "ThumbLeft", "HandLeft"]
    for name in direct:
        np.testing.assert_allclose(got.joints[J[name]], truth[J[name]], atol=0.03, err_msg=name)
    # derived joints land where the Kinect has them, within a few centimetres
    for name in ("SpineBase", "SpineMid", "SpineShoulder", "Neck", "Head"):
        assert np.linalg.norm(got.joints[J[name]] - truth[J[name]]) < 0.06, name
    assert (got.conf == 1.0).all() and got.hands is None and got.key == "me"


def test_mediapipe_distance_comes_from_segment_lengths():
    camera = Camera(640, 480, 70.0)
    for depth in (1.8, 3.0, 4.5):
        truth = body(1, z=depth).joints
        world, image, vis = _landmarks(truth, camera)
        hips = truth[[J["HipLeft"], J["HipRight"]]].mean(axis=0)
        assert hip_distance(world, image, vis, camera) == pytest.approx(hips[2], rel=0.02)
    vis[:] = 0.1
    assert landmarks_to_body(world, image, vis, camera) is None  # nothing visible enough


def test_visibility_becomes_confidence_and_derived_joints_take_the_weakest():
    assert list(confidence([0.9, 0.75, 0.5, 0.4, 0.1])) == [1.0, 1.0, 0.5, 0.5, 0.0]
    camera = Camera()
    world, image, vis = _landmarks(body(1).joints, camera)
    vis[L["left_wrist"]] = 0.5
    vis[L["right_ear"]] = 0.2
    vis[L["left_index"]] = 0.1
    got = landmarks_to_body(world, image, vis, camera)
    assert got.conf[J["WristLeft"]] == 0.5
    assert got.conf[J["HandLeft"]] == 0.0  # wrist, index, pinky: the weakest is the index
    assert got.conf[J["Head"]] == 0.0 and got.conf[J["Neck"]] == 0.0
    assert got.conf[J["SpineMid"]] == 1.0


# ---------------------------------------------------------------- Kinect v2

def test_kinect2_arrays_map_one_to_one():
    truth = body(1).joints
    states = np.full(25, 2)
    states[J["HandTipLeft"]] = 0
    states[J["KneeRight"]] = 1
    b = kinect2_body(72057594037927936, truth, states, 3, 4)
    np.testing.assert_array_equal(b.joints, truth)
    assert b.conf[J["HandTipLeft"]] == 0 and b.conf[J["KneeRight"]] == 0.5
    assert b.conf[J["Head"]] == 1.0
    assert b.hands == (HandState.CLOSED, HandState.LASSO)
    assert kinect2_body(1, truth, states, 9, 1).hands == (HandState.UNKNOWN,
                                                          HandState.NOT_TRACKED)
    assert floor_plane((0.0, 0.0, 0.0, 0.0)) is None
    np.testing.assert_array_equal(floor_plane((0.0, 0.99, 0.14, 0.8)), [0.0, 0.99, 0.14, 0.8])
    clock = RelativeClock()
    t0 = clock(10_000_000)
    assert clock(10_000_000 + 333_333) - t0 == pytest.approx(0.0333333)


# ---------------------------------------------------------------- Azure Kinect / Orbbec

def test_azure_32_joints_map_onto_the_25_in_kinect_axes():
    truth = body(1, x=-0.3).joints
    mm = np.zeros((32, 3))
    mm[AZURE_INDEX] = truth * [-1000, -1000, 1000]  # depth camera: mm, x right, y down
    levels = np.full(32, 2)
    levels[K4ABT_JOINTS.index("HANDTIP_LEFT")] = 1
    levels[K4ABT_JOINTS.index("FOOT_RIGHT")] = 0
    levels[K4ABT_JOINTS.index("NOSE")] = 0  # not one of the 25: ignored
    b = azure_body(7, mm, levels)
    np.testing.assert_allclose(b.joints, truth, atol=1e-12)
    assert b.conf[J["HandTipLeft"]] == 0.5 and b.conf[J["FootRight"]] == 0.0
    assert (np.delete(b.conf, [J["HandTipLeft"], J["FootRight"]]) == 1.0).all()
    assert K4ABT_JOINTS[AZURE_INDEX[J["SpineShoulder"]]] == "SPINE_CHEST"
    assert b.hands is None


class _FakeAzureSDK:
    """What pykinect_azure offers the client, with one body standing 3 m away.

    The real SDK needs the device; this stands in for the module so that the
    client's own glue (start, read, map, send, stop) runs against a real server.
    """
    K4A_COLOR_RESOLUTION_OFF, K4A_DEPTH_MODE_NFOV_UNBINNED = 0, 2

    def __init__(self, frames: int, stop) -> None:
        from types import SimpleNamespace as NS
        self.default_configuration = NS(color_resolution=None, depth_mode=None)
        self.started: list[str] = []
        mm = np.zeros((32, 3))
        mm[AZURE_INDEX] = body(1).joints * [-1000, -1000, 1000]
        joints = [NS(position=NS(x=x, y=y, z=z), confidence_level=2) for x, y, z in mm]
        sdk_body = NS(id=4, joints=joints)
        left = [frames]

        def update():
            left[0] -= 1
            if left[0] <= 0 and stop is not None:
                stop.set()
            return NS(get_num_bodies=lambda: 1, get_body=lambda k: sdk_body)
        self.tracker = NS(update=update,
                          destroy=lambda: self.started.append("body tracker stopped"))
        self.device = NS(update=lambda: None,
                         close=lambda: self.started.append("device closed"))

    def initialize_libraries(self, track_body):
        self.started.append(f"libraries (body tracking {track_body})")

    def start_device(self, config):
        self.started.append(f"device (colour {config.color_resolution}, depth {config.depth_mode})")
        return self.device

    def start_body_tracker(self):
        self.started.append("body tracker")
        return self.tracker


def test_the_azure_client_reads_the_sdk_and_reaches_a_real_server(monkeypatch):
    import threading
    from stage.sensors.clients import azure
    stop = threading.Event()
    sdk = _FakeAzureSDK(12, stop)
    monkeypatch.setitem(sys.modules, "pykinect_azure", sdk)
    with Server(Rig(port=0), host="127.0.0.1") as server:
        azure.run(server.address, "femto-a", stop)
        stats = _stats_after(server, frames=12)
    opened = ["libraries (body tracking True)", "device (colour 0, depth 2)", "body tracker"]
    closed = ["body tracker stopped", "device closed"]   # so that it can be opened again
    assert sdk.started == opened + closed
    assert stats["clients"]["femto-a"]["type"] == "azure-kinect"
    assert stats["counts"]["frames"] == 12 and stats["drops_total"] == 0
    assert len(stats["persons"]) == 1
    seen, waited = azure._first_body(1.0)
    np.testing.assert_allclose(seen.joints, body(1).joints, atol=1e-9)
    assert seen.key == 4 and waited < 1.0
    assert sdk.started == (opened + closed) * 2


@pytest.mark.parametrize("client, module, extra", [("webcam", "cv2", "webcam"),
                                                   ("kinect2", "pykinect2", "kinect2"),
                                                   ("azure", "pykinect_azure", "azure")])
def test_a_client_without_its_extra_says_how_to_install_it(monkeypatch, client, module, extra):
    """The hint names this project's distribution, not the unrelated 'stage' on PyPI."""
    monkeypatch.setitem(sys.modules, module, None)      # importing it now fails
    run = importlib.import_module(f"stage.sensors.clients.{client}").run
    hint = f"pip install 'stage-kuatro[{extra}]' (in a checkout: pip install -e '.[{extra}]')"
    with pytest.raises(StageError, match=re.escape(hint)):
        run(("127.0.0.1", 9), "test")


# ---------------------------------------------------------------- --check

class _Spec:
    origin = "/somewhere/module.py"


def test_kinect2_check_reports_what_is_missing_and_one_skeleton_when_all_is_there():
    from stage.sensors.clients import kinect2
    text, ok = kinect2.check(platform="linux", env={}, exists=lambda p: False,
                             find_spec=lambda name: None)
    assert not ok
    assert "[missing] Windows (64-bit): this is linux" in text
    assert "[missing] Kinect for Windows SDK 2.0: install KinectSDK-v2.0_1409-Setup.exe" in text
    assert "[missing] Python module pykinect2: missing: pip install 'stage-kuatro[kinect2]'" \
        in text
    truth = body(5).joints
    seen = kinect2_body(5, truth, np.full(25, 2), 2, 3)
    text, ok = kinect2.check(platform="win32", env={"SystemRoot": r"C:\Windows"},
                             exists=lambda p: p == r"C:\Windows\System32\Kinect20.dll",
                             find_spec=lambda name: _Spec(),
                             first_body=lambda wait: (seen, 0.4))
    assert ok, text
    assert "[ok] Kinect for Windows SDK 2.0: C:\\Windows\\System32\\Kinect20.dll" in text
    assert "[ok] a tracked body: after 0.4 s" in text
    head = truth[J["Head"]]
    assert f"  Head           {head[0]:+.3f} {head[1]:+.3f} {head[2]:+.3f}  conf 1.0" in text
    assert len([line for line in text.splitlines() if "conf" in line]) == 25
    text, ok = kinect2.check(platform="win32", env={"KINECTSDK20_DIR": r"C:\sdk"},
                             find_spec=lambda name: _Spec(),
                             first_body=lambda wait: (None, wait))
    assert not ok and "[missing] a tracked body: none in 5.0 s" in text


def test_azure_check_looks_for_both_sdks_and_the_binding():
    from stage.sensors.clients import azure
    text, ok = azure.check(platform="linux", find_spec=lambda name: None,
                           find_library=lambda name: None, exists=lambda p: False)
    assert not ok
    assert "[missing] Azure Kinect Sensor SDK (or Orbbec's K4A wrapper): not found (k4a)" in text
    assert "[missing] Azure Kinect Body Tracking SDK: not found (k4abt)" in text
    assert "pip install 'stage-kuatro[azure]'" in text
    mm = np.zeros((32, 3))
    mm[AZURE_INDEX] = body(1).joints * [-1000, -1000, 1000]
    seen = azure_body(1, mm, np.full(32, 2))
    text, ok = azure.check(platform="win32", find_spec=lambda name: _Spec(),
                           find_library=lambda name: None,
                           exists=lambda p: p.endswith(("k4a.dll", "k4abt.dll")),
                           first_body=lambda wait: (seen, 1.2))
    assert ok, text
    assert "Azure Kinect SDK v1.4.1" in text and "[ok] a tracked body: after 1.2 s" in text

    def broken(wait):
        raise RuntimeError("K4A_RESULT_FAILED: no device")
    text, ok = azure.check(platform="linux", find_spec=lambda name: _Spec(),
                           find_library=lambda name: f"lib{name}.so", first_body=broken)
    assert not ok and "[missing] device: cannot open it: K4A_RESULT_FAILED: no device" in text


def test_client_check_on_the_command_line(capsys):
    from stage.cli.main import main
    assert main(["client", "kinect2", "--check"]) == (0 if sys.platform == "win32" else 1)
    assert "stage client kinect2 --check" in capsys.readouterr().out
    assert main(["client", "sim", "--check"]) == 2
    assert "has no check" in capsys.readouterr().err
