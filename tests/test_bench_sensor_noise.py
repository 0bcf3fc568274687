"""bench/bench_sensor_noise.py's Kinect v2 reader and statistics, on NTU files made here.

The bench compares real recordings with the simulator; these tests check that
what it reads and pools is what is in the files: tracked and inferred joints
apart, frames without a body left out, short detections dropped, and bad files
refused with one line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import bench_sensor_noise as bench  # noqa: E402

from stage.joints import JOINT_INDEX as J  # noqa: E402
from stage.sensors.importers.ntu import NtuBody, write_skeleton_file  # noqa: E402

BODY = 72057594037927936


def body(body_id: int, positions: np.ndarray, states: np.ndarray) -> NtuBody:
    joints = np.zeros((25, 12))
    joints[:, :3] = positions
    joints[:, 11] = states
    return NtuBody(body_id, 0, 1, 1, 1, 1, 0, (0.0, 0.0), 2, joints)


def zigzag(n: int, step_m: float, seed: int = 0) -> np.ndarray:
    """(n, 25, 3): a person 3 m away whose every joint alternates +-step_m on every axis,
    so every |second difference| is exactly 4 * step_m."""
    rng = np.random.default_rng(seed)
    rest = rng.uniform(-0.5, 0.5, (25, 3)) + [0.0, 0.0, 3.0]
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)[:, None, None]
    return rest + sign * step_m


def test_window_deviation_is_zero_for_still_and_steadily_moving_joints():
    t = np.arange(40, dtype=float)
    still = np.ones((40, 2, 3))
    ramp = np.stack([t, 2 * t, -t], axis=1)[:, None, :].repeat(2, axis=1)
    assert np.allclose(bench.window_deviations(still), 0)
    assert np.allclose(bench.window_deviations(ramp), 0)
    assert bench.window_deviations(still).shape == (40 - bench.WINDOW + 1, 2, 3)
    assert bench.window_deviations(still[:10]).shape[0] == 0


def test_ntu_jitter_pools_tracked_and_inferred_joints_apart(tmp_path):
    n = 40
    pos = zigzag(n, 0.001)
    states = np.full((n, 25), 2)
    feet = [J[k] for k in ("AnkleLeft", "AnkleRight", "FootLeft", "FootRight")]
    states[20:, feet] = 1                          # feet inferred in the second half
    noisy = pos.copy()
    noisy[20:, feet] += np.where(np.arange(20) % 2 == 0, 0.004, -0.004)[:, None, None]
    frames = [[body(BODY, noisy[k], states[k])] for k in range(n)]
    write_skeleton_file(tmp_path / "S001C001P001R001A001.skeleton", frames)

    got = bench.kinect2_jitter(str(tmp_path))
    torso, n_torso = got["tracked"]["torso"]
    assert np.allclose(torso, 4.0) and n_torso == (n - 2) * 7
    tracked_feet, n_tracked = got["tracked"]["ankles, feet"]
    assert np.allclose(tracked_feet, 4.0) and n_tracked == 18 * 4     # triples ending <= 19
    inferred_feet, n_inferred = got["inferred"]["ankles, feet"]
    assert n_inferred == (n - 2 - 18) * 4
    assert np.all(inferred_feet > 4.0)                                  # the extra zigzag
    assert got["inferred"]["torso"][1] == 0
    f = got["facts"]
    assert (f["files"], f["bodies"], f["performers"], f["frame_triples"]) == (1, 1, 1, n - 2)
    assert f["joint_states"] == {"tracked": n * 25 - 20 * 4, "inferred": 20 * 4,
                                 "not tracked": 0}
    assert f["depth_m"][1] == pytest.approx(pos[:, J["SpineBase"], 2].mean(), abs=0.002)


def test_frames_without_the_body_and_short_detections_are_left_out(tmp_path):
    n = 40
    a = zigzag(n, 0.002, seed=1)
    b = zigzag(n, 0.0005, seed=2)
    tracked = np.full(25, 2)
    frames = []
    for k in range(n):
        bodies = [] if k == 10 else [body(BODY, a[k], tracked)]        # a gap in one frame
        if k < 5:                                                      # a 5-frame ghost
            bodies.append(body(BODY + 1, b[k] + 1.0, tracked))
        frames.append(bodies)
    write_skeleton_file(tmp_path / "S002C003P004R001A005.skeleton", frames)
    got = bench.kinect2_jitter(str(tmp_path))
    assert got["facts"]["bodies"] == 1
    assert got["facts"]["frame_triples"] == n - 2 - 3                  # 3 triples hold frame 10
    assert np.allclose(got["tracked"]["torso"][0], 8.0)


def test_a_malformed_file_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    (tmp_path / "S001C001P001R001A001.skeleton").write_text("2\n1\nnot a body line\n")
    monkeypatch.setattr(sys, "argv", ["bench", "--kinect2", str(tmp_path), "--quick"])
    assert bench.main() == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench: ") and ".skeleton:3: a body line" in err[0]


def kinectron_frame(body_id: str, t_ms: float, positions: np.ndarray) -> dict:
    return {"bodyIndex": 0, "tracked": True, "trackingId": body_id, "leftHandState": 1,
            "rightHandState": 1, "record_startime": 1518026639637, "record_timestamp": t_ms,
            "joints": [{"cameraX": x, "cameraY": y, "cameraZ": z, "depthX": 0.5}
                       for x, y, z in positions]}


def test_kinectron_frames_go_on_the_30_hz_grid_by_their_time_stamps(tmp_path):
    import json
    n = 40
    pos = zigzag(n, 0.001, seed=3)
    frames = [kinectron_frame("72057594037928243", 11 + 1000 * k / 30 + (k % 3 - 1) * 4,
                              pos[k]) for k in range(n) if k not in (20, 21)]  # 2 missed
    (tmp_path / "take.json").write_text(json.dumps(frames))
    assert bench.detect_format(str(tmp_path)) == "kinectron"
    got = bench.kinect2_jitter(str(tmp_path), "kinectron")
    assert not got["facts"]["states"] and got["facts"]["bodies"] == 1
    # the two missed frames are absent, not shorter steps: 4 triples hold one of them
    assert got["facts"]["frame_triples"] == n - 2 - 4
    assert np.allclose(got["tracked"]["ankles, feet"][0], 4.0)
    assert got["inferred"]["torso"][1] == 0


def test_a_file_that_is_not_a_kinectron_recording_is_refused(tmp_path):
    (tmp_path / "take.json").write_text('[{"trackingId": "1", "joints": []}]')
    with pytest.raises(bench.ConfigError, match="take.json.*not a Kinectron body recording"):
        bench.kinect2_jitter(str(tmp_path), "kinectron")


def test_a_folder_without_a_long_enough_body_is_one_line_and_exit_2(tmp_path, capsys,
                                                                     monkeypatch):
    n = bench.WINDOW - 1
    pos = zigzag(n, 0.001)
    write_skeleton_file(tmp_path / "S001C001P001R001A001.skeleton",
                        [[body(BODY, pos[k], np.full(25, 2))] for k in range(n)])
    monkeypatch.setattr(sys, "argv", ["bench", "--kinect2", str(tmp_path), "--quick"])
    assert bench.main() == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no ntu bodies seen for 0.5 s or more" in err[0]
