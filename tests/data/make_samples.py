"""Regenerate the small sample files in this folder (run from the repository root).

    python tests/data/make_samples.py

- ``S001C00{1,2,3}P001R001A001.skeleton``: NTU RGB+D format, three cameras of
  one simulated performance (the default scenario, seed 4), 12 frames each;
  tracking states from the simulator's confidences, hand states as sensed; a
  second person (a shifted copy) passes camera 1 in frames 5-9.
- ``a01_s01_e00_v0{1,2,3}.json``: N-UCLA JSON, the same dancer seen by the
  three sensors, cut to different lengths (the views are not aligned), the
  five joints Kinect v1 lacks dropped, one joint missing (zeros) in view 2.
- ``march.bvh``: a tiny CMU-named BVH skeleton marching forwards, 60 Hz.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from stage.sensors.importers.ntu import NtuBody, write_skeleton_file
from stage.sensors.importers.nucla import V1_TO_V2, write_nucla_json
from stage.sensors.protocol import HandStateMsg, JointCoordinates, decode_datagram
from stage.sensors.sim import Simulator

HERE = Path(__file__).parent
STATE = {0.0: 0, 0.5: 1, 1.0: 2}


def sim_frames(seconds: float = 0.9) -> dict[str, list[list[tuple]]]:
    """Per sensor: frames of (user, joints, conf, hands) from the default scenario."""
    out: dict[str, list[list[tuple]]] = {}
    for _, sensor, data in Simulator("default", seed=4).datagrams(seconds):
        msgs = [m for m, _ in decode_datagram(data).messages]
        joints = [m for m in msgs if isinstance(m, JointCoordinates)]
        if not joints:
            continue
        hands = {(m.user, m.hand): int(m.state) for m in msgs if isinstance(m, HandStateMsg)}
        out.setdefault(sensor, []).append(
            [(j.user, j.joints, j.conf, (hands.get((j.user, 0), 0), hands.get((j.user, 1), 0)))
             for j in joints])
    return out


def make_ntu(frames: dict) -> None:
    for cam, (sensor, seq) in enumerate(sorted(frames.items()), 1):
        out = []
        for bodies in seq[:12]:
            ntu = []
            for user, joints, conf, hands in bodies:
                table = np.zeros((25, 12))
                table[:, :3] = joints
                table[:, 3:5] = np.stack([256 + 300 * joints[:, 0], 212 - 300 * joints[:, 1]], axis=1)
                table[:, 5:7] = table[:, 3:5] * 3.75
                table[:, 7] = 1.0
                table[:, 11] = [STATE[float(c)] for c in conf]
                ntu.append(NtuBody(72057594037927936 + 17 * cam + user, 0, 1, hands[0], 1,
                                   hands[1], 0, (0.01, -0.02), 2, table))
            if cam == 1 and 4 <= len(out) < 9:  # a second person passes camera 1
                other = ntu[0].joints.copy()
                other[:, 0] += 0.8
                ntu.append(NtuBody(72057594037928999, 0, 1, 3, 1, 2, 0, (0.0, 0.0), 2, other))
            out.append(ntu)
        write_skeleton_file(HERE / f"S001C{cam:03d}P001R001A001.skeleton", out)


def make_nucla(frames: dict) -> None:
    for view, (sensor, seq) in enumerate(sorted(frames.items()), 1):
        length = (12, 9, 14)[view - 1]
        skel = np.stack([bodies[0][1][V1_TO_V2] for bodies in seq[:length]])
        if view == 2:
            skel[3:5, 15] = 0.0  # FootLeft missing for two frames
        write_nucla_json(HERE / f"a01_s01_e00_v{view:02d}.json", f"a01_s01_e00_v{view:02d}",
                         np.round(skel, 6), label=1)


def make_bvh() -> None:
    frames = []
    for k in range(61):
        t = k / 60
        swing = 20 * math.sin(2 * math.pi * t)
        frames.append(f"0 95 {t * 100:.4f} 0 0 0  0 0 {swing:.4f}  0 0 {max(swing, 0):.4f}  "
                      f"0 0 {-swing:.4f}  0 0 {max(-swing, 0):.4f}  0 {5 * math.sin(t):.4f} 0")
    hierarchy = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT LeftHip
  {
    OFFSET 9 -3 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT LeftKnee
    {
      OFFSET 0 -42 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT LeftAnkle
      {
        OFFSET 0 -42 0
        End Site
        {
          OFFSET 0 -8 12
        }
      }
    }
  }
  JOINT RightHip
  {
    OFFSET -9 -3 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT RightKnee
    {
      OFFSET 0 -42 0
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT RightAnkle
      {
        OFFSET 0 -42 0
        End Site
        {
          OFFSET 0 -8 12
        }
      }
    }
  }
  JOINT Chest2
  {
    OFFSET 0 45 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT Neck
    {
      OFFSET 0 10 0
      JOINT Head
      {
        OFFSET 0 10 0
        End Site
        {
          OFFSET 0 22 0
        }
      }
    }
    JOINT LeftShoulder
    {
      OFFSET 18 -2 0
      JOINT LeftElbow
      {
        OFFSET 0 -28 0
        JOINT LeftWrist
        {
          OFFSET 0 -24 0
          End Site
          {
            OFFSET 0 -8 0
          }
        }
      }
    }
    JOINT RightShoulder
    {
      OFFSET -18 -2 0
      JOINT RightElbow
      {
        OFFSET 0 -28 0
        JOINT RightWrist
        {
          OFFSET 0 -24 0
          End Site
          {
            OFFSET 0 -8 0
          }
        }
      }
    }
  }
}
MOTION
Frames: %d
Frame Time: %.8f
""" % (len(frames), 1 / 60)
    (HERE / "march.bvh").write_text(hierarchy + "\n".join(frames) + "\n")


if __name__ == "__main__":
    f = sim_frames()
    make_ntu(f)
    make_nucla(f)
    make_bvh()
    print("written:", ", ".join(sorted(p.name for p in HERE.iterdir() if p.suffix != ".py")))
