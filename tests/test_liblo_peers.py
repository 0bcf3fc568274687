"""The server against a real, independent OSC implementation: liblo's oscsend and oscdump.

oscsend plays a Kuatro sensor client (every message from a new process and
a new source port, as a separate program would); oscdump is registered as a
view and prints what the server sends. Skipped where liblo-tools is missing.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import threading
import time

import numpy as np
import pytest

from helpers import (LOCALHOST, TIMEOUT_S, Peer, Sensor, free_udp_port, joint_groups,
                     query_stats, register_view, sync)
from stage.app.server import Server
from stage.joints import JOINT_INDEX
from stage.rig import Rig
from stage.sensors.sim import standing_pose

pytestmark = pytest.mark.integration

#: Enough joints that the torso is defined: all five TORSO joints plus the head and a hand.
SENT_JOINTS = ("SpineBase", "SpineMid", "SpineShoulder", "HipLeft", "HipRight", "Head",
               "HandLeft", "HandRight")
TORSO_NAMES = ("SpineBase", "SpineMid", "SpineShoulder", "HipLeft", "HipRight")


def _require(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        pytest.skip(f"{tool} not installed: apt-get install liblo-tools")
    return path


@pytest.fixture
def oscsend():
    exe = _require("oscsend")

    def send(port: int, address: str, types: str, *args: object) -> None:
        """``oscsend HOST PORT ADDRESS TYPES ARGS...``; one process per message."""
        cmd = [exe, LOCALHOST, str(port), address, types, *map(str, args)]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S)
        assert done.returncode == 0, f"{cmd} failed: {done.stderr.strip()}"

    return send


class Dump:
    """``oscdump PORT`` in a subprocess; a thread collects its stdout lines."""

    def __init__(self, exe: str, port: int) -> None:
        self.port = port
        line_buffered = "-L" in subprocess.run([exe, "-h"], capture_output=True,
                                               text=True).stdout
        cmd = [exe, "-L", str(port)] if line_buffered else ["stdbuf", "-oL", exe, str(port)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def find(self, predicate, timeout: float) -> "DumpLine | None":
        """The first printed message satisfying ``predicate``, waiting up to ``timeout``."""
        deadline = time.monotonic() + timeout
        i = 0
        with self._cond:
            while True:
                while i < len(self.lines):
                    parsed = parse_dump_line(self.lines[i])
                    i += 1
                    if parsed is not None and predicate(parsed):
                        return parsed
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.proc.poll() is not None:
                    return None
                self._cond.wait(min(remaining, 0.2))

    def wait_for(self, predicate, timeout: float = TIMEOUT_S, what: str = "a line") -> "DumpLine":
        found = self.find(predicate, timeout)
        if found is None:
            raise AssertionError(
                f"oscdump printed no {what} within {timeout} s (exit code {self.proc.poll()});"
                " it printed:\n  " + "\n  ".join(self.lines[-20:]))
        return found

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)
        self._reader.join(timeout=5)
        self.proc.stdout.close()
        self.proc.stderr.close()


class DumpLine:
    def __init__(self, address: str, types: str, args: list) -> None:
        self.address, self.types, self.args = address, types, args

    def __repr__(self) -> str:
        return f"DumpLine({self.address} {self.types} {self.args})"


_TOKEN = re.compile(r'"[^"]*"|\S+')


def parse_dump_line(line: str) -> DumpLine | None:
    """``[timetag] /address types arg...`` -> DumpLine; strings come quoted ("left")."""
    tokens = _TOKEN.findall(line)
    starts = [k for k, tok in enumerate(tokens) if tok.startswith("/")]
    if not starts:
        return None
    k = starts[0]
    address, types = tokens[k], (tokens[k + 1] if k + 1 < len(tokens) else "")
    values = tokens[k + 2:]
    if len(values) != len(types):
        return None
    args: list = []
    for tag, tok in zip(types, values):
        if tag == "i":
            args.append(int(tok))
        elif tag in "fd":
            args.append(float(tok))
        elif tag == "s":
            assert tok.startswith('"') and tok.endswith('"'), line
            args.append(tok[1:-1])
        else:
            args.append(tok)
    return DumpLine(address, types, args)


@pytest.fixture
def dump():
    exe = _require("oscdump")
    dumper = Dump(exe, free_udp_port())
    try:
        # ready when it prints what we send it (its socket opens after the process starts)
        with Peer() as probe:
            deadline = time.monotonic() + TIMEOUT_S
            while dumper.find(lambda d: d.address == "/stage/probe", timeout=0.1) is None:
                assert time.monotonic() < deadline and dumper.proc.poll() is None, \
                    f"oscdump on port {dumper.port} never printed our probe: {dumper.lines}"
                probe.send_message((LOCALHOST, dumper.port), "/stage/probe", 1)
        yield dumper
    finally:
        dumper.close()


@pytest.fixture
def server():
    with Server(Rig(), LOCALHOST, 0) as srv:
        yield srv


def _skeleton() -> dict[str, np.ndarray]:
    joints = standing_pose((0.4, 2.3), 0.2, left_arm=1.0, right_arm=0.3)
    # three decimals: exact enough to survive oscsend's text -> float32 unchanged to 1e-6
    return {name: np.round(joints[JOINT_INDEX[name]], 3) for name in SENT_JOINTS}


def test_oscsend_sensor_and_oscdump_view(server, dump, oscsend):
    port = server.address[1]
    oscsend(port, "/registerView", "si", LOCALHOST, dump.port)
    oscsend(port, "/registerDevice", "ss", "kinect-x", "kinect2")
    skeleton = _skeleton()
    centre = np.mean([skeleton[n] for n in ("SpineBase", "SpineMid", "SpineShoulder",
                                             "HipLeft", "HipRight")], axis=0)
    oscsend(port, "/newUser", "sifff", "kinect-x", 1, *(f"{v:.3f}" for v in centre))
    args: list[object] = ["kinect-x", 1]
    for name, xyz in skeleton.items():
        args += [name, *(f"{v:.3f}" for v in xyz), "1.0"]
    oscsend(port, "/jointCoordinates", "si" + "sffff" * len(skeleton), *args)

    new = dump.wait_for(lambda d: d.address == "/newUser", what="/newUser")
    assert new.types == "ifff"
    pid = new.args[0]
    assert isinstance(pid, int) and pid >= 1
    assert np.allclose(new.args[1:], centre, atol=1e-3)

    line = dump.wait_for(lambda d: d.address == "/jointCoordinates", what="/jointCoordinates")
    assert line.types == "i" + "sffff" * len(skeleton)
    assert line.args[0] == pid
    rest = line.args[1:]
    got = {rest[k]: (np.array(rest[k + 1:k + 4]), rest[k + 4]) for k in range(0, len(rest), 5)}
    assert sorted(got) == sorted(skeleton)
    for name, xyz in skeleton.items():
        # the Kalman filter's first update is the measurement itself
        assert np.allclose(got[name][0], xyz, atol=1e-3), (name, got[name][0], xyz)
        assert got[name][1] == pytest.approx(1.0)

    oscsend(port, "/handState", "siss", "kinect-x", 1, "left", "open")
    hand = dump.wait_for(lambda d: d.address == "/handState" and d.args[1:] == ["left", "open"],
                         what='/handState ... "left" "open"')
    assert hand.types == "iss" and hand.args[0] == pid

    stats = query_stats(server.address)
    assert stats["clients"]["kinect-x"]["type"] == "kinect2"
    assert stats["clients"]["kinect-x"]["frames"] == 1
    assert stats["drops_total"] == 0


def test_oscsend_typetag_variants_are_accepted(server, dump, oscsend):
    """Other numeric typetags a client may use: float user id, double coordinates,
    int confidence, hand and state as codes."""
    port = server.address[1]
    oscsend(port, "/registerView", "si", LOCALHOST, dump.port)
    skeleton = _skeleton()
    args: list[object] = ["kinect-y", "3.0"]
    for name, xyz in skeleton.items():
        args += [name, *(f"{v:.3f}" for v in xyz), "1"]
    # f user id, d coordinates, i confidence
    oscsend(port, "/jointCoordinates", "sf" + "sdddi" * len(skeleton), *args)
    line = dump.wait_for(lambda d: d.address == "/jointCoordinates", what="/jointCoordinates")
    pid = line.args[0]
    rest = line.args[1:]
    got = {rest[k]: np.array(rest[k + 1:k + 4]) for k in range(0, len(rest), 5)}
    for name, xyz in skeleton.items():
        assert np.allclose(got[name], xyz, atol=1e-3), name
    oscsend(port, "/handState", "siii", "kinect-y", 3, 1, 3)  # right hand, closed
    dump.wait_for(lambda d: d.address == "/handState" and d.args == [pid, "right", "closed"],
                  what='/handState ... "right" "closed"')
    assert query_stats(server.address)["drops_total"] == 0


def test_oscdump_registered_with_a_forecast_gets_each_body_predicted_ahead(server, dump,
                                                                          oscsend):
    """A liblo view registered (by oscsend) for a forecast -- rate 0: every update, then
    0.05 s -- gets every fused update as a plain view does, each body predicted 50 ms past
    its capture time: a person walking at 1 m/s along x arrives 5 cm further along.

    The sensor sends real time-stamped bundles at 30 Hz (its capture times), so the
    filter's velocity is that of the walk and not of the sending process's jitter."""
    port = server.address[1]
    oscsend(port, "/registerView", "siif", LOCALHOST, dump.port, 0, 0.05)
    speed, horizon, frames = 1.0, 0.05, 45
    with Peer() as plain, Sensor("kinect-f", server.address) as sensor:
        register_view(server.address, plain)
        sensor.register()
        start = standing_pose((-0.7, 2.5), 0.0)
        t0 = time.time() + 0.05
        for k in range(frames):
            delay = t0 + k / 30 - time.time()
            if delay > 0:
                time.sleep(delay)
            joints = start + np.array([speed * k / 30, 0.0, 0.0])
            sensor.bundle([sensor.joints_message(1, joints)], t0 + k / 30)
        stats = sync(server.address, plain)
    plain_lines = [m for m in plain.received if m.address == "/jointCoordinates"]
    assert len(plain_lines) == frames, "every frame is one update of the plain view"
    forecast_lines = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(forecast_lines) < frames and time.monotonic() < deadline:
        time.sleep(0.05)
        forecast_lines = [p for p in map(parse_dump_line, list(dump.lines))
                          if p is not None and p.address == "/jointCoordinates"]
    assert len(forecast_lines) == frames, "the forecast view gets every update too"
    assert stats["forecast"]["views_s"] == {f"{LOCALHOST}:{dump.port}": horizon}

    measured = joint_groups(plain_lines[-1])
    rest = forecast_lines[-1].args[1:]
    ahead = {rest[k]: np.array(rest[k + 1:k + 4]) for k in range(0, len(rest), 5)}
    assert forecast_lines[-1].args[0] == plain_lines[-1].params[0]
    assert sorted(ahead) == sorted(measured)
    lead = np.array([ahead[name] - measured[name][0] for name in TORSO_NAMES])
    # the filter has had 1.5 s of a steady walk: its velocity is the walk's (measured:
    # 0.0500 m ahead on every torso joint). A fifth of that is allowed: on a loaded machine
    # the clock offset estimate can step (a datagram that arrived faster than any before),
    # and the capture times with it, late in the walk
    assert np.allclose(lead[:, 0], speed * horizon, atol=0.01), lead
    assert np.allclose(lead[:, 1:], 0.0, atol=0.002), lead
    # the plain view's bodies are where the sensor saw them (smoothed, a steady walk)
    last = start + np.array([speed * (frames - 1) / 30, 0.0, 0.0])
    for name in TORSO_NAMES:
        assert np.allclose(measured[name][0], last[JOINT_INDEX[name]], atol=0.02), name

