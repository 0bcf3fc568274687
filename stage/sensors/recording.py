"""Recordings: every sensor datagram with its times, append-only and crash-safe.

The streamer's raw writer and reader (seed 002: developing on recorded data
instead of restarting the sensors) for stage. A recording holds the raw OSC
datagrams exactly as they arrived, so replaying one runs the very same
decode and fusion path as the live show.

File layout (all integers big-endian)::

    magic     8 bytes  b"STAGEREC"
    version   u16      1
    hlen      u32      length of the header text
    header    hlen     UTF-8 JSON: {"format", "version", "created", "clock",
                       "record_layout", "meta": {...}}
    hcrc      u32      CRC-32 of the header text
    records, each:
      marker  2 bytes  b"\\xa5R"  (lets a reader find the next record after damage)
      length  u32      bytes from ``arrival`` to the end of ``data``
      arrival f64      seconds, engine clock of the recording run
      capture f64      seconds, same clock; NaN when unknown
      port    u16      sender's UDP port
      hostlen u8
      host    hostlen  sender's address (UTF-8)
      data    rest     the datagram, byte for byte
      crc     u32      CRC-32 of ``length`` through ``data``

Records are appended in arrival order and the file is flushed to the OS at
least every ``flush_s`` seconds (default 0.5), by the writer on each write
and by a small timer thread when writes stop, so killing the process loses
at most that much. A file cut anywhere reads up to its last whole record;
``Recording.ignored_bytes`` says how much was left over, and a damaged
record in the middle is skipped up to the next record that checks out.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import errno
import math
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator

from ..errors import ConfigError, RecordingError

log = logging.getLogger("stage.recording")

MAGIC = b"STAGEREC"
VERSION = 1
MARKER = b"\xa5R"
#: after the marker: length u32, arrival f64, capture f64, port u16, hostlen u8
_FIXED = struct.Struct(">IddHB")
_HEAD = struct.Struct(">8sHI")
_CRC = struct.Struct(">I")
_MAX_RECORD = 1 << 20  # a UDP datagram is at most 64 KiB; anything larger is damage
RECORD_LAYOUT = ("marker 2s=a5 52, length u32, arrival f64, capture f64 (NaN unknown), "
                 "port u16, hostlen u8, host utf-8, data, crc32 u32 of length..data; big-endian")


@dataclass(frozen=True, slots=True)
class Record:
    """One datagram as it arrived."""

    arrival: float              # seconds, engine clock of the recording run
    source: tuple[str, int]     # sender (host, port)
    data: bytes                 # the raw OSC datagram
    capture: float | None       # capture time on the same clock, when known


class RecordingWriter:
    """Appends records to a new recording file; usable as a context manager.

    ``meta`` is stored in the header (JSON-serialisable: e.g. the rig, the
    scenario and seed of a simulator run). Safe to call from several threads.
    """

    def __init__(self, path: str | os.PathLike, meta: dict | None = None, *,
                 flush_s: float = 0.5, clock: Callable[[], float] = time.monotonic,
                 background: bool = True) -> None:
        self.path = str(path)
        self.flush_s = flush_s
        self._clock = clock
        self._lock = threading.Lock()
        self.records = 0
        header = {
            "format": "stage-recording", "version": VERSION,
            "created": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
            "clock": "arrival and capture in seconds on the engine clock of the recording run",
            "record_layout": RECORD_LAYOUT,
            "meta": meta or {},
        }
        try:
            text = json.dumps(header, sort_keys=True, allow_nan=False).encode()
        except (TypeError, ValueError) as exc:
            raise RecordingError(f"recording meta is not plain JSON data: {exc}") from None
        try:
            self._file: BinaryIO = open(self.path, "wb")
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create recording: {exc.strerror}") from None
        self._file.write(_HEAD.pack(MAGIC, VERSION, len(text)) + text
                         + _CRC.pack(zlib.crc32(text)))
        self._file.flush()
        self._dirty = False
        self._last_flush = clock()
        self._closed = False
        self._stop = threading.Event()
        self._timer: threading.Thread | None = None
        if background:
            # flushes when writes stop coming: the last second of a show must reach
            # the disk even if nothing else arrives before the process is killed
            self._timer = threading.Thread(target=self._flush_loop, name="stage-recording-flush",
                                           daemon=True)
            self._timer.start()

    def write(self, arrival: float, source: tuple[str, int], data: bytes,
              capture: float | None = None) -> None:
        """Append one datagram. ``arrival``/``capture`` in seconds (engine clock)."""
        host = str(source[0]).encode()[:255]
        body = _FIXED.pack(0, float(arrival), math.nan if capture is None else float(capture),
                           int(source[1]) & 0xFFFF, len(host)) + host + bytes(data)
        length = len(body) - 4
        if length > _MAX_RECORD:
            raise RecordingError(f"datagram of {len(data)} bytes is too large to record")
        body = struct.pack(">I", length) + body[4:]
        record = MARKER + body + _CRC.pack(zlib.crc32(body))
        with self._lock:
            if self._closed:
                raise RecordingError(f"{self.path}: recording is closed")
            self._file.write(record)
            self.records += 1
            self._dirty = True
            now = self._clock()
            if now - self._last_flush >= self.flush_s:
                self._flush_locked(now)

    def flush(self) -> None:
        """Hand everything written so far to the operating system."""
        with self._lock:
            if not self._closed:
                self._flush_locked(self._clock())

    def _flush_locked(self, now: float) -> None:
        self._file.flush()
        self._dirty = False
        self._last_flush = now

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_s / 2):
            with self._lock:
                if self._closed:
                    return
                if self._dirty:
                    try:
                        self._flush_locked(self._clock())
                    except OSError as exc:  # disk full: say so, keep the show running
                        log.error("recording %s: flush failed: %s", self.path, exc)

    def close(self) -> None:
        """Flush, sync to disk and close (idempotent)."""
        self._stop.set()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._file.flush()
                _fsync(self._file.fileno())
            finally:
                self._file.close()
        if self._timer is not None and self._timer is not threading.current_thread():
            self._timer.join(timeout=1.0)

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Recording:
    """A recording on disk: ``meta`` from its header; iterate for ``Record`` objects.

    Each iteration reads the file afresh (streaming, so hours of recording
    need little memory). After a full iteration, ``ignored_bytes`` is the
    number of bytes that were not part of a whole, intact record (a tail cut
    by a crash, or damaged records skipped) and ``damaged`` counts the
    damaged stretches that were skipped in the middle.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = str(path)
        self.ignored_bytes = 0
        self.damaged = 0
        try:
            with open(self.path, "rb") as f:
                head = f.read(_HEAD.size)
                if len(head) < _HEAD.size or not head.startswith(MAGIC):
                    raise RecordingError(f"{self.path}: not a stage recording (no STAGEREC header)")
                _, version, hlen = _HEAD.unpack(head)
                if version != VERSION:
                    raise RecordingError(f"{self.path}: recording format version {version} is not "
                                         f"supported (this stage reads version {VERSION})")
                text = f.read(hlen)
                crc = f.read(4)
        except FileNotFoundError:
            raise RecordingError(f"{self.path}: no such file") from None
        except IsADirectoryError:
            raise RecordingError(f"{self.path}: is a directory") from None
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read: {exc.strerror}") from None
        if len(text) < hlen or len(crc) < 4 or _CRC.unpack(crc)[0] != zlib.crc32(text):
            raise RecordingError(f"{self.path}: recording header is damaged")
        self.header: dict[str, Any] = json.loads(text)
        self.meta: dict[str, Any] = self.header.get("meta", {})
        self._start = _HEAD.size + hlen + 4

    def __iter__(self) -> Iterator[Record]:
        self.ignored_bytes = 0
        self.damaged = 0
        with open(self.path, "rb") as f:
            f.seek(self._start)
            buf = b""
            pos = 0          # position in buf
            eof = False
            in_damage = False
            while True:
                if len(buf) - pos < 64 * 1024 and not eof:
                    chunk = f.read(1 << 20)
                    eof = not chunk
                    buf = buf[pos:] + chunk
                    pos = 0
                record, used = _parse_one(buf, pos)
                if record is not None:
                    in_damage = False
                    pos += used
                    yield record
                    continue
                if used == 0 and not eof:
                    chunk = f.read(1 << 20)
                    eof = not chunk
                    buf = buf[pos:] + chunk
                    pos = 0
                    continue
                if used == 0 and not _valid_record_after(buf, pos):
                    # end of file inside a record: the tail a crash cut off
                    tail = len(buf) - pos
                    self.ignored_bytes += tail
                    if tail:
                        log.warning("%s: the last %d byte(s) are not a whole record "
                                    "(cut by a crash?); ignored", self.path, tail)
                    if self.damaged:
                        log.warning("%s: %d damaged stretch(es) skipped", self.path, self.damaged)
                    return
                # damage: skip to the next marker and try again from there
                if not in_damage:
                    self.damaged += 1
                    in_damage = True
                nxt = buf.find(MARKER, pos + 1)
                skip = (nxt if nxt >= 0 else max(len(buf) - 1, pos + 1)) - pos
                self.ignored_bytes += skip
                pos += skip
                if nxt < 0 and eof:
                    self.ignored_bytes += len(buf) - pos
                    log.warning("%s: %d damaged stretch(es) skipped, %d byte(s) ignored",
                                self.path, self.damaged, self.ignored_bytes)
                    return

    def scan(self) -> dict[str, Any]:
        """One pass over the file: records, duration, sources, ignored bytes."""
        n = 0
        first = last = None
        sources: dict[str, int] = {}
        for rec in self:
            n += 1
            first = rec.arrival if first is None else first
            last = rec.arrival
            key = f"{rec.source[0]}:{rec.source[1]}"
            sources[key] = sources.get(key, 0) + 1
        return {"records": n, "start": first, "end": last,
                "duration_s": 0.0 if first is None else last - first,
                "sources": sources, "ignored_bytes": self.ignored_bytes, "damaged": self.damaged}


def _parse_one(buf: bytes, pos: int) -> tuple[Record | None, int]:
    """(record, bytes used) at ``pos``; (None, 0) if more bytes are needed; (None, -1) if damaged."""
    if len(buf) - pos < 2 + _FIXED.size:
        return None, 0 if buf[pos:pos + 2] in (MARKER, MARKER[:1], b"") else -1
    if buf[pos:pos + 2] != MARKER:
        return None, -1
    length, arrival, capture, port, hostlen = _FIXED.unpack_from(buf, pos + 2)
    if length > _MAX_RECORD or length < _FIXED.size - 4 + hostlen:
        return None, -1
    end = pos + 2 + 4 + length
    if end + 4 > len(buf):
        return None, 0
    (crc,) = _CRC.unpack_from(buf, end)
    if crc != zlib.crc32(buf[pos + 2:end]):
        return None, -1
    start = pos + 2 + _FIXED.size
    try:
        host = buf[start:start + hostlen].decode()
    except UnicodeDecodeError:
        return None, -1
    data = buf[start + hostlen:end]
    return Record(arrival, (host, port), data, None if math.isnan(capture) else capture), \
        end + 4 - pos


def _valid_record_after(buf: bytes, pos: int) -> bool:
    """Whether an intact record starts somewhere after ``pos`` (then ``pos`` is damage, not a tail)."""
    nxt = buf.find(MARKER, pos + 1)
    while nxt >= 0:
        if _parse_one(buf, nxt)[0] is not None:
            return True
        nxt = buf.find(MARKER, nxt + 1)
    return False


def read_recording(path: str | os.PathLike) -> Recording:
    """Open a recording; raises RecordingError (one line) if it is not one."""
    return Recording(path)


def check_output_path(path: str, overwrite: bool = True) -> None:
    """Fail early, with one line, when a recording cannot be written at ``path``."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{path}: is a directory, not a file")
    if not p.parent.exists():
        raise ConfigError(f"{path}: folder {p.parent} does not exist")
    if p.exists() and not overwrite:
        raise ConfigError(f"{path}: exists; choose another name")


__all__ = ["Record", "Recording", "RecordingWriter", "read_recording", "check_output_path",
           "MAGIC", "VERSION"]


def _fsync(fd: int) -> None:
    """fsync, except where the target cannot be synced (/dev/null, a pipe): nothing to lose."""
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EROFS):
            raise
