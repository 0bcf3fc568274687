"""``stage replay --max-speed --to`` a running server: is every frame fused, and how fast?

Records D seconds of the simulator's default scenario (3 sensors, one
dancer) and runs, in the same run:

- the reference: the same recording through an engine here on a manual
  clock (``stage replay --offline``'s path), which fuses every frame by
  construction; its fused-frame count is what "every frame fused" means;
- the live path: ``python -m stage serve`` as its own process with the
  recording's rig, and ``python -m stage replay FILE --max-speed --to`` as
  another; the server's ``/stage/stats`` then says how many sensor frames it
  received and how many fusions it made, and the replay says how fast it
  sent (x real time).

``--base DIR`` runs both commands from another source tree (PYTHONPATH), to
measure the same before a change. Loopback only.

    python bench/replay_to_server.py                  # 30 s recording, 3 repeats
    python bench/replay_to_server.py --base /tmp/base
    python bench/replay_to_server.py --quick          # 10 s, 1 repeat
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchlib import machine_busy_s

from stage.app.show import Show, ShowOptions
from stage.sensors.protocol import encode_message
from stage.sensors.recording import read_recording
from stage.sensors.replay import rig_from_meta
from stage.sensors.sim import Simulator


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def query_stats(port: int) -> dict:
    from pythonosc.osc_message import OscMessage
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        s.settimeout(5.0)
        s.sendto(encode_message("/stage/stats"), ("127.0.0.1", port))
        while True:
            msg = OscMessage(s.recvfrom(1 << 20)[0])
            if msg.address == "/stage/stats":
                return json.loads(msg.params[0])


def live(rec: Path, rig: Path, base: str | None, tmp: Path) -> dict:
    port = free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if base:
        env["PYTHONPATH"] = base
    log = open(tmp / "serve.log", "w")
    server = subprocess.Popen([sys.executable, "-m", "stage", "serve", "--rig", str(rig),
                               "--host", "127.0.0.1", "--port", str(port), "--no-plugins",
                               "--no-self-healing"], env=env, stderr=log,
                              stdout=subprocess.DEVNULL, cwd=tmp)
    try:
        deadline = time.monotonic() + 30
        while "listening" not in (tmp / "serve.log").read_text():
            if server.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError((tmp / "serve.log").read_text()[-400:])
            time.sleep(0.05)
        started = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "stage", "replay", str(rec), "--max-speed",
                               "--to", f"127.0.0.1:{port}"], env=env, capture_output=True,
                              text=True, timeout=300, cwd=tmp)  # cwd: not this tree first
        wall = time.monotonic() - started
        time.sleep(0.5)
        stats = query_stats(port)
    finally:
        server.terminate()
        server.wait(10)
        log.close()
    m = re.search(r"in ([0-9.]+) s \(([0-9]+)x real time\)", done.stdout)
    return {"frames_in": stats["counts"]["frames"], "fused": stats["counts"]["fused_frames"],
            "drops": stats["drops_total"], "send_s": float(m.group(1)) if m else None,
            "x_real_time": float(m.group(2)) if m else None, "process_wall_s": round(wall, 2),
            "replay_said": done.stdout.strip().splitlines()[-1]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--base", help="run serve and replay from this source tree")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.repeats = 10.0, 1
    logging.basicConfig(level=logging.ERROR)
    busy0, wall0 = machine_busy_s(), time.monotonic()
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        rec = tmp / "take.rec"
        Simulator("default", seed=5).record(str(rec), duration=args.seconds)
        rig = rig_from_meta(read_recording(str(rec)).meta)
        rig_path = tmp / "rig.yaml"
        rig.port = free_port()
        data = rig.to_dict()
        if args.base:  # an older tree reads only the keys it knew
            for key in ("allow", "limits", "alerts"):
                data.pop(key, None)
            data["clients"] = {k: data["clients"][k] for k in ("timeout_s", "max_messages_per_s")}
        import yaml
        rig_path.write_text(yaml.safe_dump(data, sort_keys=False))
        reference = Show(ShowOptions(replay=str(rec), offline=True, plugins=False,
                                     self_healing=False)).run().stats["counts"]
        runs = [live(rec, rig_path, args.base, tmp) for _ in range(args.repeats)]
    busy = (machine_busy_s() - busy0) / (time.monotonic() - wall0)
    print(f"recording: {args.seconds:g} s, default scenario (3 sensors, 1 dancer); "
          f"tree: {args.base or 'this one'}; machine busy {busy:.2f} of 2 cores")
    print(f"reference (offline engine, every frame fused): {reference['frames']} sensor frames, "
          f"{reference['fused_frames']} fused")
    for k, r in enumerate(runs, 1):
        share = r["fused"] / reference["fused_frames"] if reference["fused_frames"] else 0.0
        pace = (f"sent at {r['x_real_time']:g}x real time ({r['send_s']} s)" if r["x_real_time"]
                else f"prints no pace; the process took {r['process_wall_s']} s, start-up included")
        print(f"live run {k}: replay {pace}; "
              f"server received {r['frames_in']} frames, fused {r['fused']} "
              f"({100 * share:.1f} % of the reference), drops {r['drops']}")
    speeds = [r["x_real_time"] for r in runs if r["x_real_time"]]
    if speeds:
        print(f"median {statistics.median(speeds):.0f}x real time; fused share median "
              f"{100 * statistics.median(r['fused'] / reference['fused_frames'] for r in runs):.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
