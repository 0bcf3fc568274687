"""The rig file: loading, one-line errors with file:line:column, atomic saving."""

from __future__ import annotations

import os

import numpy as np
import pytest

from stage.errors import ConfigError
from stage.rig import Rig, load_rig, set_calibration

GOOD = """\
server: {host: 127.0.0.1, port: 7771}
reference: a
sensors:
  a: {type: kinect2}
  b:
    type: kinect2
    calibration:
      matrix: [[0, 0, 1, 2], [0, 1, 0, 0], [-1, 0, 0, 3], [0, 0, 0, 1]]
      method: rigid
      fitness: 0.97
      rms_m: 0.02
views: ["127.0.0.1:9001", "9002"]
clients: {timeout_s: 2.0}
fusion: {view_bias_m: 0.2, hand_vote: plain, hand_hold_s: 0.2}
smoothing: {enabled: false, fast_noise: 900.0, noise_per_m: 0}
"""


def write(tmp_path, text: str, name: str = "rig.yaml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_a_full_rig_loads(tmp_path):
    rig = load_rig(write(tmp_path, GOOD))
    assert (rig.host, rig.port, rig.reference) == ("127.0.0.1", 7771, "a")
    assert rig.views == [("127.0.0.1", 9001), ("127.0.0.1", 9002)]
    assert rig.clients.timeout_s == 2.0 and rig.fusion.view_bias_m == 0.2
    assert rig.fusion.hand_vote == "plain" and rig.fusion.hand_hold_s == 0.2
    assert not rig.smoothing_enabled and rig.smoothing.fast_noise == 900.0
    assert rig.smoothing.noise_per_m == 0.0
    np.testing.assert_allclose(rig.transform_for("a"), np.eye(4))
    assert rig.transform_for("b")[0, 3] == 2.0
    assert rig.transform_for("nobody") is None
    assert rig.sensors["b"].calibration.fitness == 0.97


def test_save_round_trips_and_is_atomic(tmp_path):
    path = write(tmp_path, GOOD)
    rig = load_rig(path)
    m = np.eye(4)
    m[:3, 3] = [1.5, 0.0, -2.0]
    set_calibration(rig, "c", m, "ga", fitness=0.9, rms_m=0.03)
    rig.save()
    again = load_rig(path)
    np.testing.assert_allclose(again.transform_for("c"), m)
    assert again.sensors["c"].calibration.method == "ga"
    assert again.sensors["c"].calibration.date is not None
    assert again.views == rig.views and again.fusion == rig.fusion
    assert [f for f in os.listdir(tmp_path) if f.endswith(".tmp")] == []


def test_save_failure_leaves_the_old_file(tmp_path, monkeypatch):
    path = write(tmp_path, GOOD)
    rig = load_rig(path)

    def boom(*args):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        rig.save()
    assert open(path).read() == GOOD
    assert [f for f in os.listdir(tmp_path) if f.endswith(".tmp")] == []


@pytest.mark.parametrize("text, expected", [
    ("refrence: a\n", "rig.yaml:1:1: unknown key 'refrence' in the rig; did you mean 'reference'?"),
    ("server: {port: 99999}\n", "rig.yaml:1:16: 'port' must be a whole number 1-65535, got 99999"),
    ("sensors:\n  a: {type: k, calib: {}}\n", "rig.yaml:2:16: unknown key 'calib' in sensor 'a'; "
                                              "did you mean 'calibration'?"),
    ("sensors:\n  a:\n    calibration: {matrix: [[1, 0], [0, 1]]}\n",
     "rig.yaml:3:27: 'matrix' must be a 4x4 list of finite numbers"),
    ("sensors:\n  a:\n    calibration: {method: ga}\n",
     "rig.yaml:3:18: calibration of 'a' needs a 'matrix' (4x4)"),
    ("reference: z\nsensors: {a: {}}\n", "rig.yaml:1:12: reference 'z' is not one of the sensors: a"),
    ("views: [localhost]\n", "rig.yaml:1:9: 'localhost' is not HOST:PORT with a port from 1 to 65535"),
    ("fusion: {view_bias_m: -1}\n", "rig.yaml:1:23: 'view_bias_m' must be greater than 0.0, got -1"),
    # issue 10: the keys of the old fusion go, with a line that names what replaced them
    ("fusion: {min_interval_s: 0.025}\n", "rig.yaml:1:26: 'fusion: min_interval_s' is no longer "
     "used: every sensor frame is now fused at once; there is no interval to set (see fusion: "
     "group_s, replay_s and smoothing: in CHANGELOG.md)"),
    ("fusion: {outlier_m: 0.1}\n", "rig.yaml:1:21: 'fusion: outlier_m' is no longer used: outliers "
     "are now gated by the filter: smoothing: gate_sigma and reject_sigma, and fusion: "
     "view_bias_m for views of one instant"),
    ("smoothing: {process_noise: 4}\n", "rig.yaml:1:28: 'smoothing: process_noise' is no longer "
     "used: the filter now has two motion models: smoothing: quiet_noise and fast_noise"),
    ("sensors:\n  a: {hand_reading_frames: 0}\n", "rig.yaml:2:28: 'hand_reading_frames' of "
     "sensor 'a' must be a whole number of frames 1-8 (a Kinect v2 2, a client reading hands "
     "every frame 1) or null, got 0"),
    ("fusion: {hand_reading_frames: 1.5}\n", "rig.yaml:1:31: 'hand_reading_frames' of 'fusion' "
     "must be a whole number of frames 1-8 (a Kinect v2 2, a client reading hands every frame "
     "1) or null, got 1.5"),
    ("fusion: {hand_vote: loud}\n", "rig.yaml:1:9: 'hand_vote' must be 'plain' or 'confidence', got 'loud'"),
    ("smoothing: {quiet_noise: fast}\n", "rig.yaml:1:26: 'quiet_noise' must be a number, got 'fast'"),
    ("server: [1, 2]\n", "rig.yaml:1:9: 'server' must be a mapping (key: value lines)"),
    ("server:\n  port: 1\n  port: 2\n", "rig.yaml:3:3: duplicate key 'port'"),
    ("server: {port: 1\n", "rig.yaml:2:1: YAML syntax: …"),  # wording differs between libyaml and PyYAML
])
def test_mistakes_get_one_line_errors_with_position(tmp_path, text, expected):
    with pytest.raises(ConfigError) as info:
        load_rig(write(tmp_path, text))
    message = str(info.value).replace(str(tmp_path) + os.sep, "")
    if expected.endswith("…"):
        assert message.startswith(expected[:-1])
    else:
        assert message == expected
    assert "\n" not in message


def test_hand_reading_frames_load_per_sensor_and_for_all_and_round_trip(tmp_path):
    path = write(tmp_path, "sensors:\n  a: {type: kinect2}\n  cam: {type: webcam-mediapipe, "
                           "hand_reading_frames: 1}\nfusion: {hand_reading_frames: null}\n")
    rig = load_rig(path)
    assert rig.sensors["a"].hand_reading_frames is None
    assert rig.sensors["cam"].hand_reading_frames == 1
    assert rig.fusion.hand_reading_frames is None        # null: by each sensor's type
    rig.fusion = type(rig.fusion)(hand_reading_frames=3)
    rig.save()
    again = load_rig(path)
    assert again.sensors["cam"].hand_reading_frames == 1 and again.fusion.hand_reading_frames == 3
    assert "hand_reading_frames" not in again.to_dict()["sensors"]["a"]


def test_missing_rig_file_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_rig(str(tmp_path / "nope.yaml"))


def test_empty_rig_file_gives_defaults(tmp_path):
    rig = load_rig(write(tmp_path, ""))
    assert rig.port == Rig().port and rig.sensors == {}


def test_the_forecasts_velocity_memories_load_and_zero_turns_one_off(tmp_path):
    rig = load_rig(write(tmp_path, "forecast: {foot_velocity_memory_s: 0, "
                                   "hand_velocity_memory_s: 0.079}\n"))
    assert rig.forecast.foot_velocity_memory_s == 0.0
    assert rig.forecast.hand_velocity_memory_s == 0.079
    rig.save()
    assert load_rig(rig.path).forecast == rig.forecast       # a default of 0 round-trips too
    assert load_rig(write(tmp_path, "{}\n", "empty.yaml")).forecast.foot_velocity_memory_s \
        == 0.0545
    with pytest.raises(ConfigError, match="'foot_velocity_memory_s' must be at least 0"):
        load_rig(write(tmp_path, "forecast: {foot_velocity_memory_s: -0.05}\n"))
