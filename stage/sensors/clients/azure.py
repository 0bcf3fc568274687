"""Azure Kinect / Orbbec Femto client (Azure Kinect Body Tracking SDK, through pykinect_azure).

Install the Azure Kinect Sensor SDK and Body Tracking SDK (for an Orbbec
Femto: Orbbec's K4A wrapper, which the same Body Tracking SDK drives), then
``pip install 'stage-kuatro[azure]'`` and run ``stage client azure --to
SERVER:7770 --id femto-a``. ``stage client azure --check`` says what is
installed and missing and, with a device, prints one tracked skeleton.

The body tracker reports 32 joints in millimetres in the depth camera's
space (x right, y down, z away) with a confidence level per joint (0 none,
1 low, 2 medium, 3 high). They are mapped onto the 25 Kinect v2 joints by
the skeletons' structure (the shoulders branch at Azure's SPINE_CHEST as at
Kinect v2's SpineShoulder), converted to metres and to Kinect camera axes
(x to the sensor's left, y up, z away). The body tracker has no hand states
and no floor plane, so neither is sent. The mapping is tested with recorded
arrays; ``run`` needs the device.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import sys
import time

import numpy as np

from ...joints import JOINT_INDEX
from .osc import BodyFrame
from ..source import ThreadedSource

log = logging.getLogger("stage.clients.azure")

K4ABT_JOINTS = ("PELVIS", "SPINE_NAVEL", "SPINE_CHEST", "NECK", "CLAVICLE_LEFT",
                "SHOULDER_LEFT", "ELBOW_LEFT", "WRIST_LEFT", "HAND_LEFT", "HANDTIP_LEFT",
                "THUMB_LEFT", "CLAVICLE_RIGHT", "SHOULDER_RIGHT", "ELBOW_RIGHT", "WRIST_RIGHT",
                "HAND_RIGHT", "HANDTIP_RIGHT", "THUMB_RIGHT", "HIP_LEFT", "KNEE_LEFT",
                "ANKLE_LEFT", "FOOT_LEFT", "HIP_RIGHT", "KNEE_RIGHT", "ANKLE_RIGHT", "FOOT_RIGHT",
                "HEAD", "NOSE", "EYE_LEFT", "EAR_LEFT", "EYE_RIGHT", "EAR_RIGHT")
_TO_KINECT2 = {"PELVIS": "SpineBase", "SPINE_NAVEL": "SpineMid", "SPINE_CHEST": "SpineShoulder",
               "NECK": "Neck", "HEAD": "Head"}
for _side in ("Left", "Right"):
    for _part, _k in (("Shoulder", "SHOULDER"), ("Elbow", "ELBOW"), ("Wrist", "WRIST"),
                      ("Hand", "HAND"), ("HandTip", "HANDTIP"), ("Thumb", "THUMB"),
                      ("Hip", "HIP"), ("Knee", "KNEE"), ("Ankle", "ANKLE"), ("Foot", "FOOT")):
        _TO_KINECT2[f"{_k}_{_side.upper()}"] = _part + _side
#: for each Kinect v2 joint, the index of the Azure joint it comes from
AZURE_INDEX = np.array([K4ABT_JOINTS.index(next(a for a, k in _TO_KINECT2.items() if k == name))
                        for name in JOINT_INDEX])
CONFIDENCE = np.array([0.0, 0.5, 1.0, 1.0])   # none, low, medium, high
_AXES = np.array([-1.0, -1.0, 1.0]) / 1000.0   # mm, x right / y down -> m, x left / y up


def azure_body(body_id: int, positions_mm: np.ndarray, confidence_levels: np.ndarray
               ) -> BodyFrame:
    """One Azure body (32 joints, mm, depth camera axes) -> a Kinect v2 body in metres."""
    pos = np.asarray(positions_mm, float).reshape(len(K4ABT_JOINTS), 3)
    levels = np.clip(np.asarray(confidence_levels, int).reshape(len(K4ABT_JOINTS)), 0, 3)
    joints = pos[AZURE_INDEX] * _AXES
    conf = CONFIDENCE[levels[AZURE_INDEX]]
    return BodyFrame(int(body_id), joints, conf, None)


def _open(pykinect):
    """Start the depth camera (no colour, narrow unbinned depth) and the body tracker."""
    pykinect.initialize_libraries(track_body=True)
    config = pykinect.default_configuration
    config.color_resolution = pykinect.K4A_COLOR_RESOLUTION_OFF
    config.depth_mode = pykinect.K4A_DEPTH_MODE_NFOV_UNBINNED
    return pykinect.start_device(config=config), pykinect.start_body_tracker()


def _close(device, tracker) -> None:
    """Stop the body tracker, then the camera, so the device can be opened again."""
    try:
        tracker.destroy()
    finally:
        device.close()


def _body(body) -> BodyFrame:
    """One SDK body as our BodyFrame."""
    return azure_body(body.id, [(j.position.x, j.position.y, j.position.z) for j in body.joints],
                      [j.confidence_level for j in body.joints])


def run(target: tuple[str, int], client_id: str, stop=None) -> None:
    """Read the body tracker and send until ``stop`` is set (needs the device and SDKs)."""
    from ... import install_hint
    from ...errors import StageError
    from .osc import ClientEncoder, UdpSender
    try:
        import pykinect_azure as pykinect
    except ImportError:
        raise StageError("the Azure Kinect / Orbbec client needs the Azure Kinect Sensor and "
                         f"Body Tracking SDKs and pykinect_azure: {install_hint('azure')}"
                         ) from None
    device, tracker = _open(pykinect)
    encoder, sender = ClientEncoder(client_id, "azure-kinect"), UdpSender(target)
    sender.send(encoder.register())
    try:
        while stop is None or not stop.is_set():
            device.update()
            frame = tracker.update()
            stamp = time.time()
            bodies = []
            for k in range(frame.get_num_bodies()):
                bodies.append(_body(frame.get_body(k)))
            data = encoder.frame(bodies, stamp)
            if data is not None:
                sender.send(data)
    finally:
        sender.close()
        _close(device, tracker)


#: where the SDK installers put the libraries when they are not on the loader's path
_WIN_BIN = r"sdk\windows-desktop\amd64\release\bin"
_K4A_PATHS = {"linux": ["/usr/lib/x86_64-linux-gnu/libk4a.so.1.4",
                        "/usr/lib/aarch64-linux-gnu/libk4a.so.1.4", "/usr/local/lib/libk4a.so"],
              "win32": [rf"C:\Program Files\Azure Kinect SDK v1.4.{v}\{_WIN_BIN}\k4a.dll"
                        for v in (1, 2, 0)]}
_K4ABT_PATHS = {"linux": ["/usr/lib/libk4abt.so", "/usr/lib/x86_64-linux-gnu/libk4abt.so",
                          "/usr/lib/libk4abt.so.1.1"],
                "win32": [rf"C:\Program Files\Azure Kinect Body Tracking SDK\{_WIN_BIN}"
                          r"\k4abt.dll"]}


def _first_body(wait_s: float) -> tuple[BodyFrame | None, float]:
    """Open the device and body tracker, wait up to ``wait_s`` for a body: (body or None, s)."""
    import pykinect_azure as pykinect
    device, tracker = _open(pykinect)
    start = time.monotonic()
    try:
        while time.monotonic() - start < wait_s:
            device.update()
            frame = tracker.update()
            if frame.get_num_bodies() > 0:
                return _body(frame.get_body(0)), time.monotonic() - start
        return None, time.monotonic() - start
    finally:
        _close(device, tracker)


def check(wait_s: float = 5.0, platform: str = sys.platform, find_spec=importlib.util.find_spec,
          find_library=None, exists=os.path.exists, first_body=_first_body) -> tuple[str, bool]:
    """``stage client azure --check``: (report, everything needed is there and a body was seen)."""
    import ctypes.util
    from ... import install_hint
    from .check import Item, body_items, library_item, module_item, report
    find_library = find_library or ctypes.util.find_library
    key = "win32" if platform == "win32" else "linux"
    items = [Item("Linux or Windows (x64)", platform in ("linux", "win32"), platform)]
    items.append(library_item(
        "Azure Kinect Sensor SDK (or Orbbec's K4A wrapper)", "k4a", _K4A_PATHS[key],
        "Linux: apt install libk4a1.4 k4a-tools from Microsoft's package repository (Ubuntu "
        "18.04/20.04), or Orbbec's OrbbecSDK-K4A-Wrapper for a Femto; Windows: the Azure "
        "Kinect SDK 1.4 installer", find_library, exists))
    items.append(library_item(
        "Azure Kinect Body Tracking SDK", "k4abt", _K4ABT_PATHS[key],
        "Linux: apt install libk4abt1.1; Windows: the Body Tracking SDK 1.1 installer (it needs "
        "an NVIDIA GPU with CUDA, or DirectML on Windows)", find_library, exists))
    items.append(module_item("pykinect_azure", ("pykinect_azure", "pykinect-azure"),
                             install_hint("azure"), find_spec))
    extra = body_items(items, first_body, wait_s, "device", "cannot open it",
                       "is someone 0.5-4 m in front of the sensor?",
                       "Kinect camera space, metres (x to the sensor's left, y up, z away)")
    return report("stage client azure --check", items, extra)


class AzureSource(ThreadedSource):
    """The ``azure`` source: an Azure Kinect or Orbbec Femto through the body tracking SDK; ``stage client azure``."""

    name = "azure"
    description = "an Azure Kinect or Orbbec Femto through the body tracking SDK (extra: azure)"

    def __init__(self, client_id: str = "azure") -> None:
        super().__init__()
        self.client_id = client_id

    def _run(self, target: tuple[str, int], stop) -> None:  # pragma: no cover - needs hardware
        run(target, self.client_id, stop)
