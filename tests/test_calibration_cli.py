"""``stage calibrate``: recordings in, rig and JSON and pictures out; ``--live`` over real UDP."""

from __future__ import annotations

import dataclasses
import json
import socket
import threading
import time

import numpy as np
import pytest

from stage.geometry import transform_error
from stage.calibration.synth import relative, simulate, two_sensor_rig, wander
from stage.cli.main import main
from stage.sensors.protocol import encode_bundle, encode_client_joints, encode_message
from stage.rig import Rig, load_rig

from stage.sensors import recording


def _record(path, sensors, streams, timetags: bool = True) -> None:
    """Write simulated streams as a stage recording: raw datagrams, arrival = true time.

    With ``timetags`` each frame is a bundle stamped with the sensor's own clock
    (its ``clock_offset_s``) and no capture time is recorded, so the lag must be found.
    """
    items = []
    for sensor in sensors:
        s = streams[sensor.id]
        for k in range(len(s)):
            true_t = s.t[k] - sensor.clock_offset_s
            msg = encode_client_joints(sensor.id, int(s.user[k]), s.joints[k], s.conf[k])
            data = encode_bundle([msg], 1_700_000_000.0 + s.t[k]) if timetags else msg
            items.append((true_t + 0.07, data))
        plane = sensor.floor_plane()
        items.append((0.5, encode_message("/floorPlane", sensor.id, *map(float, plane))))
    items.sort(key=lambda i: i[0])
    with recording.RecordingWriter(path, {"source": "test"}, background=False) as writer:
        for arrival, data in items:
            writer.write(arrival, ("127.0.0.1", 9000), data, None)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    rig = two_sensor_rig()
    rig[1] = dataclasses.replace(rig[1], clock_offset_s=0.25, phase_s=0.013)
    streams = simulate(rig, wander(), 20.0, seed=2)
    path = tmp_path_factory.mktemp("rec") / "rehearsal.stagerec"
    _record(path, rig, streams)
    return str(path), rig, streams


def test_json_gives_every_sensor_its_matrix_and_figures(recorded, capsys):
    path, rig, streams = recorded
    assert main(["--quiet", "calibrate", path, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["reference"] == "kinect-a" and out["method"] == "rigid"
    b = out["sensors"]["kinect-b"]
    for key in ("matrix", "rms_m", "fitness", "pairs", "method", "lag_s"):
        assert key in b, key
    m = np.array(b["matrix"])
    assert m.shape == (4, 4)
    err = transform_error(m, relative(rig[0], rig[1]), streams["kinect-b"].joints)
    assert err["rot_deg"] < 0.5 and err["rms_mm"] < 20, err
    assert b["lag_s"] == pytest.approx(0.25, abs=0.01)   # the clocks differed by 0.25 s
    assert b["pairs"] == 300 and b["method"] == "rigid"
    assert 0.8 < b["fitness"] <= 1 and 0 < b["rms_m"] < 0.05
    assert out["sensors"]["kinect-a"]["method"] == "reference"


@pytest.mark.parametrize("method", ["ga", "floor", "regression"])
def test_other_methods_from_the_command_line(recorded, capsys, method):
    path, rig, streams = recorded
    assert main(["--quiet", "calibrate", path, "--json", "--method", method]) == 0
    b = json.loads(capsys.readouterr().out)["sensors"]["kinect-b"]
    assert b["method"] == method
    err = transform_error(np.array(b["matrix"]), relative(rig[0], rig[1]),
                          streams["kinect-b"].joints)
    assert err["rms_mm"] < (110 if method == "regression" else 25), err


def test_rig_file_gets_the_calibration_section(recorded, tmp_path, capsys):
    path, rig, streams = recorded
    rig_path = tmp_path / "rig.yaml"
    existing = Rig(views=[("127.0.0.1", 9100)])
    existing.save(str(rig_path))
    assert main(["--quiet", "calibrate", path, "--rig", str(rig_path)]) == 0
    table = capsys.readouterr().out
    assert "kinect-b" in table and "rigid" in table
    loaded = load_rig(str(rig_path))
    assert loaded.reference == "kinect-a" and loaded.views == [("127.0.0.1", 9100)]
    cal = loaded.sensors["kinect-b"].calibration
    assert cal.method == "rigid" and 0.8 < cal.fitness <= 1 and cal.date
    err = transform_error(loaded.transform_for("kinect-b"), relative(rig[0], rig[1]))
    assert err["rot_deg"] < 0.5, err


def test_plot_writes_a_png(recorded, tmp_path):
    pytest.importorskip("matplotlib", reason="matplotlib is not installed")
    path, _, _ = recorded
    png = tmp_path / "calib.png"
    assert main(["--quiet", "calibrate", path, "--plot", str(png)]) == 0
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000


@pytest.mark.parametrize("argv, message", [
    (["calibrate"], "give a RECORDING"),
    (["calibrate", "/no/such/file.stagerec"], "no such file"),
    (["calibrate", "x.stagerec", "--live"], "not both"),
    (["calibrate", "{rec}", "--lag", "soon"], "--lag must be"),
    (["calibrate", "{rec}", "--reference", "kinect-z"], "sent no skeletons"),
    (["calibrate", "{rec}", "--rig", "/no/such/folder/rig.yaml"], "does not exist"),
])
def test_bad_input_is_one_line_and_exit_2(recorded, capsys, argv, message):
    argv = [a.replace("{rec}", recorded[0]) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_not_a_recording_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "notes.txt"
    bad.write_text("hello")
    assert main(["calibrate", str(bad)]) in (1, 2)   # the recording module's error class decides
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a stage recording" in err[0], err


def test_the_simulators_recording_calibrates_to_its_true_poses(tmp_path, capsys):
    sim_mod = pytest.importorskip("stage.sensors.sim", reason="the simulator (stage.sim) is not in "
                                  "this tree")
    sim = sim_mod.Simulator(sim_mod.load_scenario("default"), seed=3)
    path = tmp_path / "sim.stagerec"
    sim.record(str(path), 25.0)
    assert main(["--quiet", "calibrate", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    poses = sim.sensor_poses(0.0)
    ref = out["reference"]
    for sid, entry in out["sensors"].items():
        truth = np.linalg.inv(poses[ref].to_stage) @ poses[sid].to_stage
        err = transform_error(np.array(entry["matrix"]), truth)
        assert err["rot_deg"] < 0.5 and err["trans_mm"] < 30, (sid, err)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.integration
def test_live_calibration_over_udp_writes_the_rig(tmp_path, capsys):
    """Two fake Kinects send real OSC at 30 Hz to ``stage calibrate --live``."""
    rig = two_sensor_rig()
    streams = simulate(rig, wander(), 30.0, seed=5)
    port = _free_port()
    rig_path = tmp_path / "rig.yaml"
    Rig(reference="kinect-a", port=port).save(str(rig_path))
    stop = threading.Event()

    def send():
        socks = {s.id: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for s in rig}
        start = time.monotonic()
        k = 0
        try:
            while not stop.is_set() and k < len(streams["kinect-a"]):
                for sid, sock in socks.items():
                    s = streams[sid]
                    sock.sendto(encode_client_joints(sid, 0, s.joints[k], s.conf[k]),
                                ("127.0.0.1", port))
                k += 1
                stop.wait(max(0.0, start + k / 30.0 - time.monotonic()))
        finally:
            for sock in socks.values():
                sock.close()

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        code = main(["--quiet", "calibrate", "--live", "--rig", str(rig_path), "--pairs", "60",
                     "--timeout", "20", "--json"])
    finally:
        stop.set()
        sender.join(5.0)
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    m = np.array(out["sensors"]["kinect-b"]["matrix"])
    truth = relative(rig[0], rig[1])
    err = transform_error(m, truth)
    assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, err
    stored = load_rig(str(rig_path))
    assert np.allclose(stored.transform_for("kinect-b"), m, atol=1e-5)
    assert stored.sensors["kinect-b"].calibration.method == "rigid (live)"
