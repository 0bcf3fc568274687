"""Frames for the webcam client: a live camera, or a video file played like one.

A camera's frames are stamped with the wall clock when they are read. A
video file's frames carry their own times (the container's presentation
times, ``CAP_PROP_POS_MSEC``); the client stamps each with the wall-clock
time the video started plus that time, so the server sees the capture times
the file recorded, whatever the pace:

- ``realtime``: frames are released at the pace they were filmed (``speed``
  times that pace: 0.5 plays the film at half speed, as a camera filming a
  slowed-down performance would, and stamps it so). When the pose model is
  slower than that, late frames are skipped (counted), as a live camera drops
  what it cannot process.
- otherwise (``--max-speed``): every frame, as fast as the model goes, stamped
  with the video's own times. A server estimates each sensor's clock offset
  assuming it runs at the server's rate, so capture times from a video played
  faster or slower than it was filmed are only as good as that assumption.

The end of a video is the end of the source, not an error. A camera that
stops giving frames is retried for ``camera_timeout_s`` and then reported.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ...errors import StageError

log = logging.getLogger("stage.clients.webcam")


@dataclass
class Frame:
    image: np.ndarray     # (H, W, 3) BGR as OpenCV reads it
    t: float              # seconds from the start of the stream (video time or wall clock)
    stamp: float          # capture time, Unix seconds (the bundle's timetag): the start plus
                          # t, or plus t / speed for a video played at another speed


class FrameReader:
    """Reads, paces and stamps frames from an OpenCV capture (camera or video).

    ``cap``: an object with ``read()``, ``get(prop)`` and ``release()`` (an
    OpenCV ``VideoCapture``); ``video``: True for a file. ``monotonic``,
    ``sleep`` and ``wall`` are injectable for tests.
    """

    POS_MSEC = 0          # cv2.CAP_PROP_POS_MSEC
    FPS = 5               # cv2.CAP_PROP_FPS

    def __init__(self, cap: Any, name: str, video: bool, realtime: bool = True,
                 speed: float = 1.0, camera_timeout_s: float = 5.0, monotonic: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 wall: Callable[[], float] = time.time) -> None:
        self.cap, self.name, self.video, self.realtime = cap, name, video, realtime
        if not speed > 0:
            raise StageError(f"speed must be greater than 0, got {speed}")
        self.speed = float(speed) if realtime else 1.0
        self.camera_timeout_s = camera_timeout_s
        self._monotonic, self._sleep, self._wall = monotonic, sleep, wall
        fps = float(cap.get(self.FPS) or 0.0)
        self.fps = fps if 0 < fps < 1000 else 30.0
        self.read = 0          # frames decoded
        self.skipped = 0       # late frames dropped in real-time pacing
        self.ended = False     # a video reached its end
        self.decode_s = 0.0    # seconds the returned frame took to read (pacing excluded)
        self._start: tuple[float, float] | None = None   # (monotonic, wall) at the first frame
        self._last_t = -1.0

    def next(self, stop=None) -> Frame | None:
        """The next frame to process; None at the end of a video or when ``stop`` is set."""
        failing_since: float | None = None
        while stop is None or not stop.is_set():
            started = time.perf_counter()
            ok, image = self.cap.read()
            self.decode_s = time.perf_counter() - started
            now = self._monotonic()
            if not ok or image is None:
                if self.video:
                    self.ended = True
                    return None
                failing_since = now if failing_since is None else failing_since
                if now - failing_since > self.camera_timeout_s:
                    raise StageError(f"camera {self.name} gave no frame for "
                                     f"{self.camera_timeout_s:g} s")
                self._sleep(0.05)
                continue
            failing_since = None
            self.read += 1
            if self._start is None:
                self._start = (now, self._wall())
            if not self.video:
                t = now - self._start[0]
                return Frame(image, t, self._start[1] + t)
            t = self._video_time()
            if self.realtime:
                due = self._start[0] + t / self.speed
                if now < due:
                    self._sleep(due - now)
                elif now - due > 1.0 / (self.fps * self.speed):   # over a frame late: drop it
                    self.skipped += 1
                    continue
            return Frame(image, t, self._start[1] + t / self.speed)
        return None

    def _video_time(self) -> float:
        """This frame's time in the video (s): the container's time, else frame count / fps."""
        ms = self.cap.get(self.POS_MSEC)
        t = ms / 1000.0 if ms is not None and np.isfinite(ms) and ms >= 0 else -1.0
        if t <= self._last_t:   # no or repeated timestamps: count frames instead
            t = max(self._last_t + 1.0 / self.fps, (self.read - 1) / self.fps)
        self._last_t = t
        return t

    def release(self) -> None:
        self.cap.release()


def open_capture(cv2, camera: int, video: str | None):
    """(VideoCapture, display name, is a video); StageError when it does not open."""
    if video is not None:
        import os
        if not os.path.isfile(video):
            raise StageError(f"{video}: no such video file")
        cap = cv2.VideoCapture(video)
        if not cap.isOpened():
            raise StageError(f"{video}: OpenCV cannot read this video")
        return cap, video, True
    cap = cv2.VideoCapture(camera)
    if not cap.isOpened():
        raise StageError(f"cannot open camera {camera}")
    return cap, str(camera), False
