"""Kinect v2 client (Windows, Kinect for Windows SDK 2.0, through PyKinect2).

Install on the Windows machine the Kinect is plugged into: the Kinect for
Windows SDK 2.0, then ``pip install 'stage-kuatro[kinect2]'`` (``pykinect2024``, the
maintained fork of Microsoft's PyKinect2, imported as ``pykinect2``). Run
``stage client kinect2 --to SERVER:7770 --id kinect-a``. ``stage client
kinect2 --check`` says what is installed and missing and, with a sensor,
prints one tracked skeleton.

The SDK already speaks our contract: the 25 joints in ``JointType`` order,
camera space in metres (x to the sensor's left, y up, z away), joint
``TrackingState`` 0/1/2 (not tracked / inferred / tracked), hand states
0-4, and the frame's ``FloorClipPlane``. This module maps those arrays to
messages (tested here with recorded arrays); ``run`` is the thin loop that
reads the sensor and cannot run without one.
"""

from __future__ import annotations

import importlib.util
import logging
import ntpath
import os
import sys
import time

import numpy as np

from ...joints import N_JOINTS, HandState
from .osc import BodyFrame
from ..source import ThreadedSource

log = logging.getLogger("stage.clients.kinect2")

#: Kinect TrackingState -> confidence
TRACKING_CONF = np.array([0.0, 0.5, 1.0])
BODY_COUNT = 6


def kinect2_body(tracking_id: int, positions: np.ndarray, states: np.ndarray, hand_left: int,
                 hand_right: int) -> BodyFrame:
    """One tracked Kinect v2 body -> BodyFrame.

    positions: (25, 3) CameraSpacePoint x, y, z (metres); states: (25,)
    TrackingState 0-2; hand_left/right: HandState codes 0-4.
    """
    positions = np.asarray(positions, float).reshape(N_JOINTS, 3)
    states = np.clip(np.asarray(states, int).reshape(N_JOINTS), 0, 2)
    hands = tuple(HandState(h) if 0 <= h <= 4 else HandState.UNKNOWN for h in (hand_left,
                                                                                   hand_right))
    return BodyFrame(int(tracking_id), positions, TRACKING_CONF[states], hands)  # type: ignore[arg-type]


def floor_plane(vector4: tuple[float, float, float, float]) -> np.ndarray | None:
    """FloorClipPlane (x, y, z, w) -> /floorPlane (a, b, c, d); None before the SDK finds a floor."""
    v = np.asarray(vector4, float)
    if not np.isfinite(v).all() or np.linalg.norm(v[:3]) < 1e-6:
        return None
    return v


class RelativeClock:
    """Turns the SDK's RelativeTime (100 ns ticks since an arbitrary start) into Unix seconds."""

    def __init__(self) -> None:
        self._base: tuple[int, float] | None = None

    def __call__(self, ticks: int) -> float:
        if self._base is None:
            self._base = (int(ticks), time.time())
        return self._base[1] + (int(ticks) - self._base[0]) * 1e-7


def run(target: tuple[str, int], client_id: str, stop=None) -> None:  # pragma: no cover
    """Read body frames from the Kinect and send them until ``stop`` is set (Windows only)."""
    from ... import install_hint
    from ...errors import StageError
    from .osc import ClientEncoder, UdpSender
    try:
        from pykinect2 import PyKinectRuntime, PyKinectV2
    except ImportError:
        raise StageError("the Kinect v2 client needs Windows, the Kinect for Windows SDK 2.0 and "
                         f"PyKinect2: {install_hint('kinect2')}") from None
    kinect = PyKinectRuntime.PyKinectRuntime(PyKinectV2.FrameSourceTypes_Body)
    encoder, sender = ClientEncoder(client_id, "kinect2"), UdpSender(target)
    clock = RelativeClock()
    sender.send(encoder.register())
    try:
        while stop is None or not stop.is_set():
            if not kinect.has_new_body_frame():
                time.sleep(0.002)
                continue
            frame = kinect.get_last_body_frame()
            stamp = clock(getattr(frame, "relative_time", int(time.monotonic() * 1e7)))
            bodies = []
            for k in range(kinect.max_body_count):
                body = frame.bodies[k]
                if not body.is_tracked:
                    continue
                joints = body.joints
                positions = [(joints[j].Position.x, joints[j].Position.y, joints[j].Position.z)
                             for j in range(N_JOINTS)]
                states = [joints[j].TrackingState for j in range(N_JOINTS)]
                bodies.append(kinect2_body(body.tracking_id, positions, states,
                                           body.hand_left_state, body.hand_right_state))
            fp = frame.floor_clip_plane
            data = encoder.frame(bodies, stamp, floor_plane((fp.x, fp.y, fp.z, fp.w)))
            if data is not None:
                sender.send(data)
    finally:
        kinect.close()
        sender.close()


def _first_body(wait_s: float) -> tuple[BodyFrame | None, float]:  # pragma: no cover
    """Open the sensor and wait up to ``wait_s`` for a tracked body: (body or None, seconds)."""
    from pykinect2 import PyKinectRuntime, PyKinectV2
    kinect = PyKinectRuntime.PyKinectRuntime(PyKinectV2.FrameSourceTypes_Body)
    start = time.monotonic()
    try:
        while time.monotonic() - start < wait_s:
            if not kinect.has_new_body_frame():
                time.sleep(0.01)
                continue
            frame = kinect.get_last_body_frame()
            for k in range(kinect.max_body_count):
                body = frame.bodies[k]
                if body.is_tracked:
                    j = body.joints
                    return kinect2_body(
                        body.tracking_id,
                        [(j[n].Position.x, j[n].Position.y, j[n].Position.z) for n in range(N_JOINTS)],
                        [j[n].TrackingState for n in range(N_JOINTS)],
                        body.hand_left_state, body.hand_right_state), time.monotonic() - start
        return None, time.monotonic() - start
    finally:
        kinect.close()


def check(wait_s: float = 5.0, platform: str = sys.platform, env=os.environ,
          exists=os.path.exists, find_spec=importlib.util.find_spec,
          first_body=_first_body) -> tuple[str, bool]:
    """``stage client kinect2 --check``: (report, everything needed is there and a body was seen)."""
    from ... import install_hint
    from .check import Item, body_items, module_item, report
    items = [Item("Windows (64-bit)", platform == "win32",
                  platform if platform == "win32" else
                  f"this is {platform}: the Kinect v2 SDK runs only on Windows 8/10/11")]
    sdk_dir = env.get("KINECTSDK20_DIR")
    dll = ntpath.join(env.get("SystemRoot", r"C:\Windows"), "System32", "Kinect20.dll")
    has_sdk = bool(sdk_dir) or exists(dll)
    items.append(Item("Kinect for Windows SDK 2.0", has_sdk,
                      (sdk_dir or dll) if has_sdk else
                      "install KinectSDK-v2.0_1409-Setup.exe (Microsoft), then replug the sensor"))
    items.append(module_item("pykinect2", ("pykinect2024", "pykinect2"), install_hint("kinect2"),
                             find_spec))
    items.append(module_item("comtypes", ("comtypes",), install_hint("kinect2"), find_spec))
    extra = body_items(items, first_body, wait_s, "sensor", "cannot open the Kinect",
                       "is the sensor on USB 3, powered, and someone 1-4 m in front of it? "
                       "(Kinect Configuration Verifier tests the setup)",
                       "camera space, metres (x to the sensor's left, y up, z away)")
    return report("stage client kinect2 --check", items, extra)


class Kinect2Source(ThreadedSource):
    """The ``kinect2`` source: a Kinect v2 through the Kinect for Windows SDK 2.0; ``stage client kinect2``."""

    name = "kinect2"
    description = "a Kinect v2 through the Kinect for Windows SDK 2.0 (extra: kinect2)"

    def __init__(self, client_id: str = "kinect2") -> None:
        super().__init__()
        self.client_id = client_id

    def _run(self, target: tuple[str, int], stop) -> None:  # pragma: no cover - needs hardware
        run(target, self.client_id, stop)
