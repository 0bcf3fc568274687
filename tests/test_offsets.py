"""Each view's steady offset from the person's other views, learned and taken off
(``stage.engine.offsets``, ``fusion.view_offset_s``)."""

from __future__ import annotations

import numpy as np
import pytest

from stage.clock import ManualClock
from stage.engine import jit, offsets
from stage.engine.engine import Engine
from stage.errors import ConfigError
from stage.joints import INFERRED, JOINT_INDEX
from stage.rig import Rig, load_rig, set_calibration
from stage.sensors.sim import standing_pose
from stage.settings import FusionSettings

from test_engine import VIEW, RecordingTransport, frame, make_engine, send

SPINE = JOINT_INDEX["SpineBase"]
FPS = 30.0


def _arrays(rng: np.random.Generator):
    z = rng.normal(0.0, 1.0, (25, 3))
    conf = rng.choice([0.0, INFERRED, 1.0, 0.8], 25)
    joints = z + rng.normal(0.0, 0.2, (25, 3))
    joints[3] += 1.0                                         # beyond CAP_M: teaches nothing
    velocity = rng.normal(0.0, 1.0, (25, 3))
    known = rng.random(25) > 0.2
    table = rng.normal(0.0, 0.05, (4, 25, 3))
    live = np.array([3.0, -np.inf, 2.5, 2.9])[:len(table)]
    return z, conf, joints, velocity, known, table, live


@pytest.mark.parametrize("views", [1, 3])
def test_kernel_is_the_reference_to_the_bit(views):
    """The compiled ``_offsets`` and ``offsets.learn`` give the same bits, for one view
    alone and for three (one free row between them)."""
    assert jit.warm()
    rng = np.random.default_rng(7)
    for _ in range(20):
        z, conf, joints, velocity, known, table, live = _arrays(rng)
        if views == 1:
            table, live = table[:1].copy(), live[:1].copy()
        row = len(table) - 1
        z2, table2 = z.copy(), table.copy()
        offsets.learn(z, conf, joints, velocity, known, 0.012, table, live, row, 0.3, INFERRED)
        jit.offsets(z2, conf, joints, velocity, known, 0.012, table2, live, row, 0.3, INFERRED)
        assert z.tobytes() == z2.tobytes() and table.tobytes() == table2.tobytes()


def test_reference_corrects_reported_joints_and_learns_only_from_tracked_ones():
    z = np.zeros((25, 3))
    conf = np.full(25, 1.0)
    conf[1], conf[2] = 0.0, INFERRED
    person = np.full((25, 3), -0.05)     # every view joint is 5 cm from the person, each axis
    known = np.ones(25, dtype=bool)
    known[4] = False
    person[5] = -0.1                     # 17 cm: beyond CAP_M (15 cm), teaches nothing
    table = np.zeros((3, 25, 3))
    table[0], table[2] = 0.02, -0.01                 # this view's, and another view's
    table[1] = 5.0                                   # a free row: not in the mean
    live = np.array([1.0, -np.inf, 1.0])
    out = z.copy()
    offsets.learn(out, conf, person, np.zeros((25, 3)), known, 0.0, table, live, 0, 0.5,
                  INFERRED)
    assert np.allclose(out[0], -0.015) and np.allclose(out[2], -0.015)  # reported: corrected
    assert np.allclose(out[1], 0.0)                                      # not reported
    assert np.allclose(table[0, 0], 0.02 + 0.5 * (0.05 - 0.02))         # learned
    assert np.allclose(table[0, 1], 0.02) and np.allclose(table[0, 2], 0.02)  # not tracked
    assert np.allclose(table[0, 4], 0.02)                                # no state to learn from
    assert np.allclose(table[0, 5], 0.02) and np.allclose(out[5], -0.015)  # too far: corrected only
    assert np.allclose(table[2], -0.01) and np.allclose(table[1], 5.0)   # the others: as they were


def _engine(smoothing: bool = True, **fusion):
    """An engine with sensors a (the reference) and b in the same place."""
    rig = Rig(reference="a", views=[VIEW], fusion=FusionSettings(**fusion))
    rig.smoothing_enabled = smoothing
    for sensor in ("a", "b"):
        set_calibration(rig, sensor, np.eye(4), "test")
    clock = ManualClock(100.0)
    out = RecordingTransport()
    return Engine(rig, clock, out), clock, out


def _feed_still(engine, clock, apart: float, frames: int) -> np.ndarray:
    """``frames`` frame periods of one still person seen by sensors a and b, whose fits put
    the body ``apart`` metres apart along x, half a period apart; the body (a's view)."""
    body = standing_pose((0.0, 2.5), np.pi)
    for _ in range(frames):
        for sensor, shift in (("a", 0.0), ("b", apart)):
            clock.advance(0.5 / FPS)
            joints = body.copy()
            joints[:, 0] += shift
            send(engine, frame(sensor, 0, joints))
    return body


def _two_views(view_offset_s: float, apart: float, seconds: float = 2.0, seed: int = 3):
    """One still person seen by two sensors in the same place whose fits put the body
    ``apart`` metres apart along x, frames half a period apart; the fused SpineBase x of
    every output after the first second."""
    rng = np.random.default_rng(seed)
    engine, clock, out = _engine(view_offset_s=view_offset_s)
    body = standing_pose((0.0, 2.5), np.pi)
    xs = []
    for k in range(int(seconds * FPS)):
        for sensor, shift in (("a", 0.0), ("b", apart)):
            clock.advance(0.5 / FPS)
            joints = body + rng.normal(0.0, 0.001, body.shape)
            joints[:, 0] += shift
            send(engine, frame(sensor, 0, joints))
            if k >= FPS:
                (last,) = out.of("/jointCoordinates")[-1:]
                xs.append(last[2 + 5 * SPINE])
        out.clear()
    return np.array(xs), body[SPINE, 0]


def test_two_views_apart_no_longer_swing_and_meet_at_their_mean():
    """Views 8 cm apart: without the offsets the fused SpineBase swings from one view
    towards the other at every frame; with them it stays still, between the two."""
    off, x0 = _two_views(0.0, 0.08)
    on, _ = _two_views(0.5, 0.08)
    swing_off = np.abs(np.diff(off)).mean()
    swing_on = np.abs(np.diff(on)).mean()
    assert swing_off > 0.01                        # the defect: 1 cm and more, every frame
    assert swing_on < 0.3 * swing_off and swing_on < 0.004
    assert abs(on.mean() - (x0 + 0.04)) < 0.01     # the views' mean, not one of them


def test_smoothing_off_leaves_the_views_as_they_are():
    """With smoothing off each joint is its latest measurement, and a joint back from an
    occlusion is its old position: learning from it moved the simulator's views by tens of
    centimetres (bench_fusion.py). The offsets are off there: the same output either way."""
    runs = []
    for view_offset_s in (0.0, 0.25):
        engine, clock, out = _engine(False, view_offset_s=view_offset_s)
        _feed_still(engine, clock, 0.08, 20)
        runs.append([m.params for _, m in out.sent])
    assert runs[0] == runs[1] and len(runs[0]) > 20


def test_one_view_alone_is_never_corrected():
    """A person seen by one sensor: the same bytes out with the offsets on or off."""
    outs = []
    for view_offset_s in (0.0, 0.5):
        engine, clock, out = make_engine(view_offset_s=view_offset_s)
        rng = np.random.default_rng(5)
        for k in range(60):
            clock.advance(1 / FPS)
            body = standing_pose((0.3 * np.sin(k / 10), 2.5), np.pi)
            send(engine, frame("a", 0, body + rng.normal(0.0, 0.01, body.shape)))
        outs.append([m.params for _, m in out.sent])
    assert outs[0] == outs[1]


def test_a_view_that_leaves_takes_its_offset_and_a_new_view_starts_uncorrected():
    engine, clock, out = _engine()
    body = _feed_still(engine, clock, 0.05, 10)
    (person,) = engine.people.persons.values()
    row = person.recent[("b", 0)]
    assert np.abs(person.offsets[row, SPINE, 0]) > 0.01        # learned
    track = engine.clients["b"].tracks[0]
    engine.people.drop_track(track, clock.now())
    assert ("b", 0) not in person.recent and not person.offsets[row].any()
    assert not person.offsets.any()        # one view left: it has no offset either
    # a view new to the person: its first frame goes in as the sensor sent it
    engine.clients["b"].tracks.clear()
    joints = body.copy()
    joints[:, 0] += 0.05
    clock.advance(0.5 / FPS)
    send(engine, frame("b", 1, joints))
    assert engine.clients["b"].tracks[1].joints[SPINE, 0] == np.float32(joints[SPINE, 0])  # (OSC)


def test_rig_key(tmp_path):
    path = tmp_path / "rig.yaml"
    for text, value in (("0", 0.0), ("1.5", 1.5)):
        path.write_text(f"fusion: {{view_offset_s: {text}}}\n")
        assert load_rig(str(path)).fusion.view_offset_s == value
    path.write_text("fusion: {view_offset_s: -1}\n")
    with pytest.raises(ConfigError, match="view_offset_s"):
        load_rig(str(path))
