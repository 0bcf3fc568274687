"""A Standard MIDI File written as the show goes, valid on disk after every flush.

Format 0 (one track; outputs differ by channel), 960 ticks per beat at a
fixed 120 bpm: 1920 ticks per second, about 0.5 ms per tick, so the file
keeps the real timing of every event. Events are appended; each ``flush``
writes the end-of-track event and patches the track length, then the next
event overwrites that end-of-track. A crash loses at most what came after the
last flush (the view flushes every second).

``mido`` reads these files back (tests do); it cannot append, hence this writer.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import BinaryIO

TICKS_PER_BEAT = 960
TEMPO_US = 500_000                      # microseconds per beat: 120 bpm
TICKS_PER_S = TICKS_PER_BEAT * 1_000_000 / TEMPO_US
_END_OF_TRACK = b"\x00\xff\x2f\x00"


def varlen(value: int) -> bytes:
    """A MIDI variable-length quantity (7 bits per byte, high bit = more follows)."""
    out = [value & 0x7F]
    value >>= 7
    while value:
        out.append(0x80 | (value & 0x7F))
        value >>= 7
    return bytes(reversed(out))


class SmfWriter:
    """Appends timed MIDI messages to ``path``; ``t0`` (engine clock) is tick 0."""

    def __init__(self, path: str | os.PathLike, t0: float, name: str = "stage") -> None:
        self.path = Path(path)
        self.t0 = t0
        self._f: BinaryIO = open(self.path, "wb")
        self._f.write(b"MThd" + struct.pack(">IHHH", 6, 0, 1, TICKS_PER_BEAT))
        self._f.write(b"MTrk\0\0\0\0")
        self._track_start = self._f.tell()
        title = name.encode("utf-8")[:127]
        self._f.write(b"\x00\xff\x03" + varlen(len(title)) + title)        # track name
        self._f.write(b"\x00\xff\x51\x03" + TEMPO_US.to_bytes(3, "big"))   # tempo
        self._end = self._f.tell()       # where the next event goes (before end-of-track)
        self._tick = 0
        self.events = 0
        self._dirty = True
        self.flush()

    def write(self, t: float, data: bytes) -> None:
        """One channel or system message at engine time ``t`` (clamped to never go back)."""
        tick = max(self._tick, round((t - self.t0) * TICKS_PER_S))
        self._f.seek(self._end)
        self._f.write(varlen(tick - self._tick) + bytes(data))
        self._end = self._f.tell()
        self._tick = tick
        self.events += 1
        self._dirty = True

    def flush(self) -> None:
        """Make the file on disk a complete, valid SMF."""
        if not self._dirty or self._f.closed:
            return
        self._f.seek(self._end)
        self._f.write(_END_OF_TRACK)
        self._f.truncate()
        length = self._f.tell() - self._track_start
        self._f.seek(self._track_start - 4)
        self._f.write(struct.pack(">I", length))
        self._f.flush()
        self._dirty = False

    def close(self) -> None:
        if not self._f.closed:
            self.flush()
            self._f.close()

    @property
    def seconds(self) -> float:
        return self._tick / TICKS_PER_S
