"""Benchmark of the running server: latency per input datagram, throughput and CPU over loopback.

For each configuration S sensors x P people, ``stage serve`` runs as its own
process (so its CPU can be read from /proc on its own) with a rig that
calibrates every sensor exactly and lists this script's view socket. A load
generator here plays S Kinect clients at 30 Hz real time: one socket per
sensor, one OSC bundle per frame (capture-time timetag) holding
``/jointCoordinates`` for each of the P people plus ``/handState`` for each
hand. People stand on a grid 1.5 m apart and sway slowly; the sensors stand on
a ring around them and see each person as the simulator's Kinect model does
(``VirtualKinect``: occlusion by their own limbs, inferred joints; range
widened to the ring and each person observed on their own, so every sensor
reports every person every frame). Sensors send spread over the frame period,
as free-running Kinects do, and aligned (all at the same instant): both modes
run by default.

The figure (issue 10): latency per input datagram -- for every skeleton of
every sensor datagram, from the datagram's arrival at the server (read by the
receiver thread) to the first datagram out that includes it (the engine
records it, exactly: it knows which emission folded in which frame; the
server reports the samples since the bench's previous stats query, so the
figure covers the measuring window only). Beside it, in the same run and
under the same load: a do-nothing Python relay with the same receiver thread
-> queue -> sender thread structure, which forwards each datagram and records
the same figure per datagram. Targets: engine minus relay under 1 ms at p50
and under 2 ms at p99 in every configuration; 6 x 6 under 25 % of one core.
Also: the same figure on the injected clock (the engine offline, datagrams fed
on a manual clock): zero by design, no frame waits; send -> fused datagram
received by the bench's view (one-sensor configurations, two loopback hops);
input and output rates, drops, server CPU (and per thread), how late the
generator sent, and the CPU other processes used meanwhile.

Run ``python bench/bench_engine.py`` (all 9 configurations, spread and aligned,
relay and engine: 36 rows, 2 s warm-up + 10 s each), ``--quick`` (1 s + 2 s),
``--configs 6x6,1x1``, ``--modes aligned``, ``--json``. ``--kinect-errors`` feeds the
simulator's whole Kinect model (``ERROR_KINECT``) instead of the rest pose plus noise, so
that a person's views of an instant disagree as real sensors' do. ``--floor`` adds a third
server per configuration, the floor: a relay that decodes every datagram and
sends every skeleton on, re-encoded one datagram each as the engine sends a
fused one, but fuses nothing (``relay_serve``) -- the least any Python server
that keeps stage's wire API costs here. ``--profile DIR`` runs
the server with one cProfile per thread; ``--server-cmd`` benchmarks another
server command (A/B runs); ``--piece YAML`` runs ``stage play YAML`` as the server (the
piece listening on the engine thread, its MIDI written to a file: the performer's case);
``--wait-idle S`` waits for a quiet machine before each configuration. The servers run
from a snapshot of stage/ taken at the start, so one run measures one version of the code
even while it is being edited (``--live`` to use the working tree). PASS/FAIL is printed against the
targets; the exit status does not depend on it.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import queue
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
# the server subprocesses import the snapshot of stage/ taken when the run started
sys.path.insert(0, os.environ.get("STAGE_BENCH_SRC") or str(REPO))

from benchlib import machine_busy_s, proc_cpu_s, wait_idle  # noqa: E402
from pythonosc.osc_message import OscMessage  # noqa: E402
from pythonosc.parsing import ntp  # noqa: E402

from stage.engine.fusion import apply_transform  # noqa: E402
from stage.joints import HAND_STATE_NAMES, HandState  # noqa: E402
from stage.sensors.protocol import (JointCoordinates, decode_datagram, encode_bundle,
                                    encode_client_joints, encode_message)
from stage.rig import Rig, set_calibration  # noqa: E402
from stage.sensors.sim import (KinectModel, VirtualKinect, VirtualPose, ring_poses,  # noqa: E402
                               standing_pose)

FPS = 30.0
DIFF_P50_TARGET_MS = 1.0     # engine minus relay, per input datagram...
DIFF_P99_TARGET_MS = 2.0     # ...in every configuration
CPU_TARGET = 0.25            # fraction of one core...
CPU_TARGET_CONFIG = (6, 6)   # ...for 6 sensors x 6 people
ALL_CONFIGS = [(s, p) for s in (1, 3, 6) for p in (1, 3, 6)]
#: the rows that are the engine (judged against the targets): the rig's default, and each path forced
_ENGINES = ("engine", "native", "python")
_SERVER = {None: "engine", True: "native", False: "python"}    # by Options.native
GRID_M = 1.5                 # people stand this far apart
RING_M = 4.5                 # sensor ring radius around the grid
SWAY_M, SWAY_S = 0.15, 8.0   # each person walks a small circle: radius, period
NOISE_M = 0.005              # per-axis joint noise, from a pre-drawn table
#: the rest observation of each person: no noise or fit error (NOISE_M is added per frame),
#: range widened so the farthest corner of the grid is still seen from across the ring
REST_KINECT = KinectModel(noise_m=0.0, noise_per_m=0.0, fit_bias_m=0.0, far=7.0,
                          surface_bias_m=0.0, swap_per_s=0.0, inferred_off_m=(0.0, 0.0))
NOISE_FRAMES = 64
#: --kinect-errors: the simulator's whole Kinect model instead (bench_engine_inproc's: fit
#: and surface bias, noise growing with range, inferred joints off, limbs swapped now and
#: then; the people observed together, so they hide each other), drawn before the run for
#: one sway period, a seamless loop. Sensors in step then see views of an instant that
#: disagree, which the engine checks and replays (issue 10, stop 39).
ERROR_KINECT = KinectModel(far=7.0)
ERROR_FRAMES = int(round(SWAY_S * FPS))
HAND_CYCLE = (HandState.OPEN, HandState.CLOSED, HandState.LASSO)  # all pad to 8 bytes on the wire
HAND_PERIOD_FRAMES = 60      # a hand changes state every 2 s
BUSY_FRACTION = 0.10         # other processes above this much of a core skew a row


# ------------------------------------------------------------------ scene and rig
def grid_positions(people: int) -> np.ndarray:
    """(P, 2) floor positions (x, z), on a grid GRID_M apart, centred on the origin."""
    cols = min(people, 3)
    rows = -(-people // cols)
    out = [((c - (cols - 1) / 2) * GRID_M, (r - (rows - 1) / 2) * GRID_M)
           for r in range(rows) for c in range(cols)][:people]
    return np.array(out, dtype=float)


def sensor_poses(sensors: int) -> list[VirtualPose]:
    return ring_poses(sensors, radius=RING_M)


def sensor_ids(sensors: int) -> list[str]:
    return [f"bench-{chr(ord('a') + k)}" for k in range(sensors)]


def build_rig(sensors: int, port: int, view: tuple[str, int]) -> Rig:
    """Sensor 0 is the reference and stage space is the floor at the grid centre."""
    poses, ids = sensor_poses(sensors), sensor_ids(sensors)
    rig = Rig(host="127.0.0.1", port=port, reference=ids[0])
    rig.stage_frame = poses[0].to_stage
    inverse_reference = np.linalg.inv(poses[0].to_stage)
    set_calibration(rig, ids[0], np.eye(4), "bench", 1.0, 0.0)
    for sid, p in zip(ids[1:], poses[1:]):
        set_calibration(rig, sid, inverse_reference @ p.to_stage, "bench", 1.0, 0.0)
    rig.views = [view]
    return rig


@dataclass(frozen=True)
class Scene:
    """What every sensor looks at: P people, each with a floor spot, a heading and a sway phase."""

    floor: np.ndarray      # (P, 2) x, z metres, stage space
    headings: np.ndarray   # (P,) radians
    phases: np.ndarray     # (P,) radians

    @classmethod
    def make(cls, people: int, seed: int) -> "Scene":
        rng = np.random.default_rng(seed)
        return cls(grid_positions(people), rng.uniform(0, 2 * np.pi, people),
                   rng.uniform(0, 2 * np.pi, people))

    def sway(self, k: int) -> np.ndarray:
        """(P, 3) stage-space offset of each person at frame ``k``: a slow small circle."""
        a = 2 * np.pi * (k / FPS) / SWAY_S + self.phases
        return np.stack([SWAY_M * np.sin(a), np.zeros_like(a), SWAY_M * np.cos(a)], axis=1)


class SensorLoad:
    """One virtual Kinect: a pre-encoded bundle patched in place every frame.

    The bundle is built once with the project's own encoders; each frame only
    the joint floats (one fancy-indexed numpy write for all people), the
    timetag and, every 2 s, the 8-byte hand-state names are rewritten. The
    people move by a translation in stage space, so each frame is the rest
    observation plus that translation turned into this sensor's axes.
    """

    def __init__(self, sid: str, sensor: VirtualPose, scene: Scene, seed: int,
                 errors: bool = False) -> None:
        self.id = sid
        self.scene = scene
        rng = np.random.default_rng(seed)   # this sensor's own noise only
        people = len(scene.floor)
        truth = [standing_pose(scene.floor[u], scene.headings[u], 0.4, 0.2) for u in range(people)]
        kinect = VirtualKinect(sensor, REST_KINECT, rng)
        seen = [kinect.observe(t, user=u) for u, t in enumerate(truth)]
        if any(v is None for v in seen):
            raise RuntimeError(f"bench scene: {sid} cannot see every person")
        base, conf = zip(*seen)
        self.base = np.array(base)                      # (P, 25, 3) sensor space
        self.conf = np.array(conf)                      # (P, 25) 1 tracked, 0.5 inferred, 0 not
        self.R = sensor.observe(np.eye(3)) - sensor.observe(np.zeros(3))  # stage dir -> sensor dir
        self.noise = rng.normal(0.0, NOISE_M, (NOISE_FRAMES, people, 25, 3))
        self.frames = self.confs = None
        if errors:
            self.frames, self.confs = self._observed(sensor, truth, rng)
        self.hello = [encode_message("/registerDevice", sid, "kinect2-bench")] + [
            encode_message("/newUser", sid, u, *map(float, self.base[u, 0])) for u in range(people)]
        # all 25 joints on the wire, untracked ones too (conf 0), so every bundle has one layout
        messages, joint_at, hand_at = [], [], []
        every = np.ones(25, dtype=bool)
        for u in range(people):
            messages.append(encode_client_joints(sid, u, self.base[u], self.conf[u], every))
            for hand in ("left", "right"):
                messages.append(encode_message("/handState", sid, u, hand, "open"))
        offset = 16  # "#bundle\0" + timetag
        for k, m in enumerate(messages):
            offset += 4
            if k % 3 == 0:
                # /jointCoordinates: address, type tags, client id, user (int), then
                # (name, x, y, z, conf) for each of the 25 joints
                at = 0
                for _ in range(3):
                    at += _padded_len_at(m, at)
                at += 4
                starts = []
                for _ in range(25):
                    at += _padded_len_at(m, at)
                    starts.append(offset + at)
                    at += 16
                joint_at.append(starts)
            else:
                hand_at.append(offset + len(m) - 8)     # the state string is the last 8 bytes
            offset += len(m)
        self.buf = bytearray(encode_bundle(messages, time.time()))
        self.u8 = np.frombuffer(self.buf, dtype=np.uint8)
        starts = np.array(joint_at).reshape(people, 25)
        self.float_index = (starts[..., None] + np.arange(12)).ravel()   # x y z of each joint
        self.conf_index = (starts[..., None] + 12 + np.arange(4)).ravel()  # and its confidence
        self.hand_at = np.array(hand_at).reshape(people, 2)
        self.hand_names = [HAND_STATE_NAMES[s].encode().ljust(8, b"\0") for s in HAND_CYCLE]
        self._hands_frame = -1
        self._check()

    def _observed(self, sensor: VirtualPose, truth: list, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(ERROR_FRAMES, P, 25, 3) joints and (ERROR_FRAMES, P, 25) confidences of the whole
        Kinect model (--kinect-errors); a person the sensor loses keeps their last joints
        with confidence 0."""
        kinect = VirtualKinect(sensor, ERROR_KINECT, rng)
        people = len(truth)
        frames = np.empty((ERROR_FRAMES, people, 25, 3))
        confs = np.zeros((ERROR_FRAMES, people, 25))
        last = self.base.copy()
        for k in range(ERROR_FRAMES):
            sway = self.scene.sway(k)
            for u, seen in enumerate(kinect.observe_all([t + sway[u] for u, t in enumerate(truth)])):
                if seen is not None:
                    last[u], confs[k, u] = seen
            frames[k] = last
        return frames, confs

    def conf_at(self, k: int) -> np.ndarray:
        """(P, 25) the confidences of frame ``k``."""
        return self.conf if self.confs is None else self.confs[k % ERROR_FRAMES]

    def positions(self, k: int) -> np.ndarray:
        """(P, 25, 3) sensor-space joints of frame ``k``."""
        if self.frames is not None:
            return self.frames[k % ERROR_FRAMES]
        return (self.base + (self.scene.sway(k) @ self.R)[:, None, :]
                + self.noise[k % NOISE_FRAMES])

    def prepare(self, k: int) -> None:
        """Write frame ``k`` (positions and hand states) into the bundle; timetag is set at send."""
        self.u8[self.float_index] = self.positions(k).astype(">f4").view(np.uint8).ravel()
        if self.confs is not None:
            self.u8[self.conf_index] = self.conf_at(k).astype(">f4").view(np.uint8).ravel()
        step = k // HAND_PERIOD_FRAMES
        if step != self._hands_frame:
            self._hands_frame = step
            for u, (left, right) in enumerate(self.hand_at):
                for hand, at in enumerate((left, right)):
                    self.buf[at:at + 8] = self.hand_names[(step + u + hand) % 3]

    def stamp(self, wall: float) -> bytearray:
        self.buf[8:16] = ntp.system_time_to_ntp(wall)
        return self.buf

    def _check(self) -> None:
        """The patched bytes must decode, through the server's own decoder, to what we meant."""
        self.prepare(7)
        decoded = decode_datagram(bytes(self.stamp(time.time())), "bench")
        joints = [m for m, _ in decoded.messages if isinstance(m, JointCoordinates)]
        expected = self.positions(7)
        if (decoded.drops or len(joints) != len(self.base)
                or not np.allclose([m.joints for m in joints], expected, atol=1e-5)
                or not np.allclose([m.conf for m in joints], self.conf_at(7))):
            raise RuntimeError(f"bench bundle for {self.id} does not decode as intended: "
                               f"drops {decoded.drops}")
        self._hands_frame = -1


def check_scene(loads: list[SensorLoad], rig: Rig, k: int = 11, tol_m: float = 0.05) -> None:
    """Every sensor must report each person where the rig's calibration says: joints tracked
    by two sensors agree in stage space within noise (the engine's calibration monitor
    rightly leaves out sensors that disagree)."""
    stage = [apply_transform(rig.transform_for(load.id), load.positions(k)) for load in loads]
    for a in range(1, len(loads)):
        both = (loads[0].conf == 1.0) & (loads[a].conf == 1.0)
        err = np.linalg.norm(stage[a] - stage[0], axis=2)[both]
        if err.size and err.max() > tol_m:
            raise RuntimeError(f"bench scene inconsistent: {loads[a].id} and {loads[0].id} disagree "
                               f"by up to {err.max():.3f} m on tracked joints")


def _padded_len_at(message: bytes, at: int) -> int:
    """Length of the 4-byte-padded OSC string starting at ``at``."""
    end = message.index(b"\0", at)
    return (end - at) // 4 * 4 + 4


# ------------------------------------------------------------------ measurement helpers
def _thread_label(name: str) -> str:
    """The columns of the per-thread CPU split: receiver, engine, calibration, the rest."""
    return {"stage-receiver": "receiver", "stage-engine": "engine",
            "stage-calibration": "calibrator"}.get(name, name)


def thread_cpu_s(pid: int) -> dict[int, float]:
    """utime + stime of each thread of a process, seconds, by thread id."""
    out = {}
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            out[int(task)] = proc_cpu_s(f"{pid}/task/{task}")
        except (FileNotFoundError, ProcessLookupError):
            continue
    return out


def source_fingerprint(root: Path) -> str:
    """Short hash of every root/stage/**/*.py (the subpackages too: the engine, the
    calibrator and the receiver live there)."""
    h = hashlib.sha1()
    base = root / "stage"
    for path in sorted(base.rglob("*.py")):
        h.update(str(path.relative_to(base)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:10]


def snapshot_sources(into: str, tree: Path = REPO) -> Path:
    """Copy ``tree``'s stage/ (this checkout's by default) so that every configuration of a
    run measures the same code even while it is being edited; the servers run from the
    copy (cwd and PYTHONPATH). PYTHONPATH given to the bench itself does not choose the
    servers' code: ``--tree`` does."""
    root = Path(into) / "src"
    shutil.copytree(tree / "stage", root / "stage", ignore=shutil.ignore_patterns("__pycache__"))
    return root


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def query_stats(sock: socket.socket, target: tuple[str, int], timeout: float = 2.0) -> dict | None:
    # a late reply to an earlier query (a start-up probe that timed out under load) must not
    # be taken for this one's: it would end the window early (seen once: a row with n = 0)
    sock.setblocking(False)
    try:
        while True:
            sock.recvfrom(1 << 20)
    except (BlockingIOError, OSError):
        pass
    sock.settimeout(timeout)
    sock.sendto(encode_message("/stage/stats"), target)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            data, _ = sock.recvfrom(1 << 20)
        except socket.timeout:
            return None
        try:
            reply = OscMessage(data)
        except Exception:
            continue
        if reply.address == "/stage/stats" and reply.params:
            return json.loads(reply.params[0])
    return None


def pct(values: np.ndarray, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


class ViewSink(threading.Thread):
    """The benchmark's view: timestamps every fused /jointCoordinates datagram (and every
    datagram the relay forwards)."""

    def __init__(self) -> None:
        super().__init__(name="bench-view", daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.address = self.sock.getsockname()[:2]
        self.joint_times: list[float] = []
        self.other = 0
        self._halt = threading.Event()

    def run(self) -> None:
        recv, mono, times = self.sock.recv, time.monotonic, self.joint_times
        while not self._halt.is_set():
            try:
                data = recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            if data.startswith(b"/jointCoordinates") or data.startswith(b"#bundle"):
                times.append(mono())   # a fused skeleton, or a datagram the relay forwarded
            else:
                self.other += 1

    def stop(self) -> None:
        self._halt.set()
        if self.is_alive():
            self.join(timeout=2.0)
        self.sock.close()


class Generator(threading.Thread):
    """Sends every sensor's bundle at its absolute deadline until ``stop_at`` (monotonic)."""

    def __init__(self, loads: list[SensorLoad], target: tuple[str, int], start: float,
                 stop_at: float, aligned: bool) -> None:
        super().__init__(name="bench-generator", daemon=True)
        self.loads, self.target, self.start_at, self.stop_at = loads, target, start, stop_at
        self.aligned = aligned
        self.socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in loads]
        for sock in self.socks:
            sock.bind(("127.0.0.1", 0))
        n_max = int((stop_at - start) * FPS * len(loads)) + 8
        self.sent_at = np.zeros(n_max)       # monotonic time of each send
        self.late = np.zeros(n_max)          # send time - deadline, s
        self.n = 0
        self.errors = 0

    def run(self) -> None:
        for sock, load in zip(self.socks, self.loads):
            for m in load.hello:
                sock.sendto(m, self.target)
        S = len(self.loads)
        mono, wall, sleep = time.monotonic, time.time, time.sleep
        n = 0
        while True:
            k, s = divmod(n, S)
            deadline = self.start_at + k / FPS + (0.0 if self.aligned else s / (FPS * S))
            if deadline >= self.stop_at or n >= len(self.sent_at):
                break
            load = self.loads[s]
            load.prepare(k)                   # encode before the deadline, send on it
            delay = deadline - mono()
            if delay > 0:
                sleep(delay)
            data = load.stamp(wall())
            now = mono()
            try:
                self.socks[s].sendto(data, self.target)
            except OSError:
                self.errors += 1
            self.sent_at[n] = now
            self.late[n] = now - deadline
            n += 1
            self.n = n

    def close(self) -> None:
        for sock in self.socks:
            sock.close()


# ------------------------------------------------------------------ one configuration
@dataclass
class Options:
    warmup: float
    duration: float
    aligned: bool
    profile: str | None
    relay: bool = False        # run the do-nothing relay instead of stage serve
    floor: bool = False        # with relay: the decoding relay (the Python floor), see relay_serve
    server_cmd: list[str] | None = None  # another server command; gets --port P --rig R
    src: Path = REPO                     # where the servers import stage from
    tree: str | None = None              # --tree: the directory src was snapshotted from
    wait_idle: float = 0.0               # max s to wait for an idle machine before each config
    trace: str | None = None             # a directory: run the traced server (stalltrace.py)
    kinect_errors: bool = False          # the whole Kinect model (ERROR_KINECT)
    native: bool | None = None           # fusion.native forced on (rows "native") or off
                                         # (rows "python"); None: the rig's default
    piece: str | None = None             # run `stage play PIECE` (the piece listening, MIDI to
                                         # a file) instead of `stage serve`


def save_lean(rig: Rig, path: str) -> None:
    """Write ``rig`` with only the settings that differ from their defaults, so that a
    ``--tree`` from before a setting was added reads the file too (``Rig.save`` writes
    every setting, and a rig key a tree does not know is refused)."""
    data, default = rig.to_dict(), Rig().to_dict()
    for section in ("clients", "limits", "alerts", "fusion", "smoothing", "forecast"):
        data[section] = {k: v for k, v in data[section].items()
                         if k not in default[section] or default[section][k] != v}
    with open(path, "w", encoding="utf-8") as f:
        yaml.safe_dump(data, f, sort_keys=False)


def run_config(sensors: int, people: int, opt: Options) -> dict:
    scene = Scene.make(people, seed=10 * people)
    loads = [SensorLoad(sid, p, scene, seed=1000 * sensors + 10 * people + k,
                        errors=opt.kinect_errors)
             for k, (sid, p) in enumerate(zip(sensor_ids(sensors), sensor_poses(sensors)))]
    view = ViewSink()
    port = free_udp_port()
    target = ("127.0.0.1", port)
    tmp = tempfile.TemporaryDirectory(prefix="stage-bench-")
    rig_path = os.path.join(tmp.name, "rig.yaml")
    rig = build_rig(sensors, port, view.address)
    if opt.native is not None:
        rig.fusion = dataclasses.replace(rig.fusion, native=opt.native)
    if not opt.kinect_errors:      # (the model's own errors are the point there)
        check_scene(loads, rig)
    save_lean(rig, rig_path)
    log_path = os.path.join(tmp.name, "server.log")
    fingerprint = source_fingerprint(opt.src)
    trace_prefix = None
    if opt.trace and not opt.relay:
        trace_prefix = os.path.join(opt.trace, f"{'aligned' if opt.aligned else 'spread'}-"
                                    f"{sensors}x{people}")
    midi_path = os.path.join(tmp.name, "out.mid")
    play = ["--play", opt.piece, "--midi-file", midi_path] if opt.piece else []
    if opt.server_cmd:
        cmd = opt.server_cmd + ["--port", str(port), "--rig", rig_path]
    elif trace_prefix:
        cmd = [sys.executable, str(Path(__file__).with_name("stalltrace.py")), "_serve",
               trace_prefix, "--port", str(port), "--rig", rig_path] + play
    elif opt.piece:
        cmd = [sys.executable, "-m", "stage.cli", "--quiet", "play", opt.piece, "--midi-file",
               midi_path, "--port", str(port), "--rig", rig_path]
    elif opt.relay:
        cmd = [sys.executable, os.path.abspath(__file__), "_relay-serve", "--port", str(port),
               "--rig", rig_path] + (["--decode"] if opt.floor else [])
    elif opt.profile:
        prof_prefix = os.path.join(opt.profile, f"{sensors}x{people}")
        cmd = [sys.executable, os.path.abspath(__file__), "_profiled-serve", prof_prefix,
               "--port", str(port), "--rig", rig_path]
    else:
        cmd = [sys.executable, "-m", "stage.cli", "--quiet", "serve", "--port", str(port),
               "--rig", rig_path]
    idle_before = wait_idle(opt.wait_idle, threshold=0.05) if opt.wait_idle > 0 else None
    log = open(log_path, "w")
    env = dict(os.environ, PYTHONPATH=str(opt.src), STAGE_BENCH_SRC=str(opt.src))
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=str(opt.src), env=env)
    ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctl.bind(("127.0.0.1", 0))
    gen = None
    try:
        # the snapshot has no numba cache: the first server compiles its kernels (with the
        # native core's, about a minute on this 2-core VM, more under load), which the
        # window does not include
        ready_by = time.monotonic() + 240.0
        while query_stats(ctl, target, timeout=0.2) is None:
            if proc.poll() is not None or time.monotonic() > ready_by:
                raise RuntimeError(f"server did not start: {Path(log_path).read_text()[-2000:]}")
        view.start()
        start = time.monotonic() + 0.05
        window_start, window_end = start + opt.warmup, start + opt.warmup + opt.duration
        gen = Generator(loads, target, start, window_end + 0.3, opt.aligned)
        gen.start()

        time.sleep(max(0.0, window_start - time.monotonic()))
        t0, cpu0, me0, all0 = time.monotonic(), proc_cpu_s(proc.pid), proc_cpu_s(), machine_busy_s()
        threads0 = thread_cpu_s(proc.pid)
        stats0 = query_stats(ctl, target)
        time.sleep(max(0.0, window_end - time.monotonic()))
        t1, cpu1, me1, all1 = time.monotonic(), proc_cpu_s(proc.pid), proc_cpu_s(), machine_busy_s()
        threads1 = thread_cpu_s(proc.pid)
        stats1 = query_stats(ctl, target)
        if trace_prefix:   # the heap census, after the window so that its pause is not in it
            proc.send_signal(signal.SIGUSR1)
        gen.join()
        time.sleep(0.1)
        if trace_prefix:
            np.save(f"{trace_prefix}.gen.npy",
                    np.stack([gen.sent_at[:gen.n], gen.late[:gen.n]], axis=1))
        if stats0 is None or stats1 is None:
            raise RuntimeError("no answer to /stage/stats during the run")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20 if opt.profile else 10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()
        view.stop()
        if gen is not None:
            gen.join(timeout=2.0)
            gen.close()
        ctl.close()
    server_log = Path(log_path).read_text()
    tmp.cleanup()

    span = t1 - t0
    sent_at, late = gen.sent_at[:gen.n], gen.late[:gen.n]
    in_window = (sent_at >= t0) & (sent_at < t1)
    joints_rx = np.array(view.joint_times)
    rx_window = joints_rx[(joints_rx >= t0) & (joints_rx < t1)]
    ext = None
    if sensors == 1 and len(sent_at):
        # one sensor: every fused datagram answers the latest bundle sent (33 ms apart)
        k = np.searchsorted(sent_at, rx_window, side="right") - 1
        ok = k >= 0
        ext = (rx_window[ok] - sent_at[k[ok]]) * 1e3
    c0, c1 = stats0["counts"], stats1["counts"]
    lat = stats1.get("latency_since_last_query_ms") or {"n": 0}
    cpu = (cpu1 - cpu0) / span
    # the server names its threads in /stage/stats (name -> kernel thread id); the others
    # (numpy's BLAS threads, a relay's) keep their ids
    named = {tid: name for name, tid in (stats1.get("threads") or {}).items()}
    tids = sorted(set(threads0) & set(threads1))
    threads = {_thread_label(named.get(t, str(t))): 0.0 for t in tids}
    for t in tids:
        threads[_thread_label(named.get(t, str(t)))] += (threads1[t] - threads0[t]) / span
    result = {
        "server": (("floor" if opt.floor else "relay") if opt.relay
                   else _SERVER[opt.native]),
        "mode": "aligned" if opt.aligned else "spread",
        "config": f"{sensors}x{people}",
        "sensors": sensors, "people": people, "stage_source": fingerprint,
        "piece": None if opt.relay else opt.piece,
        "machine_busy_before": idle_before,
        "window_s": round(span, 3),
        "in_bundles_per_s": in_window.sum() / span,
        "in_skeletons_per_s": in_window.sum() * people / span,
        "out_datagrams_per_s": len(rx_window) / span,
        "server_counts_per_s": {key: (c1[key] - c0[key]) / span for key in c1},
        "drops_window": stats1["drops_total"] - stats0["drops_total"],
        "drops_total": stats1["drops_total"],
        "drops": stats1["drops"],
        # per input datagram (per skeleton in it, for the engine), the window only
        "latency_ms": lat,
        "external_latency_ms": None if ext is None or not len(ext) else {
            "n": int(len(ext)), "p50": pct(ext, 50), "p99": pct(ext, 99), "max": float(ext.max())},
        "server_cpu_core_fraction": cpu,
        "server_thread_cpu_core_fraction": threads,
        "generator_cpu_core_fraction": (me1 - me0) / span,
        # everything else the machine did meanwhile: other processes skew every figure
        "other_cpu_core_fraction": max(0.0, (all1 - all0) - (cpu1 - cpu0) - (me1 - me0)) / span,
        "send_late_ms": {"p50": pct(late[in_window] * 1e3, 50), "p99": pct(late[in_window] * 1e3, 99),
                         "max": float(late[in_window].max() * 1e3) if in_window.any() else None},
        "send_errors": gen.errors,
        "server_exit": proc.returncode,
        # the fold's figures over the window (the native core's among them, if on)
        "fusion_window": _fusion_delta(stats0.get("fusion") or {}, stats1.get("fusion") or {}),
    }
    if server_log.strip():
        result["server_log_tail"] = server_log[-1500:]
    return result


def _fusion_delta(before: dict, after: dict) -> dict:
    """``/stage/stats``' ``fusion`` counts over the window (nested dicts too)."""
    out = {}
    for key, value in after.items():
        if isinstance(value, dict):
            out[key] = _fusion_delta(before.get(key) or {}, value)
        elif isinstance(value, (int, float)) and key != "held":
            out[key] = value - (before.get(key) or 0)
        else:
            out[key] = value
    return out


def verdicts(rows: list[dict]) -> None:
    """Engine minus relay per configuration and mode, and the CPU target; adds to the rows."""
    relays = {(r["mode"], r["config"]): r for r in rows if r["server"] == "relay"}
    for r in rows:
        if r["server"] == "floor":    # for comparison only: no verdict
            relay, lat = relays.get((r["mode"], r["config"])), r["latency_ms"]
            if relay is not None and lat.get("n") and relay["latency_ms"].get("n"):
                r["diff_ms"] = {"p50": lat["p50"] - relay["latency_ms"]["p50"],
                                "p99": lat["p99"] - relay["latency_ms"]["p99"]}
            continue
        if r["server"] not in _ENGINES:
            continue
        relay = relays.get((r["mode"], r["config"]))
        lat = r["latency_ms"]
        if relay is None or not lat.get("n") or not relay["latency_ms"].get("n"):
            r["diff_ms"], r["latency_pass"] = None, False
        else:
            d50 = lat["p50"] - relay["latency_ms"]["p50"]
            d99 = lat["p99"] - relay["latency_ms"]["p99"]
            r["diff_ms"] = {"p50": d50, "p99": d99}
            r["latency_pass"] = d50 < DIFF_P50_TARGET_MS and d99 < DIFF_P99_TARGET_MS
        cfg = (r["sensors"], r["people"])
        r["cpu_pass"] = r["server_cpu_core_fraction"] < CPU_TARGET if cfg == CPU_TARGET_CONFIG else None
        r["verdict"] = "PASS" if r["latency_pass"] and r["cpu_pass"] is not False else "FAIL"


# ------------------------------------------------------------------ the injected clock
def offline_config(sensors: int, people: int, seconds: float, aligned: bool,
                   errors: bool = False) -> dict:
    """The same load fed into an in-process engine on a manual clock, datagram by datagram:
    per input skeleton, arrival -> the emission that includes it, on that clock."""
    from stage.app.offline import feed
    from stage.clock import ManualClock
    from stage.engine.engine import Engine

    scene = Scene.make(people, seed=10 * people)
    loads = [SensorLoad(sid, p, scene, seed=1000 * sensors + 10 * people + k, errors=errors)
             for k, (sid, p) in enumerate(zip(sensor_ids(sensors), sensor_poses(sensors)))]
    rig = build_rig(sensors, 7770, ("127.0.0.1", 9))
    items = [(0.0, (f"10.0.0.{k}", 5000), m) for k, load in enumerate(loads) for m in load.hello]
    epoch = 1_700_000_000.0
    for k in range(int(seconds * FPS)):
        for s, load in enumerate(loads):
            t = 0.1 + k / FPS + (0.0 if aligned else s / (FPS * sensors))
            load.prepare(k)
            load.buf[8:16] = ntp.system_time_to_ntp(epoch + t)
            items.append((t, (f"10.0.0.{s}", 5000), bytes(load.buf)))
    items.sort(key=lambda it: it[0])
    clock = ManualClock(0.0)
    engine = Engine(rig, clock, _NullTransport())
    feed(engine, clock, items)
    samples = engine.latency.count
    lat = engine.latency.summary_ms()
    return {"config": f"{sensors}x{people}", "mode": "aligned" if aligned else "spread",
            "frames": engine.counts["frames"], "samples": samples, "latency_ms": lat,
            "waited": int(np.count_nonzero(engine.latency._buf[:min(samples, len(engine.latency._buf))]))}


class _NullTransport:
    def send(self, data: bytes, address: tuple[str, int]) -> None:
        pass


# ------------------------------------------------------------------ the relay (the reference)
def relay_serve(argv: list[str]) -> int:
    """``bench_engine.py _relay-serve --port P --rig R``: a do-nothing Python relay with the
    server's thread structure (a receiver thread reads and enqueues, a second thread takes
    from a queue.Queue with the engine's 20 ms timeout and forwards every datagram as it is to
    the rig's views). It records, per datagram, arrival -> forwarded: what the two-thread
    design costs on this machine before any decoding or fusion, under the same load.

    With ``--decode`` (the *floor*, ``--floor``): the same threads, but every datagram is
    decoded as the engine decodes it (``decode_datagram``, with the engine's compiled scanner)
    and every skeleton in it is sent on at once, re-encoded as the engine encodes a fused
    skeleton (one ``/jointCoordinates`` datagram per skeleton per view, the compiled encoder);
    one latency sample per skeleton, as the engine records. No calibration, association or
    fusion: what any server that keeps stage's wire API costs in Python on this machine, the
    least the engine could cost."""
    from stage.rig import load_rig
    from stage.stats import LatencyWindow

    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--rig", required=True)
    parser.add_argument("--decode", action="store_true")
    args = parser.parse_args(argv)
    views = load_rig(args.rig).views
    if args.decode:
        from stage.engine import jit
        from stage.engine.output import _encode_joints
        from stage.sensors.messages import JointCoordinates
        from stage.sensors.protocol import decode_datagram
        jit.warm()   # the engine's kernels: the scanner and the encoder
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", args.port))
    sock.settimeout(0.2)
    inbox: queue.Queue = queue.Queue(maxsize=8192)
    stop = threading.Event()
    window = LatencyWindow(32768)
    marks: dict = {}
    counts = {"messages": 0, "frames": 0, "fused_frames": 0, "datagrams_out": 0}

    def receive() -> None:
        while not stop.is_set():
            try:
                data, source = sock.recvfrom(65536)
            except (socket.timeout, OSError):
                continue
            inbox.put((data, source, time.monotonic()))

    def forward() -> None:
        while not stop.is_set():
            try:
                data, source, arrival = inbox.get(timeout=0.02)
            except queue.Empty:
                continue
            counts["messages"] += 1
            if data.startswith(b"/stage/stats"):
                stats = {"counts": dict(counts), "drops": {}, "drops_total": 0,
                         "latency_ms": window.summary_ms(),
                         "latency_since_last_query_ms": window.summary_ms(marks.get(source, 0))}
                marks[source] = window.count
                sock.sendto(encode_message("/stage/stats", json.dumps(stats)), source)
                continue
            if not data.startswith(b"#bundle"):
                continue
            counts["frames"] += 1
            if args.decode:
                for m, _ in decode_datagram(data, f"{source[0]}:{source[1]}").messages:
                    if type(m) is JointCoordinates:
                        out = _encode_joints(m.user, m.joints, m.conf)
                        for view in views:
                            sock.sendto(out, view)
                            counts["datagrams_out"] += 1
                        window.add(time.monotonic() - arrival)
                continue
            for view in views:
                sock.sendto(data, view)
                counts["datagrams_out"] += 1
            window.add(time.monotonic() - arrival)

    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    threads = [threading.Thread(target=receive, daemon=True),
               threading.Thread(target=forward, daemon=True)]
    for thread in threads:
        thread.start()
    while not stop.wait(0.5):
        pass
    for thread in threads:
        thread.join(timeout=1.0)
    sock.close()
    return 0


# ------------------------------------------------------------------ profiled server
def profiled_serve(argv: list[str]) -> int:
    """``bench_engine.py _profiled-serve PREFIX --port P --rig R``: ``stage serve`` with one
    cProfile per server thread (``python -m cProfile`` only sees the main thread, which just
    waits). Wraps, by class, the receiver loop, the engine loop and the live calibrator's
    worker loop, then runs the real CLI; writes PREFIX.<thread>.prof and PREFIX.threads.json."""
    import cProfile
    import importlib

    parser = argparse.ArgumentParser()
    parser.add_argument("prefix")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--rig", required=True)
    args = parser.parse_args(argv)
    thread_cpu: dict[str, float] = {}
    wrapped = []
    for module, cls, method, name in (("stage.sensors.receiver", "Receiver", "run", "receiver"),
                                      ("stage.engine.engine", "Engine", "run", "engine"),
                                      ("stage.calibration.worker", "EngineWorker", "_run",
                                       "calibrator")):
        try:
            owner = getattr(importlib.import_module(module), cls)
            fn = getattr(owner, method)
        except (ImportError, AttributeError):
            # (a renamed loop would otherwise go unprofiled without a word)
            print(f"profiled server: no {module}.{cls}.{method}; its thread is not profiled",
                  file=sys.stderr)
            continue

        def run(*a, _fn=fn, _name=name, **k):
            # CPU time of this thread: the wall clock would charge the GIL waits (other
            # threads running) to whatever function was waiting
            prof = cProfile.Profile(time.thread_time)
            prof.enable()
            try:
                return _fn(*a, **k)
            finally:
                prof.disable()
                thread_cpu[_name] = time.thread_time()
                prof.dump_stats(f"{args.prefix}.{_name}.prof")

        setattr(owner, method, run)
        wrapped.append(name)
    from stage.cli.main import main as stage_main
    try:
        return stage_main(["--quiet", "serve", "--port", str(args.port), "--rig", args.rig])
    finally:
        Path(f"{args.prefix}.threads.json").write_text(json.dumps(thread_cpu))


def print_profile(prefix: str, top: int = 25) -> None:
    import pstats
    threads = Path(f"{prefix}.threads.json")
    if threads.exists():
        print(f"thread CPU (s, under the profiler): {threads.read_text()}")
    for name in ("engine", "receiver", "calibrator"):
        path = f"{prefix}.{name}.prof"
        if not os.path.exists(path):
            print(f"(no profile for the {name} thread at {path})")
            continue
        for key in ("cumulative", "tottime"):
            print(f"\n===== {os.path.basename(prefix)} {name} thread: top {top} by {key} =====")
            pstats.Stats(path, stream=sys.stdout).strip_dirs().sort_stats(key).print_stats(top)


# ------------------------------------------------------------------ output
def fmt(v: float | None, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def print_table(results: list[dict], offline: list[dict], opt: Options) -> None:
    print(f"stage engine bench: {FPS:.0f} Hz per sensor, warm-up {opt.warmup:g} s, window "
          f"{opt.duration:g} s, {os.cpu_count()} cores, python {sys.version.split()[0]}"
          f"{'; the whole Kinect model (--kinect-errors)' if opt.kinect_errors else ''}"
          f"{f'; server: stage play {os.path.basename(opt.piece)}' if opt.piece else ''}")
    print(f"targets: per input datagram, engine minus relay p50 < {DIFF_P50_TARGET_MS:g} ms and "
          f"p99 < {DIFF_P99_TARGET_MS:g} ms (every config); server CPU < {100 * CPU_TARGET:.0f} % "
          f"of a core at {CPU_TARGET_CONFIG[0]}x{CPU_TARGET_CONFIG[1]}")
    head = (f"{'mode':>7} {'config':>6} {'server':>6} | {'in dg/s':>7} {'skel/s':>6} | "
            f"{'out dg/s':>8} | {'drops':>5} | {'latency p50/p99/max ms':>22} {'(n)':>7} | "
            f"{'minus relay p50/p99':>19} | {'ext p50/p99':>11} | {'CPU %core (rx+eng+cal+rest)':>27} | "
            f"{'gen late p99':>12} | {'other %':>7} | verdict")
    print(head)
    print("-" * len(head))
    for r in results:
        lat = r["latency_ms"]
        lat_s = (f"{fmt(lat.get('p50'))}/{fmt(lat.get('p99'))}/{fmt(lat.get('max'))}"
                 if lat.get("n") else "-")
        diff = r.get("diff_ms")
        diff_s = f"{diff['p50']:+.2f}/{diff['p99']:+.2f}" if diff else ""
        ext = r["external_latency_ms"]
        ext_s = f"{fmt(ext['p50'])}/{fmt(ext['p99'])}" if ext else "-"
        cpu = f"{100 * r['server_cpu_core_fraction']:.1f}" + ("*" if r.get("cpu_pass") is not None else "")
        th = r["server_thread_cpu_core_fraction"]
        if "receiver" in th and "engine" in th:
            rest = sum(v for k, v in th.items() if k not in ("receiver", "engine", "calibrator"))
            cpu += (f" ({100 * th['receiver']:.0f}+{100 * th['engine']:.0f}+"
                    f"{100 * th.get('calibrator', 0.0):.0f}+{100 * rest:.0f})")
        notes = []
        if r["server"] in _ENGINES and not r.get("latency_pass", True):
            notes.append("latency")
        if r.get("cpu_pass") is False:
            notes.append("CPU")
        if (r["send_late_ms"]["p99"] or 0) > 2.0:
            notes.append("generator late")
        if r["other_cpu_core_fraction"] > BUSY_FRACTION:
            notes.append("machine busy")
        verdict = r.get("verdict", "ref") + (f" ({', '.join(notes)})" if notes else "")
        print(f"{r['mode']:>7} {r['config']:>6} {r['server']:>6} | {r['in_bundles_per_s']:7.1f} "
              f"{r['in_skeletons_per_s']:6.0f} | {r['out_datagrams_per_s']:8.1f} | "
              f"{r['drops_window']:5d} | {lat_s:>22} {'(' + str(lat.get('n', 0)) + ')':>7} | "
              f"{diff_s:>19} | {ext_s:>11} | {cpu:>27} | "
              f"{fmt(r['send_late_ms']['p99'], '.3f'):>9} ms | "
              f"{100 * r['other_cpu_core_fraction']:7.1f} | {verdict}")
    print("latency: per input datagram (for the engine: per skeleton in it), its arrival at the "
          "server -> the first datagram out that includes it, samples of the window only;\n"
          "minus relay: the engine's (or floor's) p50/p99 minus the relay's in the same mode and "
          "config; floor (--floor): a relay that decodes and re-encodes every skeleton; ext: "
          "send -> received by the bench's view, one-sensor configs only;\n"
          "CPU: server process utime+stime over the window (* = the config the CPU target applies "
          "to; rx+eng+cal+rest: its receiver, engine, live calibrator and other threads, as the "
          "server names them in /stage/stats);\n"
          "gen late: p99 of send time - deadline; other %: CPU other processes used meanwhile, in % "
          "of a core (> 10: the figures are skewed by other load).")
    gen = max((r["generator_cpu_core_fraction"] for r in results), default=0.0)
    print(f"bench process CPU (generator + view) at most {100 * gen:.1f} % of a core.")
    for r in results:
        if r["drops_total"]:
            print(f"  drops {r['mode']} {r['config']} {r['server']}: {r['drops']}")
        native = (r.get("fusion_window") or {}).get("native")
        if native:
            fw = r["fusion_window"]
            print(f"  native core {r['mode']} {r['config']} over the window: {native}; "
                  f"replays {fw.get('replays')}, late {fw.get('late')}")
        if r.get("server_log_tail"):
            print(f"server log ({r['mode']} {r['config']} {r['server']}):\n{r['server_log_tail']}")
    sources = sorted({r["stage_source"] for r in results})
    if len(sources) > 1:
        print(f"WARNING: stage/**/*.py changed during the run (source hashes {', '.join(sources)}): "
              "rows measured different code.")
    elif sources:
        print(f"stage/**/*.py source hash: {sources[0]}"
              f" ({'working tree' if opt.src == REPO else 'snapshot taken at the start'}"
              f"{'' if opt.tree is None else f' of {opt.tree}'})")
    if offline:
        print("\nthe same load on the injected clock (engine offline, datagrams fed on a manual "
              "clock): per input skeleton, arrival -> emission")
        for o in offline:
            lat = o["latency_ms"]
            print(f"  {o['mode']:>7} {o['config']:>5}: {o['samples']} samples, p50/p99/max "
                  f"{fmt(lat.get('p50'), '.3f')}/{fmt(lat.get('p99'), '.3f')}/"
                  f"{fmt(lat.get('max'), '.3f')} ms, frames that waited: {o['waited']}")
        zero = all(o["waited"] == 0 for o in offline)
        print(f"  zero waiting by design: {'PASS' if zero else 'FAIL'}")
    engines = [r for r in results if r["server"] == "engine"]
    print("overall:", "PASS" if engines and all(r["verdict"] == "PASS" for r in engines) else "FAIL")
    for server, what in (("native", "fusion.native on"), ("python", "the Python path")):
        rows = [r for r in results if r["server"] == server]
        if rows:
            print(f"overall with {what}:",
                  "PASS" if all(r["verdict"] == "PASS" for r in rows) else "FAIL")


def parse_configs(text: str) -> list[tuple[int, int]]:
    out = []
    for item in text.split(","):
        s, _, p = item.strip().lower().partition("x")
        if not (s.isdigit() and p.isdigit()) or not 1 <= int(s) <= 26 or not 1 <= int(p) <= 6:
            raise argparse.ArgumentTypeError(f"'{item}' is not SxP (sensors 1-26, people 1-6)")
        out.append((int(s), int(p)))
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "_profiled-serve":
        return profiled_serve(argv[1:])
    if argv and argv[0] == "_relay-serve":
        return relay_serve(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=parse_configs, default=ALL_CONFIGS,
                        help="comma-separated SxP, e.g. 6x6,1x1 (default: 1,3,6 x 1,3,6)")
    parser.add_argument("--modes", default="spread,aligned",
                        help="spread (sensors spread over the frame period), aligned (all at once)")
    parser.add_argument("--duration", type=float, default=10.0, help="steady window per config, s")
    parser.add_argument("--warmup", type=float, default=2.0, help="warm-up per config, s")
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 s warm-up, 2 s window")
    parser.add_argument("--no-relay", action="store_true", help="skip the relay rows (no verdict)")
    parser.add_argument("--no-offline", action="store_true", help="skip the injected-clock rows")
    parser.add_argument("--floor", action="store_true",
                        help="also run the floor: a relay that decodes every datagram and sends "
                             "every skeleton on re-encoded, as the engine does, without fusing")
    parser.add_argument("--profile", metavar="DIR",
                        help="run the server with one cProfile per thread; write and print the "
                             "hot spots (figures are then inflated by the profiler)")
    parser.add_argument("--server-cmd", metavar="CMD",
                        help="benchmark this command instead of stage serve (e.g. an instrumented "
                             "or patched copy, for A/B runs); '--port P --rig R' is appended, and "
                             "it must stop on SIGTERM")
    parser.add_argument("--piece", metavar="YAML",
                        help="run `stage play YAML` as the server (the piece listening on the "
                             "engine thread, its MIDI written to a file) instead of `stage serve`: "
                             "the performer's case; works with --trace")
    parser.add_argument("--wait-idle", type=float, default=0.0, metavar="S",
                        help="before each config wait up to S s for the machine to be idle "
                             "(other processes under 5 %% of a core over 2 s)")
    parser.add_argument("--retry-busy", type=int, default=0, metavar="N",
                        help="run a config again (up to N times) when other processes used more "
                             "than 10 %% of a core during its window; the last try is kept")
    parser.add_argument("--tree", metavar="DIR",
                        help="run the servers from a snapshot of DIR/stage (e.g. a `git archive` "
                             "of another commit) instead of this checkout's, for an A/B")
    parser.add_argument("--live", action="store_true",
                        help="run the servers from the working tree instead of a snapshot of "
                             "stage/ taken at the start")
    parser.add_argument("--trace", metavar="DIR",
                        help="run a traced server (bench/stalltrace.py: garbage collections, "
                             "each latency sample, every thread's CPU each 10 ms, the tracked "
                             "heap) and keep the traces in DIR; `python bench/stalltrace.py DIR` "
                             "prints who held the engine off")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--native", action="store_true",
                        help="also run each configuration's engine with fusion.native on (the "
                             "native core; rows 'native', judged as the engine's)")
    parser.add_argument("--python-path", action="store_true",
                        help="also run each configuration's engine with fusion.native off "
                             "(the Python path alone; rows 'python', judged as the engine's)")
    parser.add_argument("--kinect-errors", action="store_true",
                        help="the simulator's whole Kinect model (bias, swapped limbs, inferred "
                             "joints off): views of an instant that disagree")
    args = parser.parse_args(argv)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in ("spread", "aligned") for m in modes):
        parser.error("--modes takes spread and/or aligned")
    if args.quick:
        args.warmup, args.duration = 1.0, 2.0
    if args.profile:
        os.makedirs(args.profile, exist_ok=True)
        args.profile = os.path.abspath(args.profile)
    if args.trace:
        os.makedirs(args.trace, exist_ok=True)
        args.trace = os.path.abspath(args.trace)
    tree = REPO if args.tree is None else Path(args.tree).resolve()
    if not (tree / "stage" / "__init__.py").is_file():
        parser.error(f"--tree {args.tree}: no stage/ package there")
    if args.live and args.tree:
        parser.error("--live runs this checkout's working tree; --tree takes a snapshot of another")
    snapshot_dir = None if args.live else tempfile.TemporaryDirectory(prefix="stage-bench-src-")
    src = REPO if snapshot_dir is None else snapshot_sources(snapshot_dir.name, tree)

    def run(sensors: int, people: int, o: Options) -> dict:
        label = f"{'aligned' if o.aligned else 'spread'} {sensors}x{people} " \
                f"{('floor' if o.floor else 'relay') if o.relay else _SERVER[o.native]}"
        for attempt in range(args.retry_busy + 1):
            print(f"running {label} ...", file=sys.stderr, flush=True)
            result = run_config(sensors, people, o)
            result["attempts"] = attempt + 1
            if result["other_cpu_core_fraction"] <= BUSY_FRACTION:
                break
            print(f"  other processes used {100 * result['other_cpu_core_fraction']:.0f} % of a "
                  "core meanwhile", file=sys.stderr, flush=True)
        return result

    results, offline = [], []
    server_cmd = shlex.split(args.server_cmd) if args.server_cmd else None
    piece = os.path.abspath(args.piece) if args.piece else None
    if piece and not os.path.isfile(piece):
        parser.error(f"--piece {args.piece}: no such file")
    if piece and server_cmd:
        parser.error("--piece runs stage play; --server-cmd another server: give one")
    for mode in modes:
        aligned = mode == "aligned"
        engine_opt = Options(args.warmup, args.duration, aligned, args.profile,
                             server_cmd=server_cmd, src=src, wait_idle=args.wait_idle,
                             trace=args.trace, kinect_errors=args.kinect_errors,
                             piece=piece)
        relay_opt = Options(args.warmup, args.duration, aligned, None, relay=True, src=src,
                            wait_idle=args.wait_idle, kinect_errors=args.kinect_errors)
        floor_opt = dataclasses.replace(relay_opt, floor=True)
        for sensors, people in args.configs:
            if not args.no_relay:
                results.append(run(sensors, people, relay_opt))
            if args.floor:
                results.append(run(sensors, people, floor_opt))
            results.append(run(sensors, people, engine_opt))
            if args.native:
                results.append(run(sensors, people, dataclasses.replace(engine_opt, native=True)))
            if args.python_path:
                results.append(run(sensors, people,
                                   dataclasses.replace(engine_opt, native=False)))
        if not args.no_offline:
            for sensors, people in args.configs:
                offline.append(offline_config(sensors, people, min(args.duration, 4.0), aligned,
                                              args.kinect_errors))
    verdicts(results)
    if args.json:
        print(json.dumps({"fps": FPS, "warmup_s": args.warmup, "duration_s": args.duration,
                          "kinect_errors": args.kinect_errors,
                          "cores": os.cpu_count(),
                          "targets": {"minus_relay_p50_ms": DIFF_P50_TARGET_MS,
                                      "minus_relay_p99_ms": DIFF_P99_TARGET_MS,
                                      "cpu_core_fraction": CPU_TARGET,
                                      "cpu_config": "%dx%d" % CPU_TARGET_CONFIG},
                          "results": results, "offline": offline}, indent=2, default=_json_default))
    else:
        print_table(results, offline, Options(args.warmup, args.duration, False, None, src=src,
                                              tree=args.tree, kinect_errors=args.kinect_errors,
                                              piece=piece))
    if args.profile:
        for sensors, people in args.configs:
            print_profile(os.path.join(args.profile, f"{sensors}x{people}"))
    if snapshot_dir is not None:
        snapshot_dir.cleanup()
    return 0


def _json_default(v):
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, np.bool_):
        return bool(v)
    raise TypeError(type(v).__name__)


if __name__ == "__main__":
    raise SystemExit(main())
