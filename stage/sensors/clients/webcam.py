"""Webcam client: MediaPipe pose and hand landmarks mapped onto the 25 Kinect joints.

Anyone with a laptop can be a sensor: ``pip install 'stage-kuatro[webcam]'``
(in a checkout: ``pip install -e '.[webcam]'``) then ``stage client webcam
--to HOST:7770``, or ``--video FILE`` to play a recorded video as if a
camera were filming it. The models come inside the pinned MediaPipe wheel
(``mediapipe_models``); nothing is downloaded.

MediaPipe gives 33 landmarks per person twice: normalised image
coordinates, and "world" coordinates in metres centred on the hips (x to
the image's right, y down, z away from the camera). A single camera has no
depth, so the hips' distance is estimated with the pinhole model from how
long body segments look in the image against their length in metres; the
skeleton is then placed in Kinect camera space (x to the sensor's left, y
up, z away from it). Confidence comes from each landmark's visibility: at
least ``tracked`` -> 1, at least ``inferred`` -> 0.5, else 0. Joints
MediaPipe lacks are derived (SpineBase, SpineMid, SpineShoulder, Neck from
the hips and shoulders; Head from the ears; the palm from the wrist, index
and pinky). Hand states come from the hand landmarker (``hands``): open,
closed or lasso as the Kinect defines them, ``unknown`` when unsure,
``notTracked`` when the pose does not see the wrist.

Several people: the pose landmarker looks for up to ``people`` poses per
frame; a pose keeps its user id from frame to frame by the nearest hip
centre in the image (``PoseTracker``).

Everything but ``run`` is pure and tested on recorded landmark arrays;
``run`` needs ``mediapipe`` and OpenCV, and a camera or a video file.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ...joints import JOINT_INDEX as J
from ...joints import N_JOINTS, HandState
from .hands import Hand, assign_hands
from .osc import BodyFrame
from ..source import ThreadedSource

log = logging.getLogger("stage.clients.webcam")

# MediaPipe Pose landmark indices (the person's own left/right)
L = {"nose": 0, "left_ear": 7, "right_ear": 8, "left_shoulder": 11, "right_shoulder": 12,
     "left_elbow": 13, "right_elbow": 14, "left_wrist": 15, "right_wrist": 16, "left_pinky": 17,
     "right_pinky": 18, "left_index": 19, "right_index": 20, "left_thumb": 21, "right_thumb": 22,
     "left_hip": 23, "right_hip": 24, "left_knee": 25, "right_knee": 26, "left_ankle": 27,
     "right_ankle": 28, "left_heel": 29, "right_heel": 30, "left_foot_index": 31,
     "right_foot_index": 32}
N_LANDMARKS = 33

#: Kinect joint -> MediaPipe landmarks averaged to make it
_DIRECT: dict[str, tuple[str, ...]] = {}
for _side, _s in (("Left", "left"), ("Right", "right")):
    _DIRECT.update({
        "Shoulder" + _side: (f"{_s}_shoulder",), "Elbow" + _side: (f"{_s}_elbow",),
        "Wrist" + _side: (f"{_s}_wrist",),
        "Hand" + _side: (f"{_s}_wrist", f"{_s}_index", f"{_s}_pinky"),
        "HandTip" + _side: (f"{_s}_index",), "Thumb" + _side: (f"{_s}_thumb",),
        "Hip" + _side: (f"{_s}_hip",), "Knee" + _side: (f"{_s}_knee",),
        "Ankle" + _side: (f"{_s}_ankle",), "Foot" + _side: (f"{_s}_foot_index",),
    })
_DIRECT["Head"] = ("left_ear", "right_ear")
_DIRECT["SpineShoulder"] = ("left_shoulder", "right_shoulder")
# segments whose apparent length gives the distance: (landmark a, landmark b)
_SEGMENTS = (("left_shoulder", "right_shoulder"), ("left_hip", "right_hip"),
             ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"),
             ("left_hip", "left_knee"), ("right_hip", "right_knee"))


@dataclass(frozen=True)
class Camera:
    """A webcam's geometry: image size in pixels and horizontal field of view in degrees."""

    width: int = 1280
    height: int = 720
    fov_h: float = 60.0

    @property
    def focal(self) -> float:
        return (self.width / 2) / math.tan(math.radians(self.fov_h) / 2)


def confidence(visibility: np.ndarray, tracked: float = 0.75, inferred: float = 0.4) -> np.ndarray:
    """Landmark visibility (0-1) -> Kinect confidence 1 / 0.5 / 0."""
    v = np.asarray(visibility, float)
    return np.where(v >= tracked, 1.0, np.where(v >= inferred, 0.5, 0.0))


def hip_distance(world: np.ndarray, image: np.ndarray, visibility: np.ndarray, camera: Camera,
                 min_visibility: float = 0.5) -> float | None:
    """Metres from the camera to the hips: median over body segments of f * length / pixels."""
    px = image[:, :2] * [camera.width, camera.height]
    estimates = []
    for a, b in _SEGMENTS:
        i, j = L[a], L[b]
        if min(visibility[i], visibility[j]) < min_visibility:
            continue
        metres = float(np.linalg.norm(world[i] - world[j]))
        pixels = float(np.linalg.norm(px[i] - px[j]))
        if pixels > 2.0 and metres > 0.05:
            estimates.append(camera.focal * metres / pixels)
    return float(np.median(estimates)) if estimates else None


def landmarks_to_body(world: np.ndarray, image: np.ndarray, visibility: np.ndarray,
                      camera: Camera = Camera(), key: object = 0, tracked: float = 0.75,
                      inferred: float = 0.4,
                      hands: tuple[HandState, HandState] | None = None) -> BodyFrame | None:
    """One person's MediaPipe landmarks -> a Kinect-like body in camera space.

    world: (33, 3) metres, hip-centred, x right / y down / z away (MediaPipe
    ``pose_world_landmarks``); image: (33, 2 or 3) normalised image
    coordinates (``pose_landmarks``); visibility: (33,); hands: the (left,
    right) hand states to send, or None. Returns None when the distance
    cannot be estimated (too little of the body is visible).
    """
    world = np.asarray(world, float)
    image = np.asarray(image, float)
    visibility = np.asarray(visibility, float)
    depth = hip_distance(world, image, visibility, camera)
    if depth is None:
        return None
    hips_px = 0.5 * (image[L["left_hip"], :2] + image[L["right_hip"], :2]) * \
        [camera.width, camera.height]
    f = camera.focal
    hip_cam = np.array([(hips_px[0] - camera.width / 2) * depth / f,
                        (hips_px[1] - camera.height / 2) * depth / f, depth])
    # image axes (x right, y down, z away) -> Kinect camera axes (x left, y up, z away)
    flip = np.array([-1.0, -1.0, 1.0])
    points = (world + hip_cam) * flip
    conf_lm = confidence(visibility, tracked, inferred)
    joints = np.zeros((N_JOINTS, 3))
    conf = np.zeros(N_JOINTS)
    for name, sources in _DIRECT.items():
        idx = [L[s] for s in sources]
        joints[J[name]] = points[idx].mean(axis=0)
        conf[J[name]] = conf_lm[idx].min()
    hips = [L["left_hip"], L["right_hip"]]
    hip_mid = points[hips].mean(axis=0)
    spine_shoulder = joints[J["SpineShoulder"]]
    hip_conf = conf_lm[hips].min()
    # Kinect proportions (the simulator's kinematics.REST_POSE): SpineBase just above the hip
    # joints, SpineMid 53 % of the way up to SpineShoulder, Neck a third of the way on to the head
    joints[J["SpineBase"]] = hip_mid + 0.06 * (spine_shoulder - hip_mid)
    conf[J["SpineBase"]] = min(hip_conf, conf[J["SpineShoulder"]])
    joints[J["SpineMid"]] = joints[J["SpineBase"]] + 0.53 * (spine_shoulder - joints[J["SpineBase"]])
    conf[J["SpineMid"]] = conf[J["SpineBase"]]
    joints[J["Neck"]] = spine_shoulder + 0.35 * (joints[J["Head"]] - spine_shoulder)
    conf[J["Neck"]] = min(conf[J["SpineShoulder"]], conf[J["Head"]])
    return BodyFrame(key, joints, conf, hands)


class PoseTracker:
    """Keeps each person's key from frame to frame: the nearest hip centre in the image.

    MediaPipe's pose landmarker numbers the poses it finds in each frame
    afresh; a Kinect keeps a tracking id while it follows someone. A pose
    takes the key of the nearest pose of the previous frame (normalised
    image units, at most ``max_jump``); the others get new keys.
    """

    def __init__(self, max_jump: float = 0.2) -> None:
        self.max_jump = max_jump
        self._last: dict[int, np.ndarray] = {}
        self._next = 0

    def keys(self, centres: list[np.ndarray]) -> list[int]:
        pairs = sorted((float(np.linalg.norm(c[:2] - prev[:2])), i, key)
                       for i, c in enumerate(centres) for key, prev in self._last.items())
        out: list[int | None] = [None] * len(centres)
        taken: set[int] = set()
        for d, i, key in pairs:
            if d <= self.max_jump and out[i] is None and key not in taken:
                out[i] = key
                taken.add(key)
        for i in range(len(out)):
            if out[i] is None:
                out[i] = self._next
                self._next += 1
        self._last = {key: np.asarray(c, float) for key, c in zip(out, centres)}
        return out  # type: ignore[return-value]


def hand_states(image: np.ndarray, visibility: np.ndarray, hands: list[Hand], camera: Camera,
                inferred: float = 0.4) -> tuple[HandState, HandState]:
    """(left, right) hand states of one pose from the hands found in the same frame.

    A wrist the pose does not see is ``notTracked``; a seen wrist takes the
    state of the detected hand whose own wrist is nearest (within 60 % of
    the forearm's length in the image), else ``unknown``.
    """
    px = np.asarray(image, float)[:, :2] * [camera.width, camera.height]
    wrists = px[[L["left_wrist"], L["right_wrist"]]]
    forearms = np.linalg.norm(wrists - px[[L["left_elbow"], L["right_elbow"]]], axis=1)
    scaled = [Hand(h.wrist_image[:2] * [camera.width, camera.height], h.state, h.confidence)
              for h in hands]
    given = assign_hands(wrists, scaled, np.maximum(0.6 * forearms, 10.0))
    out = []
    for wrist, hand in zip((L["left_wrist"], L["right_wrist"]), given):
        if visibility[wrist] < inferred:
            out.append(HandState.NOT_TRACKED)
        else:
            out.append(hand.state if hand is not None else HandState.UNKNOWN)
    return out[0], out[1]


def _percentiles(values: list[float]) -> str:
    if not values:
        return "-"
    p50, p95 = np.percentile(np.asarray(values) * 1000, [50, 95])
    return f"{p50:.1f}/{p95:.1f}"


@dataclass
class WebcamStats:
    """What a run did, for the summary line and the tests."""

    read: int = 0
    processed: int = 0
    skipped: int = 0
    with_body: int = 0
    bodies: int = 0
    hands: dict = field(default_factory=lambda: {s.wire_name: 0 for s in HandState})
    decode_s: list = field(default_factory=list)
    mediapipe_s: list = field(default_factory=list)
    stage_s: list = field(default_factory=list)
    sent: int = 0
    ended: bool = False

    def summary(self) -> str:
        known = sum(self.hands[s] for s in ("open", "closed", "lasso"))
        return (f"{self.read} frames read, {self.processed} processed, {self.skipped} skipped "
                f"(late); {self.with_body} with a body ({self.bodies} bodies); hand states: "
                f"{known} known (open {self.hands['open']}, closed {self.hands['closed']}, "
                f"lasso {self.hands['lasso']}), {self.hands['unknown']} unknown, "
                f"{self.hands['notTracked']} not tracked; per frame ms p50/p95: decode "
                f"{_percentiles(self.decode_s)}, MediaPipe {_percentiles(self.mediapipe_s)}, "
                f"stage client {_percentiles(self.stage_s)}; {self.sent} datagrams sent"
                + ("; the video ended" if self.ended else ""))


def run(target: tuple[str, int], client_id: str, camera_index: int = 0, fov_h: float = 60.0,
        model: str | None = None, show: bool = False, stop=None, video: str | None = None,
        realtime: bool = True, people: int = 1, hands: bool = True,
        hand_model: str | None = None, stats: WebcamStats | None = None, speed: float = 1.0
        ) -> WebcamStats:  # pragma: no cover - needs mediapipe and a camera or video
    """Capture from a camera (or play ``video``) and send the Client-to-Server API.

    Runs until ``stop`` is set or the video ends. Needs the ``webcam`` extra.
    ``people``: how many poses to look for; ``hands``: send hand states;
    ``speed``: a video's pace, times the pace it was filmed (with ``realtime``).
    ``stats`` (optional) is filled in as it goes and returned.
    """
    from .mediapipe_models import Landmarkers, import_mediapipe
    from .osc import ClientEncoder, UdpSender
    from .video import FrameReader, open_capture
    _, cv2 = import_mediapipe()
    stats = stats if stats is not None else WebcamStats()
    cap, name, is_video = open_capture(cv2, camera_index, video)
    try:
        reader = FrameReader(cap, name, is_video, realtime, speed)
    except Exception:
        cap.release()
        raise
    width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    camera = Camera(width, height, fov_h)
    try:
        marks = Landmarkers(people, hands, model, hand_model)
    except Exception:
        reader.release()
        raise
    encoder, sender = ClientEncoder(client_id, "webcam-mediapipe"), UdpSender(target)
    sender.send(encoder.register())
    tracker = PoseTracker()
    log.info("webcam: %s, %dx%d, %.0f degrees across, up to %d people", name, width, height,
             fov_h, people)
    try:
        while stop is None or not stop.is_set():
            frame = reader.next(stop)
            stats.read, stats.skipped = reader.read, reader.skipped
            if frame is None:
                break
            t1 = time.perf_counter()
            rgb = cv2.cvtColor(frame.image, cv2.COLOR_BGR2RGB)
            found = marks.detect(rgb, frame.t)
            keys = tracker.keys([0.5 * (p.image[L["left_hip"]] + p.image[L["right_hip"]])
                                 for p in found.people])
            bodies = []
            for key, person in zip(keys, found.people):
                states = hand_states(person.image, person.visibility, found.hands, camera) \
                    if hands else None
                body = landmarks_to_body(person.world, person.image, person.visibility,
                                         camera=camera, key=key, hands=states)
                if body is not None:
                    bodies.append(body)
                    for state in states or ():
                        stats.hands[state.wire_name] += 1
            data = encoder.frame(bodies, frame.stamp)
            if data is not None:
                sender.send(data)
            t3 = time.perf_counter()
            stats.processed += 1
            stats.with_body += bool(bodies)
            stats.bodies += len(bodies)
            stats.decode_s.append(reader.decode_s)
            stats.mediapipe_s.append(found.inference_s)
            stats.stage_s.append((t3 - t1) - found.inference_s)
            stats.sent = sender.sent
            if show:
                cv2.imshow("stage webcam (q quits)", frame.image)
                if cv2.waitKey(1) & 0xFF == ord("q"):
                    break
        if reader.ended:
            stats.ended = True
            final = encoder.frame([], time.time())   # the people leave with the video
            if final is not None:
                sender.send(final)
            log.info("webcam: %s ended after %d frames", name, reader.read)
    finally:
        stats.sent = sender.sent
        marks.close()
        reader.release()
        sender.close()
    return stats


class WebcamSource(ThreadedSource):
    """The ``webcam`` source: a webcam or a video file through MediaPipe; ``stage client webcam``."""

    name = "webcam"
    description = "a webcam or a video file through MediaPipe pose estimation (extra: webcam)"

    def __init__(self, client_id: str = "webcam", camera: int = 0, fov: float = 60.0,
                 model: str | None = None, show: bool = False, video: str | None = None,
                 realtime: bool = True, people: int = 1, hands: bool = True,
                 hand_model: str | None = None, speed: float = 1.0) -> None:
        super().__init__()
        self.client_id, self.camera, self.fov = client_id, camera, fov
        self.model, self.show, self.video, self.realtime = model, show, video, realtime
        self.people, self.hands, self.hand_model = people, hands, hand_model
        self.speed = speed
        self.stats = WebcamStats()

    def describe(self) -> str:
        return f"webcam {self.video!r}" if self.video else f"webcam camera {self.camera}"

    def summary(self) -> str:
        """One line: frames, bodies, hand states, time per frame (printed by ``stage client``)."""
        return self.stats.summary()

    def _run(self, target: tuple[str, int], stop) -> None:  # pragma: no cover - needs mediapipe
        run(target, self.client_id, self.camera, self.fov, self.model, self.show, stop,
            self.video, self.realtime, self.people, self.hands, self.hand_model, self.stats,
            self.speed)
