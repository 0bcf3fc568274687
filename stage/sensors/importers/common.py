"""Writing imported skeletons as a recording: each camera becomes one sensor client.

Every sensor sends exactly what a live client would (``ClientEncoder``):
``/registerDevice`` before its first frame, ``/newUser``/``/lostUser`` as
bodies come and go (user ids 0-5), one bundle per frame with the frame's
time as timetag. Datasets carry no network timing, so arrival = capture =
the frame's time (seconds from the start of the take).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from ..clients.osc import BodyFrame, ClientEncoder
from ..recording import RecordingWriter, check_output_path

#: imported sensor clocks count from here (Unix seconds), so imports are reproducible
EPOCH = 1_600_000_000.0


@dataclass
class Frame:
    t: float                                  # seconds from the start of the take
    bodies: list[BodyFrame] = field(default_factory=list)
    floor: np.ndarray | None = None           # (4,) floor plane, when the source has one


@dataclass
class Take:
    """One camera's frames: sensor id, sensor type, frames in time order."""

    sensor: str
    sensor_type: str
    frames: list[Frame]


def write_takes(path: str, takes: list[Take], meta: dict) -> int:
    """Write several cameras' takes as one recording, merged by time; returns datagrams written."""
    check_output_path(path)
    encoders = [ClientEncoder(t.sensor, t.sensor_type) for t in takes]
    queue: list[tuple[float, int, int]] = []
    for k, take in enumerate(takes):
        if take.frames:
            queue.append((take.frames[0].t, k, -1))  # -1: register first
    heapq.heapify(queue)
    n = 0
    with RecordingWriter(path, meta) as writer:
        while queue:
            t, k, i = heapq.heappop(queue)
            take, encoder = takes[k], encoders[k]
            source = ("import", k + 1)
            if i < 0:
                writer.write(t, source, encoder.register(), t)
                n += 1
                heapq.heappush(queue, (t, k, 0))
                continue
            frame = take.frames[i]
            data = encoder.frame(frame.bodies, EPOCH + frame.t, frame.floor)
            if data is not None:
                writer.write(frame.t, source, data, frame.t)
                n += 1
            if i + 1 < len(take.frames):
                heapq.heappush(queue, (take.frames[i + 1].t, k, i + 1))
            else:
                final = encoder.frame([], EPOCH + frame.t + 1 / 30)  # the take ends: users leave
                if final is not None:
                    writer.write(frame.t + 1 / 30, source, final, frame.t + 1 / 30)
                    n += 1
    return n
