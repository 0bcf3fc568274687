"""The live monitor without a browser: what it sends, its web server, `stage monitor`.

The browser test (headless Chromium drawing bodies and zones) is in
test_monitor_browser.py.
"""

from __future__ import annotations

import http.client
import json
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from stage_plugins.monitor.state import event_text, frame_json, normalise_zone, status_json
from stage.clock import ManualClock
from stage.events import (AllNotesOff, MappingValue, Note, OscOut, SectionChange, TriggerFired,
                          ZoneState)
from stage.views import SensorStatus, Status, ViewHost
from test_views import make_body, make_frame


# ---------------------------------------------------------------- what the page is sent

# issue 12: a zone without a height is 3 m high here as in the piece language (was 2.5 m)
@pytest.mark.parametrize("zone,expected", [
    ({"name": "a", "shape": "box", "min": [1, 0, 2], "max": [0, 2, 3]},
     {"name": "a", "shape": "box", "min": [0, 0, 2], "max": [1, 2, 3]}),
    ({"name": "b", "shape": "box", "centre": [1, 2], "size": [2, 4]},
     {"name": "b", "shape": "box", "min": [0, 0, 0], "max": [2, 3.0, 4]}),
    ({"name": "c", "shape": "cylinder", "center": [0.5, -1.0], "radius": 0.8},
     {"name": "c", "shape": "cylinder", "centre": [0.5, 0.0, -1.0], "radius": 0.8, "y0": 0.0,
      "y1": 3.0}),
    ({"name": "d", "shape": "cylinder", "centre": [0, 0, 0], "radius": 1, "y": [1.5, 3]},
     {"name": "d", "shape": "cylinder", "centre": [0, 0, 0], "radius": 1, "y0": 1.5, "y1": 3}),
    # what stage.piece's Zone.scene() gives for a cylinder
    ({"name": "p", "shape": "cylinder", "centre": [1.0, 2.0], "radius": 0.5, "bottom": 0.2,
      "height": 2.0},
     {"name": "p", "shape": "cylinder", "centre": [1.0, 0.0, 2.0], "radius": 0.5, "y0": 0.2,
      "y1": 2.2}),
    ({"name": "e", "shape": "sphere", "centre": [0, 1.6, 0], "radius": 0.4},
     {"name": "e", "shape": "sphere", "centre": [0, 1.6, 0], "radius": 0.4}),
    ({"name": "f", "shape": "sphere", "centre": [0, "x", 0], "radius": 0.4},
     {"name": "f", "shape": "unknown"}),
    ({"name": "g", "shape": "torus"}, {"name": "g", "shape": "unknown"}),
])
def test_zones_are_normalised_for_drawing(zone, expected):
    assert normalise_zone(zone) == expected


def test_frame_and_status_json():
    body = make_body(3, 1.0, -1.0)
    body.joints[5] = np.nan               # never a NaN on the wire
    data = frame_json(make_frame(2.0, body), fps=29.7)
    assert data["fps"] == 29.7 and data["bodies"][0]["id"] == 3
    assert len(data["bodies"][0]["joints"]) == 25 and data["bodies"][0]["joints"][5] == [0, 0, 0]
    assert data["bodies"][0]["hands"] == ["open", "closed"]
    json.dumps(data, allow_nan=False)
    status = Status(1.0, {"drops": {"k1": {"late": 2, "malformed": 1}, "k2": {"late": 3}},
                          "drops_total": 6, "persons": {"1": {}}},
                    {"k1": SensorStatus("k1", (0.0, 0.8, -2.5), 30.0, True, True, 0.97, "ok",
                                        True, "", 3),
                     "k2": SensorStatus("k2", None, 0.0, False, True, None, "", False,
                                        "lost tracking: silent for 2.0 s", 3)},
                    {"midi": {"state": "running", "frames_dropped": 0, "events_dropped": 0},
                     "slow": {"state": "failed", "error": "on_frame: ValueError: x",
                              "frames_dropped": 4, "events_dropped": 0}})
    s = status_json(status)
    assert s["engine"]["drops"] == {"late": 5, "malformed": 1} and s["view_drops"] == 4
    assert [x["id"] for x in s["sensors"]] == ["k1", "k2"]
    assert s["sensors"][1]["reason"] == "lost tracking: silent for 2.0 s"
    assert s["views"]["slow"]["state"] == "failed"


def test_event_texts():
    assert event_text(Note(0, "keys", 0, 60, 100, 0.5)) == "note 60 vel 100 ch 1 0.50 s -> keys"
    assert event_text(SectionChange(0, "storm", "intro", 1, "hands up")) == \
        "section storm (from intro) by hands up"
    assert event_text(ZoneState(0, "centre", True, (1, 2))) == "zone centre occupied by 1, 2"
    assert event_text(TriggerFired(0, "s", "raise", 2, "HandLeft")) == \
        "trigger raise person 2 HandLeft"
    assert event_text(AllNotesOff(0)) == "all notes off all outputs"


# ---------------------------------------------------------------- the server

class Sse:
    """A server-sent-events reader on the monitor's /events."""

    def __init__(self, url: str, host_header: str | None = None) -> None:
        host, port = url.split("//")[1].strip("/").split(":")
        self.conn = http.client.HTTPConnection(host, int(port), timeout=5)
        headers = {"Host": host_header} if host_header else {}
        self.conn.request("GET", "/events", headers=headers)
        self.response = self.conn.getresponse()
        self.seen: list[tuple[str | None, object]] = []

    def next(self, kind: str, timeout: float = 5.0) -> dict | list:
        """The next message of ``kind``; the messages of other kinds read meanwhile are kept."""
        deadline = time.monotonic() + timeout
        event = None
        while time.monotonic() < deadline:
            line = self.response.fp.readline().decode()
            if line.startswith("event: "):
                event = line[7:].strip()
            elif line.startswith("data: "):
                data = json.loads(line[6:])
                self.seen.append((event, data))
                if event == kind:
                    return data
        raise AssertionError(f"no '{kind}' event within {timeout} s")

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
def monitor():
    clock = ManualClock(0.0)
    host = ViewHost.for_play([], monitor=0, clock=clock, plugins=False, threaded=False)
    host.set_scene([{"name": "centre", "shape": "cylinder", "centre": [0, 0], "radius": 1}],
                   ["intro", "storm"])
    host.start()
    host.pump()
    yield host, clock
    host.stop()


def test_page_and_assets_are_served_locally_with_no_external_references(monitor):
    host, _ = monitor
    url = host.monitor_url
    assert url.startswith("http://127.0.0.1:")
    page = urllib.request.urlopen(url, timeout=5).read().decode()
    assert '<canvas id="top"' in page and '<canvas id="front"' in page
    for asset in ("monitor.js", "monitor.css"):
        with urllib.request.urlopen(url + asset, timeout=5) as reply:
            assert reply.status == 200
            body = reply.read().decode()
        assert "http://" not in body and "https://" not in body   # no CDN, no internet
    assert "https://" not in page and "http://" not in page
    with pytest.raises(urllib.error.HTTPError, match="404"):
        urllib.request.urlopen(url + "nope", timeout=5)


def test_foreign_host_names_are_refused(monitor):
    host, _ = monitor
    port = int(host.monitor_url.rsplit(":", 1)[1].strip("/"))
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request("GET", "/state.json", headers={"Host": f"evil.example:{port}"})
    assert conn.getresponse().status == 403
    conn.close()


def test_the_event_stream_carries_scene_frames_piece_state_and_events(monitor):
    host, clock = monitor
    sse = Sse(host.monitor_url)
    try:
        scene = sse.next("scene")
        assert scene["sections"] == ["intro", "storm"]
        assert scene["zones"][0]["shape"] == "cylinder"
        clock.set(1.0)
        host._on_frame(make_frame(1.0, make_body(1, 0.5, 0.5), new=(1,)))
        host.emit([SectionChange(1.0, "storm", "intro", 1, "hands up"),
                   ZoneState(1.0, "centre", True, (1,)), MappingValue(1.0, "height", 0.75),
                   OscOut(1.0, "space", "/liminal/pan", (-0.5, 2))])
        host.pump()
        before = len(sse.seen)
        frame = sse.next("frame")
        assert frame["bodies"][0]["id"] == 1
        # the frame is published last (on tick, after the events of the same delivery)
        kinds = [k for k, _ in sse.seen[before:]]
        assert kinds == ["events", "piece", "frame"], kinds
        events, piece = sse.seen[before][1], sse.seen[before + 1][1]
        assert piece["section"] == "storm" and piece["index"] == 1
        assert piece["zones"] == {"centre": [1]} and piece["mappings"] == {"height": 0.75}
        # continuous values (mappings, OSC out) go to a table, not the event list
        assert [e["type"] for e in events] == ["SectionChange", "ZoneState"]
        assert piece["outputs"] == {"space /liminal/pan": "-0.500 2"}
        assert events[0]["t"] == 1.0         # seconds since the monitor started
    finally:
        sse.close()
    state = json.loads(urllib.request.urlopen(host.monitor_url + "state.json", timeout=5).read())
    assert state["piece"]["section"] == "storm" and len(state["log"]) == 1


def test_frames_are_sent_at_most_30_a_second_newest_first(monitor):
    host, clock = monitor
    view = host.view("monitor")
    for k in range(10):                       # 10 frames in 1/10 s
        clock.set(2.0 + k / 100)
        host._on_frame(make_frame(clock.now(), make_body(1, k / 10, 0.0)))
        host.pump()
    assert view.frames_published == 3         # at 2.00, 2.04 (>= 1/30 s later), 2.08
    clock.set(2.2)
    host.pump()
    assert view.frames_published == 4         # the newest frame (x = 0.9) is not lost
    state = json.loads(urllib.request.urlopen(host.monitor_url + "state.json", timeout=5).read())
    assert state["frame"]["bodies"][0]["position"][0] == pytest.approx(0.9, abs=0.01)


# ---------------------------------------------------------------- `stage monitor`

def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.integration
def test_stage_monitor_demo_serves_the_page_and_shows_sensors():
    port = _free_tcp_port()
    proc = subprocess.Popen([sys.executable, "-m", "stage.cli", "monitor", "--demo",
                             "--duration", "6", "--http", str(port), "--no-plugins"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        assert first.startswith(f"stage monitor: open http://127.0.0.1:{port}/"), \
            first + proc.stderr.read()
        sse = Sse(f"http://127.0.0.1:{port}/")
        try:
            status = sse.next("status")
            while len(status["sensors"]) < 3:
                status = sse.next("status")
            assert [s["id"] for s in status["sensors"]] == ["demo-a", "demo-b", "demo-c"]
            assert all(s["ok"] and s["position"] is not None for s in status["sensors"])
            assert sse.next("frame")["bodies"]
        finally:
            sse.close()
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err  # stopped by SIGTERM: interrupted (issue 9: was 0)


def test_stage_monitor_with_its_port_taken_is_a_one_line_failure():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = subprocess.run([sys.executable, "-m", "stage.cli", "monitor", "--port", "0",
                               "--http", str(port), "--no-plugins", "--duration", "1"],
                              capture_output=True, text=True, timeout=30)
    assert done.returncode == 1
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("stage: the monitor did not start: cannot serve the monitor on "
                           f"http://127.0.0.1:{port}/"), done.stderr
