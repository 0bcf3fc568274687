"""Pair collection, time alignment, stream decoding and copied-stream detection."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stage.calibration.methods import calibrate
from stage.geometry import transform_error
from stage.calibration.pairs import find_lag, pair_streams
from stage.errors import CalibrationError
from stage.calibration.streams import Stream, find_identical_streams, streams_from_datagrams
from stage.sensors.sim import Simulator
from stage.testing import simdata
from stage.sensors.protocol import encode_bundle, encode_client_joints, encode_message


def _streams(offset: float = 0.0, phase: float = 0.0, seed: int = 3, duration: float = 20.0,
             lockstep: bool = False, realistic: bool = False):
    """kinect-b's clock ``offset`` s ahead, its frames ``phase`` s into each period; times on
    each sensor's own clock when there is an offset to find, else the capture times.
    ``lockstep``: no frame-time jitter and no dropped frames, so the two sensors' frames
    come at the very same instants. CLEAN unless ``realistic``: these tests hold fits to the
    clean budget's precision (docs/calibration.md); the realistic model's heavy tails and
    view-dependent bias are tested for the lag search below."""
    kinect = {} if realistic else dict(simdata.CLEAN_KINECT)
    if lockstep:
        kinect.update({"frame_jitter_s": 0.0, "drop_p": 0.0})
    sim = Simulator(simdata.two_sensors(offset_s=offset, phase_s=phase, kinect=kinect), seed)
    return sim, simdata.streams(sim, duration, "sensor" if offset else "capture")


@pytest.mark.parametrize("lag", [0.37, -0.25, 0.0])
def test_time_alignment_recovers_a_known_lag(lag):
    _, s = _streams(offset=lag, phase=0.011)
    found = find_lag(s["kinect-a"], s["kinect-b"])
    assert found.lag_s == pytest.approx(lag, abs=0.010)
    back = find_lag(s["kinect-b"], s["kinect-a"])
    assert back.lag_s == pytest.approx(-lag, abs=0.010)
    assert found.pairs >= 100 and np.nanmin(found.mse) < 0.002


@pytest.mark.parametrize("lag", [0.37, -0.25])
def test_the_lag_is_found_on_the_realistic_model(lag):
    _, s = _streams(offset=lag, phase=0.011, realistic=True)
    found = find_lag(s["kinect-a"], s["kinect-b"])
    assert found.lag_s == pytest.approx(lag, abs=0.010)
    assert find_lag(s["kinect-b"], s["kinect-a"]).lag_s == pytest.approx(-lag, abs=0.010)
    # at the lag, the views disagree by what the heavy tails leave (median joint distance
    # around 6 cm); the search is still sure of it
    assert found.pairs >= 100 and np.nanmin(found.residual) < 0.075
    assert found.confidence > 0.5


def test_lag_matters_for_the_calibration():
    sim, s = _streams(offset=0.37)
    truth = simdata.true_transform(sim, "kinect-b")
    aligned = calibrate(pair_streams(s["kinect-a"], s["kinect-b"], 0.37).evenly(300), "rigid")
    ignored = calibrate(pair_streams(s["kinect-a"], s["kinect-b"], 0.0).evenly(300), "rigid")
    good = transform_error(aligned.matrix, truth, s["kinect-b"].joints)["rms_mm"]
    bad = transform_error(ignored.matrix, truth, s["kinect-b"].joints)["rms_mm"]
    assert good < 20 and bad > 3 * good, (good, bad)
    assert ignored.rms_m > 2 * aligned.rms_m


def test_lag_search_without_overlap_is_a_clear_error():
    _, s = _streams()
    late = s["kinect-b"].shifted(100.0)
    with pytest.raises(CalibrationError, match="never saw one person at the same time"):
        find_lag(s["kinect-a"], late)


def test_interpolation_removes_half_a_frame_of_motion():
    sim, s = _streams(phase=1 / 60)  # frames exactly between the reference's
    truth = simdata.true_transform(sim, "kinect-b")
    interp = pair_streams(s["kinect-a"], s["kinect-b"])
    nearest = pair_streams(s["kinect-a"], s["kinect-b"], interpolate=False)
    assert len(interp) > 500 and len(nearest) > 500
    e_i = transform_error(calibrate(interp, "rigid").matrix, truth, interp.other)
    e_n = transform_error(calibrate(nearest, "rigid").matrix, truth, nearest.other)
    assert calibrate(interp, "rigid").rms_m < calibrate(nearest, "rigid").rms_m
    assert e_i["rms_mm"] < 20 and e_n["rms_mm"] < 40


def test_nan_frames_are_dropped_and_only_shared_joints_count():
    _, s = _streams(duration=5.0, lockstep=True)
    b = s["kinect-b"]
    b.joints[10, 3] = np.nan       # one NaN joint spoils the whole frame (seed 002)
    b.conf[20, :12] = 0.0          # a half-tracked frame keeps its other joints
    pairs = pair_streams(s["kinect-a"], b, interpolate=False)
    assert b.t[10] not in pairs.t
    k = int(np.flatnonzero(pairs.t == b.t[20])[0])
    assert (pairs.weight[k, :12] == 0).all() and (pairs.weight[k, 12:] > 0).any()
    assert np.isfinite(pairs.other).all() and np.isfinite(pairs.ref).all()
    assert set(np.unique(pairs.weight)) <= {0.0, 0.25, 0.5, 1.0}  # products of confidences


def test_frames_with_two_people_in_view_are_not_paired():
    _, s = _streams(duration=6.0)
    a = s["kinect-a"]
    crowd = (a.t > 2.0) & (a.t < 3.0)  # a second user in the reference's view for one second
    second = a.subset(np.flatnonzero(crowd))
    second.user = np.ones(len(second), dtype=int)
    second.joints = second.joints + 1.0
    merged = Stream("kinect-a", np.concatenate([a.t, second.t]),
                    np.concatenate([a.user, second.user]),
                    np.concatenate([a.joints, second.joints]), np.concatenate([a.conf, second.conf]))
    order = np.argsort(merged.t, kind="stable")
    merged = merged.subset(order)
    pairs = pair_streams(merged, s["kinect-b"])
    # the crowd's frames run from 2.033 to 2.967 s; 0.25 s either side is not single-user
    assert not ((pairs.t > 1.78) & (pairs.t < 3.22)).any()
    assert ((pairs.t < 1.78) | (pairs.t > 3.22)).sum() > 100


def test_streams_from_datagrams_use_capture_then_timetag_then_arrival():
    joints = np.tile(np.array([[0.1, 0.2, 2.0]]), (25, 1))
    conf = np.ones(25)
    records = [
        (10.0, encode_client_joints("a", 0, joints, conf), 9.5),                       # capture
        (11.0, encode_bundle([encode_client_joints("b", 0, joints, conf)], 1234.5), None),  # timetag
        (12.0, encode_client_joints("b", 1, joints, conf), None),                      # arrival
        (12.5, encode_message("/floorPlane", "a", 0.0, 2.0, 0.0, 1.6), None),
        (13.0, b"garbage", None),
        (13.5, encode_message("/jointCoordinates", "a", 0, "Nose", 0.0, 0.0, 1.0, 1.0), None),
    ]
    streams, drops = streams_from_datagrams(records)
    assert streams["a"].t.tolist() == [9.5]
    assert sorted(streams["b"].t.tolist()) == [12.0, 1234.5]
    assert np.allclose(streams["a"].floor, [0, 1, 0, 0.8])  # normalised: d is the height
    assert streams["b"].floor is None
    assert drops == {"malformed": 1, "unknown_joint": 1}


def test_copied_streams_are_found():
    _, s = _streams(duration=4.0)
    copy = dataclasses.replace(s["kinect-b"], sensor="kinect-x")
    found = find_identical_streams({"kinect-a": s["kinect-a"], "kinect-b": s["kinect-b"],
                                    "kinect-x": copy})
    assert found == [("kinect-b", "kinect-x", len(copy))]
    assert find_identical_streams(s) == []


def test_evenly_spreads_pairs_over_the_recording():
    _, s = _streams(duration=20.0)
    pairs = pair_streams(s["kinect-a"], s["kinect-b"])
    few = pairs.evenly(50)
    assert len(few) == 50
    assert few.t[0] == pairs.t[0] and few.t[-1] == pairs.t[-1]
    assert pairs.evenly(0) is pairs


def test_a_paused_lag_search_finds_the_same_lag_and_pauses_between_lags():
    # the live worker gives way to the engine between candidate lags (pause); the search
    # itself must not change
    _, s = _streams(offset=0.37, phase=0.011, duration=8.0)
    calls = []
    plain = find_lag(s["kinect-a"], s["kinect-b"])
    paused = find_lag(s["kinect-a"], s["kinect-b"], pause=lambda: calls.append(1))
    assert paused.lag_s == plain.lag_s and paused.pairs == plain.pairs
    np.testing.assert_array_equal(paused.lags, plain.lags)
    np.testing.assert_array_equal(paused.residual, plain.residual)
    # after each lag paired and each lag scored: at least twice per lag tried
    assert len(calls) >= 2 * len(plain.lags)
