"""Replaying recordings: offline into an engine, or in real time over UDP or in-process.

Offline (``replay_offline``) is deterministic: every record is handed to the
engine at its recorded arrival time on a ManualClock, the engine ticks on a
fixed grid, and nothing depends on the machine's speed, so the same
recording (and the same seed, for a simulated one) gives the same fused
output bit for bit, as fast as the CPU allows.

Real time (``ReplaySource``) paces the records by their arrival times
(x ``speed``, or as fast as possible), from one UDP socket per recorded
sender so the server sees the same distinct clients, or straight into a
running engine's queue. Bundle timetags are re-anchored to the wall clock
when playback starts (keeping the sensors' clock offsets to one another),
scaled with ``--speed``, and keep moving forwards across ``--loop`` restarts,
so the server sees what it would from live clients.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import struct
import tempfile
import threading
import time
from typing import Iterable, Iterator

from pythonosc.parsing import ntp

from ..clock import ManualClock
from ..engine.engine import Engine
from .protocol import Inbound
from ..errors import ConfigError
from .protocol import decode_datagram
from .recording import Record, read_recording
from ..rig import Rig, load_rig

log = logging.getLogger("stage.replay")

TICK_S = 0.02  # the engine thread's tick in `stage serve` (Engine.run)


def drive(engine: Engine, clock: ManualClock, items: Iterable[tuple[float, tuple[str, int], bytes]],
          tick_s: float = TICK_S, until: float | None = None) -> int:
    """Feed (arrival, source, datagram) items, in arrival order, into ``engine`` offline.

    The clock is set to each item's arrival before the engine handles it, and
    the engine ticks every ``tick_s`` on a grid starting at the clock's
    reading now, exactly as often as it would in real time. ``until``: keep
    ticking up to this time after the last item. Returns the items fed.
    """
    next_tick = clock.now() + tick_s
    n = 0
    for arrival, source, data in items:
        while next_tick <= arrival:
            clock.set(max(clock.now(), next_tick))
            engine.tick(clock.now())
            next_tick += tick_s
        clock.set(max(clock.now(), arrival))
        engine.handle_datagram(data, source, clock.now())
        n += 1
    while until is not None and next_tick <= until:
        clock.set(max(clock.now(), next_tick))
        engine.tick(clock.now())
        next_tick += tick_s
    return n


def replay_offline(path: str | os.PathLike, engine: Engine, clock: ManualClock, *,
                   tick_s: float = TICK_S, start: float | None = None, until: float | None = None
                   ) -> int:
    """Feed every record of a recording into ``engine`` at its recorded arrival time.

    Arrival times are used as recorded when the clock has not passed the
    first one; otherwise the recording is shifted to start at the clock's
    reading (``start`` forces a start time). ``until``: keep ticking up to
    this clock time after the last record (as ``Simulator.feed`` does with its
    duration). Returns the records fed; a recording cut by a crash replays up
    to its last whole record.
    """
    recording = read_recording(path)
    first: list[float] = []
    shift = [0.0]

    def items() -> Iterator[tuple[float, tuple[str, int], bytes]]:
        for rec in recording:
            if not first:
                first.append(rec.arrival)
                begin = start if start is not None else max(clock.now(), rec.arrival)
                shift[0] = begin - rec.arrival
            yield rec.arrival + shift[0], rec.source, rec.data
    n = drive(engine, clock, items(), tick_s, until=until)
    if recording.ignored_bytes:
        log.warning("%s: replayed %d records; %d byte(s) after the last whole record ignored",
                    path, n, recording.ignored_bytes)
    return n


def rig_from_meta(meta: dict) -> Rig | None:
    """The rig a recording carries in its header (the simulator stores its exact one)."""
    data = meta.get("rig")
    if not isinstance(data, dict):
        return None
    import yaml
    fd, tmp = tempfile.mkstemp(suffix=".yaml")
    try:
        with os.fdopen(fd, "w") as f:
            yaml.safe_dump(data, f)
        rig = load_rig(tmp)
    except ConfigError as exc:
        raise ConfigError(f"the rig stored in the recording is not valid: {exc.bare_message}"
                          ) from None
    finally:
        os.unlink(tmp)
    rig.path = None
    return rig


# ---------------------------------------------------------------- timetags

def _retimed(data: bytes, fn) -> bytes:
    """``data`` with every bundle timetag t (Unix s) replaced by fn(t); messages unchanged."""
    if not data.startswith(b"#bundle\0") or len(data) < 16:
        return data
    out = bytearray(data)
    _retime_into(out, 0, len(out), fn, 0)
    return bytes(out)


def _retime_into(buf: bytearray, start: int, end: int, fn, depth: int) -> None:
    if depth > 8 or end - start < 16:
        return
    (stamp,) = struct.unpack_from(">Q", buf, start + 8)
    if stamp != 1:  # 1 = "immediately": leave it
        t = ntp.ntp_to_system_time(bytes(buf[start + 8:start + 16]))
        buf[start + 8:start + 16] = ntp.system_time_to_ntp(fn(t))
    i = start + 16
    while i + 4 <= end:
        (size,) = struct.unpack_from(">i", buf, i)
        i += 4
        if size <= 0 or i + size > end:
            return  # malformed: leave the rest for the server to count as a drop
        if buf[i:i + 8] == b"#bundle\0":
            _retime_into(buf, i, i + size, fn, depth + 1)
        i += size


class ReplaySource:
    """Plays a recording in real time into a UDP target or an in-process engine.

    ``speed``: 1 real time, 2 twice as fast, ``math.inf`` as fast as possible.
    ``loop``: start again at the end (sensor clocks keep going forwards).
    Use ``start()``/``stop()``; ``done`` is set when it finishes.
    """

    def __init__(self, path: str | os.PathLike, *, target: tuple[str, int] | None = None,
                 engine: Engine | None = None, speed: float = 1.0, loop: bool = False) -> None:
        if (target is None) == (engine is None):
            raise ValueError("give exactly one of target and engine")
        if not speed > 0:
            raise ConfigError("--speed must be greater than 0")
        self.path = str(path)
        self.recording = read_recording(self.path)  # fails now, with one line, if unreadable
        self.target, self.engine = target, engine
        self.speed, self.loop = speed, loop
        self.sent = 0
        self.loops = 0
        self._first_tag: float | None = None  # the first timetag in the recording
        self.done = threading.Event()
        self._stop = threading.Event()
        self._socks: dict[tuple[str, int], socket.socket] = {}
        self._thread = threading.Thread(target=self._run, name="stage-replay", daemon=True)

    def start(self) -> "ReplaySource":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def wait(self, timeout: float | None = None) -> bool:
        return self.done.wait(timeout)

    def _run(self) -> None:
        try:
            self._play()
        except Exception:  # the show must not die with its source; say why it stopped
            log.exception("replay of %s stopped", self.path)
        finally:
            for sock in self._socks.values():
                sock.close()
            self.done.set()

    def _play(self) -> None:
        fast = not math.isfinite(self.speed)
        mono0, wall0 = time.monotonic(), time.time()
        offset = 0.0  # recording seconds already played by earlier loops
        while not self._stop.is_set():
            first = None
            last = 0.0
            for rec in self.recording:
                if first is None:
                    first = rec.arrival
                last = rec.arrival - first
                at = offset + last
                if not fast:
                    delay = mono0 + at / self.speed - time.monotonic()
                    if delay > 0 and self._stop.wait(delay):
                        return
                if self._stop.is_set():
                    return
                self._emit(rec, self._clock_of(wall0, offset))
            if first is None:
                log.warning("%s holds no records", self.path)
                return
            if not self.loop:
                return
            self.loops += 1
            offset += last + 1.0 / 30.0  # the next pass starts one frame after the last record

    def _clock_of(self, wall0: float, offset: float):
        """Timetag mapping: sensor clocks re-anchored to now, scaled by the speed, and moved on
        by the loops already played, so they always run forwards like a live client's."""
        speed = self.speed if math.isfinite(self.speed) else 1.0

        def fn(t: float) -> float:
            if self._first_tag is None:
                self._first_tag = t
            return wall0 + ((t - self._first_tag) + offset) / speed
        return fn

    def _emit(self, rec: Record, fn) -> None:
        data = _retimed(rec.data, fn)
        self.sent += 1
        if self.target is not None:
            sock = self._socks.get(rec.source)
            if sock is None:
                sock = self._socks[rec.source] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.sendto(data, self.target)
            except OSError:
                pass  # the server went away; keep the rhythm, it may come back
            return
        engine = self.engine
        arrival = engine.clock.now()
        decoded = decode_datagram(data, f"{rec.source[0]}:{rec.source[1]}")
        for client, reason in decoded.drops:
            engine.drops.add(client, reason)
        for message, timetag in decoded.messages:
            engine.submit(Inbound(message, arrival, rec.source, timetag))


def offline_engine(path: str | os.PathLike, rig: Rig | None = None, seed_clock: float = 0.0,
                   ) -> tuple[Engine, ManualClock]:
    """An in-process engine for replaying ``path``: the given rig, else the recording's own."""
    if rig is None:
        rig = rig_from_meta(read_recording(path).meta) or Rig()
    clock = ManualClock(seed_clock)
    return Engine(rig, clock), clock


def fused_json(frame) -> dict:
    """A FusedFrame as plain JSON (floats kept exact: json writes the shortest repr)."""
    return {"t": frame.t, "updated": list(frame.updated), "new": list(frame.new),
            "lost": list(frame.lost),
            "bodies": {str(pid): {"joints": b.joints.tolist(), "conf": b.conf.tolist(),
                                  "hands": [int(b.hands[0]), int(b.hands[1])],
                                  "position": b.position.tolist(), "sensors": list(b.sensors)}
                       for pid, b in sorted(frame.bodies.items())}}


__all__ = ["drive", "replay_offline", "rig_from_meta", "offline_engine", "ReplaySource",
           "fused_json", "TICK_S"]
