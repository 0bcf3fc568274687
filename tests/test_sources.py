"""Sources through the stage.sources.v1 entry points, and one show for every command (issue 9).

The built-in sources (sim, replay, webcam, kinect2, azure) are found exactly like
a third party's; a third-party source made on the fly (a dist-info on sys.path,
as pip leaves it) runs through `stage client NAME` into a real UDP peer and feeds
a live show. Offline, one recording gives the same fused output bit for bit
through `stage replay --offline` and `stage play --replay --offline`.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from stage import DISTRIBUTION
from stage.app.show import Show, ShowOptions
from stage.errors import ConfigError, StageError
from stage.sensors.protocol import JointCoordinates, decode_datagram
from stage.sensors.replay import ReplaySource
from stage.sensors.sim import SimSource, Simulator
from stage.sensors.source import GROUP, Source, discover_sources, load_source
from test_plugins import make_distribution

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "stage.cli"]

WAVING = '''
import math, threading, time
import numpy as np
from stage.joints import HandState
from stage.sensors.source import ThreadedSource
from stage.sensors.clients.osc import BodyFrame, ClientEncoder, UdpSender


class Waving(ThreadedSource):
    """a standing person waving, from a third party"""
    name = "waving"
    description = "a standing person waving"

    def __init__(self, frames=60):
        super().__init__()
        self.frames = frames

    def _run(self, target, stop):
        encoder, sender = ClientEncoder("waver", "test"), UdpSender(target)
        joints = np.zeros((25, 3)) + [0.0, 1.0, 2.5]
        joints[:, 1] += np.linspace(-0.9, 0.7, 25)
        sender.send(encoder.register())
        for k in range(self.frames):
            if stop.is_set():
                break
            wave = joints.copy()
            wave[7] += [0.3 * math.sin(k / 5), 0.5, 0]
            sender.send(encoder.frame([BodyFrame("w", wave, np.ones(25), (HandState.OPEN,) * 2)],
                                      time.time()))
            self.sent += 1
            stop.wait(1 / 30)
        sender.close()
'''


@pytest.fixture
def site(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    make_distribution(site, "stage-waving", {"waving": "stage_waving:Waving",
                                             "nope": "stage_nope:Nope"},
                      {"stage_waving": WAVING, "stage_nope": "import not_installed_anywhere\n"},
                      group=GROUP)
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", str(site))
    return site


def test_the_built_in_sources_are_found_through_entry_points():
    found = discover_sources()
    for name in ("sim", "replay", "webcam", "kinect2", "azure"):
        info = found[name]
        assert info.loaded and info.distribution == DISTRIBUTION, info
        assert issubclass(info.obj, Source) and info.obj.name == name
    assert found["sim"].obj.offline and found["replay"].obj.offline
    assert not found["webcam"].obj.offline


def test_an_unknown_or_broken_source_is_one_clear_error(site):
    with pytest.raises(ConfigError, match=r"no source named 'kinect9' is installed \(installed: "
                                          r"azure, .*waving, webcam"):
        load_source("kinect9")
    with pytest.raises(StageError, match="the nope source failed to load: ModuleNotFoundError"):
        load_source("nope")


def test_a_source_without_its_library_fails_with_a_hint_not_a_traceback():
    source = load_source("kinect2", client_id="k").start(("127.0.0.1", 9))
    assert source.wait(10.0)
    assert "Kinect" in source.error and "pip install" in source.error


def test_the_simulator_source_is_deterministic_offline():
    a = list(SimSource("default", seed=4, duration=2.0).items())
    b = list(SimSource("default", seed=4, duration=2.0).items())
    assert a == b and len(a) > 100
    assert [x[0] for x in a] == sorted(x[0] for x in a)        # arrival order
    direct = [(d.arrival, d.source, d.data) for d in Simulator("default", seed=4).stream(2.0)]
    assert a == direct


def test_the_replay_source_gives_the_recording_as_recorded(tmp_path):
    path = tmp_path / "take.rec"
    Simulator("default", seed=2).record(str(path), 2.0)
    source = ReplaySource(path)
    items = list(source.items())
    assert items[0][0] == source.start_time
    assert abs(source.duration - (items[-1][0] - items[0][0])) < 1e-9
    assert source.rig() is not None and source.rig().reference == "kinect-a"


@pytest.mark.integration
def test_a_third_party_source_runs_as_a_client_into_a_real_udp_peer(site):
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    peer.settimeout(10.0)
    port = peer.getsockname()[1]
    proc = subprocess.Popen([*CLI, "client", "waving", "--to", f"127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    frames = 0
    try:
        while frames < 60:
            data, _ = peer.recvfrom(65536)
            frames += sum(isinstance(m, JointCoordinates)
                          for m, _ in decode_datagram(data).messages)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        peer.close()
    assert proc.returncode == 0, err
    assert frames == 60
    assert "stage client: waving" in out


@pytest.mark.integration
def test_a_third_party_source_feeds_a_live_show(site):
    fused = []
    show = Show(ShowOptions(source="waving", source_options={"frames": 45}, plugins=False))
    show.start()
    show.engine.listeners.append(lambda frame: fused.append(frame))
    show.wait()          # ends when the source does
    result = show.stop()
    assert result.stats["clients"]["waver"]["frames"] == 45
    assert any(frame.bodies for frame in fused)


def test_one_recording_gives_the_same_fused_output_through_replay_and_play(tmp_path):
    """`stage replay --offline` and `stage play --replay --offline` run the same show."""
    rec = tmp_path / "take.rec"
    Simulator("duet", seed=5).record(str(rec), 8.0)
    a, b = tmp_path / "replay.jsonl", tmp_path / "play.jsonl"
    for healing in ([], ["--no-self-healing"]):
        done = subprocess.run([*CLI, "--quiet", "replay", str(rec), "--offline", "--fused", str(a),
                               *healing], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        done = subprocess.run([*CLI, "--quiet", "play", str(ROOT / "pieces" / "liminal.yaml"),
                               "--replay", str(rec), "--offline", "--fused", str(b), "--seed", "1",
                               "--midi-file", str(tmp_path / "x.mid"), *healing],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        lines = a.read_text().splitlines()
        assert len(lines) > 100
        assert a.read_bytes() == b.read_bytes()
        assert all(json.loads(line)["t"] >= 0 for line in lines[:3])


def test_offline_show_matches_a_live_engine_fed_the_same_datagrams(tmp_path):
    """The offline driver gives what the library's own offline run gives: one definition."""
    from stage.app.offline import offline_engine, replay_offline
    from stage.frames import fused_json
    rec = tmp_path / "take.rec"
    Simulator("default", seed=7).record(str(rec), 5.0)
    engine, clock = offline_engine(rec)
    direct: list[str] = []
    engine.listeners.append(lambda f: direct.append(json.dumps(fused_json(f))))
    from stage.calibration import attach_live
    attach_live(engine, None, threaded=False, save=False)
    replay_offline(rec, engine, clock)
    out = tmp_path / "show.jsonl"
    Show(ShowOptions(replay=str(rec), offline=True, fused=str(out), plugins=False)).run()
    assert out.read_text().splitlines() == direct
