"""What every sensor client sends, independent of the sensor: the Client-to-Server API.

``ClientEncoder`` turns "these bodies are tracked in this frame" into the
paper's messages: ``/newUser`` when a body appears (user ids 0-5, the lowest
free one, as a Kinect hands out body slots), ``/lostUser`` when it goes,
``/jointCoordinates`` and ``/handState`` per body, ``/floorPlane`` when the
sensor reports one, all in one OSC bundle whose timetag is the capture time
on the client's clock. Used by the real-sensor clients, the dataset
importers and the simulator, so they all speak exactly the same way.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from typing import Hashable

import numpy as np

from ...joints import HANDS, JOINT_INDEX, N_JOINTS, HandState
from ..protocol import MAX_USER_ID, encode_bundle, encode_client_joints, encode_message

_SPINE_MID = JOINT_INDEX["SpineMid"]
_ALL = np.ones(N_JOINTS, dtype=bool)


@dataclass
class BodyFrame:
    """One tracked body in one frame, in the sensor's own camera space.

    key: the sensor's own tracking id (any hashable); joints: (25, 3) metres,
    Kinect camera space (x to the sensor's left, y up, z away from it);
    conf: (25,) 0 not tracked, 0.5 inferred, 1 tracked; hands: (left, right)
    or None where the sensor reports no hand state.
    """

    key: Hashable
    joints: np.ndarray
    conf: np.ndarray
    hands: tuple[HandState, HandState] | None = None


class UserSlots:
    """Tracking keys -> user ids 0-5; a new body takes the lowest free id."""

    def __init__(self, size: int = MAX_USER_ID + 1) -> None:
        self.size = size
        self.ids: dict[Hashable, int] = {}

    def get(self, key: Hashable) -> int | None:
        return self.ids.get(key)

    def assign(self, key: Hashable) -> int | None:
        """The id of ``key``, assigning a free one; None when all are taken."""
        if key in self.ids:
            return self.ids[key]
        used = set(self.ids.values())
        for uid in range(self.size):
            if uid not in used:
                self.ids[key] = uid
                return uid
        return None

    def release(self, key: Hashable) -> int | None:
        return self.ids.pop(key, None)

    def clear(self) -> None:
        self.ids.clear()


class ClientEncoder:
    """Builds one client's datagrams. Not thread-safe: one per sensor thread.

    ``send_all_joints``: send all 25 joints with their confidence, as a Kinect
    client does (not-tracked ones with confidence 0); False sends only the
    joints with confidence > 0 (less bandwidth; the server treats both alike).
    """

    def __init__(self, client_id: str, sensor_type: str = "kinect2",
                 send_all_joints: bool = True) -> None:
        self.client = client_id
        self.sensor_type = sensor_type
        self.send_all_joints = send_all_joints
        self.slots = UserSlots()
        self.untracked = 0        # bodies seen while all six ids were taken

    def register(self) -> bytes:
        return encode_message("/registerDevice", self.client, self.sensor_type)

    def reset(self) -> None:
        """Forget the users (the sensor was restarted: the server will time them out)."""
        self.slots.clear()

    def frame(self, bodies: list[BodyFrame], timetag: float | None = None,
              floor: np.ndarray | None = None, nan_users: frozenset = frozenset()) -> bytes | None:
        """One frame's bundle (None when there is nothing to say).

        ``timetag``: capture time on the client's clock, Unix seconds (None:
        the bundle is "immediate"). ``floor``: (4,) a, b, c, d of the floor
        plane in camera space (Kinect's FloorClipPlane), sent as /floorPlane.
        ``nan_users``: keys whose joints are sent as NaN (a broken frame).
        """
        messages: list[bytes] = []
        present = {b.key for b in bodies}
        for key in [k for k in self.slots.ids if k not in present]:
            uid = self.slots.release(key)
            messages.append(encode_message("/lostUser", self.client, uid))
        for body in bodies:
            uid = self.slots.get(body.key)
            if uid is None:
                uid = self.slots.assign(body.key)
                if uid is None:
                    self.untracked += 1
                    continue
                centre = body.joints[_SPINE_MID] if body.conf[_SPINE_MID] > 0 else \
                    body.joints[body.conf > 0].mean(axis=0) if (body.conf > 0).any() else \
                    body.joints[_SPINE_MID]
                messages.append(encode_message("/newUser", self.client, uid,
                                               *(float(v) for v in centre)))
            joints = body.joints
            if body.key in nan_users:
                joints = np.full_like(joints, np.nan)
            messages.append(encode_client_joints(self.client, uid, joints, body.conf,
                                                 _ALL if self.send_all_joints else None))
            if body.hands is not None:
                for hand, state in enumerate(body.hands):
                    messages.append(encode_message("/handState", self.client, uid, HANDS[hand],
                                                   HandState(state).wire_name))
        if floor is not None:
            messages.append(encode_message("/floorPlane", self.client,
                                           *(float(v) for v in floor)))
        if not messages:
            return None
        return encode_bundle(messages, timetag)


class UdpSender:
    """One UDP socket for one sensor client; send errors are counted, never raised."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.errors = 0
        self.sent = 0

    def send(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.target)
            self.sent += 1
        except OSError:  # the server is restarting or the network is down: keep going
            self.errors += 1

    def close(self) -> None:
        self.sock.close()
