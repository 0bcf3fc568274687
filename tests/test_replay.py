"""Replay: offline bit-for-bit, cut recordings, real time over UDP, timetags, `stage record`."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from helpers import free_udp_port, query_stats

from stage.clock import ManualClock
from stage.engine.engine import Engine
from stage.sensors.protocol import JointCoordinates, decode_datagram, encode_bundle, encode_message
from stage.sensors.recording import RecordingWriter, read_recording
from stage.app.offline import feed, offline_engine, replay_offline
from stage.app.server import Server
from stage.frames import fused_json
from stage.sensors.replay import ReplaySource, _retimed, rig_from_meta
from stage.sensors.sim import Simulator


def fused_log(engine: Engine) -> list[str]:
    out: list[str] = []
    engine.listeners.append(lambda frame: out.append(json.dumps(fused_json(frame))))
    return out


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """A simulated live run fed into an engine, recorded on the way."""
    path = tmp_path_factory.mktemp("rec") / "live.rec"
    sim = Simulator("default", seed=11)
    clock = ManualClock(0.0)
    engine = Engine(sim.rig(), clock)
    log = fused_log(engine)
    with RecordingWriter(path, sim.meta()) as writer:
        feed(engine, clock, sim.stream(12.0), until=12.0, recorder=writer)
    return path, log, engine


def test_replay_gives_the_live_runs_fused_output_bit_for_bit(live_run):
    path, live, live_engine = live_run
    engine, clock = offline_engine(path)  # the rig stored in the recording
    replayed = fused_log(engine)
    replay_offline(path, engine, clock, until=12.0)
    assert len(replayed) == len(live) > 300
    assert replayed == live
    assert engine.counts == live_engine.counts


def test_same_recording_twice_same_output(live_run):
    path = live_run[0]
    outs = []
    for _ in range(2):
        engine, clock = offline_engine(path)
        outs.append(fused_log(engine))
        replay_offline(path, engine, clock)
    assert outs[0] == outs[1] and outs[0]


def test_a_recording_cut_mid_record_replays_up_to_the_cut(live_run, tmp_path):
    path = live_run[0]
    records = list(read_recording(path))
    data = path.read_bytes()
    cut = tmp_path / "cut.rec"
    cut.write_bytes(data[:len(data) * 2 // 3 + 7])  # 7 bytes into some record
    survivors = list(read_recording(cut))
    assert survivors == records[:len(survivors)] and 0 < len(survivors) < len(records)
    engine, clock = offline_engine(cut)
    n = replay_offline(cut, engine, clock)
    assert n == len(survivors)
    skeletons = sum(isinstance(m, JointCoordinates) for r in survivors
                    for m, _ in decode_datagram(r.data).messages)
    assert engine.counts["frames"] == skeletons
    assert len(engine.bodies()) == 1


def test_the_recording_carries_the_exact_rig(live_run):
    rig = rig_from_meta(read_recording(live_run[0]).meta)
    sim = Simulator("default", seed=11)
    for sid in sim.sensor_poses():
        np.testing.assert_allclose(rig.transform_for(sid), sim.rig().transform_for(sid))


def test_retiming_moves_bundle_timetags_only():
    msg = encode_message("/handState", "k", 0, "left", "open")
    data = encode_bundle([msg, encode_bundle([msg], 1000.5)], 1000.0)
    out = _retimed(data, lambda t: t + 25.0)
    decoded = decode_datagram(out)
    assert [round(tt, 4) for _, tt in decoded.messages] == [1025.0, 1025.5]
    assert out[16:16 + 4 + len(msg)] == data[16:16 + 4 + len(msg)]
    assert _retimed(msg, lambda t: t + 1) == msg
    immediate = encode_bundle([msg], None)
    assert _retimed(immediate, lambda t: t + 1) == immediate


@pytest.mark.integration
def test_looping_keeps_sensor_clocks_going_forward(live_run):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)
    got: list[bytes] = []
    done = threading.Event()

    def receive() -> None:  # a real UDP peer reading everything the replay sends
        while not done.is_set():
            try:
                got.append(sock.recvfrom(65536)[0])
            except socket.timeout:
                continue
    reader = threading.Thread(target=receive, daemon=True)
    reader.start()
    source = ReplaySource(live_run[0], speed=float("inf"), loop=True).start(sock.getsockname())
    deadline = time.monotonic() + 10.0
    while source.loops < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    source.stop()
    time.sleep(0.2)
    done.set()
    reader.join(2.0)
    sock.close()
    assert source.loops >= 2
    last: dict[str, float] = {}
    n = 0
    for data in got:
        for message, timetag in decode_datagram(data).messages:
            client = getattr(message, "client", None)
            if timetag is None or client is None:
                continue
            assert timetag >= last.get(client, -1.0), client
            last[client] = timetag
            n += 1
    assert n > 2 * 1000


@pytest.mark.integration
def test_real_time_replay_over_udp_reaches_a_server(live_run):
    path = live_run[0]
    rig = rig_from_meta(read_recording(path).meta)
    rig.port = 0
    with Server(rig, host="127.0.0.1") as server:
        started = time.monotonic()
        source = ReplaySource(path, speed=6.0).start(server.address)
        assert source.wait(10.0)
        elapsed = time.monotonic() - started
        stats = query_stats(server.address)
        stats = query_stats(server.address)
    records = list(read_recording(path))
    span = records[-1].arrival - records[0].arrival
    assert span / 6.0 * 0.9 < elapsed < span / 6.0 + 2.0  # paced, not dumped
    assert set(stats["clients"]) == {"kinect-a", "kinect-b", "kinect-c"}
    assert {r for d in stats["drops"].values() for r in d} <= {"non_finite"}
    skeletons = sum(isinstance(m, JointCoordinates) for r in records
                    for m, _ in decode_datagram(r.data).messages)
    assert stats["counts"]["frames"] == skeletons
    assert len(stats["persons"]) == 1


@pytest.mark.integration
def test_stage_record_killed_loses_at_most_the_last_second(tmp_path):
    port = free_udp_port()
    out = tmp_path / "killed.rec"
    proc = subprocess.Popen([sys.executable, "-m", "stage.cli", "record", "--out", str(out),
                             "--port", str(port), "--host", "127.0.0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        line = proc.stdout.readline().decode()
        assert "stage record" in line, line + proc.stderr.read().decode()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sent = []
        for k in range(40):
            data = encode_message("/handState", "k", 0, "left", "open") + b""
            data = encode_bundle([data], 1000.0 + k)
            sock.sendto(data, ("127.0.0.1", port))
            sent.append(data)
            time.sleep(0.01)
        sock.close()
        time.sleep(1.2)  # more than the flush interval: all of it must be on disk
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        proc.stdout.close()
        proc.stderr.close()
    rec = read_recording(out)
    got = [r.data for r in rec]
    assert got == sent
    assert rec.meta["source"] == "stage record"
