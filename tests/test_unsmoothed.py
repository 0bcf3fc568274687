"""Smoothing off (``smoothing: enabled: false``): each joint is its latest accepted
measurement, whichever sensor sent it (``fuser``, ``hold``)."""

from __future__ import annotations

import numpy as np

from stage.joints import JOINT_INDEX
from stage.sensors.sim import standing_pose

from test_engine import frame, send
from test_offsets import FPS, _engine

HAND = JOINT_INDEX["HandLeft"]


def _joints(args: list) -> tuple[int, dict[str, np.ndarray]]:
    """A /jointCoordinates' person id and its joints by name."""
    rest = args[1:]
    return args[0], {rest[k]: np.array(rest[k + 1:k + 4]) for k in range(0, len(rest), 5)}


def _send(engine, body: np.ndarray, sensor: str, shift: float) -> np.ndarray:
    """A frame of ``body`` moved ``shift`` m along x from ``sensor``; b never reports the
    left hand. The joints sent."""
    joints = body.copy()
    joints[:, 0] += shift
    conf = np.ones(25)
    if sensor == "b":
        conf[HAND] = 0.0
    send(engine, frame(sensor, 0, joints, conf))
    return joints


def test_two_sensors_apart_make_one_person_whose_joints_are_the_latest_measurements():
    """Two sensors see one still person 8 cm apart along x, their frames half a period
    apart, and only a sees the left hand. Every output is one person (before, the filter's
    velocity -- 8 cm over 17 ms, and growing -- carried the person away from the next view
    and made a second person); each joint is where the latest frame put it, and the hand,
    which b does not report, stays where a last saw it (before, it was carried on by that
    velocity)."""
    engine, clock, out = _engine(smoothing=False)
    body = standing_pose((0.0, 2.5), np.pi)
    names = list(JOINT_INDEX)
    outputs = 0
    for k in range(int(2 * FPS)):
        for sensor, shift in (("a", 0.0), ("b", 0.08)):
            clock.advance(0.5 / FPS)
            joints = _send(engine, body, sensor, shift)
            sent = out.of("/jointCoordinates")
            assert {args[0] for args in sent} <= {1}, f"frame {k}: persons {sent}"
            if k < 2 or not sent:
                out.clear()
                continue
            _, got = _joints(sent[-1])
            for j in (JOINT_INDEX["SpineBase"], JOINT_INDEX["Head"], JOINT_INDEX["FootRight"]):
                assert np.allclose(got[names[j]], joints[j], atol=1e-4), (k, sensor, names[j])
            assert np.allclose(got[names[HAND]], body[HAND], atol=1e-4), (k, sensor)
            outputs += 1
            out.clear()
    assert outputs >= 2 * (2 * FPS - 2) - 2
    (person,) = engine.bodies().values()
    assert not person.velocity.any()


def test_views_of_one_instant_are_held_where_they_were_seen_with_no_velocity():
    """The two sensors' frames captured at the same instant, 15 cm apart (so they disagree:
    the instant is chosen and replayed), of a person walking at 0.9 m/s: one person, the
    joints between the two views, the hand where a saw it, and no velocity (before, the
    replayed states kept theirs: the person's was the walk's)."""
    engine, clock, out = _engine(smoothing=False)
    names = list(JOINT_INDEX)
    spine = names[JOINT_INDEX["SpineBase"]]
    for k in range(int(2 * FPS)):
        clock.advance(1.0 / FPS)
        body = standing_pose((0.0, 2.5 - 0.03 * k), np.pi)
        for sensor, shift in (("a", 0.0), ("b", 0.15)):
            _send(engine, body, sensor, shift)
        sent = out.of("/jointCoordinates")
        assert {args[0] for args in sent} <= {1}, f"frame {k}: persons {sent}"
        if k >= 2:
            _, got = _joints(sent[-1])
            assert -1e-4 <= got[spine][0] - body[0, 0] <= 0.15 + 1e-4, k
            assert np.allclose(got[spine][1:], body[0, 1:], atol=1e-4), k
            assert np.allclose(got[names[HAND]], body[HAND], atol=1e-4), k
        out.clear()
        if k >= 2:
            (person,) = engine.bodies().values()
            assert not person.velocity.any(), k
    assert engine.people.fuser.stats.replays > 0          # the instant path was taken
