"""The webcam client on a real video, into a real server: what arrives, and what each frame costs.

Starts `stage serve --fused` on a free loopback port, runs
`stage client webcam --video FILE` into it (the video's own pace by default,
`--max-speed` for every frame), stops the server and prints:

- the client's summary: frames read, processed, skipped (late), frames with a
  body, hand states sent, and per frame (p50/p95 ms) the video decoding,
  MediaPipe's inference (pose and hand landmarkers) and the stage client's own
  share (colour conversion, joint mapping, hand assignment, OSC encoding,
  sending) - MediaPipe is the reference the client's share is measured beside;
- the server's line (sensor frames in, fused, latency);
- from the fused bodies: frames with a body, bone lengths (median, min, max,
  metres) and the hand states the fused bodies carried.

    python bench/bench_webcam.py [--video FILE] [--speed X | --max-speed] [--people N]
                                 [--repeats N]
    python bench/bench_webcam.py --quick      # one run at max speed (a smoke test)

Needs the webcam extra (pip install -e '.[webcam]').
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VIDEO = ROOT / "tests" / "data" / "dancer.mp4"
CLI = [sys.executable, "-m", "stage"]
BONES = {"head-spine base": ("Head", "SpineBase"), "thigh": ("HipLeft", "KneeLeft"),
         "shin": ("KneeRight", "AnkleRight"), "upper arm": ("ShoulderLeft", "ElbowLeft"),
         "shoulder width": ("ShoulderLeft", "ShoulderRight")}
HAND_NAMES = {0: "unknown", 1: "notTracked", 2: "open", 3: "closed", 4: "lasso"}


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_run(video: str, max_speed: bool, people: int, work: Path, k: int,
            speed: float = 1.0) -> dict:
    from stage.joints import JOINT_INDEX as J
    fused = work / f"fused{k}.jsonl"
    port = free_port()
    server = subprocess.Popen([*CLI, "serve", "--host", "127.0.0.1", "--port", str(port),
                               "--fused", str(fused), "--no-plugins", "--no-self-healing"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    time.sleep(1.5)   # the server binds its port
    client = subprocess.run([*CLI, "client", "webcam", "--video", video, "--to",
                             f"127.0.0.1:{port}", "--id", "bench-cam", "--people", str(people),
                             *(["--max-speed"] if max_speed else ["--speed", str(speed)])],
                            capture_output=True, text=True)
    time.sleep(0.5)
    server.send_signal(signal.SIGINT)
    server_out, _ = server.communicate(timeout=30)
    summary = next((line for line in client.stdout.splitlines()
                    if "frames read" in line), client.stdout + client.stderr)
    rows = [json.loads(line) for line in fused.read_text().splitlines()]
    updated = [r for r in rows if r["updated"]]
    bodies = [b for r in updated for b in r["bodies"].values()]
    lengths = {name: [float(np.linalg.norm(np.subtract(b["joints"][J[a]], b["joints"][J[c]])))
                      for b in bodies] for name, (a, c) in BONES.items()}
    hands = collections.Counter(HAND_NAMES[h] for b in bodies for h in b["hands"])
    times = {m.group(1): (float(m.group(2)), float(m.group(3))) for m in re.finditer(
        r"(decode|MediaPipe|stage client) ([\d.]+)/([\d.]+)", summary)}
    return {"client": summary.split(": ", 1)[-1], "returncode": client.returncode,
            "traceback": "Traceback" in client.stderr or "Logging error" in client.stderr,
            "server": server_out.strip().splitlines()[-1].split("stopped; ")[-1],
            "fused_updates": len(updated), "with_body": sum(1 for r in updated if r["bodies"]),
            "bones": {n: (float(np.median(v)), float(min(v)), float(max(v)))
                      for n, v in lengths.items() if v},
            "hands": dict(hands), "times": times}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--video", default=str(VIDEO))
    ap.add_argument("--max-speed", action="store_true")
    ap.add_argument("--speed", type=float, default=1.0, help="the video's pace (default 1)")
    ap.add_argument("--people", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="one run at max speed")
    args = ap.parse_args()
    repeats, max_speed = (1, True) if args.quick else (args.repeats, args.max_speed)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        runs = [one_run(args.video, max_speed, args.people, Path(tmp), k, args.speed)
                for k in range(repeats)]
    print(f"machine load (1 min) {load:.2f} at the start; {Path(args.video).name}, "
          f"{'max speed' if max_speed else f'{args.speed:g} x its pace'}, up to {args.people} "
          f"people, "
          f"{repeats} run(s)")
    for k, r in enumerate(runs, 1):
        print(f"\nrun {k}: client exit {r['returncode']}, traceback: {r['traceback']}")
        print(f"  client: {r['client']}")
        print(f"  server: {r['server']}")
        print(f"  fused updates {r['fused_updates']}, with a body {r['with_body']}; "
              f"hand states on the fused bodies: {r['hands']}")
        for name, (med, lo, hi) in r["bones"].items():
            print(f"  {name:<16} median {med:.3f} m  min {lo:.3f}  max {hi:.3f}")
    for part in ("decode", "MediaPipe", "stage client"):
        p50s = [r["times"][part][0] for r in runs if part in r["times"]]
        p95s = [r["times"][part][1] for r in runs if part in r["times"]]
        if p50s:
            print(f"{part:<13} ms per frame: p50 {np.median(p50s):.1f} (runs {p50s}), "
                  f"p95 {np.median(p95s):.1f}")
    mp = [r["times"]["MediaPipe"][0] for r in runs if "MediaPipe" in r["times"]]
    own = [r["times"]["stage client"][0] for r in runs if "stage client" in r["times"]]
    if mp and own:
        print(f"stage client's share of MediaPipe's time (p50/p50): "
              f"{np.median(own) / np.median(mp):.1%}")


if __name__ == "__main__":
    main()
