"""The engine thread owns all live state, the rig included (issue 9).

A calibrator worker that saves hundreds of calibrations while views and the
status collector read the rig on the engine thread must never break them.
Before the engine owned the rig, the worker mutated ``rig.sensors`` on its
own thread; the status collector's walk over it then raised "dictionary
changed size during iteration" inside the view host's listener, which the
engine disabled: every view stopped receiving frames for the rest of the show.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

import numpy as np

from stage.calibration import attach_live
from stage.calibration.methods import CalibrationResult
from stage.clock import MonotonicClock
from stage.engine.engine import Engine
from stage.rig import Rig, load_rig, set_calibration
from stage.sensors.protocol import Inbound, decode_datagram, encode_client_joints
from stage.views import View, ViewHost

SAVES = 300


class CountingView(View):
    """Counts frames and status reports (on its own slot thread)."""

    def __init__(self) -> None:
        self.frames = 0
        self.statuses = 0

    def on_frame(self, frame):
        self.frames += 1

    def on_status(self, status):
        self.statuses += 1


def _result(k: int) -> CalibrationResult:
    m = np.eye(4)
    m[:3, 3] = (0.01 * k, 0.0, 2.0)
    return CalibrationResult(matrix=m, method="rigid", fitness=0.95, rms_m=0.02, pairs=300)


def test_worker_saves_never_break_views_reading_the_rig(tmp_path, caplog):
    rig = Rig(reference="s0")
    for k in range(50):  # a longer walk for the status collector on every frame
        set_calibration(rig, f"listed-{k}", np.eye(4), "manual")
    path = str(tmp_path / "rig.yaml")
    rig.save(path)
    engine = Engine(rig, MonotonicClock())
    view = CountingView()
    host = ViewHost([view], threaded=True, status_interval_s=0.0)  # status on every frame
    host.attach(engine)
    calibrator = attach_live(engine, path, threaded=True)
    stop = threading.Event()
    engine_thread = threading.Thread(target=engine.run, args=(stop,), daemon=True)
    joints = np.tile(np.array([0.0, 1.0, 2.0]), (25, 1)) + np.linspace(0, 0.5, 25)[:, None]
    frame = encode_client_joints("s0", 0, joints, np.ones(25))

    def feed() -> None:  # the receiver's path: one sensor at ~1 kHz, each frame fused and
        # followed by a status walk over the rig
        while not stop.is_set():
            for message, timetag in decode_datagram(frame).messages:
                engine.submit(Inbound(message, engine.clock.now(), ("127.0.0.1", 9000), timetag))
            time.sleep(0.001)

    def save_from_the_worker_thread() -> None:  # as the calibrator's worker does after a fit
        for k in range(SAVES):
            calibrator._save(f"new-{k}", _result(k))
            calibrator._send()

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)  # switch threads as often as possible: make a race show
    caplog.set_level(logging.ERROR, logger="stage")
    try:
        host.start()
        engine_thread.start()
        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        time.sleep(0.2)
        saver = threading.Thread(target=save_from_the_worker_thread)
        saver.start()
        saver.join(60)
        frames_after_saves = view.frames
        deadline = time.monotonic() + 20.0
        while view.frames <= frames_after_saves + 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        still_listening = host._on_frame in engine.listeners
    finally:
        sys.setswitchinterval(switch)
        stop.set()
        engine_thread.join(5)
        calibrator.stop()
        host.stop()
    disabled = [r.getMessage() for r in caplog.records if "it is disabled" in r.getMessage()]
    assert disabled == []
    assert still_listening
    assert view.frames > frames_after_saves + 3     # still receiving after all the saves
    assert view.statuses > 0
    # every calibration reached the rig, on the engine thread, and the file
    assert all(f"new-{k}" in rig.sensors for k in range(SAVES))
    assert engine.rig_store.flush(5.0)
    on_disk = load_rig(path)
    assert all(f"new-{k}" in on_disk.sensors for k in range(SAVES))
    assert on_disk.sensors["new-7"].calibration.method == "rigid (live)"
