"""The live monitor in a real browser: headless Chromium driven through the DevTools protocol.

Debian's ``chromium`` with a fresh profile; the protocol is spoken over a
minimal WebSocket client written here (standard library only, nothing
downloaded). The page must load, draw a body that moves between two frames,
light a zone when a ``ZoneState`` says it is occupied, show a sensor whose
fitness fell in red with the reason, and keep up with six people at 30 frames
a second. A screenshot is kept in tests/artifacts/monitor.png (and the draw
timings in tests/artifacts/monitor_perf.json).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from stage.sensors.sim import standing_pose
from stage.clock import ManualClock
from stage.frames import Body, FusedFrame
from stage.events import SectionChange, ZoneState
from stage.joints import HandState
from stage.views import SensorStatus, Status, ViewHost

pytestmark = pytest.mark.integration

ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--window-size=1400,1000", "--remote-debugging-port=0"]
BODY_BLUE = (79, 195, 247)   # the first colour of the page's palette (#4fc3f7)


def find_chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no Chromium: apt-get install chromium")


class DevTools:
    """Just enough WebSocket (RFC 6455) for the DevTools protocol: text frames, masked sends."""

    def __init__(self, ws_url: str) -> None:
        rest = ws_url.split("://", 1)[1]
        hostport, path = rest.split("/", 1)
        host, port = hostport.rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /{path} HTTP/1.1\r\nHost: {hostport}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           "Sec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            assert chunk, "DevTools closed the connection during the handshake"
            head += chunk
        assert head.split(b"\r\n", 1)[0].split()[1] == b"101", head
        self._buffer = head.split(b"\r\n\r\n", 1)[1]
        self._id = 0

    def _read(self, n: int) -> bytes:
        while len(self._buffer) < n:
            chunk = self.sock.recv(1 << 16)
            if not chunk:
                raise ConnectionError("DevTools connection closed")
            self._buffer += chunk
        out, self._buffer = self._buffer[:n], self._buffer[n:]
        return out

    def _frame(self) -> tuple[int, bytes]:
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._read(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._read(8))[0]
        mask = self._read(4) if b1 & 0x80 else None
        data = self._read(n)
        if mask:
            data = bytes(b ^ mask[k % 4] for k, b in enumerate(data))
        return b0, data

    def _send(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        head += (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
                 if n < 1 << 16 else bytes([0x80 | 127]) + struct.pack(">Q", n))
        self.sock.sendall(head + mask + bytes(b ^ mask[k % 4] for k, b in enumerate(payload)))

    def _message(self) -> dict:
        parts = []
        while True:
            b0, data = self._frame()
            opcode = b0 & 0x0F
            if opcode == 0x9:
                self._send(0xA, data)
                continue
            if opcode == 0x8:
                raise ConnectionError("DevTools closed the connection")
            parts.append(data)
            if b0 & 0x80:
                return json.loads(b"".join(parts))

    def call(self, method: str, **params) -> dict:
        self._id += 1
        self._send(0x1, json.dumps({"id": self._id, "method": method, "params": params}).encode())
        while True:
            message = self._message()
            if message.get("id") == self._id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})

    def js(self, expression: str):
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                           awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait(self, expression: str, timeout: float = 10.0, what: str = ""):
        deadline = time.monotonic() + timeout
        while True:
            value = self.js(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"page never showed {what or expression}")
            time.sleep(0.05)

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def browser(tmp_path):
    exe = find_chromium()
    profile = tmp_path / "profile"
    proc = subprocess.Popen([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 30
        while not (port_file.exists() and port_file.read_text().strip()):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail("chromium did not open its DevTools port")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as reply:
            pages = [t for t in json.load(reply) if t["type"] == "page"]
        tools = DevTools(pages[0]["webSocketDebuggerUrl"])
        try:
            yield tools
        finally:
            tools.close()
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


def dancer(pid: int, x: float, z: float, arm: float = 0.3) -> Body:
    joints = standing_pose((x, z), 0.0, left_arm=arm, right_arm=0.2)
    return Body(pid, joints, np.ones(25), np.zeros((25, 3)), (HandState.OPEN, HandState.CLOSED),
                joints[[0, 1, 20, 12, 16]].mean(axis=0), ("kinect-a",))


def close_to(pixel: list[int], rgb: tuple[int, int, int], tol: int = 40) -> bool:
    return all(abs(a - b) <= tol for a, b in zip(pixel[:3], rgb))


def test_monitor_draws_moving_bodies_lit_zones_and_red_sensors_in_chromium(browser):
    clock = ManualClock(0.0)
    host = ViewHost.for_play([], monitor=0, clock=clock, plugins=False, threaded=False)
    host.set_scene([{"name": "centre", "shape": "cylinder", "centre": [1.5, 0.0], "radius": 0.7},
                    {"name": "door", "shape": "box", "min": [-2.5, 0, 1.5], "max": [-1.5, 2.2, 2.5]}],
                   ["intro", "storm"])
    host.start()
    (slot,) = host.slots
    try:
        host.pump()
        browser.call("Page.navigate", url=host.monitor_url)
        browser.wait("window.stageMonitor && stageMonitor.received.scene > 0", what="the scene")
        slot.offer_status(Status(0.0, {"drops": {"kinect-b": {"late": 3}}, "drops_total": 3,
                                       "latency_ms": {"n": 10, "p50": 0.8, "p99": 1.9}},
                                 {"kinect-a": SensorStatus("kinect-a", (0.0, 0.8, -2.5), 30.0, True,
                                                           True, 0.97, "ok", True, "", 0),
                                  "kinect-b": SensorStatus("kinect-b", (2.2, 0.8, 1.3), 29.0, True,
                                                           False, 0.38, "suspect", False,
                                                           "calibration suspect: fitness 0.38 "
                                                           "for 2.0 s", 3)}))
        # frame A: the dancer at x = -1.5
        clock.set(1.0)
        a = dancer(1, -1.5, 0.0)
        host._on_frame(FusedFrame(1.0, {1: a}, (1,), (1,), ()))
        host.emit([SectionChange(1.0, "storm", "intro", 1, "hands up")])
        host.pump()
        browser.wait("stageMonitor.received.frame >= 1 && stageMonitor.perf.draws > 0 && "
                     "stageMonitor.state.frame.t === 1", what="frame A drawn")
        browser.wait("new Promise(r => requestAnimationFrame(() => r(true)))")
        head_a = a.joints[3].tolist()
        assert close_to(browser.js(f"stageMonitor.pixel('top', {head_a})"), BODY_BLUE)
        assert close_to(browser.js(f"stageMonitor.pixel('front', {head_a})"), BODY_BLUE)
        zone_probe = [1.5, 0.0, -0.5]    # inside the zone, behind where the dancer will stand
        idle = browser.js(f"stageMonitor.pixel('top', {zone_probe})")

        # frame B: the dancer walked to x = +1.5, into the zone, which the piece says is occupied
        clock.set(1.1)
        b = dancer(1, 1.5, 0.0, arm=2.8)
        host._on_frame(FusedFrame(1.1, {1: b}, (1,), (), ()))
        host.emit([ZoneState(1.1, "centre", True, (1,))])
        host.pump()
        browser.wait("stageMonitor.state.frame.t === 1.1 && "
                     "document.querySelector('li[data-zone=\"centre\"]').classList.contains('occupied')",
                     what="frame B and the lit zone")
        browser.wait("new Promise(r => requestAnimationFrame(() => r(true)))")
        head_b = b.joints[3].tolist()
        assert close_to(browser.js(f"stageMonitor.pixel('top', {head_b})"), BODY_BLUE)
        assert not close_to(browser.js(f"stageMonitor.pixel('top', {head_a})"), BODY_BLUE), \
            "the body must have moved away from where it was"
        lit = browser.js(f"stageMonitor.pixel('top', {zone_probe})")
        assert lit[0] > idle[0] + 60 and lit[0] > lit[2] + 60, (idle, lit)   # bluish -> amber
        hand = b.joints[7].tolist()       # the raised left hand, drawn open (green) from the front
        assert close_to(browser.js(f"stageMonitor.pixel('front', {hand})"), (60, 207, 110))

        page = browser.js("""({
            section: document.getElementById('section').textContent,
            people: document.getElementById('people').textContent,
            bad: [...document.querySelectorAll('#sensors tr.bad')].map(r => r.textContent),
            ok: [...document.querySelectorAll('#sensors tr.ok')].map(r => r.dataset.sensor),
            events: [...document.querySelectorAll('#events li')].map(l => l.textContent),
            door: document.querySelector('li[data-zone="door"]').className})""")
        assert page["section"] == "storm" and page["people"] == "1"
        assert page["ok"] == ["kinect-a"]
        assert len(page["bad"]) == 1 and "kinect-b" in page["bad"][0]
        assert "calibration suspect: fitness 0.38 for 2.0 s" in page["bad"][0]
        assert page["door"] == "" and any("zone centre occupied by 1" in e for e in page["events"])
        sensor_colour = browser.js("stageMonitor.pixel('top', [2.2, 0.8, 1.35])")
        assert sensor_colour[0] > 200 and sensor_colour[1] < 120    # the red marker

        # six people at 30 frames a second for two seconds
        rng = np.random.default_rng(7)
        spots = rng.uniform(-2.0, 2.0, size=(6, 2))
        before = browser.js("stageMonitor.received.frame")
        t0 = time.monotonic()
        for k in range(60):
            clock.set(2.0 + k / 30)
            bodies = {pid: dancer(pid, *(spots[pid - 1] + 0.3 * np.sin(k / 10 + pid)),
                                  arm=1.5 + np.sin(k / 5))
                      for pid in range(1, 7)}
            host._on_frame(FusedFrame(clock.now(), bodies, tuple(bodies), (), ()))
            host.pump()
            time.sleep(max(0.0, t0 + (k + 1) / 30 - time.monotonic()))
        last_t = round(clock.now(), 4)
        browser.wait(f"stageMonitor.state.frame.t === {last_t} && "
                     "stageMonitor.state.frame.bodies.length === 6", what="the last of 60 frames")
        browser.wait("new Promise(r => requestAnimationFrame(() => r(true)))")
        perf = browser.js("""(() => {
            const ms = stageMonitor.perf.drawMs.slice(-60).sort((a, b) => a - b);
            return {received: stageMonitor.received.frame, draws: stageMonitor.perf.draws,
                    p50: ms[Math.floor(ms.length / 2)], p99: ms[Math.floor(ms.length * 0.99)],
                    max: ms[ms.length - 1]};})()""")
        perf["frames_sent"] = 60
        perf["received_during_run"] = perf["received"] - before
        ARTIFACTS.mkdir(exist_ok=True)
        (ARTIFACTS / "monitor_perf.json").write_text(json.dumps(perf, indent=2))
        print(f"\nmonitor, 6 people at 30 Hz: {perf['received_during_run']} of 60 frames received, "
              f"draw p50 {perf['p50']:.2f} ms p99 {perf['p99']:.2f} ms max {perf['max']:.2f} ms")
        assert browser.js("document.querySelector('#connection').textContent") == "live"
        shot = browser.call("Page.captureScreenshot", format="png")
        (ARTIFACTS / "monitor.png").write_bytes(base64.b64decode(shot["data"]))
    finally:
        host.stop()
