"""The relay view: two stage servers on loopback, a person relayed from one to the other.

Room A is a ``Server`` in this process with the relay view; room B is a real
``stage serve`` process whose rig places room A 3 m to the right (the relay
is one more sensor there, calibrated like any other). A view registered on B
must see A's dancer appear, move and leave.
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from helpers import (LOCALHOST, TIMEOUT_S, Peer, Sensor, free_udp_port, joint_groups,
                     query_stats, register_view, sync)
from stage.sensors.sim import standing_pose
from stage.clock import ManualClock
from stage.frames import FusedFrame
from stage.joints import JOINT_INDEX
from stage.sensors.protocol import (HandStateMsg, JointCoordinates, LostUser, NewUser,
                                    RegisterDevice, decode_datagram)
from stage.rig import Rig
from stage.app.server import Server
from stage.views import Status, ViewHost
from test_views import make_body, make_frame

pytestmark = pytest.mark.integration

ROOM_A_IN_B = [[1, 0, 0, 3.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


@pytest.fixture
def room_b(tmp_path):
    """``stage serve`` with a rig that knows the relay from room A as a calibrated sensor."""
    port = free_udp_port()
    rig = tmp_path / "room-b.yaml"
    rig.write_text(f"""\
server: {{host: {LOCALHOST}, port: {port}}}
reference: kinect-b
sensors:
  kinect-b: {{type: kinect2}}
  relay-room-a:
    type: stage-relay
    calibration: {{matrix: {ROOM_A_IN_B}, method: manual}}
""")
    proc = subprocess.Popen([sys.executable, "-m", "stage.cli", "--quiet", "serve", "--rig",
                             str(rig)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    address = (LOCALHOST, port)
    deadline = time.monotonic() + 15
    while True:
        try:
            query_stats(address, timeout=0.3)
            break
        except AssertionError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"stage serve did not come up: {proc.stderr.read()[-800:]}")
    try:
        yield address
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_a_person_in_room_a_appears_moves_and_leaves_in_room_b(room_b):
    with Peer() as view_b, Server(Rig(), LOCALHOST, 0) as room_a:
        register_view(room_b, view_b)
        host = ViewHost.for_play([], relay=[room_b], plugins=False, clock=room_a.clock,
                                 plugin_options={"relay": {"client_id": "relay-room-a"}})
        host.attach(room_a.engine).start()
        try:
            with Sensor("kinect-a", room_a.address) as kinect:
                kinect.register()
                kinect.new_user(0, np.array([0.5, 1.0, 2.0]))
                joints = standing_pose((0.5, 2.0), 0.3, left_arm=1.2)
                for _ in range(5):
                    kinect.frame(0, joints)
                    kinect.hand(0, "left", "lasso")
                    sync(room_a.address)
                new = view_b.wait_for(lambda m: m.address == "/newUser", what="/newUser in B")
                line = view_b.wait_for(lambda m: m.address == "/jointCoordinates",
                                       start=view_b.received.index(new), what="joints in B")
                view_b.wait_for(lambda m: m.address == "/handState" and m.params[1] == "left"
                                and m.params[2] == "lasso", what="the lasso in B")
                got = joint_groups(line)
                expected = joints + np.array([3.0, 0.0, 0.0])   # room A stands 3 m right in B
                assert len(got) == 25
                for name, (xyz, conf) in got.items():
                    assert np.allclose(xyz, expected[JOINT_INDEX[name]], atol=0.02), name
                    assert conf == 1.0
                stats_b = query_stats(room_b)
                relay = stats_b["clients"]["relay-room-a"]
                assert relay["type"] == "stage-relay" and relay["calibrated"]
                assert relay["frames"] >= 1 and stats_b["drops_total"] == 0
                assert list(stats_b["persons"].values())[0]["sensors"] == ["relay-room-a"]

                # the dancer walks 1 m towards +x in room A: B sees it 1 m further too
                moved = joints + np.array([1.0, 0.0, 0.0])
                # 1 s at the sensor's 30 Hz (sooner frames are coalesced): room A's and room
                # B's Kalman filters, in series, settle after a 1 m jump well within that
                for _ in range(30):
                    kinect.frame(0, moved)
                    sync(room_a.address)
                    time.sleep(1 / 30)
                start = len(view_b.received)
                last = view_b.wait_for(
                    lambda m: m.address == "/jointCoordinates"
                    and abs(joint_groups(m)["SpineBase"][0][0] - (moved[0, 0] + 3.0)) < 0.05,
                    start=start, what="the moved body in B")
                assert last.params[0] == new.params[0]          # still the same person in B

                kinect.lost_user(0)
                view_b.wait_for(lambda m: m.address == "/lostUser" and m.params[0] == new.params[0],
                                timeout=TIMEOUT_S, what="/lostUser in B")
        finally:
            host.stop()
        assert host.stats()["relay"]["view"]["send_errors"] == 0


# ---------------------------------------------------------------- the view alone

def _decode_all(data_list: list[bytes]) -> list:
    return [m for data in data_list for m, _ in decode_datagram(data).messages]


def test_ids_map_onto_six_user_slots_and_relayed_people_are_not_echoed():
    with Peer() as target:
        target.sock.settimeout(TIMEOUT_S)
        clock = ManualClock(0.0)
        host = ViewHost.for_play([], relay=[(LOCALHOST, target.port)], plugins=False,
                                 threaded=False, clock=clock,
                                 plugin_options={"relay": {"client_id": "relay-x"}}).start()
        datagrams = [target.sock.recvfrom(65536)[0]]           # /registerDevice at start
        # people 1-7 from our own sensors, person 9 only seen through another room's relay
        bodies = [make_body(pid, 0.5 * pid, 0.0) for pid in range(1, 8)]
        echo = make_body(9, 0.0, 3.0)
        echo.sensors = ("relay-elsewhere",)
        host.slots[0].offer_status(Status(0.0, {"clients": {"relay-elsewhere": {
            "type": "stage-relay"}}}, {}, {}, ()))
        host._on_frame(make_frame(0.1, *bodies, echo, new=tuple(range(1, 8)) + (9,)))
        host.pump()
        datagrams.append(target.sock.recvfrom(65536)[0])
        host._on_frame(FusedFrame(0.2, {b.id: b for b in bodies[1:]}, (), (), (1,)))
        host.pump()
        datagrams.append(target.sock.recvfrom(65536)[0])
        host.stop()
        datagrams.append(target.sock.recvfrom(65536)[0])
    messages = _decode_all(datagrams)
    assert isinstance(messages[0], RegisterDevice) and messages[0].sensor_type == "stage-relay"
    new = [m for m in messages if isinstance(m, NewUser)]
    assert [m.user for m in new] == [0, 1, 2, 3, 4, 5]          # six slots, the seventh waits
    assert all(m.client == "relay-x" for m in messages)
    assert sum(isinstance(m, JointCoordinates) for m in messages) == 6
    assert sum(isinstance(m, HandStateMsg) for m in messages) == 12
    lost = [m.user for m in messages if isinstance(m, LostUser)]
    assert lost[0] == 0                                           # person 1 left: slot 0 freed
    assert sorted(lost[1:]) == [1, 2, 3, 4, 5]                    # stop: nobody left as a ghost
    stats = host.stats()["relay"]["view"]
    assert stats["persons_over_6"] == 1 and stats["echo_skipped"] == 1
