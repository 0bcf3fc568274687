"""BVH takes through the whole path: `stage import bvh`, `stage serve`, `stage replay`.

For each BVH file: import it (naming scheme and unit detected), start a real
`stage serve` writing every fused frame (`--fused`), replay the recording into
it over UDP, and measure on the fused bodies:

- bone lengths: for each rigid limb bone (upper arm, forearm, thigh, shin,
  foot, both sides), max - min of its length over the take, in mm; beside
  the same figure on the imported recording itself (the reference: what the
  server was sent);
- the floor: per frame the lowest foot joint (Ankle/Foot, both sides) above
  y = 0, in mm: 5th, 50th, 95th percentile and the minimum (a dancer on the
  floor has a low foot near 0 whenever standing, and never below it).

    python bench/bench_bvh_serve.py FILE.bvh [FILE.bvh ...] [--speed X] [--quick]

Public takes, not committed: the CMU files in ../shared/data/cmu/, and the
Bandai Namco Research Motion Dataset (CC BY-NC 4.0, github.com/BandaiNamcoResearchInc/
Bandai-Namco-Research-Motiondataset; fetch it under bench/data/, which git ignores).
The takes `dataset-1_dance-short_normal_001` and `dataset-1_dance-long_normal_001`
are held out for evaluating the smoothing: this script refuses them.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stage.joints import JOINT_INDEX as J  # noqa: E402
from stage.sensors.protocol import JointCoordinates, decode_datagram  # noqa: E402
from stage.sensors.recording import read_recording  # noqa: E402

HELD_OUT = ("dataset-1_dance-short_normal_001", "dataset-1_dance-long_normal_001")
BONES = [(f"{a}{s}", f"{b}{s}") for s in ("Left", "Right")
         for a, b in (("Shoulder", "Elbow"), ("Elbow", "Wrist"), ("Hip", "Knee"),
                      ("Knee", "Ankle"), ("Ankle", "Foot"))]
FEET = [J[n] for n in ("AnkleLeft", "AnkleRight", "FootLeft", "FootRight")]
CLI = [sys.executable, "-m", "stage"]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bone_spread(frames: np.ndarray) -> dict[str, float]:
    """max - min length (mm) of each bone over (T, 25, 3) frames."""
    out = {}
    for a, b in BONES:
        lengths = np.linalg.norm(frames[:, J[a]] - frames[:, J[b]], axis=1)
        out[f"{a}-{b}"] = float(np.ptp(lengths) * 1000)
    return out


def recorded_frames(path: str) -> np.ndarray:
    frames = []
    for rec in read_recording(path):
        for msg, _ in decode_datagram(rec.data).messages:
            if isinstance(msg, JointCoordinates):
                frames.append(msg.joints)
    return np.array(frames)


def run_one(bvh: str, speed: float, work: Path, rig: str | None = None) -> dict:
    name = Path(bvh).stem
    if any(h in name for h in HELD_OUT):
        raise SystemExit(f"{name} is held out for evaluating the smoothing: not used")
    rec, fused = work / f"{name}.rec", work / f"{name}.fused.jsonl"
    imported = subprocess.run([*CLI, "import", "bvh", bvh, "--out", str(rec)],
                              capture_output=True, text=True, check=True).stdout
    port = free_port()
    server = subprocess.Popen([*CLI, "serve", "--host", "127.0.0.1", "--port", str(port),
                               "--fused", str(fused), "--no-plugins", "--no-self-healing",
                               *(["--rig", rig] if rig else [])],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    time.sleep(1.5)   # the server binds its port (a bench, not a test: no barrier needed)
    subprocess.run([*CLI, "replay", str(rec), "--to", f"127.0.0.1:{port}", "--speed",
                    str(speed), "--quiet"], check=True)
    time.sleep(1.0)
    server.send_signal(signal.SIGINT)
    server_out, _ = server.communicate(timeout=30)
    rows = [json.loads(line) for line in fused.read_text().splitlines()]
    bodies = [np.array(next(iter(r["bodies"].values()))["joints"]) for r in rows
              if r["updated"] and len(r["bodies"]) == 1]
    fused_frames = np.array(bodies)
    sent = recorded_frames(str(rec))
    low = fused_frames[:, FEET, 1].min(axis=1) * 1000
    return {"file": name, "import": " ".join(imported.split("\n")[0].split()[2:]),
            "server": server_out.strip().splitlines()[-1].split("stopped; ")[-1],
            "frames_sent": len(sent), "fused_frames": len(fused_frames),
            "bones_sent_mm": bone_spread(sent), "bones_fused_mm": bone_spread(fused_frames),
            "floor_mm": {"p5": float(np.percentile(low, 5)), "p50": float(np.median(low)),
                         "p95": float(np.percentile(low, 95)), "min": float(low.min())}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--speed", type=float, default=1.0, help="replay speed (default 1)")
    ap.add_argument("--quick", action="store_true", help="replay at 4x (a smoke test)")
    ap.add_argument("--rig", help="the server's rig file (e.g. other smoothing: settings)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    speed = 4.0 if args.quick else args.speed
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        results = [run_one(f, speed, Path(tmp), args.rig) for f in args.files]
    if args.json:
        print(json.dumps({"load": load, "results": results}, indent=1))
        return
    print(f"machine load (1 min) {load:.2f}; replay speed {speed:g}x; server rig: "
          f"{args.rig or 'none (defaults)'}")
    for r in results:
        print(f"\n{r['file']}: {r['import']}; {r['frames_sent']} frames sent, "
              f"{r['fused_frames']} fused with one body; server: {r['server']}")
        print(f"  {'bone':<24} {'sent max-min mm':>16} {'fused max-min mm':>17}")
        for bone in r["bones_sent_mm"]:
            print(f"  {bone:<24} {r['bones_sent_mm'][bone]:16.3f} "
                  f"{r['bones_fused_mm'][bone]:17.3f}")
        f = r["floor_mm"]
        print(f"  lowest foot joint above the floor, mm: p5 {f['p5']:.1f}, p50 {f['p50']:.1f}, "
              f"p95 {f['p95']:.1f}, min {f['min']:.1f}")


if __name__ == "__main__":
    main()
