"""MediaPipe pose and hand landmarkers, built from the models inside the mediapipe wheel.

The ``webcam`` extra pins a MediaPipe (0.10.18) whose wheel carries the
BlazePose GHUM "full" pose models and the hand models (for its legacy
``solutions`` API) and has wheels for CPython 3.11 on Linux x86_64 and
aarch64, Windows and macOS. Newer MediaPipe releases ship no model at all
and expect a ``.task`` file downloaded by hand; nothing here downloads
anything.

The legacy ``solutions.pose`` follows one person. MediaPipe's Tasks API
(``PoseLandmarker``, ``HandLandmarker``) follows several, but reads a model
*bundle* (a zip of a detector and a landmark model whose input tensors carry
normalisation metadata). The shipped models lack that metadata, so the
bundles are made here in memory: the same TFLite files with the input
ranges their own legacy graphs use (pose detector -1..1, pose landmarks,
palm detector and hand landmarks 0..1; from MediaPipe's
``modules/*/..._cpu.pbtxt``). The webcam tests check the result against the
legacy ``solutions.pose`` on a real video.

A ``.task`` file given with ``--model`` / ``--hand-model`` (e.g. the
``heavy`` pose model, or any MediaPipe without shipped models) is used as is.
"""

from __future__ import annotations

import io
import os
import time
import zipfile
from dataclasses import dataclass, field

import numpy as np

from ...errors import StageError
from .hands import Hand, classify

#: bundle member -> (file in the mediapipe package, input mean, input std, output tensors)
_BUNDLES = {
    "pose": {
        "pose_detector.tflite": ("modules/pose_detection/pose_detection.tflite", 127.5, 127.5, 2),
        "pose_landmarks_detector.tflite": ("modules/pose_landmark/pose_landmark_full.tflite",
                                           0.0, 255.0, 5),
    },
    "hand": {
        "hand_detector.tflite": ("modules/palm_detection/palm_detection_full.tflite",
                                 0.0, 255.0, 2),
        "hand_landmarks_detector.tflite": ("modules/hand_landmark/hand_landmark_full.tflite",
                                           0.0, 255.0, 4),
    },
}


def import_mediapipe():
    """(mediapipe, cv2), or StageError with the install hint."""
    from ... import install_hint
    try:
        import cv2
        import mediapipe as mp
    except ImportError as exc:
        raise StageError(f"the webcam client needs mediapipe and opencv ({exc.name} is "
                         f"missing): {install_hint('webcam')}") from None
    return mp, cv2


def shipped_model_files(mp) -> dict[str, str | None]:
    """Each shipped TFLite file the bundles need -> its path, or None where missing."""
    root = os.path.dirname(mp.__file__)
    out: dict[str, str | None] = {}
    for members in _BUNDLES.values():
        for rel, *_ in members.values():
            path = os.path.join(root, rel)
            out[rel] = path if os.path.isfile(path) else None
    return out


def shipped_bundle(mp, kind: str) -> bytes:
    """The ``kind`` ("pose" or "hand") model bundle made from the wheel's own TFLite files."""
    from mediapipe.tasks.python.metadata.metadata_writers import metadata_writer
    files = shipped_model_files(mp)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as bundle:
        for member, (rel, mean, std, n_outputs) in _BUNDLES[kind].items():
            path = files[rel]
            if path is None:
                raise StageError(f"this mediapipe ({mp.__version__}) ships no {rel}: install the "
                                 "pinned one (the webcam extra) or give a .task model file")
            with open(path, "rb") as f:
                writer = metadata_writer.MetadataWriter.create(bytearray(f.read()))
            writer.add_general_info(os.path.basename(rel)).add_image_input([mean], [std])
            for _ in range(n_outputs):
                writer.add_feature_output()
            bundle.writestr(member, bytes(writer.populate()[0]))
    return buf.getvalue()


@dataclass
class Person:
    """One pose: world (33, 3) metres hip-centred, image (33, 3) normalised, visibility (33,)."""

    world: np.ndarray
    image: np.ndarray
    visibility: np.ndarray


@dataclass
class Detection:
    """What one frame gave: the poses, the hands and the inference time (seconds)."""

    people: list[Person] = field(default_factory=list)
    hands: list[Hand] = field(default_factory=list)
    inference_s: float = 0.0


class Landmarkers:
    """MediaPipe pose (and hand) landmarkers in VIDEO mode: one RGB frame at a time.

    ``people``: how many poses to look for; ``hands``: also find hands (for
    hand states); ``model`` / ``hand_model``: ``.task`` files to use instead of
    the shipped models.
    """

    def __init__(self, people: int = 1, hands: bool = True, model: str | None = None,
                 hand_model: str | None = None) -> None:
        mp, _ = import_mediapipe()
        from mediapipe.tasks.python import BaseOptions, vision
        self._mp = mp
        self.pose = vision.PoseLandmarker.create_from_options(vision.PoseLandmarkerOptions(
            base_options=_options(BaseOptions, mp, "pose", model),
            running_mode=vision.RunningMode.VIDEO, num_poses=int(people)))
        self.hand = None
        if hands:
            self.hand = vision.HandLandmarker.create_from_options(vision.HandLandmarkerOptions(
                base_options=_options(BaseOptions, mp, "hand", hand_model),
                running_mode=vision.RunningMode.VIDEO, num_hands=2 * int(people)))
        self._last_ms = -1

    def detect(self, rgb: np.ndarray, t_s: float) -> Detection:
        """Landmarks of one frame (H, W, 3 uint8 RGB) captured at ``t_s`` seconds (increasing)."""
        # VIDEO mode needs strictly increasing whole milliseconds
        t_ms = max(int(round(t_s * 1000)), self._last_ms + 1)
        self._last_ms = t_ms
        image = self._mp.Image(image_format=self._mp.ImageFormat.SRGB,
                               data=np.ascontiguousarray(rgb))
        start = time.perf_counter()
        result = self.pose.detect_for_video(image, t_ms)
        hands = self.hand.detect_for_video(image, t_ms) if self.hand is not None else None
        out = Detection(inference_s=time.perf_counter() - start)
        for world, img in zip(result.pose_world_landmarks, result.pose_landmarks):
            out.people.append(Person(np.array([[p.x, p.y, p.z] for p in world]),
                                     np.array([[p.x, p.y, p.z] for p in img]),
                                     np.array([_visibility(p) for p in img])))
        if hands is not None:
            for world, img, handed in zip(hands.hand_world_landmarks, hands.hand_landmarks,
                                          hands.handedness):
                score = max((c.score for c in handed), default=1.0)
                state, conf = classify(np.array([[p.x, p.y, p.z] for p in world]), score)
                out.hands.append(Hand(np.array([img[0].x, img[0].y]), state, conf))
        return out

    def close(self) -> None:
        for landmarker in (self.pose, self.hand):
            if landmarker is not None:
                landmarker.close()


def _visibility(p) -> float:
    v = getattr(p, "visibility", None)
    return 1.0 if v is None else float(v)


def _options(BaseOptions, mp, kind: str, path: str | None):
    if path is None:
        return BaseOptions(model_asset_buffer=shipped_bundle(mp, kind))
    if not os.path.isfile(path):
        raise StageError(f"{path}: no such model file")
    return BaseOptions(model_asset_path=path)


def check(people: int = 2) -> list[str]:
    """What is installed and whether the models load and run; StageError when they do not."""
    mp, cv2 = import_mediapipe()
    lines = [f"mediapipe {mp.__version__} ({os.path.dirname(mp.__file__)})",
             f"opencv {cv2.__version__}"]
    missing = [rel for rel, path in shipped_model_files(mp).items() if path is None]
    lines.append("shipped models: " + ("all present" if not missing else
                                       "missing " + ", ".join(missing)))
    if missing:
        raise StageError("; ".join(lines) + ": install the webcam extra's pinned mediapipe")
    start = time.perf_counter()
    marks = Landmarkers(people=people, hands=True)
    loaded = time.perf_counter() - start
    found = marks.detect(np.zeros((240, 320, 3), np.uint8), 0.0)
    marks.close()
    lines.append(f"pose and hand landmarkers loaded in {loaded:.2f} s (up to {people} people); "
                 f"a blank frame: {len(found.people)} people, {len(found.hands)} hands, "
                 f"{found.inference_s * 1000:.0f} ms")
    return lines
