"""docs/security.md: who may send, where output may go, and bounded memory whatever arrives.

In-process tests use the engine on a ManualClock; the UDP tests use a real
server on loopback with peers on other loopback addresses (127.0.0.x are
all this machine on Linux) as strangers.
"""

from __future__ import annotations

import json
import socket
import sys
import time

import numpy as np
import pytest
from pythonosc.osc_message import OscMessage

from helpers import LOCALHOST, Peer, Sensor, query_stats, sync
from stage.app.server import Server
from stage.calibration import attach_live
from stage.clock import ManualClock, MonotonicClock
from stage.engine.engine import Engine
from stage.engine.output import encode_stats
from stage.network import Networks, canonical_ipv4
from stage.rig import Rig, SensorConfig, load_rig
from stage.sensors.protocol import (Inbound, decode_datagram, encode_bundle, encode_client_joints,
                                    encode_message)
from stage.sensors.receiver import Receiver
from stage.sensors.sim import standing_pose
from stage.settings import LimitSettings
from stage.stats import OTHER, DropCounter


class Recorder:
    def __init__(self) -> None:
        self.sent: list[tuple[tuple[str, int], bytes]] = []

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        self.sent.append((address, data))

    def to(self, address: tuple[str, int]) -> list[bytes]:
        return [d for a, d in self.sent if a == address]


def engine_with(rig: Rig | None = None, transport=None) -> tuple[Engine, ManualClock]:
    clock = ManualClock(100.0)
    return Engine(rig or Rig(), clock, transport), clock


def frame(sensor: str, user: int = 0, where=(0.0, 2.5), timetag: float | None = None) -> bytes:
    msg = encode_client_joints(sensor, user, standing_pose(where, np.pi), np.ones(25))
    return msg if timetag is None else encode_bundle([msg], timetag)


def feed(engine: Engine, data: bytes, source=("127.0.0.1", 5000)) -> None:
    engine.handle_datagram(data, source)


# ---------------------------------------------------------------- allow-lists

def test_allow_lists_read_addresses_networks_and_words():
    nets = Networks(["loopback", "10.1.2.0/24", "192.168.5.7"])
    assert nets.allows("127.0.0.9") and nets.allows("10.1.2.200") and nets.allows("192.168.5.7")
    assert not nets.allows("10.1.3.1") and not nets.allows("192.168.5.8")
    assert not nets.allows("not an address")
    assert Networks(["any"]).allows("8.8.8.8") and not Networks([]).allows("127.0.0.1")
    with pytest.raises(ValueError, match="not an IPv4 address"):
        Networks(["10.0.0.0/33"])


def test_the_default_allow_list_is_loopback_and_the_machines_own_networks():
    rig = Rig()
    assert rig.allow_sensors.allows("127.0.0.1") and rig.allow_views.allows("127.0.0.1")
    assert not rig.allow_sensors.allows("203.0.113.9")  # documentation range: never local


def test_the_rig_file_carries_allow_lists_and_a_sensor_pinned_to_an_address(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text("allow: {sensors: [10.0.0.0/24], views: loopback}\n"
                    "sensors: {k1: {address: 10.0.0.5}}\nlimits: {max_clients: 8}\n")
    rig = load_rig(str(path))
    assert rig.allow_sensors.allows("10.0.0.9") and not rig.allow_sensors.allows("127.0.0.1")
    assert rig.allow_views.allows("127.0.0.1") and not rig.allow_views.allows("10.0.0.9")
    assert rig.sensors["k1"].address.allows("10.0.0.5") and rig.limits.max_clients == 8
    rig.save(str(tmp_path / "again.yaml"))
    again = load_rig(str(tmp_path / "again.yaml"))
    assert again.allow_sensors.entries == ("10.0.0.0/24",)
    assert again.sensors["k1"].address.entries == ("10.0.0.5",)
    path.write_text("allow: {sensors: [10.0.0.300]}\n")
    with pytest.raises(Exception, match=r"rig.yaml:1:\d+: 'sensors': '10.0.0.300'"):
        load_rig(str(path))


def test_a_stranger_is_dropped_at_the_edge_under_one_key():
    drops = DropCounter()
    got: list[Inbound] = []
    receiver = Receiver(socket.socket(socket.AF_INET, socket.SOCK_DGRAM), got.append, drops,
                        ManualClock(0.0), 3000, Networks(["127.0.0.1"]))
    receiver.sock.close()
    for port in range(100):
        receiver.handle(encode_message("/registerView", "127.0.0.1", 9000),
                        ("127.0.0.66", 1000 + port), 0.0)
    receiver.handle(frame("k"), ("127.0.0.1", 5000), 0.0)
    assert drops.snapshot() == {OTHER: {"not_allowed": 100}}
    assert len(got) == 1 and receiver.sources == 2


def test_many_source_ports_neither_grow_the_tables_nor_escape_the_host_budget():
    drops = DropCounter()
    got: list[Inbound] = []
    receiver = Receiver(socket.socket(socket.AF_INET, socket.SOCK_DGRAM), got.append, drops,
                        ManualClock(0.0), max_messages_per_s=100, max_per_host_s=1000,
                        max_sources=64)
    receiver.sock.close()
    data = encode_message("/lostUser", "k", 0)
    for k in range(20000):  # one second, 20,000 datagrams from 20,000 ports of one host
        receiver.handle(data, ("127.0.0.1", 1024 + k), k / 20000)
    assert receiver.sources <= 64 + 1
    accepted = len(got)
    flood = sum(r.get("flood", 0) for r in drops.snapshot().values())
    assert accepted + flood == 20000
    assert accepted <= 1000 * 1.0 + 500 + 1  # the host's rate plus its half-second burst


def test_drop_keys_are_capped_but_every_drop_is_counted():
    drops = DropCounter(max_keys=16)
    drops.keep("real-sensor")
    for k in range(1000):
        drops.add(f"junk-{k}" + "x" * 30000, "malformed")
    drops.add("real-sensor", "late")
    snap = drops.snapshot()
    assert len(snap) <= 16 + 2 and snap["real-sensor"] == {"late": 1}  # + OTHER + the kept one
    assert OTHER in snap
    assert sum(n for r in snap.values() for n in r.values()) == 1001
    assert all(len(key) <= 64 for key in snap)


# ---------------------------------------------------------------- binding, caps, reference

def test_a_sensor_id_is_bound_to_its_host_and_its_frames_to_one_socket():
    engine, clock = engine_with()
    feed(engine, encode_message("/registerDevice", "k", "kinect2"), ("127.0.0.1", 5000))
    feed(engine, frame("k"), ("127.0.0.1", 5000))
    assert engine.counts["fused_frames"] == 1
    clock.advance(0.05)
    feed(engine, frame("k", where=(0.7, 2.5)), ("127.0.0.1", 6666))   # a spoof, same host
    feed(engine, frame("k", where=(0.7, 2.5)), ("127.0.0.9", 5000))   # another host
    assert engine.drops.snapshot()["k"] == {"wrong_source": 2}
    assert len(engine.persons) == 1 and engine.counts["fused_frames"] == 1
    # re-registering moves the binding (the real client restarted on a new port)
    feed(engine, encode_message("/registerDevice", "k", "kinect2"), ("127.0.0.1", 7000))
    clock.advance(0.05)
    feed(engine, frame("k"), ("127.0.0.1", 7000))
    assert engine.counts["fused_frames"] == 2


def test_a_rig_may_pin_a_sensor_to_a_network():
    rig = Rig(reference="k")
    rig.sensors["k"] = SensorConfig("k", address=Networks(["10.0.0.5"]))
    engine, clock = engine_with(rig)
    feed(engine, frame("k"), ("10.0.0.6", 5000))
    feed(engine, frame("k"), ("10.0.0.5", 5000))
    clock.advance(0.05)
    feed(engine, frame("k"), ("10.0.0.5", 5001))  # any port of the pinned address
    assert engine.drops.snapshot()["k"] == {"wrong_source": 1}
    assert engine.counts["fused_frames"] == 2


def test_a_hundred_thousand_ids_keep_the_client_table_bounded():
    rig = Rig(limits=LimitSettings(max_clients=32))
    engine, clock = engine_with(rig)
    feed(engine, frame("real"))
    for k in range(100_000):
        engine.handle_datagram(encode_message("/registerDevice", f"id-{k}", "x"),
                               ("127.0.0.1", 6000 + k % 50000))
        if k % 1000 == 0:
            clock.advance(0.01)
            feed(engine, frame("real"))          # the real sensor keeps streaming
            engine.tick()
    assert len(engine.clients) <= 32 and "real" in engine.clients
    assert len(engine.drops) <= rig.limits.max_drop_keys + 32
    assert engine.registry.evicted > 99_000


def test_a_full_table_of_live_sensors_refuses_a_newcomer():
    rig = Rig(limits=LimitSettings(max_clients=3))
    engine, clock = engine_with(rig)
    for sid in ("a", "b", "c"):
        feed(engine, frame(sid, where=(0.0, 2.5)), ("127.0.0.1", 5000))
    feed(engine, frame("d"), ("127.0.0.1", 5000))
    assert "d" not in engine.clients and engine.drops.snapshot()["d"] == {"too_many_clients": 1}


def test_a_stray_registering_first_then_silent_does_not_keep_real_sensors_out():
    engine, clock = engine_with()
    feed(engine, encode_message("/registerDevice", "stray", "kinect2"), ("127.0.0.1", 4000))
    clock.advance(0.1)
    feed(engine, frame("real"), ("127.0.0.1", 5000))
    assert engine.reference == "real"                 # registering alone never elects
    assert engine.counts["fused_frames"] == 1


def test_a_stray_reference_that_goes_silent_before_any_calibration_is_replaced():
    engine, clock = engine_with()
    feed(engine, frame("stray"), ("127.0.0.1", 4000))  # one skeleton, then nothing
    assert engine.reference == "stray"
    for k in range(1, 60):
        clock.advance(1 / 30)
        feed(engine, frame("real", timetag=None), ("127.0.0.1", 5000))
        engine.tick()
    assert engine.reference == "real"
    assert engine.clients["real"].transform is not None
    assert engine.counts["fused_frames"] > 20


def test_a_skeleton_needs_two_torso_joints_seen_to_count_towards_the_reference():
    from stage.engine.clients import _two_torso_joints
    from stage.joints import TORSO
    rng = np.random.default_rng(3)
    for _ in range(3000):
        conf = rng.choice([0.0, -1.0, np.nan, 0.5, 1.0], 25, p=[0.5, 0.1, 0.1, 0.15, 0.15])
        assert _two_torso_joints(conf) == (np.count_nonzero(conf[list(TORSO)] > 0) >= 2)
    conf = np.zeros(25)
    conf[[j for j in range(25) if j not in TORSO]] = 1.0     # limbs alone are no person
    assert not _two_torso_joints(conf)


def test_the_rigs_reference_is_never_replaced():
    engine, clock = engine_with(Rig(reference="ref"))
    feed(engine, frame("ref"), ("127.0.0.1", 4000))
    for _ in range(60):
        clock.advance(1 / 30)
        feed(engine, frame("other"), ("127.0.0.1", 5000))
        engine.tick()
    assert engine.reference == "ref"


# ---------------------------------------------------------------- clocks

def test_a_timetag_far_from_the_real_time_is_refused_and_counted():
    engine = Engine(Rig(), MonotonicClock())   # live: timetags are judged against our clock
    engine.handle_datagram(frame("k", timetag=time.time()), ("127.0.0.1", 5000))
    engine.handle_datagram(frame("k", timetag=time.time() + 365 * 86400), ("127.0.0.1", 5000))
    engine.handle_datagram(frame("k", timetag=time.time() + 0.03), ("127.0.0.1", 5000))
    assert engine.drops.snapshot()["k"] == {"bad_time": 1}
    assert engine.counts["fused_frames"] == 2   # the next real frame is fused: nothing froze


def test_a_client_clock_going_back_is_a_restart_not_lateness():
    engine, clock = engine_with(Rig(reference="k"))
    tag = 1_700_000_000.0
    for k in range(30):
        clock.advance(1 / 30)
        feed(engine, frame("k", timetag=tag + k / 30))
    assert engine.counts["fused_frames"] == 30
    # the sensor PC restarted: its clock is 5 s behind, its users are new
    clock.advance(1 / 30)
    feed(engine, frame("k", timetag=tag - 5.0))
    for k in range(1, 10):
        clock.advance(1 / 30)
        feed(engine, frame("k", timetag=tag - 5.0 + k / 30))
    assert engine.drops.total("late") == 0
    assert engine.clients["k"].restarts == 1
    assert engine.counts["fused_frames"] == 40


def test_a_client_sending_faster_than_real_time_keeps_its_time_line():
    engine, clock = engine_with(Rig(reference="k"))
    tag = 1_700_000_000.0
    for k in range(300):  # 10 s of frames arriving in 0.5 s (20x)
        clock.advance(1 / 600)
        feed(engine, frame("k", where=(0.001 * k, 2.5), timetag=tag + k / 30))
    assert engine.counts["fused_frames"] == 300



def test_a_bundles_messages_share_the_capture_time_each_would_get_alone():
    """ClientRegistry.capture_times works a bundle's time out once; the same times, drops and
    clocks as asking for every message alone, through new clients, other hosts and ports,
    re-registrations, far timetags, clocks going back and jumping ahead."""
    rng = np.random.default_rng(7)
    engines = [engine_with()[0] for _ in range(2)]
    seen: list[list] = [[], []]
    for k, engine in enumerate(engines):
        registry = engine.registry
        registry.wall_minus_clock = 1_700_000_000.0      # tags near 1.7e9 + the engine's time
        one = registry.capture_times if k == 0 else (
            lambda batch, r=registry: [type(r).capture_times(r, [item])[0] for item in batch])
        registry.capture_times = (lambda batch, one=one, out=seen[k]:
                                  out.append(one(batch)) or out[-1])
    pose = standing_pose((0.0, 2.5), np.pi)
    tags = {"a": 1_700_000_100.0, "b": 1_700_000_100.0}
    arrival = 100.0
    for _ in range(400):
        arrival += float(rng.uniform(0.0, 0.04))
        sensor = "ab"[int(rng.integers(2))]
        tags[sensor] += float(rng.choice([1 / 30, 1 / 30, 1 / 30, -5.0, 3.0, 0.0]))
        tag = tags[sensor] + (1e6 if rng.random() < 0.03 else 0.0)      # a far timetag
        host = "127.0.0.2" if rng.random() < 0.05 else "127.0.0.1"
        port = 5000 + int(rng.integers(3))
        msgs = [encode_message("/registerDevice", sensor, "kinect")] if rng.random() < 0.1 else []
        for user in range(int(rng.integers(1, 3))):
            msgs += [encode_message("/handState", sensor, user, "left", "open"),
                     encode_client_joints(sensor, user, pose, np.ones(25)),
                     encode_message("/handState", sensor, user, "right", "closed")]
        rng.shuffle(msgs)
        data = encode_bundle(msgs, tag)
        if rng.random() < 0.8:
            for engine in engines:
                engine.handle_datagram(data, (host, port), arrival)
            continue
        # a backlog: the same bundle from two ports, read at the same time, one batch
        batch = [Inbound(m, arrival, source, t) for source in ((host, port), (host, port + 1))
                 for m, t in decode_datagram(data).messages]
        for engine in engines:
            engine.process(batch)
    assert seen[0] == seen[1] and sum(len(b) for b in seen[0]) > 1000
    assert engines[0].drops.snapshot() == engines[1].drops.snapshot()
    assert engines[0].drops.total("bad_time") > 0 and engines[0].drops.total("wrong_source") > 0
    assert engines[0].counts == engines[1].counts
    for cid in ("a", "b"):
        c0, c1 = (e.clients[cid].offset for e in engines)
        assert (c0.offset, c0.last_tag, c0.last_arrival, c0.latest) == \
            (c1.offset, c1.last_tag, c1.last_arrival, c1.latest)
        assert list(c0.estimator._mins) == list(c1.estimator._mins)
        assert engines[0].clients[cid].restarts == engines[1].clients[cid].restarts > 0


# ---------------------------------------------------------------- views and replies

def register(engine: Engine, host: str, port: int, source=("127.0.0.1", 7000)) -> None:
    engine.handle_datagram(encode_message("/registerView", host, port), source)


def test_views_are_deduplicated_by_address_however_written():
    out = Recorder()
    engine, clock = engine_with(transport=out)
    for host in ("127.0.0.1", "127.1", "0x7f000001", "2130706433", "127.000.000.001",
                 "localhost", "0177.0.0.1"):
        register(engine, host, 9000)
    assert engine.views == [("127.0.0.1", 9000)]
    assert canonical_ipv4("example.org") is None


def test_a_view_outside_the_allow_list_or_over_the_cap_is_refused():
    out = Recorder()
    rig = Rig(limits=LimitSettings(max_views=3))
    rig.allow_views = Networks(["127.0.0.1"])
    engine, clock = engine_with(rig, out)
    register(engine, "127.0.0.2", 9000)
    for port in range(9000, 9010):
        register(engine, "127.0.0.1", port)
    assert len(engine.views) == 3
    drops = engine.drops.snapshot()["127.0.0.1:7000"]
    assert drops == {"not_allowed": 1, "too_many_views": 7}


def test_views_expire_unless_they_register_again():
    out = Recorder()
    rig = Rig(limits=LimitSettings(view_ttl_s=10.0))
    engine, clock = engine_with(rig, out)
    register(engine, "127.0.0.1", 9000)
    register(engine, "127.0.0.1", 9001)
    for _ in range(5):   # 9000 re-registers every 4 s (as Kuatro views may); 9001 never does
        clock.advance(4.0)
        register(engine, "127.0.0.1", 9000)
        engine.tick()
    assert engine.views == [("127.0.0.1", 9000)]
    assert engine.output.expired == 1


def test_a_view_the_kernel_reports_unreachable_is_dropped():
    from stage.sensors.protocol import ViewUnreachable
    engine, clock = engine_with(transport=Recorder())
    register(engine, "127.0.0.1", 9000)
    for _ in range(LimitSettings().view_send_errors):
        engine.process([Inbound(ViewUnreachable("127.0.0.1", 9000), clock.now(), ("engine", 0))])
    assert engine.views == [] and engine.output.dropped_unreachable == 1


def test_the_stats_reply_always_fits_one_datagram():
    engine, clock = engine_with(Rig(limits=LimitSettings(max_clients=1000, max_drop_keys=5000)))
    for k in range(900):
        feed(engine, encode_message("/registerDevice", f"sensor-{k:04d}", "t" * 64))
        engine.drops.add(f"junk-{k}", "malformed")
    reply = encode_stats(engine.stats(), 8192)
    assert len(reply) <= 8192
    body = json.loads(OscMessage(reply).params[0])
    assert "truncated" in body and body["drops_total"] == 900
    assert len(body["clients"]) < 900


def test_stats_are_answered_only_to_allowed_addresses():
    out = Recorder()
    rig = Rig()
    rig.allow_views = Networks(["127.0.0.1"])
    engine, clock = engine_with(rig, out)
    engine.handle_datagram(encode_message("/stage/stats"), ("127.0.0.1", 7001))
    engine.handle_datagram(encode_message("/stage/stats", 9999), ("127.0.0.2", 7002))
    assert [a for a, _ in out.sent] == [("127.0.0.1", 7001)]


# ---------------------------------------------------------------- the calibrator

@pytest.mark.parametrize("n", [9, 100, 1000])
def test_the_nth_sensor_id_crashes_nothing(n, caplog):
    rig = Rig(reference="s0", limits=LimitSettings(max_clients=64))
    engine, clock = engine_with(rig)
    calibrator = attach_live(engine, None, threaded=False)
    try:
        for k in range(n):
            clock.advance(0.001)
            feed(engine, frame(f"s{k}", where=(0.0, 2.5)), ("127.0.0.1", 5000 + k % 1000))
        clock.advance(0.1)
        feed(engine, frame("s0"), ("127.0.0.1", 5000))
    finally:
        calibrator.stop()
    assert calibrator.crashes == 0, calibrator.last_crash
    assert engine.drops.total("internal_error") == 0
    assert "it is disabled" not in caplog.text


def test_a_calibrator_failure_is_logged_counted_and_restarted(caplog):
    engine, clock = engine_with(Rig(reference="s0"))
    calibrator = attach_live(engine, None, threaded=False)
    boom = {"n": 1}
    original = calibrator._new_state

    def failing(frame):
        if boom["n"]:
            boom["n"] -= 1
            raise RuntimeError("a bug")
        return original(frame)
    calibrator._new_state = failing
    feed(engine, frame("s0"))
    clock.advance(0.05)
    feed(engine, frame("s0"))
    assert calibrator.crashes == 1 and "a bug" in calibrator.last_crash
    assert calibrator._observe in engine.frame_observers        # still attached
    assert "s0" in calibrator.states()                          # working again
    assert "restarted" in caplog.text
    calibrator.stop()


# ---------------------------------------------------------------- over UDP

@pytest.mark.integration
def test_a_stranger_cannot_make_the_server_send_anything():
    rig = Rig()
    rig.allow_sensors = Networks(["127.0.0.1"])
    rig.allow_views = Networks(["127.0.0.1"])
    victim = Peer("127.0.0.3")
    stranger = Peer("127.0.0.2")
    with Server(rig, LOCALHOST, 0) as server:
        sensor = Sensor("k", server.address)
        for _ in range(3):
            stranger.send_message(server.address, "/registerView", "127.0.0.3", victim.port)
            stranger.send_message(server.address, "/stage/stats", victim.port)
            stranger.send_message(server.address, "/stage/health", victim.port)
        sensor.register()
        sensor.frame(0, standing_pose((0.0, 2.5), np.pi))
        stats = query_stats(server.address)
        sensor.close()
    assert victim.drain() == [] and stranger.drain() == []
    assert stats["drops"][OTHER] == {"not_allowed": 9}
    victim.close()
    stranger.close()


@pytest.mark.integration
def test_a_closed_view_port_is_dropped_by_the_servers_own_socket():
    rig = Rig(limits=LimitSettings(view_send_errors=3))
    gone = Peer()
    port = gone.port
    gone.close()                                    # nobody listens there any more
    with Server(rig, LOCALHOST, 0) as server:
        sensor = Sensor("k", server.address)
        sensor.send_message(server.address, "/registerView", LOCALHOST, port)
        view = Peer()
        sensor.send_message(server.address, "/registerView", LOCALHOST, view.port)
        body = standing_pose((0.0, 2.5), np.pi)
        for k in range(40):
            sensor.frame(0, body + 0.001 * k)
            stats = sync(server.address, view)
            if stats["counts"]["views_unreachable"]:
                break
        sensor.close()
    assert stats["counts"]["views_unreachable"] == 1
    assert stats["views"] == [f"{LOCALHOST}:{view.port}"]      # the live one stays
    assert view.messages("/jointCoordinates")
    view.close()


@pytest.mark.integration
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SO_RXQ_OVFL is Linux's")
def test_datagrams_the_kernel_drops_are_counted_too():
    import threading
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)   # a queue that overflows
    sock.bind((LOCALHOST, 0))
    drops = DropCounter()
    got: list[Inbound] = []
    receiver = Receiver(sock, got.append, drops, ManualClock(0.0), 1e9, None, 1e9)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    data = encode_message("/lostUser", "k", 0) + b""
    n = 400
    for _ in range(n):                       # nobody reads yet: most are dropped by the kernel
        sender.sendto(data, sock.getsockname())
    stop = threading.Event()
    thread = threading.Thread(target=receiver.run, args=(stop,), daemon=True)
    thread.start()
    deadline = time.monotonic() + 5
    while len(got) + receiver.kernel_drops < n and time.monotonic() < deadline:
        # the kernel reports its count on the next datagram read: send one more now and then
        sender.sendto(data, sock.getsockname())
        n += 1
        time.sleep(0.05)
    stop.set()
    thread.join(2)
    sender.close()
    sock.close()
    assert receiver.kernel_drops > 0
    assert drops.snapshot()["(kernel)"]["kernel_overflow"] == receiver.kernel_drops
    assert len(got) + receiver.kernel_drops == n        # every datagram: read or counted
