"""`stage sim`, `stage replay --offline`: the commands a composer and an installer type."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import Peer

from stage.cli.main import main
from stage.sensors.recording import read_recording
from stage.rig import load_rig
from stage.sensors.sim import Simulator, load_truth


def test_sim_writes_recording_truth_and_rig(tmp_path, capsys):
    rec, truth, rig = tmp_path / "t.rec", tmp_path / "t.npz", tmp_path / "rig.yaml"
    assert main(["sim", "--out", str(rec), "--truth", str(truth), "--rig-out", str(rig),
                 "--duration", "3", "--seed", "5"]) == 0
    out = capsys.readouterr().out
    assert "scenario 'default' (3 sensor(s), 1 performer(s)), seed 5: 3 s" in out
    meta = read_recording(rec).meta
    assert meta["seed"] == 5 and meta["scenario"] == "default" and "rig" in meta
    t = load_truth(str(truth))
    assert t.names == ["dancer"] and t.joints.shape == (90, 1, 25, 3)
    sim = Simulator("default", seed=5)
    np.testing.assert_allclose(t.joints[45, 0], sim.truth(1.5)["dancer"][0], atol=1e-5)
    loaded = load_rig(str(rig))
    for sid in ("kinect-a", "kinect-b", "kinect-c"):
        np.testing.assert_allclose(loaded.transform_for(sid), sim.rig().transform_for(sid),
                                   atol=1e-9)


def test_replay_offline_prints_a_summary_and_writes_fused_frames(tmp_path, capsys):
    rec, fused = tmp_path / "t.rec", tmp_path / "fused.jsonl"
    assert main(["sim", "--out", str(rec), "--duration", "4"]) == 0
    assert main(["replay", str(rec), "--offline", "--fused", str(fused)]) == 0
    out = capsys.readouterr().out
    assert "x real time)" in out and "1 person(s) at the end" in out
    frames = [json.loads(line) for line in fused.read_text().splitlines()]
    assert len(frames) > 100
    assert frames[0]["new"] == [1] and set(frames[-1]["bodies"]["1"]["sensors"]) == {
        "kinect-a", "kinect-b", "kinect-c"}


@pytest.mark.parametrize("argv, message", [
    (["sim", "no-such-scenario"], "no built-in scenario 'no-such-scenario'"),
    (["sim", "missing.yaml"], "missing.yaml: no such file"),
    (["replay", "missing.rec"], "missing.rec: no such file"),
    (["replay", "x.rec", "--offline", "--to", "127.0.0.1:9"], "--offline runs the engine here"),
])
def test_one_line_errors(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if "x.rec" in argv:
        Simulator("default").record(str(tmp_path / "x.rec"), 0.5)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stage: ") and message in err and "\n" not in err


def test_sim_needs_a_duration_for_a_recording_without_one(tmp_path, capsys):
    scenario = tmp_path / "open.yaml"
    scenario.write_text("performers: [{name: p}]\n")
    assert main(["sim", str(scenario), "--out", str(tmp_path / "x.rec")]) == 2
    assert "give --duration" in capsys.readouterr().err


@pytest.mark.integration
def test_sim_over_udp_at_max_speed_sends_what_datagrams_yields():
    with Peer() as server:
        assert main(["sim", "--to", f"127.0.0.1:{server.port}", "--duration", "1",
                     "--max-speed", "--seed", "2"]) == 0
        server.drain()  # everything was sent before main returned
    expected = [d for _, _, d in Simulator("default", seed=2).datagrams(1.0)]
    addresses = [m.address for m in server.received]
    assert addresses.count("/registerDevice") == 3
    assert addresses.count("/jointCoordinates") == sum(d.count(b"/jointCoordinates")
                                                       for d in expected) > 50
