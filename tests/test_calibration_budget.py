"""The live calibrator's frame budget (``LiveSettings.frame_budget``): in a crowd each view is
thinned evenly in time, so that the calibrator's cost stops growing with the number of views;
below the budget nothing changes; copies and bumps are still caught.

The ring harness of test_calibration_healing (one dancer, n sensors at 30 Hz, inline
calibrator, injected clock): with a budget of 45 frames a second, three sensors (90 a
second) are over it, and each view is kept at 45 / 3 = 15 Hz.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stage.rig import set_calibration
from test_calibration_healing import Run, copying_s1


def _times(run, sensor: str) -> np.ndarray:
    return np.array([e[0].t for e in run.cal._buffers[(sensor, 0)]])


def test_within_the_budget_every_frame_is_kept(tmp_path):
    run = Run(tmp_path, n=3)                   # 90 frames a second, budget 540
    run.run_until(3.0)
    assert run.cal.frames_thinned == 0 and run.cal._keep_every == 0.0
    for sid in run.ids:
        gaps = np.diff(_times(run, sid))
        assert np.allclose(gaps, 1 / 30, atol=1e-6), sid


def test_over_the_budget_each_view_is_thinned_evenly(tmp_path):
    run = Run(tmp_path, n=3, frame_budget=45.0)
    run.run_until(1.0)
    assert run.cal.frames_thinned == 0         # a second's count before any judgement
    run.run_until(4.0)
    assert run.cal._keep_every == 3 / 45.0
    thinned = run.cal.frames_thinned
    assert 2 * 3 * 30 * 0.4 < thinned < 3 * 3 * 30 * 0.6   # about half of 2-3 s of frames
    for sid in run.ids:
        t = _times(run, sid)
        gaps = np.diff(t[t > 1.5])
        # the first frame of each 1/15 s bin: 1/30 or 1/10 s apart (a bin edge between two
        # frames moves one), 1/15 s on average, never two frames of one bin
        assert gaps.min() > 1 / 30 - 1e-6 and gaps.max() < 0.1 + 1e-6, sid
        assert abs(gaps.mean() - 1 / 15) < 0.004, sid
        assert len(np.unique(np.floor(t[t > 1.5] / (3 / 45.0)))) == len(t[t > 1.5])


def test_the_views_are_whole_again_when_the_crowd_thins(tmp_path):
    run = Run(tmp_path, n=3, frame_budget=45.0)
    run.run_until(3.0)
    assert run.cal._keep_every > 0
    run.cal.settings = dataclasses.replace(run.cal.settings, frame_budget=120.0)
    run.run_until(4.5)        # 90 frames a second, under 90 % of 120
    assert run.cal._keep_every == 0.0
    before = run.cal.frames_thinned
    run.run_until(6.0)
    assert run.cal.frames_thinned == before
    gaps = np.diff(_times(run, "s1"))
    assert np.allclose(gaps[-30:], 1 / 30, atol=1e-6)


def test_a_copy_is_still_caught_at_its_fifth_frame_while_thinning(tmp_path):
    """Every frame is checked for copies, kept or not (a copy's clock need not fall in the
    same bins as the original's)."""
    run = Run(tmp_path, n=3, frame_budget=45.0)
    set_calibration(run.rig, "s9", run.rig.sensors["s1"].calibration.matrix, "copied")
    copy_s1, copies = copying_s1(run, 2.0)
    run.run_until(3.5, hook=copy_s1)
    assert run.cal._keep_every > 0 and run.cal.frames_thinned > 0
    flagged = run.events("identical", "s9")
    assert len(flagged) == 1 and flagged[0].t == copies[4]


def test_a_bumped_sensor_is_caught_while_thinning(tmp_path):
    run = Run(tmp_path, n=3, frame_budget=45.0)
    run.run_until(3.0)
    assert run.cal._keep_every > 0
    run.bump("s1", 10.0)
    run.run_until(4.0)
    suspect = run.events("suspect")
    assert suspect and 3.0 <= suspect[0].t <= 3.5
    assert not run.events("suspect", "s0") and not run.events("suspect", "s2")


def test_a_tiny_budget_still_keeps_ten_frames_a_second_of_each_view(tmp_path):
    """Frames further apart than ``live.IDENTITY_GAP_S`` would each start a new identity."""
    run = Run(tmp_path, n=3, frame_budget=3.0)
    run.run_until(3.0)
    assert run.cal._keep_every == 0.1
    t = _times(run, "s2")
    assert np.diff(t[t > 1.5]).max() < 0.1 + 1 / 30 + 1e-6


def test_a_budget_turned_off_while_thinning_keeps_every_frame_at_once(tmp_path):
    run = Run(tmp_path, n=3, frame_budget=45.0)
    run.run_until(3.0)
    assert run.cal._keep_every > 0
    run.cal.settings = dataclasses.replace(run.cal.settings, frame_budget=0.0)
    run.run_until(3.2)            # the next poll
    assert run.cal._keep_every == 0.0
    before = run.cal.frames_thinned
    run.run_until(4.0)
    assert run.cal.frames_thinned == before


def test_the_stats_say_what_the_budget_does(tmp_path):
    """``/stage/stats`` has a ``calibrator`` section while a live calibrator is attached: the
    frames it takes a second, its budget, the rate each view is kept at (null: every
    frame) and what it left out."""
    import json

    run = Run(tmp_path, n=3, frame_budget=45.0)
    run.run_until(4.0)
    cal = run.engine.stats()["calibrator"]
    json.dumps(cal)
    assert 80.0 < cal["frames_per_s"] < 100.0            # three views at 30 Hz
    assert cal["frame_budget"] == 45.0 and cal["kept_hz"] == 15.0
    assert cal["frames_thinned"] == run.cal.frames_thinned > 0
    assert cal["inbox_dropped"] == 0 and cal["crashes"] == 0
    run.cal.stop()
    assert "calibrator" not in run.engine.stats()


def test_the_stats_say_every_frame_is_kept_within_the_budget(tmp_path):
    run = Run(tmp_path, n=3)
    assert run.engine.stats()["calibrator"]["frames_per_s"] is None   # not a second yet
    run.run_until(3.0)
    cal = run.engine.stats()["calibrator"]
    assert 80.0 < cal["frames_per_s"] < 100.0 and cal["kept_hz"] is None
    assert cal["frames_thinned"] == 0


def test_frames_a_stuck_worker_cannot_take_are_counted_and_logged(tmp_path, caplog):
    """Threaded, the engine thread only queues frames; when the worker does not empty the
    inbox, the oldest frames go, counted in the stats and logged once per 10 s, never
    per frame."""
    import logging

    run = Run(tmp_path, n=3, threaded=True)
    cal = run.cal
    cal._stop.set()               # the worker ends: nothing empties the inbox any more
    cal._wake.set()
    cal._worker.join(timeout=10.0)
    cal._inbox_max = 30
    with caplog.at_level(logging.WARNING, logger="stage.calibration"):
        run.run_until(12.0)        # 3 sensors x 30 Hz x 12 s = 1080 frames into 30 places
    said = [r.getMessage() for r in caplog.records if "inbox" in r.getMessage()]
    seen = run.engine.counts["frames"]     # every frame the engine took (a few are lost)
    assert seen > 1000 and cal.inbox_dropped == seen - 30 and len(cal._inbox) == 30
    assert run.engine.stats()["calibrator"]["inbox_dropped"] == seen - 30
    assert len(said) == 2, said    # at the first drop, then 10 s later
    assert said[0].startswith("calibrator: its worker is behind: 1 frame(s) dropped")
    assert said[1].endswith(" in all)") and "(1 in all)" not in said[1]
