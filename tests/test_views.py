"""The view host: delivery order, per-view queues, slow and broken views, status.

Fake views are real ``View`` subclasses that record what they get. Unthreaded
hosts (``threaded=False``) with a ``ManualClock`` make most of this
deterministic; the threaded tests check that the engine side never waits.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from stage.sensors.sim import standing_pose
from stage.clock import ManualClock
from stage.frames import Body, FusedFrame
from stage.engine.engine import Engine
from stage.events import MappingValue, Note, SectionChange
from stage.joints import HandState
from stage.sensors.protocol import encode_client_joints, encode_message
from stage.rig import Rig, set_calibration
from stage.views import Scene, Status, View, ViewHost, sensor_health
from stage.views.base import overrides


def make_body(pid: int = 1, x: float = 0.0, z: float = 0.0) -> Body:
    joints = standing_pose((x, z), 0.0)
    return Body(pid, joints, np.ones(25), np.zeros((25, 3)), (HandState.OPEN, HandState.CLOSED),
                joints[[0, 1, 20, 12, 16]].mean(axis=0), ("kinect-a",))


def make_frame(t: float, *bodies: Body, new: tuple[int, ...] = (),
               lost: tuple[int, ...] = ()) -> FusedFrame:
    return FusedFrame(t, {b.id: b for b in bodies}, tuple(b.id for b in bodies), new, lost)


class Recorder(View):
    """Records every call in order."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def start(self, ctx):
        self.calls.append(("start",))

    def on_scene(self, scene):
        self.calls.append(("scene", scene))

    def on_events(self, events):
        self.calls.append(("events", list(events)))

    def on_status(self, status):
        self.calls.append(("status", status))

    def on_frame(self, frame):
        self.calls.append(("frame", frame.t))

    def stop(self):
        self.calls.append(("stop",))

    def kinds(self) -> list[str]:
        return [c[0] for c in self.calls]


class FramesOnly(View):
    def __init__(self) -> None:
        self.frames: list[float] = []

    def on_frame(self, frame):
        self.frames.append(frame.t)


def test_only_overridden_streams_are_delivered():
    view = FramesOnly()
    assert overrides(view, "on_frame") and not overrides(view, "on_events")
    host = ViewHost([view], threaded=False, clock=ManualClock())
    host.start()
    host.emit([MappingValue(0.0, "m", 0.5)])
    host._on_frame(make_frame(1.0, make_body()))
    host.pump()
    assert view.frames == [1.0]
    assert host.stats()["framesonly"]["events"] == 0  # the event never entered its queue


def test_frames_and_events_arrive_in_emission_order_and_scene_first():
    view = Recorder()
    host = ViewHost([view], threaded=False, clock=ManualClock())
    host.set_scene([{"name": "centre", "shape": "sphere", "centre": [0, 1, 0], "radius": 1}],
                   ["intro", "storm"])
    host.start()
    host._on_frame(make_frame(1.0, make_body()))
    host.emit([SectionChange(1.0, "intro", None, 0, "start")])
    host.emit([MappingValue(1.0, "height", 0.3)])
    host._on_frame(make_frame(2.0, make_body()))
    host.pump()
    host.stop()
    assert view.kinds() == ["start", "scene", "frame", "events", "frame", "stop"]
    assert view.calls[1][1] == Scene(({"name": "centre", "shape": "sphere", "centre": [0, 1, 0],
                                       "radius": 1},), ("intro", "storm"))
    # the two emit() calls between the frames are one batch, in order
    assert [type(e).__name__ for e in view.calls[3][1]] == ["SectionChange", "MappingValue"]


def test_a_slow_view_drops_its_oldest_frames_counted_and_never_delays_the_engine():
    gate, inside = threading.Event(), threading.Event()

    class Slow(View):
        max_pending_frames = 4

        def __init__(self):
            self.frames = []

        def on_frame(self, frame):
            inside.set()
            gate.wait(10)
            self.frames.append(frame.t)

    class Roomy(FramesOnly):
        max_pending_frames = 64   # enough room for the burst below: it must lose nothing

    slow, fast = Slow(), Roomy()
    host = ViewHost([slow, fast]).start()
    try:
        host._on_frame(make_frame(0.0, make_body()))
        assert inside.wait(5)                 # the slow view is now stuck in frame 0
        t0 = time.perf_counter()
        for k in range(1, 50):
            host._on_frame(make_frame(float(k), make_body()))
        offer_s = time.perf_counter() - t0
        deadline = time.monotonic() + 5
        while len(fast.frames) < 50 and time.monotonic() < deadline:
            time.sleep(0.01)
        gate.set()
        deadline = time.monotonic() + 5
        while host.stats()["slow"]["frames_pending"] and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        host.stop()
    stats = host.stats()["slow"]
    assert host.stats()["roomy"]["frames_dropped"] == 0
    # the slow view got the first frame (it was blocked in it), then the newest four
    assert slow.frames == [0.0, 46.0, 47.0, 48.0, 49.0]
    assert stats["frames"] == 50 and stats["frames_dropped"] == 50 - len(slow.frames)
    assert fast.frames == [float(k) for k in range(50)]       # its neighbour lost nothing
    assert offer_s < 1.0, "offering 49 frames must not wait for the slow view (it waits 10 s)"


class Exploding(View):
    def __init__(self, where: str = "on_frame") -> None:
        self.where = where
        self.stopped = False
        self.frames = 0

    def start(self, ctx):
        if self.where == "start":
            raise OSError("port busy")

    def on_frame(self, frame):
        self.frames += 1
        if self.where == "on_frame" and frame.t >= 2:
            raise ValueError("bad maths")

    def stop(self):
        self.stopped = True


@pytest.mark.parametrize("where", ["start", "on_frame"])
def test_a_raising_view_is_named_disabled_and_the_show_goes_on(where, caplog):
    bad, good = Exploding(where), FramesOnly()
    host = ViewHost(threaded=False, clock=ManualClock())
    host.add(bad, "exploding")
    host.add(good)
    with caplog.at_level(logging.WARNING, logger="stage.views"):
        host.start()
        for t in range(5):
            host._on_frame(make_frame(float(t), make_body()))
            host.pump()
        host.stop()
    assert good.frames == [0.0, 1.0, 2.0, 3.0, 4.0]
    stats = host.stats()["exploding"]
    assert stats["state"] == "failed"
    assert (stats["error"] == "start: OSError: port busy" if where == "start"
            else stats["error"] == "on_frame: ValueError: bad maths")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "view 'exploding'" in warnings[0] and "disabled" in warnings[0]
    assert bad.stopped, "a failed view is still given the chance to release its ports"
    assert bad.frames == (0 if where == "start" else 3)  # nothing after the failure


def test_stop_delivers_queued_events_before_view_stop_and_is_idempotent():
    view = Recorder()
    host = ViewHost([view]).start()
    host.emit([Note(0.0, "keys", 0, 60, 100, 0.5)])
    host.stop()
    host.stop()
    assert view.kinds() == ["start", "events", "stop"]
    host.emit([Note(0.0, "keys", 0, 62, 100, 0.5)])  # after stop: ignored, no error
    assert view.kinds()[-1] == "stop"


def test_tick_deadlines_are_honoured_in_an_unthreaded_host():
    class Timer(View):
        def __init__(self):
            self.ticks = []

        def tick(self, now):
            self.ticks.append(now)
            return now + 0.25 if len(self.ticks) < 3 else None

    clock = ManualClock(10.0)
    timer = Timer()
    host = ViewHost([timer], threaded=False, clock=clock).start()
    assert host.next_deadline() == 10.25
    clock.set(10.1)
    host.pump()
    assert timer.ticks == [10.0]          # not due yet
    clock.set(10.25)
    host.pump()
    clock.set(10.6)
    host.pump()
    assert timer.ticks == [10.0, 10.25, 10.6] and host.next_deadline() is None


def test_a_threaded_view_is_woken_at_its_deadline_without_frames():
    class Alarm(View):
        def __init__(self):
            self.rang = threading.Event()
            self.at = None

        def start(self, ctx):
            self.when = ctx.now() + 0.05

        def tick(self, now):
            if now >= self.when:
                self.at = now
                self.rang.set()
                return None
            return self.when

    alarm = Alarm()
    with ViewHost([alarm]):
        assert alarm.rang.wait(2.0)
    assert alarm.at >= alarm.when


def test_names_are_unique():
    host = ViewHost(threaded=False)
    a, b = host.add(FramesOnly()), host.add(FramesOnly())
    assert (a.name, b.name) == ("framesonly", "framesonly-2")


# ---------------------------------------------------------------- status

def _engine_with_two_sensors(clock: ManualClock) -> Engine:
    rig = Rig(reference="kinect-a")
    offset = np.eye(4)
    offset[:3, 3] = (2.0, 0.0, 1.0)
    set_calibration(rig, "kinect-b", offset, "manual", fitness=0.95)
    set_calibration(rig, "kinect-c", np.eye(4), "manual")
    engine = Engine(rig, clock)
    joints = standing_pose((0.0, 2.0), 0.0)
    for k in range(10):
        clock.advance(1 / 30)
        for sensor in ("kinect-a", "kinect-b"):
            engine.handle_datagram(encode_client_joints(sensor, 0, joints, np.ones(25)))
    return engine


def test_status_has_sensor_positions_rates_and_health():
    clock = ManualClock(100.0)
    engine = _engine_with_two_sensors(clock)
    host = ViewHost(threaded=False, clock=clock)
    view = host.add(Recorder())
    host.attach(engine).start()
    host.collect_status()                 # the first status gives the baseline for rates
    for _ in range(15):
        clock.advance(1 / 30)
        engine.handle_datagram(encode_client_joints("kinect-a", 0, standing_pose((0.0, 2.0)),
                                                    np.ones(25)))
    engine.sensor_notes["kinect-b"] = {"fitness": 0.41, "state": "degraded",
                                       "reason": "moved 12 cm since calibration"}
    status = host.collect_status()
    host.pump()
    a, b, c = (status.sensors[s] for s in ("kinect-a", "kinect-b", "kinect-c"))
    assert a.position == (0.0, 0.0, 0.0) and a.ok and a.fps == pytest.approx(30.0)
    assert b.position == (2.0, 0.0, 1.0) and b.fps == 0.0
    assert not b.ok and b.reason == "calibration degraded: moved 12 cm since calibration"
    assert b.fitness == 0.41
    assert not c.ok and c.reason == "in the rig but not connected" and c.position == (0, 0, 0)
    assert status.engine["counts"]["frames"] == 35
    delivered = [c[1] for c in view.calls if c[0] == "status"]
    assert isinstance(delivered[-1], Status) and delivered[-1] is status
    # the silent sensor: after the client timeout it is shown as having lost tracking
    clock.advance(2.0)
    engine.tick()
    status = host.collect_status()
    assert not status.sensors["kinect-b"].ok
    assert status.sensors["kinect-b"].reason.startswith("lost tracking: silent for")


def test_frames_from_a_real_engine_reach_views_and_status_follows_at_its_interval():
    clock = ManualClock(5.0)
    engine = Engine(Rig(), clock)
    host = ViewHost(threaded=False, clock=clock, status_interval_s=0.5)
    view = host.add(Recorder())
    host.attach(engine).start()
    joints = standing_pose((0.5, 1.0), 0.0)
    engine.handle_datagram(encode_message("/registerDevice", "k", "kinect2"))
    for _ in range(30):
        clock.advance(1 / 30)
        engine.handle_datagram(encode_client_joints("k", 0, joints, np.ones(25)))
        host.pump()
    kinds = view.kinds()
    assert kinds.count("frame") == 30
    assert 2 <= kinds.count("status") <= 3   # 1 s of frames, one status per 0.5 s
    host.stop()
    assert engine.listeners == []            # detached


def test_status_reaches_views_on_an_empty_stage_through_call_soon():
    clock = ManualClock(0.0)
    engine = Engine(Rig(), clock)
    view = Recorder()
    host = ViewHost([view], clock=clock, status_interval_s=0.05).attach(engine).start()
    try:
        deadline = time.monotonic() + 5
        while not any(k == "status" for k in view.kinds()) and time.monotonic() < deadline:
            clock.advance(0.1)
            engine.drain()        # the engine thread's work: runs what call_soon queued
            time.sleep(0.02)
    finally:
        host.stop()
    assert "status" in view.kinds()


@pytest.mark.parametrize("client,ok,reason", [
    ({"active": True, "calibrated": True, "calibration": {}}, True, ""),
    ({"active": True, "calibrated": True, "calibration": {"fitness": 0.97, "state": "ok"}},
     True, ""),
    ({"active": False, "silent_s": 3.21, "calibrated": True}, False,
     "lost tracking: silent for 3.2 s"),
    ({"active": True, "calibrated": False}, False, "not calibrated: its frames are not fused"),
    ({"active": True, "calibrated": True, "calibration": {"fitness": 0.41}}, False,
     "calibration fitness 0.41 below 0.50"),
    # the live calibrator's state rules: "ok" at 0.45 is its call (hysteresis), not ours
    ({"active": True, "calibrated": True, "calibration": {"fitness": 0.45, "state": "ok"}},
     True, ""),
    ({"active": True, "calibrated": True,
      "calibration": {"fitness": 0.9, "state": "recalibrating", "reason": "drift"}}, False,
     "calibration recalibrating: drift"),
    ({"active": True, "calibrated": False,
      "calibration": {"state": "suspect", "fitness": 0.31, "reason": "torso jumped 0.4 m",
                      "progress": "12/50 pairs"}}, False,
     "calibration suspect: torso jumped 0.4 m (12/50 pairs)"),
])
def test_sensor_health(client, ok, reason):
    assert sensor_health(client)[:2] == (ok, reason)


def test_the_rig_files_fitness_is_used_when_no_live_calibrator_says_anything():
    assert sensor_health({"active": True, "calibrated": True}, rig_fitness=0.3)[:3] == (
        False, "calibration fitness 0.30 below 0.50", 0.3)
