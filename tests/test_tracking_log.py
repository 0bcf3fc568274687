"""The tracker's "picked up again" line is logged at most once a second per person: an
engine that fell behind drops and picks up views every frame (745 lines in 5 s once, issue
10 stop 33), and every line slowed it further."""

from __future__ import annotations

import logging

import numpy as np

from stage.engine.tracking import Tracker, Track
from stage.settings import FusionSettings


def _view(track: Track, t: float) -> None:
    rng = np.random.default_rng(int(t * 1000))
    track.joints = np.array([0.0, 1.0, 2.0]) + rng.normal(scale=0.005, size=(25, 3))
    track.conf = np.ones(25)
    track.t = t


def test_a_person_picked_up_every_frame_is_logged_once_a_second(caplog):
    tracker = Tracker(FusionSettings())
    a, b = Track("kinect-a", 0), Track("kinect-b", 0)
    _view(a, 0.0)
    person = tracker.associate(a, 0.0)
    person.joints, person.known = a.joints.copy(), np.ones(25, bool)
    caplog.set_level(logging.INFO, logger="stage.engine")
    t = 0.0
    for k in range(60):                     # 2 s of frames at 30 Hz
        t = k / 30
        tracker.unbind(a, t)                # orphaned ...
        _view(b, t)
        assert tracker.associate(b, t) is person   # ... and picked up again
        tracker.unbind(b, t)
        _view(a, t)
        assert tracker.associate(a, t) is person
    lines = [r.getMessage() for r in caplog.records if "picked up again" in r.getMessage()]
    assert len(lines) == 2, lines          # at 0 s and at 1 s; 119 picks in all
    assert lines[0] == f"person {person.id} picked up again by sensor kinect-b"
    assert lines[1].startswith(f"person {person.id} picked up again by sensor kinect-")
    assert "(and 59 more time(s) since the last such line)" in lines[1]
