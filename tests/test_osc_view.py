"""The OSC view: encoding, targets and routing over real UDP, bundles, and liblo's oscdump.

Receivers are plain UDP sockets (``helpers.Peer``, decoding with python-osc)
and, in the integration test, liblo's ``oscdump`` (skipped where missing).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import threading
import time

import numpy as np
import pytest
from pythonosc import osc_bundle, osc_message

from helpers import LOCALHOST, TIMEOUT_S, Peer, Sensor, free_udp_port, sync
from stage_plugins.osc.encode import (FrameEncoder, bundles, osc_out_message, piece_event_message)
from stage.sensors.sim import standing_pose
from stage.clock import ManualClock
from stage.errors import ConfigError
from stage.events import (MappingValue, Note, OscOut, OutputDecl, SectionChange, TriggerFired,
                          ZoneState)
from stage.joints import HandState
from stage.rig import Rig
from stage.app.server import Server
from stage.views import Status, ViewHost
from test_views import make_body, make_frame


def decode(data: bytes) -> tuple[str, list]:
    msg = osc_message.OscMessage(data)
    return msg.address, list(msg.params)


# ---------------------------------------------------------------- encoding (pure)

def test_piece_events_have_documented_addresses_and_arguments():
    assert decode(piece_event_message(SectionChange(1.0, "storm", "intro", 1, "hands up"))) == \
        ("/stage/section", ["storm", 1, "intro", "hands up"])
    assert decode(piece_event_message(SectionChange(0.0, "intro", None, 0, "start"))) == \
        ("/stage/section", ["intro", 0, "", "start"])
    assert decode(piece_event_message(TriggerFired(1.0, "storm", "raise", 3, "HandLeft", 1.8))) == \
        ("/stage/trigger", ["storm", "raise", 3, "HandLeft", pytest.approx(1.8)])
    assert decode(piece_event_message(TriggerFired(1.0, "storm", "clap"))) == \
        ("/stage/trigger", ["storm", "clap", -1, "", 0.0])
    assert decode(piece_event_message(MappingValue(1.0, "height", 0.25))) == \
        ("/stage/mapping", ["height", 0.25])
    assert decode(piece_event_message(ZoneState(1.0, "centre", True, (1, 4)))) == \
        ("/stage/zone", ["centre", 1, 1, 4])
    assert decode(piece_event_message(ZoneState(1.0, "centre", False))) == \
        ("/stage/zone", ["centre", 0])
    assert piece_event_message(Note(0.0, "k", 0, 60, 100, 1.0)) is None
    assert piece_event_message(MappingValue(1.0, "x", float("nan"))) is None


def test_osc_out_arguments_are_coerced_or_refused():
    assert decode(osc_out_message(OscOut(0.0, "fx", "/fx/reverb", (np.float32(0.5), np.int64(3),
                                                                   True, "hall")))) == \
        ("/fx/reverb", [0.5, 3, 1, "hall"])
    with pytest.raises(ValueError, match="cannot send"):
        osc_out_message(OscOut(0.0, "fx", "/fx", (None,)))
    with pytest.raises(ValueError, match="start with '/'"):
        osc_out_message(OscOut(0.0, "fx", "fx", ()))
    with pytest.raises(ValueError, match="int32"):
        osc_out_message(OscOut(0.0, "fx", "/fx", (2 ** 40,)))


def test_frame_encoder_speaks_the_server_to_view_api():
    enc = FrameEncoder()
    body = make_body(7, 1.0, 2.0)
    first = [decode(m) for m in enc.messages(make_frame(1.0, body, new=(7,)))]
    assert [a for a, _ in first] == ["/newUser", "/jointCoordinates", "/handState", "/handState"]
    assert first[0][1][0] == 7 and np.allclose(first[0][1][1:], body.position, atol=1e-5)
    assert first[2][1] == [7, "left", "open"] and first[3][1] == [7, "right", "closed"]
    # unchanged hands are not repeated; a change is sent once
    second = [a for a, _ in map(decode, enc.messages(make_frame(1.1, body)))]
    assert second == ["/jointCoordinates"]
    body.hands = (HandState.LASSO, HandState.CLOSED)
    third = [decode(m) for m in enc.messages(make_frame(1.2, body))]
    assert [a for a, _ in third] == ["/jointCoordinates", "/handState"]
    assert third[1][1] == [7, "left", "lasso"]
    lost = [decode(m) for m in enc.messages(FusedFrame_lost(1.3, 7))]
    assert lost == [("/lostUser", [7])]


def FusedFrame_lost(t: float, pid: int):
    from stage.frames import FusedFrame
    return FusedFrame(t, {}, (), (), (pid,))


def test_bundles_are_split_under_the_size_limit_and_keep_the_timetag():
    messages = [osc_out_message(OscOut(0.0, "x", "/x", ("a" * 100,))) for _ in range(30)]
    parts = bundles(messages, 1_700_000_000.25, max_bytes=1024)
    assert len(parts) > 1 and all(len(p) <= 1024 for p in parts)
    decoded = [osc_bundle.OscBundle(p) for p in parts]
    assert sum(b.num_contents for b in decoded) == 30
    assert all(abs(b.timestamp - 1_700_000_000.25) < 1e-6 for b in decoded)


# ---------------------------------------------------------------- the view over UDP

@pytest.fixture
def peers():
    made: list[Peer] = []

    def make() -> Peer:
        made.append(Peer())
        return made[-1]

    yield make
    for p in made:
        p.close()


def wait_count(peer: Peer, n: int, timeout: float = TIMEOUT_S) -> list:
    deadline = time.monotonic() + timeout
    while len(peer.received) < n and time.monotonic() < deadline:
        peer._receive(0.05)
    return peer.received


def test_targets_routing_and_future_events(peers):
    piece_target, cli_target, registered = peers(), peers(), peers()
    clock = ManualClock(10.0)
    outputs = [OutputDecl("visuals", "osc", f"{LOCALHOST}:{piece_target.port}"),
               OutputDecl("fx", "osc")]
    host = ViewHost.for_play(outputs, osc=[(LOCALHOST, cli_target.port)], clock=clock,
                             plugins=False, threaded=False).start()
    # the engine's registered views (rig, /registerView) arrive with the status
    (slot,) = [s for s in host.slots if s.name == "osc"]
    slot.offer_status(Status(10.0, {}, {}, {}, ((LOCALHOST, registered.port),)))
    host.emit([OscOut(10.0, "visuals", "/scene/colour", (0.2, 0.4, "red")),
               OscOut(10.0, "fx", "/fx/reverb", (0.7,)),
               OscOut(10.5, "visuals", "/scene/flash", ()),         # in half a second
               SectionChange(10.0, "storm", "intro", 1, "hands up")])
    host._on_frame(make_frame(10.0, make_body(1), new=(1,)))
    host.pump()
    got = {p: [m.address for m in wait_count(p, n)] for p, n in
           ((piece_target, 2), (cli_target, 2), (registered, 1))}
    # issue 12: a piece's OSC outputs used to get the whole skeleton stream too; now only
    # the piece's messages, unless the piece asks (skeletons: true, the next test)
    assert got[piece_target] == ["/scene/colour", "/stage/section"]
    assert got[cli_target] == ["/fx/reverb", "/stage/section"]
    assert got[registered] == ["/stage/section"]     # bodies come from the engine itself
    assert piece_target.received[0].params == (pytest.approx(0.2), pytest.approx(0.4), "red")
    assert host.next_deadline() == 10.5
    clock.set(10.5)
    host.pump()
    assert wait_count(piece_target, 3)[2].address == "/scene/flash"
    host.stop()
    assert len(cli_target.drain()) == 0 and len(registered.drain()) == 0


def test_the_skeleton_stream_goes_where_the_piece_asks_or_to_a_plain_view(peers):
    asked, plain, carrier = peers(), peers(), peers()
    clock = ManualClock(10.0)
    outputs = [OutputDecl("space", "osc", f"{LOCALHOST}:{asked.port}", skeletons=True),
               OutputDecl("lights", "osc", f"{LOCALHOST}:{carrier.port}")]
    host = ViewHost.for_play(outputs, osc=[(LOCALHOST, plain.port)], clock=clock,
                             plugins=False, threaded=False).start()
    host.emit([OscOut(10.0, "lights", "/lights/on", (1,))])
    host._on_frame(make_frame(10.0, make_body(1), new=(1,)))
    host.pump()
    body = ["/newUser", "/jointCoordinates", "/handState", "/handState"]
    assert [m.address for m in wait_count(asked, 4)] == body
    assert [m.address for m in wait_count(plain, 4)] == body   # no piece output rides on it
    assert [m.address for m in wait_count(carrier, 1)] == ["/lights/on"]
    host.stop()
    assert not asked.drain() and not plain.drain() and not carrier.drain()


def test_an_osc_view_with_no_target_taking_skeletons_is_given_no_frames(peers):
    """Piece events only (or registered views only, as `stage play` without --osc): the host
    queues it no frame and its thread is not woken for one; its events still go out."""
    carrier = peers()
    clock = ManualClock(10.0)
    host = ViewHost.for_play([OutputDecl("lights", "osc", f"{LOCALHOST}:{carrier.port}")],
                             clock=clock, plugins=False, threaded=False).start()
    (slot,) = [s for s in host.slots if s.name == "osc"]
    assert not slot.wants_frames
    host.emit([OscOut(10.0, "lights", "/lights/on", (1,))])
    for k in range(5):
        host._on_frame(make_frame(10.0, make_body(1), new=(1,) if k == 0 else ()))
    host.pump()
    assert [m.address for m in wait_count(carrier, 1)] == ["/lights/on"]
    assert slot.frames_in == 0
    host.stop()
    assert not carrier.drain()
    # one target that takes skeletons: frames again
    asked = peers()
    host = ViewHost.for_play([OutputDecl("space", "osc", f"{LOCALHOST}:{asked.port}",
                                         skeletons=True)],
                             clock=clock, plugins=False, threaded=False).start()
    (slot,) = [s for s in host.slots if s.name == "osc"]
    host._on_frame(make_frame(10.0, make_body(1), new=(1,)))
    host.pump()
    assert slot.wants_frames and slot.frames_in == 1
    assert wait_count(asked, 4)[0].address == "/newUser"
    host.stop()


def test_bundles_carry_the_engine_time_as_wall_time(peers):
    target = peers()
    clock = ManualClock(100.0)
    host = ViewHost.for_play([], osc=[(LOCALHOST, target.port)], osc_bundles=True, clock=clock,
                             plugins=False, threaded=False).start()
    wall_minus_clock = time.time() - clock.now()
    host._on_frame(make_frame(100.0, make_body(2), new=(2,)))
    host.emit([MappingValue(100.0, "height", 0.5)])
    host.pump()
    target.sock.settimeout(TIMEOUT_S)
    datagrams = [target.sock.recvfrom(65536)[0] for _ in range(2)]
    host.stop()
    for data in datagrams:
        assert data.startswith(b"#bundle\0")
        stamp = osc_bundle.OscBundle(data).timestamp
        assert abs(stamp - (100.0 + wall_minus_clock)) < 0.05
    addresses = [m.address for d in datagrams for m in osc_bundle.OscBundle(d)]
    assert addresses == ["/newUser", "/jointCoordinates", "/handState", "/handState",
                         "/stage/mapping"]


def test_an_osc_output_without_any_target_is_dropped_counted_with_one_warning(peers, caplog):
    host = ViewHost.for_play([OutputDecl("fx", "osc")], clock=ManualClock(0.0), plugins=False,
                             threaded=False)
    with caplog.at_level("WARNING"):
        host.start()
        host.emit([OscOut(0.0, "fx", "/a", ()), OscOut(0.0, "fx", "/b", ())])
        host.pump()
    host.stop()
    assert host.stats()["osc"]["view"]["dropped"] == 2
    messages = [r.getMessage() for r in caplog.records]
    assert sum("'fx'" in m for m in messages) == 1   # once, at start


def test_a_bad_piece_target_is_a_user_error():
    with pytest.raises(ConfigError, match="output 'visuals'"):
        ViewHost.for_play([OutputDecl("visuals", "osc", "localhost:99999")], plugins=False)


# ---------------------------------------------------------------- real peer: oscdump

class OscDump:
    """``oscdump -L PORT`` in a subprocess; lines collected by a thread."""

    LINE = re.compile(r"^([0-9a-f]{8})\.([0-9a-f]{8}) (/\S+) ?(\S*)(.*)$")

    def __init__(self, port: int) -> None:
        self.proc = subprocess.Popen(["oscdump", "-L", str(port)], stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def parsed(self) -> list[tuple[float, str, str, str]]:
        out = []
        for line in list(self.lines):
            m = self.LINE.match(line)
            if m:
                stamp = int(m.group(1), 16) - 2208988800 + int(m.group(2), 16) / 2 ** 32
                out.append((stamp, m.group(3), m.group(4), m.group(5).strip()))
        return out

    def wait(self, predicate, timeout: float = TIMEOUT_S):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hits = [p for p in self.parsed() if predicate(p)]
            if hits:
                return hits
            time.sleep(0.02)
        raise AssertionError("oscdump printed nothing matching; it printed:\n  "
                             + "\n  ".join(self.lines[-20:]))

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@pytest.mark.integration
def test_oscdump_receives_the_server_to_view_api_and_piece_events_in_bundles():
    if shutil.which("oscdump") is None:
        pytest.skip("oscdump not installed: apt-get install liblo-tools")
    port = free_udp_port()
    dump = OscDump(port)
    try:
        with Peer() as probe:   # ready once it prints what we send
            deadline = time.monotonic() + TIMEOUT_S
            while not any(p[1] == "/probe" for p in dump.parsed()):
                assert time.monotonic() < deadline, "oscdump never came up"
                probe.send_message((LOCALHOST, port), "/probe", 1)
                time.sleep(0.05)
        with Server(Rig(), LOCALHOST, 0) as server:
            # skeletons: the piece asks for the Server-to-View API on this output (issue 12)
            host = ViewHost.for_play([OutputDecl("visuals", "osc", f"{LOCALHOST}:{port}",
                                                 skeletons=True)],
                                     osc_bundles=True, plugins=False, clock=server.clock)
            host.attach(server.engine).start()
            try:
                with Sensor("kinect-x", server.address) as sensor:
                    sensor.register()
                    joints = standing_pose((0.5, 2.0), 0.0)
                    for k in range(3):   # three frames at the sensor's 30 Hz: three fusions
                        sensor.frame(0, joints + 0.01 * k)
                        sensor.hand(0, "left", "open")
                        sync(server.address)
                        time.sleep(1 / 30)
                    server.engine.call_soon(lambda e: host.emit(
                        [SectionChange(e.clock.now(), "storm", "intro", 1, "hands up"),
                         ZoneState(e.clock.now(), "centre", True, (1,)),
                         OscOut(e.clock.now(), "visuals", "/scene/flash", (1.5,))]))
                    sync(server.address)
                    dump.wait(lambda p: p[1] == "/scene/flash")
            finally:
                host.stop()
    finally:
        dump.close()
    lines = [p for p in dump.parsed() if p[1] != "/probe"]
    addresses = [p[1] for p in lines]
    assert addresses[:4] == ["/newUser", "/jointCoordinates", "/handState", "/handState"]
    # three frames at 30 Hz: three fusions; the OSC view also re-sends a body whose hand
    # vote changed (here left: unknown -> open), depending on how the datagrams were batched
    assert 3 <= addresses.count("/jointCoordinates") <= 4
    assert ["/stage/section", "/stage/zone", "/scene/flash"] == addresses[-3:]
    types = {p[1]: p[2] for p in lines}
    assert types["/newUser"] == "ifff" and types["/jointCoordinates"] == "i" + "sffff" * 25
    assert types["/stage/section"] == "siss" and types["/stage/zone"] == "sii"
    assert lines[-3][3] == '"storm" 1 "intro" "hands up"'
    assert lines[-1][3].startswith("1.5")
    now = time.time()
    assert all(now - 30 < p[0] <= now + 1 for p in lines), "timetags are the frames' wall time"
