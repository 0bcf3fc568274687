"""Simulated shows as datagrams, for tests and benchmarks that replay them into an engine."""

from __future__ import annotations

import numpy as np

from ..sensors.protocol import encode_bundle, encode_client_joints, encode_message
from ..sensors.sim import KinectModel, VirtualKinect, ring_poses, standing_pose


#: a Unix time for bundles' timetags: show time 0
EPOCH = 1.7e9


def three_dancers(seed: int = 5, seconds: float = 6.0, aligned: bool = False,
                  timetags: bool = False, kinect: dict | None = None):
    """Datagrams of 3 simulated Kinects round three dancers who turn, raise their arms and
    walk to the edge of the sensors' range (inferred and lost joints: carried joints);
    ``aligned``: the sensors in step, each frame's views of a person one instant;
    ``timetags``: each bundle stamped with its capture time (``EPOCH`` + show time), so that
    a datagram that arrives late is placed where it was captured; ``kinect``: the
    simulated Kinects' ``KinectModel`` keywords (default: the real model's errors)."""
    rng = np.random.default_rng(seed)
    poses = ring_poses(3, radius=3.2)
    kinects = [VirtualKinect(p, KinectModel(**(kinect or {})), rng) for p in poses]
    out = []
    for f in range(int(seconds * 30)):
        for s, kinect in enumerate(kinects):
            msgs = []
            for u in range(3):
                x = -1.2 + 1.2 * u + 1.6 * np.sin(f / 40 + u)
                truth = standing_pose((x, 0.4 * u - 0.4), 0.05 * f * (u + 1),
                                      1.5 * np.sin(f / 9 + u), 1.5 * np.cos(f / 11),
                                      stride_phase=f / 5, stride_amp=0.3)
                seen = kinect.observe(truth, user=u)
                if seen is None:                          # out of this sensor's view
                    continue
                joints, conf = seen
                state = ("open", "closed", "lasso")[int(rng.integers(3))]
                msgs += [encode_client_joints(f"s{s}", u, joints, conf),
                         encode_message("/handState", f"s{s}", u, "left", state),
                         encode_message("/handState", f"s{s}", u, "right", "open")]
            t = f / 30 + (0.0 if aligned else s / 90)
            out.append((t, encode_bundle(msgs, EPOCH + t if timetags else None)))
    return poses, out
