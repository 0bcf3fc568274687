"""The built-in demo: three virtual Kinects around one dancer, sending real OSC.

Each virtual sensor sends the Client-to-Server API over UDP from its own
socket, 30 frames a second, every frame as a bundle whose timetag is the
capture time on that sensor's own (deliberately offset) clock. Noise,
inferred back-side joints and misread hand states make the fusion work.
The dancer walks a circle, raises the arms in turn, and opens, closes and
points the hands. Seeded: the same seed gives the same performance.
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from .body import SensorPose, misread_hand, observe_with_errors, pose, ring_of_sensors
from .joints import HandState
from .sensors.protocol import encode_bundle, encode_client_joints, encode_message
from .rig import Rig, set_calibration

FPS = 30.0


@dataclass
class DemoSensor:
    id: str
    pose: SensorPose
    clock_offset_s: float   # this sensor's clock minus the true time


def demo_rig(n_sensors: int = 3, port: int = 0) -> tuple[Rig, list[DemoSensor]]:
    """A rig whose calibration is exact for the demo sensors (no calibration step needed).

    Stage space has its origin on the floor at the centre of the ring, y up.
    """
    poses = ring_of_sensors(n_sensors)
    sensors = [DemoSensor(f"demo-{chr(ord('a') + k)}", p, 3.0 * k - 2.5)
               for k, p in enumerate(poses)]
    rig = Rig(port=port, reference=sensors[0].id)
    rig.stage_frame = sensors[0].pose.to_stage
    inverse_reference = np.linalg.inv(sensors[0].pose.to_stage)
    set_calibration(rig, sensors[0].id, np.eye(4), "demo")
    for s in sensors[1:]:
        set_calibration(rig, s.id, inverse_reference @ s.pose.to_stage, "demo", 1.0, 0.0)
    return rig, sensors


def dancer(t: float) -> tuple[np.ndarray, tuple[HandState, HandState]]:
    """The demo choreography: (true joints (25,3) stage space, true hand states)."""
    angle = 2 * np.pi * t / 20.0
    position = np.array([np.sin(angle), np.cos(angle)]) * 1.0
    heading = angle + np.pi / 2
    left = 0.5 * np.pi * (1 + np.sin(2 * np.pi * t / 6.0))
    right = 0.5 * np.pi * (1 + np.sin(2 * np.pi * t / 6.0 + np.pi))
    stride = 0.35 * np.sin(2 * np.pi * t / 1.1)
    cycle = (HandState.OPEN, HandState.CLOSED, HandState.LASSO)
    hands = (cycle[int(t / 2.0) % 3], cycle[int(t / 3.0 + 1) % 3])
    return pose(position, heading, left, right, stride), hands


class DemoSource:
    """Sends the demo sensors' OSC to ``target`` in real time, on its own thread."""

    def __init__(self, target: tuple[str, int], sensors: list[DemoSensor], seed: int = 1,
                 misread_p: float = 0.1) -> None:
        self.target, self.sensors = target, sensors
        self.rng = np.random.default_rng(seed)
        self.misread_p = misread_p
        self.socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in sensors]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stage-demo", daemon=True)
        self.frames_sent = 0

    def start(self) -> "DemoSource":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for sock in self.socks:
            sock.close()

    def frame_datagrams(self, sensor: DemoSensor, t: float, wall: float) -> bytes:
        """One sensor's bundle for time ``t`` of the choreography."""
        truth, hands = dancer(t)
        joints, conf = observe_with_errors(sensor.pose, truth, self.rng)
        messages = [encode_client_joints(sensor.id, 0, joints, conf)]
        for hand, state in enumerate(hands):
            seen = misread_hand(state, self.rng, self.misread_p)
            messages.append(encode_message("/handState", sensor.id, 0,
                                           ("left", "right")[hand], seen.wire_name))
        return encode_bundle(messages, wall + sensor.clock_offset_s)

    def _run(self) -> None:
        for sock, sensor in zip(self.socks, self.sensors):
            truth, _ = dancer(0.0)
            centre = sensor.pose.observe(truth[1])
            sock.sendto(encode_message("/registerDevice", sensor.id, "kinect2-demo"), self.target)
            sock.sendto(encode_message("/newUser", sensor.id, 0, *map(float, centre)), self.target)
        start = time.monotonic()
        k = 0
        while not self._stop.is_set():
            t = k / FPS
            wall = time.time()
            for sock, sensor in zip(self.socks, self.sensors):
                try:
                    sock.sendto(self.frame_datagrams(sensor, t, wall), self.target)
                except OSError:
                    pass  # the server went away; keep the rhythm, it may come back
            self.frames_sent += 1
            k += 1
            delay = start + k / FPS - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
