"""Gait analysis against walks whose gait is known: the simulator's planted-feet walker.

Step length, step width and cadence are set in the simulator (``GaitClip``);
the walk is watched by seed 003's six-sensor walkway (the built-in
``walkway`` scenario, whose Kinect model -- noise, fit error, occlusion,
drops -- is spelled out in full in that file, so these tolerances do not move
when the simulator's default error model does), integrated seed 003's way
and analysed. Stated tolerances, two-sided (all six sensors):

* mean step length within 2 cm and mean step width within 3 cm of the set
  values; cadence and walking speed within 3 %;
* per step (paired with the true placements): RMS error of length and
  width under 3.5 cm, of step time under 25 ms;

one-sided (the three sensors on the walker's left): the same means, width
within 4 cm, RMS errors under 5 cm and 30 ms. (Seeds 1-3 and 5 of these
gaits give at most: mean length off by 0.6 cm, width 2.4 cm, cadence and
speed 1.6 %, RMS 2.7 cm and 12 ms two-sided; 0.7 cm, 2.9 cm, 1.6 %, 4.1 cm
and 17 ms one-sided.) Without sensors (the truth itself at 30 Hz) lengths
and widths are exact to 2 mm.
"""

from __future__ import annotations


import numpy as np
import pytest

from stage.analysis.analyze import Subset, analyse_trajectory, compare
from stage.analysis.gait import LiveSteps, foot_events, match_steps, summary
from stage.analysis.integrate import SensorFrames, integrate, read_frames
from stage.analysis.trajectory import Trajectory
from stage.joints import JOINT_INDEX as J
from stage.rig import Rig, set_calibration
from stage.sensors.sim.gait import GaitClip
from stage.testing.walks import LEFT, gait_walker, simulate, truth, walkway

GAITS = [  # (step length m, step width m, cadence steps/min)
    (0.70, 0.12, 110.0),
    (0.55, 0.20, 95.0),
    (0.80, 0.08, 125.0),
]
SEEDS = (1, 2, 3)


def sampled(clip: GaitClip, rate: float = 30.0) -> Trajectory:
    t = np.arange(0.0, clip.duration, 1.0 / rate)
    return Trajectory(t, np.stack([clip.joints(x) for x in t]))


# ------------------------------------------------------------------ foot events on the truth
@pytest.mark.parametrize("length,width,cadence", GAITS)
def test_foot_events_of_the_exact_walk(length, width, cadence):
    clip = GaitClip(10, length, width, cadence)
    steps = foot_events(sampled(clip))
    # nine placements pass-by (the last one only closes); the first has no step before it
    assert len(steps) == 9 and steps[0].length is None
    assert [s.side for s in steps] == ["left", "right"] * 4 + ["left"]
    for s in steps[1:]:
        assert s.length == pytest.approx(length, abs=0.002)
        assert s.width == pytest.approx(width, abs=0.002)
    for s in steps[2:]:
        assert s.time == pytest.approx(60.0 / cadence, abs=0.005)
        if s.index >= 3:
            assert s.stride == pytest.approx(2 * length, abs=0.002)
    g = summary(steps)
    assert g["cadence"] == pytest.approx(cadence, rel=0.02)
    assert g["speed"] == pytest.approx(length * cadence / 60.0, rel=0.02)
    placed = {(round(p.x, 3), round(p.z, 3)) for p in clip.placements}
    assert {(round(s.x, 3), round(s.z, 3)) for s in steps} <= placed


def test_live_steps_agree_with_the_offline_ones():
    clip = GaitClip(10, 0.7, 0.12, 110.0)
    traj = sampled(clip)
    offline = foot_events(traj)
    live = LiveSteps()
    found = [s for k in range(len(traj)) if (s := live.update(traj.t[k], traj.joints[k]))]
    assert len(found) == len(offline)
    pairs = match_steps(found, offline, max_dt=0.1)
    assert len(pairs) == len(offline)
    for a, b in pairs[2:]:
        assert a.length == pytest.approx(b.length, abs=0.002)
        assert a.width == pytest.approx(b.width, abs=0.003)
        assert a.time == pytest.approx(b.time, abs=1 / 30)


# ------------------------------------------------------------------ watched by the walkway
def _walkway(length, width, cadence, seed):
    performer, clip = gait_walker(10, length, width, cadence)
    duration = performer.length + 0.5
    frames, rig, _ = simulate(walkway(performer, duration), seed)
    return frames, rig, performer, clip, duration


@pytest.mark.parametrize("gait,seed", list(zip(GAITS, SEEDS)))
def test_gait_recovered_from_the_six_sensor_walkway(gait, seed):
    length, width, cadence = gait
    frames, rig, performer, clip, duration = _walkway(length, width, cadence, seed)
    true = analyse_trajectory(truth(performer, duration), Subset("truth"))
    for name, sensors, tol_width, tol_rms, tol_time in (("two-sided", None, 0.03, 0.035, 0.025),
                                                         ("one-sided", list(LEFT), 0.04, 0.05,
                                                          0.030)):
        r = analyse_trajectory(integrate(frames, rig, sensors), Subset(name, sensors))
        g = r.gait
        assert g["used"] == 8, name                          # nine placements, eight steps
        assert g["step_length"]["all"]["mean"] == pytest.approx(length, abs=0.02), name
        assert g["step_width"]["all"]["mean"] == pytest.approx(width, abs=tol_width), name
        assert g["cadence"] == pytest.approx(cadence, rel=0.03), name
        assert g["speed"] == pytest.approx(length * cadence / 60, rel=0.03), name
        compare(r, true)
        a = r.agreement
        assert r.placements == 9 and len(r.pairs) == 8, name   # every placement and step found
        assert a["step_length"]["all"]["rmse"] < tol_rms, name
        assert a["step_width"]["all"]["rmse"] < tol_rms, name
        assert a["step_time"]["all"]["rmse"] < tol_time, name


def test_live_steps_on_the_engines_fused_frames():
    # what a piece's step: gait trigger sees: the engine's fused, smoothed bodies
    from stage.app.offline import feed
    from stage.clock import ManualClock
    from stage.engine import Engine
    from stage.sensors.sim import Simulator
    performer, clip = gait_walker(10, 0.7, 0.12, 110.0)
    sim = Simulator(walkway(performer, performer.length + 0.5), 3)
    clock = ManualClock(0.0)
    engine = Engine(sim.rig(), clock)
    live: dict[int, LiveSteps] = {}
    steps = []

    def listen(frame):
        for pid, body in frame.bodies.items():
            j = np.array(body.joints)
            j[body.conf < 0.5] = np.nan
            s = live.setdefault(pid, LiveSteps()).update(frame.t, j)
            if s is not None and s.length is not None:
                steps.append(s)
    engine.listeners.append(listen)
    feed(engine, clock, sim.stream(performer.length + 0.5))
    assert len(steps) >= 7
    assert np.mean([s.length for s in steps]) == pytest.approx(0.70, abs=0.03)
    assert np.mean([s.width for s in steps]) == pytest.approx(0.12, abs=0.03)
    assert 60 / np.median([s.time for s in steps]) == pytest.approx(110, rel=0.05)


# ------------------------------------------------------------------ seed 003's integration
def _frames(sid, t, joints, conf, user=0):
    n = len(t)
    return SensorFrames(sid, np.asarray(t, float), np.full(n, user), np.asarray(joints, float),
                        np.asarray(conf, float))


def test_integration_resamples_averages_and_treats_inferred_as_missing():
    rig = Rig(reference="a")
    shift = np.eye(4)
    shift[0, 3] = 1.0                       # sensor b sees everything 1 m further along -x
    set_calibration(rig, "b", shift, "test")
    t = np.arange(0, 1.0, 1 / 30) + 0.01   # off the grid: resampled
    base = np.zeros((len(t), 25, 3))
    base[:, :, 2] = t[:, None]             # everything moves along z at 1 m/s
    conf_a = np.ones((len(t), 25))
    conf_b = np.ones((len(t), 25))
    conf_b[:, J["AnkleRight"]] = 0.5        # inferred by b: missing
    conf_a[10:20, J["AnkleRight"]] = 0.0    # untracked by a for a third of a second
    b_joints = base.copy()
    b_joints[:, :, 0] -= 1.0
    b_joints[:, :, 1] += 0.02               # b reads 2 cm high
    frames = {"a": _frames("a", t, base, conf_a), "b": _frames("b", t, b_joints, conf_b)}
    tr = integrate(frames, rig)
    assert tr.rate == pytest.approx(30.0)
    assert tr.joints[:, J["Head"], 2] == pytest.approx(tr.t, abs=1e-9)    # linear, exact
    assert tr.joints[:, J["Head"], 1] == pytest.approx(np.full(len(tr), 0.01))  # equal weights
    assert (tr.count[:, J["Head"]] == 2).all()
    ankle = tr.joints[:, J["AnkleRight"], 1]
    gap = (tr.t > t[9]) & (tr.t < t[20])
    assert np.isnan(ankle[gap]).all() and (tr.count[gap, J["AnkleRight"]] == 0).all()
    assert ankle[~gap] == pytest.approx(np.zeros((~gap).sum()))            # a's alone
    assert integrate(frames, rig, keep_inferred=True).count[:, J["AnkleRight"]].max() == 2
    one = integrate(frames, rig, ["b"])
    assert one.meta["sensors"] == ["b"] and np.isnan(one.joints[:, J["AnkleRight"]]).all()
    with pytest.raises(Exception, match="no frames from sensor"):
        integrate(frames, rig, ["c"])


def test_integration_without_capture_times_aligns_sensor_clocks_from_timetags():
    from stage.sensors.sim import Simulator
    performer, _ = gait_walker(6, 0.7, 0.12, 110.0)
    sim = Simulator(walkway(performer, 6.0), 2)
    # as `stage record` stores them: arrival times only; the sensors' clocks are +-2 s off
    records = [(d.arrival + 100.0, d.data, None) for d in sim.stream(6.0)]
    frames, _ = read_frames(records)
    assert {f.timing for f in frames.values() if len(f)} == {"timetag"}
    clocks = sim.sensor_clocks()
    for sid, f in frames.items():
        if len(f):   # moved onto the recording's clock: capture + the sensor's latency
            assert f.t[0] >= 100.0 - 0.01 and f.t[-1] <= 106.2
    tr = integrate(frames, sim.rig())
    steps = foot_events(tr)
    assert len(steps) >= 4
    assert np.nanmean([s.length for s in steps if s.length]) == pytest.approx(0.7, abs=0.03)
    assert max(abs(c["offset_s"]) for c in clocks.values()) > 0.1   # the offsets were real


# ------------------------------------------------------------------ real walking
@pytest.mark.parametrize("take", ["131_01", "131_02"])
def test_cmu_walk_watched_one_sided_and_two_sided_against_the_motion_capture(take):
    """A real walk (CMU motion capture, "start, walk, stop") played along the walkway: both
    analyses find the motion capture's own steps, the two-sided one at least as closely.
    (This seed, RMS errors of step length and width: 131_01 one-sided 3.3 and 1.7 cm,
    two-sided 1.2 and 1.0 cm; 131_02 2.7/2.9 and 2.0/2.5 cm. bench/bench_gait.py does this
    for 16 virtual subjects with seed 003's statistics.)"""
    from stage.testing.walks import cmu_file, cmu_walker
    path = cmu_file(take)
    if path is None:
        pytest.skip("CMU motion capture not found ($STAGE_CMU_DIR or shared/data/cmu above "
                    "the checkout)")
    performer = cmu_walker(path, height=1.75)
    duration = performer.length + 0.5
    frames, rig, _ = simulate(walkway(performer, duration), 1)
    true = analyse_trajectory(truth(performer, duration), Subset("truth"))
    assert true.gait["used"] >= 4
    errors = {}
    for name, sensors in (("one-sided", list(LEFT)), ("two-sided", None)):
        r = analyse_trajectory(integrate(frames, rig, sensors), Subset(name, sensors))
        compare(r, true)
        assert len(r.pairs) >= true.gait["used"] - 1, name      # at most one step missed
        a = r.agreement
        errors[name] = (a["step_length"]["all"]["rmse"], a["step_width"]["all"]["rmse"])
        assert a["step_length"]["all"]["rmse"] < 0.05, name
        assert a["step_width"]["all"]["rmse"] < 0.05, name
        assert a["step_time"]["all"]["rmse"] < 0.03, name
    assert sum(errors["two-sided"]) <= sum(errors["one-sided"]) + 0.005
