"""The webcam client: hand states, several people, video pacing, and a real video end to end.

The pure parts (hand-state rules, hands to bodies, pose keys, pacing and
timestamps) run everywhere. The rest needs the ``webcam`` extra (MediaPipe
and OpenCV; CI installs it) and runs the real models on ``tests/data/dancer.mp4``
(a man dancing, 5.1 s; see ``tests/data/README.md`` for its source and licence)
through ``stage client webcam --video`` into a real ``stage serve``.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import free_udp_port, query_stats

from stage.joints import JOINT_INDEX as J
from stage.joints import HandState
from stage.sensors.clients.hands import Hand, assign_hands, classify, straightness
from stage.sensors.clients.video import FrameReader
from stage.sensors.clients.webcam import L, Camera, PoseTracker, hand_states

DATA = Path(__file__).parent / "data"
VIDEO = DATA / "dancer.mp4"
CLI = [sys.executable, "-m", "stage"]


# ---------------------------------------------------------------- hand states

def _hand(fingers: dict[str, bool | float], scale: float = 1.0) -> np.ndarray:
    """21 hand landmarks (metres): a palm facing the camera, each finger straight (True),
    curled (False: 80 degrees at each of its three joints) or bent by that many degrees."""
    lm = np.zeros((21, 3))
    lm[1:5] = [[-0.03, 0.02, 0], [-0.05, 0.04, 0], [-0.06, 0.06, 0], [-0.07, 0.08, 0]]  # thumb
    bases = {"index": (5, -0.02), "middle": (9, 0.0), "ring": (13, 0.02), "pinky": (17, 0.04)}
    for name, (first, x) in bases.items():
        point, direction = np.array([x, 0.09, 0.0]), np.array([0.0, 1.0, 0.0])
        lm[first] = point
        for k, length in enumerate((0.04, 0.025, 0.02)):
            bend = fingers[name]
            bend = 0.0 if bend is True else 80.0 if bend is False else float(bend)
            if bend:   # bend at each joint, towards the palm (-z)
                a = np.radians(bend)
                direction = np.array([0.0, direction[1] * np.cos(a) + direction[2] * np.sin(a),
                                      -direction[1] * np.sin(a) + direction[2] * np.cos(a)])
            point = point + length * direction
            lm[first + 1 + k] = point
    return lm * scale


OPEN = dict(index=True, middle=True, ring=True, pinky=True)
FIST = dict(index=False, middle=False, ring=False, pinky=False)
LASSO = dict(index=True, middle=True, ring=False, pinky=False)


def test_fingers_straight_and_curled_are_told_apart():
    s = straightness(_hand(LASSO))
    assert s["index"] > 0.99 and s["middle"] > 0.99
    assert s["ring"] < 0.55 and s["pinky"] < 0.55


@pytest.mark.parametrize("fingers, state", [(OPEN, HandState.OPEN), (FIST, HandState.CLOSED),
                                            (LASSO, HandState.LASSO)])
def test_hand_states_as_the_kinect_defines_them(fingers, state):
    for scale in (0.8, 1.0, 1.3):   # a child's hand, a large hand: straightness has no units
        got, conf = classify(_hand(fingers, scale))
        assert got == state and conf == pytest.approx(1.0)
    # MediaPipe's presence score scales the confidence; below the threshold: unknown
    assert classify(_hand(fingers), presence=0.6) == (state, pytest.approx(0.6))
    assert classify(_hand(fingers), presence=0.3) == (HandState.UNKNOWN, pytest.approx(0.3))


def test_a_hand_matching_no_kinect_state_is_unknown():
    pointing = dict(index=True, middle=False, ring=False, pinky=False)   # one finger
    assert classify(_hand(pointing))[0] == HandState.UNKNOWN
    # a middle finger half bent: the hand is less certainly open, or not open at all
    for bend, expected in ((35.0, HandState.OPEN), (45.0, HandState.UNKNOWN)):
        state, conf = classify(_hand(dict(OPEN, middle=bend)))
        assert state == expected and 0.0 < conf < 1.0, (bend, state, conf)


def test_hands_go_to_the_nearest_free_wrist():
    wrists = np.array([[100.0, 100.0], [300.0, 100.0], [np.nan, np.nan]])
    hands = [Hand(np.array([305.0, 98.0]), HandState.OPEN, 0.9),
             Hand(np.array([104.0, 103.0]), HandState.CLOSED, 0.8),
             Hand(np.array([900.0, 900.0]), HandState.LASSO, 1.0)]   # nobody's
    got = assign_hands(wrists, hands, 30.0)
    assert [h.state if h else None for h in got] == [HandState.CLOSED, HandState.OPEN, None]
    # two hands near one wrist: the nearer wins, the other stays unassigned
    got = assign_hands(wrists[:1], hands[:2] + [Hand(np.array([101.0, 100.0]),
                                                     HandState.LASSO, 1.0)], 30.0)
    assert got[0].state == HandState.LASSO


def test_a_pose_gets_hand_states_from_the_hands_near_its_wrists():
    camera = Camera(600, 600)
    image = np.full((33, 3), 0.5)
    image[L["left_wrist"], :2], image[L["left_elbow"], :2] = [0.7, 0.5], [0.7, 0.35]
    image[L["right_wrist"], :2], image[L["right_elbow"], :2] = [0.3, 0.5], [0.3, 0.35]
    vis = np.ones(33)
    hands = [Hand(np.array([0.71, 0.52]), HandState.LASSO, 0.9)]
    assert hand_states(image, vis, hands, camera) == (HandState.LASSO, HandState.UNKNOWN)
    vis[L["left_wrist"]] = 0.1   # the pose does not see that wrist
    assert hand_states(image, vis, hands, camera) == (HandState.NOT_TRACKED, HandState.UNKNOWN)


def test_poses_keep_their_keys_from_frame_to_frame():
    tracker = PoseTracker(max_jump=0.2)
    a, b = np.array([0.3, 0.5]), np.array([0.7, 0.5])
    assert tracker.keys([a, b]) == [0, 1]
    assert tracker.keys([b + 0.02, a - 0.01]) == [1, 0]       # listed the other way round
    assert tracker.keys([a]) == [0]                             # one left the picture
    assert tracker.keys([np.array([0.95, 0.1]), a]) == [2, 0]   # a newcomer gets a new key


# ---------------------------------------------------------------- pacing and timestamps

class FakeCapture:
    """An OpenCV capture of ``n`` frames at ``fps`` (times in ms, as CAP_PROP_POS_MSEC)."""

    def __init__(self, n: int, fps: float = 20.0, failures: int = 0) -> None:
        self.n, self.fps, self.failures, self.k = n, fps, failures, -1

    def read(self):
        if self.failures:
            self.failures -= 1
            return False, None
        if self.k + 1 >= self.n:
            return False, None
        self.k += 1
        return True, np.full((2, 2, 3), self.k, np.uint8)

    def get(self, prop):
        return {FrameReader.FPS: self.fps, FrameReader.POS_MSEC: self.k * 1000.0 / self.fps}[prop]

    def release(self):
        pass


class FakeTime:
    def __init__(self) -> None:
        self.t = 100.0

    def monotonic(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s

    def wall(self) -> float:
        return 1_700_000_000.0 + self.t


def _reader(cap, clock, video=True, realtime=True):
    return FrameReader(cap, "test", video, realtime, camera_timeout_s=1.0,
                       monotonic=clock.monotonic, sleep=clock.sleep, wall=clock.wall)


def test_a_video_is_paced_like_the_camera_that_filmed_it():
    clock = FakeTime()
    reader = _reader(FakeCapture(10), clock)
    frames = []
    while (frame := reader.next()) is not None:
        frames.append(frame)
        clock.t += 0.01                         # processing is faster than the film
    assert [f.t for f in frames] == pytest.approx([k * 0.05 for k in range(10)])
    # capture times: the start plus each frame's own time in the video
    assert [f.stamp - frames[0].stamp for f in frames] == pytest.approx([f.t for f in frames])
    assert reader.skipped == 0 and reader.ended and reader.read == 10


def test_late_frames_are_skipped_in_real_time_and_kept_at_max_speed():
    # the model takes 0.165 s, over three frame times: in real time a frame is kept when it
    # is at most one frame time late (frame 3 is 0.015 s late, 4 and 5 more), and so on
    for realtime, kept in ((True, [0, 3, 6, 9, 13, 16, 19]), (False, list(range(20)))):
        clock = FakeTime()
        reader = _reader(FakeCapture(20), clock, realtime=realtime)
        frames = []
        while (frame := reader.next()) is not None:
            frames.append(frame)
            clock.t += 0.165
        # a kept frame keeps its own video time, whatever was skipped before it
        assert [f.t for f in frames] == pytest.approx([k * 0.05 for k in kept])
        assert reader.skipped == 20 - len(kept)
        assert frames[-1].stamp - frames[0].stamp == pytest.approx(frames[-1].t)


def test_a_video_played_slower_is_stamped_as_filmed_at_that_pace():
    clock = FakeTime()
    reader = FrameReader(FakeCapture(5), "test", True, True, speed=0.5,
                         monotonic=clock.monotonic, sleep=clock.sleep, wall=clock.wall)
    frames = []
    while (frame := reader.next()) is not None:
        frames.append(frame)
        clock.t += 0.06           # slower than the film (50 ms), faster than half its pace
    assert reader.skipped == 0
    assert [f.t for f in frames] == pytest.approx([0, 0.05, 0.1, 0.15, 0.2])
    assert [f.stamp - frames[0].stamp for f in frames] == pytest.approx([0, 0.1, 0.2, 0.3, 0.4])


def test_a_camera_without_frames_is_retried_then_reported():
    from stage.errors import StageError
    clock = FakeTime()
    reader = _reader(FakeCapture(3, failures=5), clock, video=False)
    assert reader.next() is not None            # 5 failures = 0.25 s: retried, then a frame
    reader = _reader(FakeCapture(3, failures=100), clock, video=False)
    with pytest.raises(StageError, match="camera test gave no frame for 1 s"):
        reader.next()
    stop = threading.Event()
    stop.set()
    assert _reader(FakeCapture(3), clock).next(stop) is None


# ---------------------------------------------------------------- the real models

def _mediapipe():
    mp = pytest.importorskip("mediapipe", reason="the webcam extra is not installed "
                             "(pip install -e '.[webcam]'; CI installs it)")
    cv2 = pytest.importorskip("cv2")
    return mp, cv2


def _frames(cv2, step: int = 1):
    cap = cv2.VideoCapture(str(VIDEO))
    k = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        if k % step == 0:
            yield k, cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        k += 1
    cap.release()


def test_the_bundles_made_from_the_shipped_models_agree_with_mediapipe_solutions_pose():
    """The in-memory bundles' normalisation is right: the same landmarks as the legacy API."""
    mp, cv2 = _mediapipe()
    from stage.sensors.clients.mediapipe_models import Landmarkers
    marks = Landmarkers(people=1, hands=False)
    legacy = mp.solutions.pose.Pose(model_complexity=1, static_image_mode=True)
    errors = []
    for k, rgb in _frames(cv2, step=10):
        ours = marks.detect(rgb, k / 20)
        theirs = legacy.process(rgb)
        assert ours.people and theirs.pose_landmarks, k
        image = np.array([[p.x, p.y] for p in theirs.pose_landmarks.landmark])
        errors.append(np.abs(ours.people[0].image[:, :2] - image).mean())
    marks.close()
    legacy.close()
    # mean landmark disagreement under 2 % of the picture (a wrong input range finds no pose
    # or puts landmarks tens of percent away)
    assert np.mean(errors) < 0.02, errors


def _start_server(tmp_path, port):
    """A real `stage serve` writing its fused frames; returns once it answers /stage/stats."""
    fused = tmp_path / "fused.jsonl"
    server = subprocess.Popen([*CLI, "serve", "--host", "127.0.0.1", "--port", str(port),
                               "--fused", str(fused), "--no-plugins", "--no-self-healing"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 60.0
    while True:   # up when it answers; each try waits for a reply, no fixed sleep
        assert server.poll() is None, f"stage serve exited early: {server.communicate()}"
        try:
            query_stats(("127.0.0.1", port), timeout=0.2)
            return server, fused
        except AssertionError:
            assert time.monotonic() < deadline, "stage serve never answered /stage/stats"


def _stop(server) -> str:
    server.send_signal(signal.SIGINT)
    out, _ = server.communicate(timeout=30)
    return out


def _bones(joints) -> dict[str, float]:
    j = np.asarray(joints)
    length = lambda a, b: float(np.linalg.norm(j[J[a]] - j[J[b]]))  # noqa: E731
    return {"head to spine base": length("Head", "SpineBase"),
            "thigh": length("HipLeft", "KneeLeft"), "shin": length("KneeRight", "AnkleRight"),
            "upper arm": length("ShoulderLeft", "ElbowLeft"),
            "shoulders": length("ShoulderLeft", "ShoulderRight")}


#: adult proportions (metres) wide enough for any adult and for MediaPipe's estimates
PLAUSIBLE = {"head to spine base": (0.45, 0.85), "thigh": (0.3, 0.55), "shin": (0.28, 0.55),
             "upper arm": (0.18, 0.4), "shoulders": (0.22, 0.5)}


@pytest.mark.integration
def test_a_real_video_through_the_client_into_a_real_server(tmp_path):
    """The film at a quarter of its pace (250 ms a frame: time for MediaPipe on a slow,
    busy machine), stamped as a camera filming at that pace: every frame it processes
    reaches the server and becomes a fused body of adult proportions."""
    _mediapipe()
    port = free_udp_port()
    server, fused = _start_server(tmp_path, port)
    try:
        client = subprocess.run([*CLI, "client", "webcam", "--video", str(VIDEO), "--speed",
                                 "0.25", "--to", f"127.0.0.1:{port}", "--id", "dancer-cam"],
                                capture_output=True, text=True, timeout=600)
        query_stats(("127.0.0.1", port))   # a barrier: every datagram before it is handled
    finally:
        server_out = _stop(server)
    out = client.stdout + client.stderr
    assert client.returncode == 0, out
    assert "Traceback" not in out and "Logging error" not in out, out
    found = re.search(r"102 frames read, (\d+) processed, (\d+) skipped \(late\); "
                      r"(\d+) with a body \((\d+) bodies\)", out)
    assert found, out
    processed, skipped, with_body, bodies = map(int, found.groups())
    assert processed + skipped == 102 and processed >= 51, out   # at most half skipped
    # the dancer is in every frame of the film: every processed frame has one body
    assert with_body == bodies == processed and "the video ended" in out, out
    assert f"{processed} sensor frames in, {processed} fused" in server_out, server_out
    rows = [json.loads(line) for line in fused.read_text().splitlines()]
    frames = [r for r in rows if r["updated"]]
    assert len(frames) == processed and all(len(r["bodies"]) == 1 for r in frames)
    for r in frames:
        body = next(iter(r["bodies"].values()))
        for bone, length in _bones(body["joints"]).items():
            low, high = PLAUSIBLE[bone]
            assert low <= length <= high, (r["t"], bone, length)
    known = [h for r in frames for b in r["bodies"].values() for h in b["hands"]
             if h in (HandState.OPEN, HandState.CLOSED, HandState.LASSO)]
    assert len(known) >= 3, "no hand states reached the fused bodies"


def test_several_people_in_one_picture(tmp_path):
    """Two dancers side by side (the film and its mirror image): two bodies in every frame."""
    _, cv2 = _mediapipe()
    from stage.app.server import Server
    from stage.rig import Rig
    from stage.sensors.clients.webcam import WebcamStats, run
    two = tmp_path / "two.avi"
    writer = cv2.VideoWriter(str(two), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (1200, 600))
    for _, rgb in _frames(cv2, step=2):
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        writer.write(np.ascontiguousarray(np.hstack([bgr, bgr[:, ::-1]])))
    writer.release()
    with Server(Rig(port=0), host="127.0.0.1") as server:
        stats = run(server.address, "duo", video=str(two), realtime=False, people=2, hands=False,
                    stats=WebcamStats())
        seen = query_stats(server.address)
    assert stats.processed == 51 and stats.bodies == 2 * 51, stats.summary()
    # the server counts one frame per body per sensor frame
    assert seen["counts"]["frames"] == 2 * 51 and len(seen["persons"]) == 2, seen
