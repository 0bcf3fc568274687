"""Live calibration and self-healing on an in-process engine (ManualClock, no sleeps).

Frames: the simulator's Kinect model (``VirtualKinect``, its realistic defaults: heavy-tailed
joints, view-dependent bias, limb swaps, guessed inferred joints) on a ring around the demo
scenario's dancer, 30 Hz, sent as real ``/jointCoordinates`` datagrams. A test that checks
the precision of a re-calibration (rotation within 1 degree, translation within 5 cm, the
fused error of healthy sensors under 3 cm) asks for ``CLEAN_KINECT``, the error budget that
precision is stated for (docs/calibration.md), and says so: two sensors facing each other
see opposite sides of a body, and the realistic model's view-dependent bias alone puts them
4-6 cm apart, which no calibration removes.
"""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from stage.app.offline import feed
from stage.geometry import invert, transform_error
from stage.calibration.healing import attach_live
from stage.clock import ManualClock
from stage.engine.engine import Engine
from stage.sensors.protocol import encode_client_joints
from stage.rig import Rig, load_rig, set_calibration
from stage.sensors.sim import VirtualKinect, demo_scenario, ring_poses
from stage.testing.simdata import CLEAN_KINECT, kinect_model

FPS = 30.0
_DANCER = demo_scenario(1).performers[0]


def dancer(t: float):
    """The demo dancer's (joints (25, 3) stage space, hands) at ``t``."""
    return _DANCER.state(t)


class Run:
    """An engine with the live calibrator, fed by n ring sensors; sensor s1 may be bumped."""

    def __init__(self, tmp_path, n: int = 2, calibrated: bool = True, threaded: bool = False,
                 seed: int = 1, kinect: dict | None = None, **settings) -> None:
        self.poses = ring_poses(n)
        self.ids = [f"s{k}" for k in range(n)]
        self.rig = Rig(reference="s0")
        self.rig.stage_frame = self.poses[0].to_stage
        for sid, pose in zip(self.ids, self.poses):
            if calibrated or sid == "s0":
                set_calibration(self.rig, sid, invert(self.poses[0].to_stage) @ pose.to_stage,
                                "test")
        self.rig_path = str(tmp_path / "rig.yaml")
        self.rig.save(self.rig_path)
        self.clock = ManualClock(0.0)
        self.engine = Engine(self.rig, self.clock)
        self.fused: list[tuple[float, float, tuple[str, ...]]] = []  # t, error (m), sensors
        self.engine.listeners.append(self._listen)
        self.cal = attach_live(self.engine, self.rig_path, threaded=threaded, **settings)
        self.rng = np.random.default_rng(seed)
        self.kinects = [VirtualKinect(p, kinect_model(**(kinect or {})), self.rng)
                        for p in self.poses]
        self.t = 0.0

    def _listen(self, frame) -> None:
        truth = dancer(frame.t)[0]
        for body in frame.bodies.values():
            seen = body.conf > 0
            err = float(np.linalg.norm(body.joints[seen] - truth[seen], axis=1).mean())
            self.fused.append((frame.t, err, body.sensors))

    def bump(self, sensor: str, degrees: float) -> None:
        k = self.ids.index(sensor)
        self.kinects[k].pose = self.kinects[k].pose.moved(yaw=np.radians(degrees))

    def frame(self, sensor: str, joints: np.ndarray, conf: np.ndarray, t: float) -> None:
        self.clock.set(max(self.clock.now(), t))
        port = 9000 + self.ids.index(sensor)
        self.engine.handle_datagram(encode_client_joints(sensor, 0, joints, conf),
                                    ("127.0.0.1", port))

    def run_until(self, until: float, hook=None) -> None:
        while self.t < until - 1e-9:
            truth, _ = dancer(self.t)
            for k, sid in enumerate(self.ids):
                seen = self.kinects[k].observe(truth)
                if seen is not None:
                    self.frame(sid, *seen, self.t + 0.002 * k)
            self.engine.tick()
            if hook is not None:
                hook(self)
            self.t = round(self.t + 1 / FPS, 9)

    def events(self, kind: str, sensor: str = "s1"):
        return [e for e in self.cal.events if e.kind == kind and e.sensor == sensor]

    def truth_to_stage(self, sensor: str) -> np.ndarray:
        return self.kinects[self.ids.index(sensor)].pose.to_stage


#: the fused skeleton's mean joint error (m) never exceeds this during a bump episode;
#: healthy fusion of these sensors stays under 0.03 m, the bumped sensor's data would
#: pull it to 0.25-0.3 m (asserted below), and a zone edge 0.06 m away cannot be crossed
FUSED_BOUND_M = 0.06


def test_a_sensor_rotated_10_degrees_is_caught_left_out_and_recalibrated(tmp_path):
    # CLEAN: the bounds below (healthy fusion under 3 cm, the new transform within 1 degree
    # and 5 cm) are the precision stated for the clean budget, for two sensors facing each
    # other; test_simulated_kinects_bumped_mid_show runs a bump on the realistic model
    run = Run(tmp_path, n=2, kinect=CLEAN_KINECT)
    run.run_until(5.0)
    assert run.engine.sensor_notes["s1"]["state"] == "ok"
    healthy = max(e for _, e, _ in run.fused)
    assert healthy < 0.03
    bump_t = run.t
    run.bump("s1", 10.0)
    run.run_until(12.0)
    suspect = run.events("suspect")
    calibrated = run.events("calibrated")
    assert len(suspect) == 1 and len(calibrated) == 1
    detected, recovered = suspect[0].t, calibrated[0].t
    assert detected - bump_t <= 1.0          # detected within 1 s (here: its first frame)
    assert recovered - bump_t <= 5.0         # recovered within 5 s
    # left out of fusion from detection until fixed
    during = [(t, e, s) for t, e, s in run.fused if detected <= t < recovered]
    assert during and all("s1" not in s for _, _, s in during)
    after = [s for t, _, s in run.fused if t > recovered + 0.2]
    assert after and all("s1" in s for s in after)
    # its bad data never reached the fused output
    episode = [e for t, e, _ in run.fused if t >= bump_t]
    assert max(episode) <= FUSED_BOUND_M, max(episode)
    # the new transform is the sensor's new pose
    err = transform_error(calibrated[0].matrix, run.truth_to_stage("s1"))
    assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, err
    note = run.engine.sensor_notes["s1"]
    assert note["state"] == "ok" and note["fitness"] > 0.8 and "re-calibrated" in note["reason"]


def test_without_self_healing_the_bumped_sensors_data_would_break_the_bound(tmp_path):
    """The bound above is meaningful: the bumped sensor's data would break it.

    Issue 10: this test used to assert that, without self-healing, the fused output
    itself goes 0.2 m wrong. Fusion now checks the views of one instant against each
    other and the filter's prediction, so the bumped sensor's joints are left out even
    without the calibrator; what the bound guards against is the sensor's own data.
    CLEAN: FUSED_BOUND_M is a mean over all joints, stated for the clean budget (the
    realistic model's guessed joints alone exceed it now and then, bump or not)."""
    run = Run(tmp_path, n=2, heal=False, kinect=CLEAN_KINECT)
    run.run_until(5.0)
    bump_t = run.t
    run.bump("s1", 10.0)
    stale = run.rig.transform_for("s1")
    errors = []

    def own_error(r: Run) -> None:
        truth = dancer(r.t)[0]
        seen = r.kinects[1].observe(truth)
        if seen is not None:
            joints, conf = seen
            stage = joints @ stale[:3, :3].T + stale[:3, 3]
            ok = conf > 0
            errors.append(float(np.linalg.norm(stage[ok] - truth[ok], axis=1).mean()))

    run.run_until(7.0, hook=own_error)
    assert min(errors) > 0.2                 # every frame of it is 0.2 m off or more
    assert not run.cal.events
    assert max(e for t, e, _ in run.fused if t >= bump_t) <= FUSED_BOUND_M
    assert run.engine.stats()["fusion"]["joints_disagreeing"] > 0


def test_the_rig_file_is_rewritten_atomically_after_a_recalibration(tmp_path, monkeypatch):
    replaced = []
    real_replace = os.replace

    def spy(src, dst):
        replaced.append((str(src), str(dst), open(src).read()))
        return real_replace(src, dst)

    run = Run(tmp_path, n=2)
    monkeypatch.setattr(os, "replace", spy)
    before = open(run.rig_path).read()
    run.run_until(3.0)
    run.bump("s1", 10.0)
    run.run_until(9.0)
    assert len(run.events("calibrated")) == 1
    # written to a temporary file in the same folder, then renamed over the rig in one step
    assert len(replaced) == 1
    src, dst, text = replaced[0]
    assert dst == run.rig_path and os.path.dirname(src) == os.path.dirname(dst) and src != dst
    assert open(run.rig_path).read() == text != before
    rig = load_rig(run.rig_path)
    stored = rig.transform_for("s1")
    err = transform_error(stored, run.truth_to_stage("s1"))
    assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, err
    assert rig.sensors["s1"].calibration.method == "rigid (live)"
    assert np.allclose(rig.transform_for("s0"), run.poses[0].to_stage)


def test_a_small_bump_is_caught_by_the_fitness_monitor(tmp_path):
    run = Run(tmp_path, n=3)     # 4 degrees: 17 cm, under the jump gate
    run.run_until(4.0)
    bump_t = run.t
    run.bump("s2", 4.0)
    run.run_until(11.0)
    suspect = run.events("suspect", "s2")
    calibrated = run.events("calibrated", "s2")
    assert len(suspect) == 1 and "stayed below" in suspect[0].detail
    assert suspect[0].t - bump_t <= 1.0
    assert calibrated and calibrated[0].t - bump_t <= 5.0
    assert not run.events("suspect", "s1") and not run.events("suspect", "s0")
    err = transform_error(calibrated[0].matrix, run.truth_to_stage("s2"))
    assert err["rot_deg"] < 1.0, err


def test_judging_in_chunks_wakes_at_once_when_a_sensor_drifts_apart(tmp_path):
    """While all agree the monitor judges 0.3 s chunks (``idle_poll_s``); the jump gate's
    distances wake it as soon as a bumped sensor's views move away from the others, so a
    bump under the jump gate is caught as soon as judging every poll catches it. Without the
    wake (``idle_wake_m`` inf) the same bumps are caught up to 0.2 s later."""
    def detected(phase: float, **settings) -> tuple[float, float]:
        run = Run(tmp_path, n=3, **settings)
        judged = []
        monitor = run.cal._monitor
        run.cal._monitor = lambda *a: (judged.append(run.t), monitor(*a))[1]
        run.run_until(4.0 + phase)
        rate = len(judged) / run.t
        assert run.cal.stats()["judgements"] == len(judged)
        assert run.cal.stats()["woken"] == 0        # nobody drifted apart before the bump
        bump_t = run.t
        run.bump("s2", 3.0)      # 13 cm: under the jump gate
        run.run_until(5.5 + phase)
        suspect = run.events("suspect", "s2")
        assert len(suspect) == 1 and "stayed below" in suspect[0].detail
        # chunks woken by the drift: counted, so that an installer can see it happen
        assert (run.cal.stats()["woken"] > 0) == (run.cal.settings.idle_wake_m < 1.0
                                                    and run.cal.settings.idle_poll_s > 0.1)
        return suspect[0].t - bump_t, rate

    phases = (0.0, 0.1, 0.2)
    every, rate_every = zip(*[detected(p, idle_poll_s=0.1) for p in phases])
    woken, rate = zip(*[detected(p) for p in phases])
    asleep, _ = zip(*[detected(p, idle_wake_m=float("inf")) for p in phases])
    # judgements a second before the bump: every 0.1 s poll, or 0.3 s chunks
    assert min(rate_every) > 8.0 and max(rate) < 4.5, (rate_every, rate)
    assert max(w - e for w, e in zip(woken, every)) <= 0.01, (woken, every)
    assert max(a - e for a, e in zip(asleep, every)) >= 0.1, (asleep, every)


def test_a_glitch_is_restored_without_recalibration(tmp_path):
    run = Run(tmp_path, n=2)
    run.run_until(3.0)
    # for 4 frames s1 reports the dancer 0.6 m off (a tracking glitch), then is fine again
    run.kinects[1].pose = run.poses[1].moved(move=np.array([0.6, 0.0, 0.0]))
    run.run_until(3.0 + 4 / FPS)
    run.kinects[1].pose = run.poses[1]
    run.run_until(6.0)
    assert len(run.events("suspect")) == 1
    restored = run.events("restored")
    assert len(restored) == 1 and not run.events("calibrated")
    assert np.allclose(restored[0].matrix, run.rig.transform_for("s1"))
    assert run.engine.sensor_notes["s1"]["state"] == "ok"


def test_an_uncalibrated_sensor_is_calibrated_when_one_person_is_visible(tmp_path):
    run = Run(tmp_path, n=3, calibrated=False, pairs=150)
    run.run_until(1.0)
    assert run.engine.sensor_notes["s1"]["state"] == "uncalibrated"
    assert all(s == ("s0",) for _, _, s in run.fused)  # only the reference is fused meanwhile
    run.run_until(8.0)
    for sid in ("s1", "s2"):
        done = run.events("calibrated", sid)
        assert len(done) == 1, sid
        err = transform_error(done[0].matrix, run.truth_to_stage(sid))
        assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, (sid, err)
        assert run.engine.sensor_notes[sid]["state"] == "ok"
    assert set(run.fused[-1][2]) == {"s0", "s1", "s2"}
    rig = load_rig(run.rig_path)
    assert rig.reference == "s0" and rig.sensors["s2"].calibration is not None


def test_two_people_in_view_hold_the_calibration_back(tmp_path):
    run = Run(tmp_path, n=2, calibrated=False, pairs=60)

    def second_person(r):
        # 1 m to the side of the dancer, inside s1's field of view
        truth = dancer(r.t + 7.0)[0] + np.array([1.0, 0.0, 0.0])
        seen = r.kinects[1].observe(truth, user=1)
        if seen is not None:
            r.engine.handle_datagram(encode_client_joints("s1", 1, *seen), ("127.0.0.1", 9001))

    run.run_until(4.0, hook=second_person)
    assert not run.events("calibrated")
    assert "2 people in its view" in run.engine.sensor_notes["s1"]["reason"]
    run.run_until(9.0)
    assert len(run.events("calibrated")) == 1


def copying_s1(run: Run, after: float):
    """A hook for ``run.run_until``: from ``after`` on, sensor "s9" re-sends s1's skeleton
    byte for byte after every frame; returns (hook, the copies' times as they are sent)."""
    last: dict[str, tuple] = {}
    original_frame = run.frame

    def frame(sensor, joints, conf, t):
        if sensor == "s1":
            last["s1"] = (joints, conf)
        original_frame(sensor, joints, conf, t)

    copies: list[float] = []

    def copy_s1(r):
        if r.t >= after:
            copies.append(r.clock.now())
            r.engine.handle_datagram(encode_client_joints("s9", 0, *last["s1"]),
                                     ("127.0.0.1", 9009))

    run.frame = frame
    return copy_s1, copies


def test_bit_identical_streams_are_flagged(tmp_path):
    run = Run(tmp_path, n=2)
    # the copy even has a calibration (the installer duplicated s1's entry): it is fused at first
    set_calibration(run.rig, "s9", run.rig.sensors["s1"].calibration.matrix, "copied")
    copy_s1, copies = copying_s1(run, 1.0)
    run.run_until(3.0, hook=copy_s1)
    flagged = run.events("identical", "s9")
    assert len(flagged) == 1 and "bit-identical to s1" in flagged[0].detail
    assert flagged[0].t == copies[4]     # at the fifth identical frame
    assert run.engine.sensor_notes["s9"]["state"] == "suspect"
    assert "copied stream" in run.engine.sensor_notes["s9"]["reason"]
    assert not run.events("calibrated", "s9")  # a copy is never "calibrated" as a perfect fit
    assert any("s9" in s for t, _, s in run.fused if t < flagged[0].t)
    assert all("s9" not in s for t, _, s in run.fused if t > flagged[0].t)
    assert not run.events("suspect", "s1")      # the original keeps working


def test_the_worker_thread_calibrates_without_blocking_the_engine(tmp_path):
    # CLEAN: the transform's precision is asserted (1 degree, 5 cm: the clean budget's)
    run = Run(tmp_path, n=2, calibrated=False, threaded=True, pairs=90, kinect=CLEAN_KINECT)
    worker = [t for t in threading.enumerate() if t.name == "stage-calibration"]
    assert len(worker) == 1

    def sync(r):  # let the worker catch up, then apply what it asked for (deterministic)
        r.cal.flush()
        r.engine.drain()

    # the engine hands it each frame once the frame's batch is sent (it only queues them)
    assert run.engine.late_frame_observers == [run.cal._observe]
    assert run.engine.frame_observers == []
    try:
        run.run_until(6.0, hook=sync)
    finally:
        run.cal.stop()
    done = run.events("calibrated")
    assert len(done) == 1
    assert run.engine.sensor_notes["s1"]["state"] == "ok"
    err = transform_error(done[0].matrix, run.truth_to_stage("s1"))
    assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, err
    assert not worker[0].is_alive()
    assert run.engine.frame_observers == [] and run.engine.late_frame_observers == []


def test_request_recalibrates_on_demand_while_still_fused(tmp_path):
    run = Run(tmp_path, n=2, pairs=60)
    run.run_until(2.0)
    assert run.cal.request() == ["s1"]
    run.run_until(2.5)
    assert "s1" in run.fused[-1][2]   # still fused while the new pairs come in
    run.run_until(5.0)
    assert len(run.events("calibrated")) == 1
    assert not run.events("suspect")


def _sim_run(bump_deg: float | None):
    """The simulator's default rehearsal (3 Kinects, one dancer), fed offline with the
    calibrator attached; optionally kinect-b is turned by ``bump_deg`` at 10 s."""
    from stage.sensors import sim as sim_mod
    from importlib import resources

    from stage.yamlio import loads_marked
    text = (resources.files("stage.sensors.sim") / "scenarios" / "default.yaml").read_text()
    if bump_deg is not None:
        text += f"\nevents:\n  - {{bump: kinect-b, at: 10, yaw: {bump_deg}}}\n"
    sim = sim_mod.Simulator(sim_mod.parse_scenario(loads_marked(text), "bump.yaml"), seed=2)
    rig = sim.rig(calibrated=True)
    clock = ManualClock(0.0)
    engine = Engine(rig, clock)
    fused: list[tuple[float, float, tuple[str, ...]]] = []

    def listen(frame):
        truth = sim.truth(frame.t)
        for body in frame.bodies.values():
            if truth:
                joints = next(iter(truth.values()))[0]
                seen = body.conf > 0
                fused.append((frame.t, float(np.linalg.norm(body.joints[seen] - joints[seen],
                                                            axis=1).mean()), body.sensors))
    engine.listeners.append(listen)
    cal = attach_live(engine, None, threaded=False)
    feed(engine, clock, sim.stream(16.0), until=16.0)
    return sim, cal, fused


def test_simulated_kinects_bumped_mid_show(tmp_path):
    """Kinect-faithful data (occlusion, correlated noise, latency): no false alarm in 16 s,
    and a 10 degree bump changes the fused output by no more than leaving the sensor out.
    The scenario's own model: the realistic default (heavy tails), the same bounds as
    before it was."""
    _, quiet_cal, quiet = _sim_run(None)
    assert quiet_cal.events == []            # no false suspicion on healthy sensors
    sim, cal, bumped = _sim_run(10.0)
    suspect = [e for e in cal.events if e.kind == "suspect"]
    done = [e for e in cal.events if e.kind == "calibrated"]
    assert [e.sensor for e in suspect] == ["kinect-b"] and [e.sensor for e in done] == ["kinect-b"]
    assert suspect[0].t - 10.0 <= 1.0 and done[0].t - 10.0 <= 5.0
    err = transform_error(done[0].matrix, sim.sensor_poses(12.0)["kinect-b"].to_stage)
    assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, err
    # the fused output during the episode: as good as with the sensor healthy, give or take
    # what one sensor fewer costs (3 cm), far from the ~0.25 m the bumped data would cause
    healthy = {round(t, 4): e for t, e, _ in quiet}
    diffs = [abs(e - healthy[round(t, 4)]) for t, e, _ in bumped
             if 10.0 <= t <= done[0].t and round(t, 4) in healthy]
    assert len(diffs) > 20 and max(diffs) < 0.03, max(diffs)  # fused at matching times
    assert all("kinect-b" not in s for t, _, s in bumped if suspect[0].t <= t < done[0].t)


#: Liminal's last steps (pieces/liminal.sim.yaml, four Kinects on a 3.2 m ring): the dancer
#: walks from the centre to (-2.5, 0.5), out of kinect-b's view at its edge and on into
#: kinect-c's far range, then back in
_WALK_OUT = """
name: walk-out
duration: 7
sensors:
  ring: {count: 4, radius: 3.2, height: 1.0, start_angle: 45}
performers:
  - name: dancer
    height: 1.70
    position: [0.0, 0.0]
    facing: 90
    timeline:
      - {wait: 1}
      - {walk: [-2.5, 0.5], speed: 1.0}
      - {walk: [0.0, 0.0], speed: 1.0}
"""


def _walk_out_run(seed: int, events: str = ""):
    from stage.sensors import sim as sim_mod
    from stage.yamlio import loads_marked
    sim = sim_mod.Simulator(sim_mod.parse_scenario(loads_marked(_WALK_OUT + events),
                                                   "walk-out.yaml"), seed=seed)
    engine = Engine(sim.rig(calibrated=True), ManualClock(0.0))
    cal = attach_live(engine, None, threaded=False)
    feed(engine, engine.clock, sim.stream(7.0), until=7.0)
    return cal


def test_walking_out_of_a_sensors_view_is_not_a_jump():
    """A body leaving a sensor's view at its edge is tracked a moment longer by the torso
    joints still inside (kinect-b: at last one hip alone, 17-24 cm below and beside the
    whole torso's centre, the centre sliding 3 m/s as joints drop out). The jump gate
    compares two views on the torso joints both track, so healthy sensors are not made
    suspect (before: kinect-c "jumped 0.34-0.36 m away from kinect-b" on each of these
    seeds, and at 79 s of `stage play pieces/liminal.yaml --sim --seed 24627`); a real
    bump of the sensor she walked out of and back into is still caught at once."""
    for seed in (1, 2, 3):
        cal = _walk_out_run(seed)
        assert [e for e in cal.events if e.kind == "suspect"] == [], seed
    cal = _walk_out_run(1, "events:\n  - {bump: kinect-b, at: 5.0, yaw: 10}\n")
    suspect = [e for e in cal.events if e.kind == "suspect"]
    assert [e.sensor for e in suspect] == ["kinect-b"] and "jumped" in suspect[0].detail
    assert suspect[0].t - 5.0 <= 0.2


def test_a_moved_reference_is_recalibrated_and_stage_space_stays_put(tmp_path):
    """The reference turned: the other sensors agree among themselves, so the reference is the
    one left out and re-calibrated; its new placement becomes the rig's stage frame and the
    other calibrations are re-expressed, so every sensor still maps to the same stage space.
    CLEAN: every sensor's transform is held to the clean budget's precision (1 degree, 5 cm)
    and the fused error to FUSED_BOUND_M as a mean over all joints."""
    run = Run(tmp_path, n=3, kinect=CLEAN_KINECT)
    run.run_until(3.0)
    run.bump("s0", 10.0)
    run.run_until(9.0)
    assert [e.kind for e in run.cal.events if e.sensor == "s0"] == ["suspect", "calibrated"]
    assert not [e for e in run.cal.events if e.sensor != "s0"]
    fused_after = [e for t, e, _ in run.fused if t > 3.0]
    assert max(fused_after) <= FUSED_BOUND_M
    rig = load_rig(run.rig_path)
    for sid in ("s0", "s1", "s2"):
        err = transform_error(rig.transform_for(sid), run.truth_to_stage(sid))
        assert err["rot_deg"] < 1.0 and err["trans_mm"] < 50, (sid, err)


def test_threaded_the_observer_only_queues_and_the_worker_still_catches_a_bump(tmp_path):
    """Live, the engine thread only queues frames; the worker ingests them (buffers, jump
    gate) at its poll. Polled here after every frame (flush: deterministic), a bump is
    caught at its first frames and healed, as inline."""
    run = Run(tmp_path, n=3, threaded=True)
    queued = []

    def poll(r):
        queued.append(len(r.cal._inbox))
        r.cal.flush()          # the worker's poll, as it runs every poll_s live
        r.engine.drain()       # its changes, through call_soon
    try:
        run.run_until(4.0, poll)
        bump_t = run.t
        run.bump("s1", 10.0)
        run.run_until(9.0, poll)
    finally:
        run.cal.stop()
    assert max(queued) == 3 and not run.cal._inbox   # one frame per sensor, all ingested
    suspect = run.events("suspect")
    assert len(suspect) == 1 and "jumped" in suspect[0].detail
    assert suspect[0].t - bump_t <= 0.1
    calibrated = run.events("calibrated")
    assert calibrated and calibrated[0].t - bump_t <= 5.0
    assert run.cal.inbox_dropped == 0 and run.cal.crashes == 0


@pytest.mark.parametrize("path", ["datagram", "stacked"])
def test_the_worker_judges_a_datagram_of_several_people_at_once_and_catches_a_bump(tmp_path,
                                                                                   path):
    """Live, the worker puts one datagram's skeletons (one sensor, one capture time) through
    the jump gate together: as decoded, in one compiled call (``JumpGate.check_frames``),
    or -- where the kernel does not take the arrays -- stacked (``JumpGate.check_many``);
    a bump moves every view of the sensor, and is caught at its first frames as one view
    at a time would."""
    from stage.sensors.protocol import encode_bundle

    run = Run(tmp_path, n=3, threaded=True)
    offset = np.array([1.2, 0.0, 0.0])
    grouped = []
    check_many, check_frames = run.cal._gate.check_many, run.cal._gate.check_frames

    def spy(sensor, users, t, points, tracked):
        grouped.append(("stacked", len(users)))
        return check_many(sensor, users, t, points, tracked)

    def spy_frames(sensor, users, t, joints, conf, matrix):
        if path == "stacked":
            raise TypeError("not C-ordered")     # what numba says of arrays it does not take
        grouped.append(("datagram", len(users)))
        return check_frames(sensor, users, t, joints, conf, matrix)

    def run_until(until: float) -> None:
        while run.t < until - 1e-9:
            truth, _ = dancer(run.t)
            for k, sid in enumerate(run.ids):
                msgs = []
                for user, body in enumerate((truth, truth + offset)):
                    seen = run.kinects[k].observe(body, user=user)
                    if seen is not None:
                        msgs.append(encode_client_joints(sid, user, *seen))
                if msgs:
                    run.clock.set(max(run.clock.now(), run.t + 0.002 * k))
                    run.engine.handle_datagram(encode_bundle(msgs), ("127.0.0.1", 9000 + k))
            run.engine.tick()
            run.cal._gate.check_many = spy   # (a crash restart would build a new gate)
            run.cal._gate.check_frames = spy_frames
            run.cal.flush()
            run.engine.drain()
            run.t = round(run.t + 1 / FPS, 9)
    try:
        run_until(4.0)
        bump_t = run.t
        run.bump("s1", 10.0)
        run_until(6.0)
    finally:
        run.cal.stop()
    # a datagram of both people went through the path, no group held more than its two
    assert (path, 2) in grouped and max(n for _, n in grouped) == 2
    assert path == "datagram" or ("datagram", 2) not in grouped
    suspect = run.events("suspect")
    assert len(suspect) == 1 and "2 of its views jumped" in suspect[0].detail
    assert suspect[0].t - bump_t <= 0.1
    assert not run.events("suspect", "s0") and not run.events("suspect", "s2")
    assert run.cal.crashes == 0


def test_check_many_decides_as_one_view_at_a_time():
    """``JumpGate.check_many`` on one sensor's views of one instant gives the verdicts, the
    links and the velocities of checking them one by one (the distance it reports may
    differ in the last bit), whichever torso joints each view tracks."""
    from stage.calibration.gate import JumpGate

    rng = np.random.default_rng(7)
    jumps = 0
    for trial in range(60):
        one, many = JumpGate(), JumpGate()
        for gate in (one, many):
            for sid in ("a", "b", "c"):
                gate.trust(sid, sid != "c" or trial % 3 != 0)
        base = rng.normal(size=(4, 1, 3)) + rng.normal(scale=0.15, size=(4, 5, 3))
        for step in range(40):
            t = step / 30
            for sid in ("a", "b", "c"):
                points = base + 0.01 * step + rng.normal(scale=0.03, size=(4, 5, 3))
                tracked = rng.random((4, 5)) < 0.85     # a joint now and then untracked...
                points[~tracked] += 0.4                 # ...where the sensor only guesses it
                if sid == "b" and step > 20 and trial % 2:
                    points = points + [0.4, 0.0, 0.0]   # bumped
                if rng.random() < 0.05:
                    points[rng.integers(4)] += 0.5      # one view jumps alone
                users = [int(u) for u in rng.permutation(4)[:rng.integers(1, 5)]]
                expected = [one.check(sid, u, t, points[u], tracked[u]) for u in users]
                got = many.check_many(sid, users, t, points[users], tracked[users])
                for e, g in zip(expected, got):
                    assert (e is None) == (g is None)
                    if e is not None:
                        assert e[0] == g[0] and abs(e[1] - g[1]) < 1e-12
                        jumps += 1
                if rng.random() < 0.05:
                    user = int(rng.integers(4))
                    one.forget(sid, user)
                    many.forget(sid, user)
        n = len(one._index)
        assert one._index == many._index
        assert np.array_equal(one._links[:n, :n], many._links[:n, :n])
        assert np.allclose(one._v[:n], many._v[:n], rtol=0, atol=1e-12)
    assert jumps > 100


def test_views_built_together_are_the_views_built_one_by_one():
    """``View.many`` (one poll's buffers at once) gives ``View.of``'s arrays to the bit,
    through every way a buffer splits into identities: gaps, torso jumps, another person,
    a new run of the user id, frames without a torso, sensors without a transform."""
    from stage.calibration.live import View
    from stage.frames import SensorFrame

    rng = np.random.default_rng(11)
    transforms = [None, np.eye(4), invert(ring_poses(3)[1].to_stage)]
    for trial in range(40):
        snapshot = []
        for b in range(int(rng.integers(1, 7))):
            m = transforms[int(rng.integers(3))]
            t, centre, person, run, entries = 0.0, rng.normal(size=3), 1, 0, []
            for k in range(int(rng.integers(1, 16))):
                t += 1 / 30 + (0.3 if rng.random() < 0.08 else 0.0)
                centre = centre + (0.5 if rng.random() < 0.08 else 0.01)
                if rng.random() < 0.06:
                    person += 1
                if rng.random() < 0.05:
                    run += 1
                joints = centre + rng.normal(scale=0.2, size=(25, 3))
                conf = rng.choice([0.0, 0.5, 1.0], size=25)
                if rng.random() < 0.1:
                    conf[:] = 0.0
                frame = SensorFrame(f"s{b % 3}", b, t + rng.normal(scale=0.002), joints, conf,
                                    m, None)
                entries.append((frame, None if rng.random() < 0.2 else person, run))
            snapshot.append(entries[::-1])   # as the poll takes them: newest first
        shifts = [float(rng.choice([0.0, 0.38, -1.2])) for _ in snapshot]  # sensors' lags
        singles = [View.of(e, shift) for e, shift in zip(snapshot, shifts)]
        for one, many in zip(singles, View.many(snapshot, shifts), strict=True):
            assert (one.sensor, one.user, one.person) == (many.sensor, many.user, many.person)
            assert one.shift == many.shift and (one.entries is None) == (many.entries is None)
            for whole in (False, True):  # the newest run, then every run (View.whole)
                for name in ("t", "raw", "conf", "stage"):
                    a, b = getattr(one, name), getattr(many, name)
                    assert a.shape == b.shape and a.tobytes() == b.tobytes(), name
                assert one.transform is many.transform
                one, many = one.whole(), many.whole()
            assert np.array_equal(one.run, many.run)


def test_the_monitors_batched_resampling_and_pairs_match_one_view_at_a_time():
    """``Sampled.of_many`` and ``resample_many`` (one pass for a poll's views) give
    ``Sampled.of``'s and ``pairs.resample``'s numbers to the bit, and ``Sampled.histograms``
    the histograms of the distances of every two views joint by joint, pooled person by
    person, in the order the pairs first saw a joint: gaps, NaN rows, instants before and
    after a view, a person with one view, a pair that sees no joint in one person."""
    from stage.calibration.live import View
    from stage.calibration.pairs import resample
    from stage.calibration.scoring import CORE, Sampled, grid, histogram, resample_many

    rng = np.random.default_rng(5)
    for trial in range(30):
        at = grid(1.0, 1.0 + rng.uniform(0.05, 0.4))
        groups = []
        for person in range(int(rng.integers(1, 5))):
            views = []
            for s in range(int(rng.integers(1, 5))):
                n = int(rng.integers(1, 20))
                t = 0.9 + np.sort(rng.uniform(0, 0.6, n))
                if rng.random() < 0.3:
                    t = t + 0.1 * (np.arange(n) > n // 2)          # a gap
                raw = rng.normal(size=(n, 25, 3))
                conf = rng.choice([0.0, 0.5, 1.0], size=(n, 25))
                stage = raw + 0.01 * rng.normal(size=raw.shape)
                if rng.random() < 0.3:
                    stage[rng.integers(n)] = np.nan                  # no transform then
                views.append(View(f"s{s}", person, t, raw, conf, stage, person=person))
            groups.append(views)
        expected: dict = {}                 # pair -> (distances, weights), laid end to end
        many_all = Sampled.of_many(groups, at)
        for one, many in zip([Sampled.of(v, at) for v in groups], many_all, strict=True):
            assert one.sensors == many.sensors
            assert one.joints.tobytes() == many.joints.tobytes()
            assert one.conf.tobytes() == many.conf.tobytes()
            for i in range(len(one.sensors)):
                for k in range(i + 1, len(one.sensors)):
                    w = one.conf[i] * one.conf[k] * CORE
                    key = tuple(sorted((one.sensors[i], one.sensors[k])))
                    if not (w > 0).any():
                        continue
                    d = np.linalg.norm(one.joints[i][w > 0] - one.joints[k][w > 0], axis=-1)
                    d0, w0 = expected.get(key, (np.zeros(0), np.zeros(0)))
                    expected[key] = (np.concatenate([d0, d]), np.concatenate([w0, w[w > 0]]))
        found = Sampled.histograms(many_all)
        assert list(found) == list(expected)
        for key, (d, w) in expected.items():
            assert found[key].tobytes() == histogram(d, w).tobytes()
        streams = [(v.t, v.raw, v.conf) for views in groups for v in views]
        j, c = resample_many(streams, at, 0.1, 0.05)
        for k, (t, raw, conf) in enumerate(streams):
            rj, rc, _ = resample(t, raw, conf, at, max_gap=0.1, max_dt=0.05)
            assert rj.tobytes() == j[k].tobytes() and rc.tobytes() == c[k].tobytes()
