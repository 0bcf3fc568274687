"""The live calibrator gives the engine thread its GIL while the engine has datagrams to
fuse: ``Engine.idle`` and ``EngineWorker._yield`` (docs/architecture.md, threads)."""

from __future__ import annotations

import threading
from types import SimpleNamespace

from stage.calibration.worker import YIELD_MAX_S, EngineWorker
from stage.engine.engine import Engine
from stage.sensors.messages import Inbound
from stage.sensors.protocol import decode_datagram, encode_message


class _Idle:
    """Stands in for ``Engine.idle``: records each wait, reports a busy engine."""

    def __init__(self) -> None:
        self.waits: list[float] = []

    def wait(self, timeout: float) -> bool:
        self.waits.append(timeout)
        return False


def test_a_threaded_worker_waits_for_an_idle_engine_between_chunks():
    engine = SimpleNamespace(idle=_Idle())
    worker = EngineWorker(engine, threaded=True)
    worker._yield()
    assert engine.idle.waits == [YIELD_MAX_S]      # bounded: the calibrator still progresses
    worker._yield(wait=False)                      # catching up: no wait
    assert engine.idle.waits == [YIELD_MAX_S]


def test_an_inline_worker_never_waits():
    # offline and in tests the worker polls on the engine thread: nothing to give way to,
    # and replays stay exactly as they were
    engine = SimpleNamespace(idle=_Idle())
    EngineWorker(engine, threaded=False)._yield()
    assert engine.idle.waits == []


def _register(sensor: str) -> list[Inbound]:
    decoded = decode_datagram(encode_message("/registerDevice", sensor, "kinect2"), "test")
    return [Inbound(m, 0.0, ("127.0.0.1", 9000), tt) for m, tt in decoded.messages]


def test_the_engine_is_idle_only_with_nothing_queued():
    engine = Engine()
    assert engine.idle.is_set()                    # an engine not running holds nobody up
    assert engine.submit_batch(_register("k1"))
    assert not engine.idle.is_set()                # a datagram queued: busy
    stop = threading.Event()
    thread = threading.Thread(target=engine.run, args=(stop,), daemon=True)
    thread.start()
    try:
        assert engine.idle.wait(10.0)              # the queue drained: idle again
        done = threading.Event()
        engine.call_soon(lambda e: done.set())
        assert done.wait(10.0)
    finally:
        stop.set()
        thread.join(10.0)
    assert "k1" in engine.clients
