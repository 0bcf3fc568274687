"""Webcam client: MediaPipe pose landmarks mapped onto the 25 Kinect joints.

Anyone with a laptop can be a sensor: ``pip install 'stage-kuatro[webcam]'``
(in a checkout: ``pip install -e '.[webcam]'``) then ``stage client webcam
--to HOST:7770``. MediaPipe gives 33 landmarks twice:
normalised image coordinates, and "world" coordinates in metres centred on
the hips (x to the image's right, y down, z away from the camera). A single
camera has no depth, so the hips' distance is estimated with the pinhole
model from how long body segments look in the image against their length
in metres; the skeleton is then placed in Kinect camera space (x to the
sensor's left, y up, z away from it). Confidence comes from each landmark's
visibility: at least ``tracked`` -> 1, at least ``inferred`` -> 0.5, else 0.
Joints MediaPipe lacks are derived (SpineBase, SpineMid, SpineShoulder,
Neck from the hips and shoulders; Head from the ears; the palm from the
wrist, index and pinky). Pose landmarks say nothing about fingers, so no
hand state is sent.

Everything but ``run`` is pure and tested on recorded landmark arrays;
``run`` needs ``mediapipe`` and ``opencv-python`` and a camera.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from ...joints import JOINT_INDEX as J
from ...joints import N_JOINTS
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
                      inferred: float = 0.4) -> BodyFrame | None:
    """One person's MediaPipe landmarks -> a Kinect-like body in camera space.

    world: (33, 3) metres, hip-centred, x right / y down / z away (MediaPipe
    ``pose_world_landmarks``); image: (33, 2 or 3) normalised image
    coordinates (``pose_landmarks``); visibility: (33,). Returns None when
    the distance cannot be estimated (too little of the body is visible).
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
    return BodyFrame(key, joints, conf, None)


def run(target: tuple[str, int], client_id: str, camera_index: int = 0, fov_h: float = 60.0,
        model: str | None = None, show: bool = False, stop=None) -> None:  # pragma: no cover
    """Capture from a webcam and send the Client-to-Server API until ``stop`` is set.

    Needs ``mediapipe`` and ``opencv-python`` (``pip install 'stage-kuatro[webcam]'``).
    Uses MediaPipe's legacy ``solutions.pose`` (model inside the package)
    when present, else the Tasks API with the ``pose_landmarker`` model file
    given as ``model`` (download it once; nothing is downloaded at run time).
    """
    from ... import install_hint
    from ...errors import StageError
    from .osc import ClientEncoder, UdpSender
    try:
        import cv2
        import mediapipe as mp
    except ImportError as exc:
        raise StageError(f"the webcam client needs mediapipe and opencv-python ({exc.name} is "
                         f"missing): {install_hint('webcam')}") from None
    cap = cv2.VideoCapture(camera_index)
    if not cap.isOpened():
        raise StageError(f"cannot open camera {camera_index}")
    width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    camera = Camera(width, height, fov_h)
    detect = _detector(mp, model)
    encoder, sender = ClientEncoder(client_id, "webcam-mediapipe"), UdpSender(target)
    sender.send(encoder.register())
    try:
        while stop is None or not stop.is_set():
            ok, frame = cap.read()
            if not ok:
                log.warning("camera %d gave no frame", camera_index)
                time.sleep(0.1)
                continue
            stamp = time.time()
            found = detect(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB), stamp)
            bodies = []
            if found is not None:
                body = landmarks_to_body(*found, camera=camera)
                if body is not None:
                    bodies.append(body)
            data = encoder.frame(bodies, stamp)
            if data is not None:
                sender.send(data)
            if show:
                cv2.imshow("stage webcam (q quits)", frame)
                if cv2.waitKey(1) & 0xFF == ord("q"):
                    break
    finally:
        cap.release()
        sender.close()


def _detector(mp, model: str | None):  # pragma: no cover - needs mediapipe
    """A function rgb image -> (world (33,3), image (33,3), visibility (33,)) or None."""
    solutions = getattr(mp, "solutions", None)
    if model is None and solutions is not None and hasattr(solutions, "pose"):
        pose = solutions.pose.Pose(model_complexity=1, smooth_landmarks=True)

        def legacy(rgb, stamp):
            result = pose.process(rgb)
            if result.pose_world_landmarks is None or result.pose_landmarks is None:
                return None
            w = result.pose_world_landmarks.landmark
            i = result.pose_landmarks.landmark
            return (np.array([[p.x, p.y, p.z] for p in w]), np.array([[p.x, p.y, p.z] for p in i]),
                    np.array([p.visibility for p in i]))
        return legacy
    from ...errors import StageError
    if model is None:
        raise StageError("this mediapipe has no solutions.pose: give --model pose_landmarker.task "
                         "(MediaPipe's pose landmarker model file)")
    from mediapipe.tasks.python import BaseOptions, vision
    options = vision.PoseLandmarkerOptions(base_options=BaseOptions(model_asset_path=model),
                                           running_mode=vision.RunningMode.VIDEO)
    landmarker = vision.PoseLandmarker.create_from_options(options)

    def tasks(rgb, stamp):
        image = mp.Image(image_format=mp.ImageFormat.SRGB, data=rgb)
        result = landmarker.detect_for_video(image, int(stamp * 1000))
        if not result.pose_world_landmarks:
            return None
        w, i = result.pose_world_landmarks[0], result.pose_landmarks[0]
        return (np.array([[p.x, p.y, p.z] for p in w]), np.array([[p.x, p.y, p.z] for p in i]),
                np.array([p.visibility for p in i]))
    return tasks


class WebcamSource(ThreadedSource):
    """The ``webcam`` source: a webcam or camera through MediaPipe pose estimation; ``stage client webcam``."""

    name = "webcam"
    description = "a webcam or camera through MediaPipe pose estimation (extra: webcam)"

    def __init__(self, client_id: str = "webcam", camera: int = 0, fov: float = 60.0,
                 model: str | None = None, show: bool = False) -> None:
        super().__init__()
        self.client_id, self.camera, self.fov = client_id, camera, fov
        self.model, self.show = model, show

    def _run(self, target: tuple[str, int], stop) -> None:  # pragma: no cover - needs hardware
        run(target, self.client_id, self.camera, self.fov, self.model, self.show, stop)
