"""Attacking a running server on loopback: what a stranger can make it do (docs/security.md).

Starts ``python -m stage --quiet serve`` as its own process (from this tree,
or with ``--base DIR`` from another source tree, e.g. the commit before the
change, to measure "before") and plays, on loopback only:

1. reflection: one sensor at 127.0.0.1 streams a person at 30 Hz; a stranger
   at 127.0.0.2 (not in the allow-lists) sends ``/registerView`` naming a
   victim at 127.0.0.3, the same view written 13 ways, and ``/stage/stats``
   queries with the victim's port; prints bytes the victim received per byte
   the stranger sent (the reflection ratio) over ``--window`` seconds;
2. memory and CPU: RSS and idle CPU of the server process at rest, after
   100,000 distinct client ids (``/registerDevice``), and after 30 s of
   30 KB junk drop-counter keys at 1,000/s; idle CPU over 10 s each time;
3. a stray client registering first and going silent: how many frames of a
   real sensor arriving after it are fused (a server with no rig);
4. the ninth, hundredth and thousandth sensor id with self-healing on: does
   the live calibrator (or anything) crash (server log) and is the server
   still fusing.

    python bench/attack.py                 # all four, this tree
    python bench/attack.py --base /tmp/base  # the same against another tree
    python bench/attack.py --quick         # smaller numbers, shorter windows

Loopback only (127.0.0.x). Prints one line per figure and a JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchlib import machine_busy_s, proc_cpu_s

from stage.sensors.protocol import encode_bundle, encode_client_joints, encode_message
from stage.sensors.sim import standing_pose

STRANGER, VICTIM, SENSOR = "127.0.0.2", "127.0.0.3", "127.0.0.1"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``stage serve`` in its own process; stderr kept in a file."""

    def __init__(self, rig_text: str, base: str | None, tmp: Path, name: str) -> None:
        self.port = free_port()
        rig = tmp / f"{name}-rig.yaml"
        rig.write_text(rig_text.replace("PORT", str(self.port)))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if base:
            env["PYTHONPATH"] = base
        self.log_path = tmp / f"{name}.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "stage", "serve", "--rig", str(rig),
                                      "--no-plugins"], env=env, stdout=subprocess.DEVNULL,
                                     stderr=self._log, cwd=tmp)
        deadline = time.monotonic() + 30
        while "listening" not in self.log_path.read_text():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"server did not start: {self.log_path.read_text()[-500:]}")
            time.sleep(0.05)
        self.address = ("127.0.0.1", self.port)

    def rss_mb(self) -> float:
        with open(f"/proc/{self.proc.pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        return float("nan")

    def cpu_percent(self, seconds: float) -> float:
        a = proc_cpu_s(self.proc.pid)
        time.sleep(seconds)
        return 100.0 * (proc_cpu_s(self.proc.pid) - a) / seconds

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self._log.close()


def stats(address: tuple[str, int], timeout: float = 3.0) -> dict | None:
    from pythonosc.osc_message import OscMessage
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        s.settimeout(timeout)
        s.sendto(encode_message("/stage/stats"), address)
        try:
            while True:
                data, _ = s.recvfrom(1 << 20)
                msg = OscMessage(data)
                if msg.address == "/stage/stats":
                    return json.loads(msg.params[0])
        except (socket.timeout, OSError):
            return None


class Streamer(threading.Thread):
    """One sensor at 30 Hz with one person, timetagged."""

    def __init__(self, client: str, address: tuple[str, int], host: str = SENSOR) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.client, self.address = client, address
        self.stop = threading.Event()
        self.frames = 0

    def run(self) -> None:
        self.sock.sendto(encode_message("/registerDevice", self.client, "kinect2"), self.address)
        t0 = time.monotonic()
        k = 0
        while not self.stop.is_set():
            body = standing_pose((0.3 * np.sin(k / 30), 2.5), np.pi)
            data = encode_bundle([encode_client_joints(self.client, 0, body, np.ones(25))],
                                 time.time())
            self.sock.sendto(data, self.address)
            self.frames += 1
            k += 1
            delay = t0 + k / 30 - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)
        self.sock.close()


def reflection(base: str | None, tmp: Path, window: float, allow: bool) -> dict:
    rig = "server: {host: 127.0.0.1, port: PORT}\nreference: k\nsensors: {k: {}}\n"
    if allow:
        rig += "allow: {sensors: [127.0.0.1], views: [127.0.0.1]}\n"
    server = ServerProcess(rig, base, tmp, "reflection")
    victim = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    victim.bind((VICTIM, 0))
    victim.settimeout(0.2)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind((STRANGER, 0))
    got = {"bytes": 0, "datagrams": 0}
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            try:
                data, _ = victim.recvfrom(65536)
            except socket.timeout:
                continue
            got["bytes"] += len(data)
            got["datagrams"] += 1
    reader = threading.Thread(target=receive, daemon=True)
    reader.start()
    sensor = Streamer("k", server.address)
    sensor.start()
    time.sleep(1.0)
    sent = 0
    vport = victim.getsockname()[1]
    ways = [VICTIM, "127.0.0.03", "127.0.0.003", "0x7f000003", "2130706435", "127.0.3",
            "127.3", "0177.0.0.3", "0x7f.0.0.3", "127.0.0x3", "0x7f.0x0.0x0.0x3",
            "0177.0.0.03", "127.000.000.003"]
    for host in ways:
        data = encode_message("/registerView", host, vport)
        stranger.sendto(data, server.address)
        sent += len(data)
    t_end = time.monotonic() + window
    queries = 0
    while time.monotonic() < t_end:
        data = encode_message("/stage/stats", vport)
        stranger.sendto(data, server.address)
        sent += len(data)
        queries += 1
        time.sleep(0.1)
    time.sleep(0.5)
    sensor.stop.set()
    sensor.join(2)
    done.set()
    reader.join(2)
    final = stats(server.address)
    server.stop()
    victim.close()
    stranger.close()
    return {"stranger_sent_bytes": sent, "victim_received_bytes": got["bytes"],
            "victim_received_datagrams": got["datagrams"], "ratio": got["bytes"] / sent,
            "views_registered": None if final is None else len(final.get("views", [])),
            "stats_queries": queries, "window_s": window}


def memory(base: str | None, tmp: Path, ids: int, junk_s: float, junk_rate: int,
           junk_kb: int) -> dict:
    rig = "server: {host: 127.0.0.1, port: PORT}\n"
    server = ServerProcess(rig, base, tmp, "memory")
    out: dict = {"start_rss_mb": round(server.rss_mb(), 1),
                 "start_idle_cpu_percent": round(server.cpu_percent(10.0), 2)}
    socks = []
    for _ in range(64):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    t0 = time.monotonic()
    rate = 6000.0  # per second over 64 sockets: under any per-source limit
    for k in range(ids):
        socks[k % 64].sendto(encode_message("/registerDevice", f"id-{k:06d}", "kinect2"),
                             server.address)
        delay = t0 + (k + 1) / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    time.sleep(2.0)
    s = stats(server.address, 10.0) or {}
    out["ids_sent"] = ids
    out["clients_in_stats"] = len(s.get("clients", {}))
    out["clients_forgotten"] = s.get("counts", {}).get("clients_forgotten")  # None: before
    out["stats_truncated"] = "truncated" in s
    out["after_ids_rss_mb"] = round(server.rss_mb(), 1)
    out["after_ids_idle_cpu_percent"] = round(server.cpu_percent(10.0), 2)
    # junk drop-counter keys: /junk with a fresh 30 KB first argument each time
    rng = np.random.default_rng(0)
    alphabet = np.frombuffer(b"abcdefghijklmnopqrstuvwxyz0123456789", dtype=np.uint8)
    n = int(junk_s * junk_rate)
    t0 = time.monotonic()
    body = alphabet[rng.integers(0, len(alphabet), junk_kb * 1024)].tobytes().decode()
    for k in range(n):
        key = f"{k:08d}" + body[8:]
        socks[k % 64].sendto(encode_message("/junk", key), server.address)
        delay = t0 + (k + 1) / junk_rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    out["junk_sent"] = n
    out["junk_seconds"] = round(time.monotonic() - t0, 1)
    time.sleep(2.0)
    out["after_junk_rss_mb"] = round(server.rss_mb(), 1)
    out["after_junk_idle_cpu_percent"] = round(server.cpu_percent(10.0), 2)
    s = stats(server.address, 10.0)
    out["stats_reply"] = "answered" if s is not None else "no answer"
    if s is not None:
        out["drops_by_reason"] = {r: n for d in s.get("drops", {}).values() for r, n in d.items()}
        out["drop_keys_in_stats"] = len(s.get("drops", {}))
        out["drops_total"] = s.get("drops_total")
        out["stats_truncated_after_junk"] = "truncated" in s
    for sock in socks:
        sock.close()
    server.stop()
    return out


def stray(base: str | None, tmp: Path, seconds: float) -> dict:
    server = ServerProcess("server: {host: 127.0.0.1, port: PORT}\n", base, tmp, "stray")
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.sendto(encode_message("/registerDevice", "stray", "kinect2"), server.address)
    s.close()
    time.sleep(0.3)
    sensor = Streamer("real", server.address)
    sensor.start()
    time.sleep(seconds)
    sensor.stop.set()
    sensor.join(2)
    st = stats(server.address) or {}
    server.stop()
    return {"real_frames_sent": sensor.frames,
            "real_frames_received": st.get("clients", {}).get("real", {}).get("frames"),
            "fused_frames": st.get("counts", {}).get("fused_frames"),
            "reference": st.get("reference")}


def many_ids(base: str | None, tmp: Path, counts: list[int]) -> dict:
    rig = "server: {host: 127.0.0.1, port: PORT}\nreference: s0\nsensors: {s0: {}}\n"
    server = ServerProcess(rig, base, tmp, "many")
    out: dict = {}
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    body = standing_pose((0.0, 2.5), np.pi)
    k = 0
    for target in counts:
        while k < target:
            sock.sendto(encode_client_joints(f"s{k}", 0, body, np.ones(25)), server.address)
            k += 1
            if k % 200 == 0:
                time.sleep(0.05)
        time.sleep(1.0)
        log = server.log_path.read_text()
        found = re.findall(r".*(?:IndexError|it is disabled|live calibrator failed).*", log)
        crashed = bool(found)
        if found:
            out.setdefault("crash_lines", found[:3])
        st = stats(server.address)
        out[f"after_{target}_ids"] = {"server_alive": server.proc.poll() is None,
                                      "calibrator_crash_in_log": crashed,
                                      "stats_answered": st is not None,
                                      "internal_errors": None if st is None else sum(
                                          d.get("internal_error", 0)
                                          for d in st.get("drops", {}).values())}
    sensor = Streamer("s0", server.address)
    sensor.start()
    time.sleep(2.0)
    sensor.stop.set()
    sensor.join(2)
    st = stats(server.address) or {}
    out["s0_fused_after"] = st.get("counts", {}).get("fused_frames")
    sock.close()
    server.stop()
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", help="run the server from this source tree (PYTHONPATH)")
    parser.add_argument("--quick", action="store_true", help="smaller numbers (smoke test)")
    parser.add_argument("--only", choices=["reflection", "memory", "stray", "ids"])
    parser.add_argument("--window", type=float, default=30.0, help="reflection window, s")
    args = parser.parse_args()
    quick = args.quick
    busy0, wall0 = machine_busy_s(), time.monotonic()
    results: dict = {"tree": args.base or "this tree"}
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        if args.only in (None, "reflection"):
            r = reflection(args.base, tmp, 5.0 if quick else args.window, allow=not args.base)
            results["reflection"] = r
            print(f"reflection: the stranger sent {r['stranger_sent_bytes']} B, the victim got "
                  f"{r['victim_received_bytes']} B in {r['victim_received_datagrams']} datagrams "
                  f"over {r['window_s']:g} s: ratio {r['ratio']:.2f}:1 "
                  f"(views registered {r['views_registered']})", flush=True)
        if args.only in (None, "memory"):
            m = memory(args.base, tmp, 10_000 if quick else 100_000, 5.0 if quick else 30.0,
                       1000, 30)
            results["memory"] = m
            print("memory: " + ", ".join(f"{k} {v}" for k, v in m.items()), flush=True)
        if args.only in (None, "stray"):
            s = stray(args.base, tmp, 3.0 if quick else 5.0)
            results["stray"] = s
            print("stray first: " + ", ".join(f"{k} {v}" for k, v in s.items()), flush=True)
        if args.only in (None, "ids"):
            i = many_ids(args.base, tmp, [9, 100, 1000])
            results["ids"] = i
            print("sensor ids: " + json.dumps(i), flush=True)
    results["machine_busy_cores"] = round((machine_busy_s() - busy0) / (time.monotonic() - wall0),
                                          2)
    print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
