"""Replaying recordings: the ``replay`` source.

Offline (``ReplaySource.items``) every record comes with its recorded arrival
time, so an in-process engine on a manual clock (``stage.app.offline``) gives
the same fused output bit for bit, as fast as the CPU allows.

Live (``ReplaySource.start``) paces the records by their arrival times
(x ``speed``, or as fast as possible) from one UDP socket per recorded
sender, so the server sees the same distinct clients. Every datagram goes
out in a bundle whose timetag is its original capture time shifted to now
(the recorded capture time, else its own timetag brought onto the
recording's clock, else its arrival), on one clock for all senders and
moving forwards across ``--loop`` restarts. Faster than real time the
timetags keep the recording's pace, so a server fuses every frame at any
speed (it follows a client sending faster than real time on that client's
own time line); slower than real time they are slowed with the playback.
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
from typing import Iterator

from pythonosc.parsing import ntp

from ..errors import ConfigError
from ..rig import Rig, load_rig
from .protocol import encode_bundle
from .recording import Record, read_recording
from .source import ThreadedSource

log = logging.getLogger("stage.replay")

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


class ReplaySource(ThreadedSource):
    """A recording (``stage record``, ``stage sim --out``, ``stage import``) as a source.

    ``speed``: 1 real time, 2 twice as fast, ``math.inf`` as fast as possible.
    ``loop``: start again at the end (sensor clocks keep going forwards).
    """

    name = "replay"
    description = "a recording of sensor datagrams (stage record, stage sim --out, stage import)"
    offline = True

    def __init__(self, path: str | os.PathLike, speed: float = 1.0, loop: bool = False) -> None:
        super().__init__()
        if not speed > 0:
            raise ConfigError("--speed must be greater than 0")
        self.path = str(path)
        try:
            self.recording = read_recording(self.path)  # fails now, with one line, if unreadable
        except FileNotFoundError:
            raise ConfigError(f"{self.path}: no such recording") from None
        self.speed, self.loop = speed, loop
        self.loops = 0
        self._scan: dict | None = None

    def describe(self) -> str:
        return f"replay of {self.path}"

    def rig(self) -> Rig | None:
        return rig_from_meta(self.recording.meta)

    def info(self) -> dict:
        """The recording's scan: records, duration_s, sources, ignored_bytes."""
        if self._scan is None:
            self._scan = self.recording.scan()
        return self._scan

    @property
    def duration(self) -> float | None:
        return None if self.loop else self.info()["duration_s"]

    @property
    def start_time(self) -> float:
        start = self.info()["start"]
        return 0.0 if start is None else start

    def items(self) -> Iterator[tuple[float, tuple[str, int], bytes]]:
        """Every record at its recorded arrival time (the recorder's clock, seconds)."""
        for rec in self.recording:
            yield rec.arrival, rec.source, rec.data
        if self.recording.ignored_bytes:
            log.warning("%s: %d byte(s) after the last whole record ignored (a cut recording)",
                        self.path, self.recording.ignored_bytes)

    def _run(self, target: tuple[str, int], stop: threading.Event) -> None:
        socks: dict[tuple[str, int], socket.socket] = {}
        try:
            self._play(target, stop, socks)
        finally:
            for sock in socks.values():
                sock.close()

    def _play(self, target: tuple[str, int], stop: threading.Event,
              socks: dict[tuple[str, int], socket.socket]) -> None:
        fast = not math.isfinite(self.speed)
        # timetags advance at the recording's pace (x1) when playing faster, and slow down
        # with the playback when playing slower, so they never run behind the arrivals
        pace = min(self.speed, 1.0)
        clocks = self._source_clocks()
        mono0, wall0 = time.monotonic(), time.time()
        offset = 0.0  # recording seconds already played by earlier loops
        while not stop.is_set():
            first = None
            last = 0.0
            for rec in self.recording:
                if first is None:
                    first = rec.arrival
                last = rec.arrival - first
                at = offset + last
                if not fast:
                    delay = mono0 + at / self.speed - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        return
                if stop.is_set():
                    return
                captured = _capture_of(rec, clocks)
                self._send(rec, wall0 + (offset + captured - first) / pace, target, socks)
            if first is None:
                log.warning("%s holds no records", self.path)
                return
            if not self.loop:
                return
            self.loops += 1
            offset += last + 1.0 / 30.0  # the next pass starts one frame after the last record

    def _source_clocks(self) -> dict[tuple[str, int], list[float]]:
        """Per sender, its clock's offset onto the recording's clock: the minimum of
        ``arrival - timetag`` per 10 s block (network delay only ever adds to it)."""
        blocks: dict[tuple[str, int], dict[int, float]] = {}
        start = None
        for rec in self.recording:
            start = rec.arrival if start is None else start
            tag = _bundle_tag(rec.data)
            if tag is None:
                continue
            k = int((rec.arrival - start) // _BLOCK_S)
            per = blocks.setdefault(rec.source, {})
            d = rec.arrival - tag
            if d < per.get(k, math.inf):
                per[k] = d
        out: dict[tuple[str, int], list[float]] = {}
        for source, per in blocks.items():
            n = max(per) + 1
            values = [per.get(k, math.inf) for k in range(n)]
            best = [min(values[max(k - 1, 0):k + 2]) for k in range(n)]
            filled, last = [], next(v for v in best if math.isfinite(v))
            for v in best:  # blocks with no bundle take their neighbour's
                last = v if math.isfinite(v) else last
                filled.append(last)
            out[source] = [start or 0.0] + filled
        return out

    def _send(self, rec: Record, captured: float, target: tuple[str, int],
              socks: dict[tuple[str, int], socket.socket]) -> None:
        data = _stamped(rec.data, captured)
        self.sent += 1
        sock = socks.get(rec.source)
        if sock is None:
            sock = socks[rec.source] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.sendto(data, target)
        except OSError:
            pass  # the server went away; keep the rhythm, it may come back


_BLOCK_S = 10.0


def _bundle_tag(data: bytes) -> float | None:
    """The outer timetag of a bundle (Unix s), or None (not a bundle, or "immediately")."""
    if not data.startswith(b"#bundle\0") or len(data) < 16:
        return None
    (stamp,) = struct.unpack_from(">Q", data, 8)
    return None if stamp == 1 else ntp.ntp_to_system_time(data[8:16])


def _capture_of(rec: Record, clocks: dict[tuple[str, int], list[float]]) -> float:
    """A record's capture time on the recording's clock (see the module docstring)."""
    if rec.capture is not None and math.isfinite(rec.capture):
        return rec.capture
    tag = _bundle_tag(rec.data)
    clock = clocks.get(rec.source)
    if tag is None or clock is None:
        return rec.arrival
    k = int((rec.arrival - clock[0]) // _BLOCK_S)
    offset = clock[1 + min(max(k, 0), len(clock) - 2)]
    return min(tag + offset, rec.arrival)


def _stamped(data: bytes, t: float) -> bytes:
    """``data`` in a bundle timetagged ``t`` (Unix s): a bundle's timetags all move by the
    same amount (nested ones keep their spacing); a message is wrapped; other bytes (not
    OSC) go out unchanged, for the server to count."""
    if data.startswith(b"#bundle\0") and len(data) >= 16:
        tag = _bundle_tag(data)
        if tag is None:  # "immediately": give it the capture time
            return data[:8] + ntp.system_time_to_ntp(t) + data[16:]
        return _retimed(data, lambda old: old + (t - tag))
    if data.startswith(b"/") and len(data) % 4 == 0:
        return encode_bundle([data], t)
    return data


__all__ = ["rig_from_meta", "ReplaySource"]
