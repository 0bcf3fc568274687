"""The recording format: round trip, crash tails, damage, flushing."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from stage.errors import RecordingError
from stage.sensors.recording import MAGIC, Record, RecordingWriter, read_recording


def _records(n: int, seed: int = 3) -> list[Record]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        data = rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes()
        capture = None if i % 3 == 0 else i * 0.033 - 0.07
        out.append(Record(i * 0.033, (f"10.0.0.{i % 4}", 40000 + i % 7), data, capture))
    return out


def _write(path, records, meta=None) -> list[int]:
    """Write records; return the file size after each one (the record boundaries)."""
    ends = []
    with RecordingWriter(path, meta, background=False) as w:
        for r in records:
            w.write(r.arrival, r.source, r.data, r.capture)
            w.flush()
            ends.append(os.path.getsize(path))
    return ends


def test_round_trip_keeps_every_field_and_the_meta(tmp_path):
    path = tmp_path / "a.rec"
    records = _records(200)
    _write(path, records, {"scenario": "default", "seed": 4, "rig": {"sensors": {}}})
    rec = read_recording(path)
    assert rec.meta == {"scenario": "default", "seed": 4, "rig": {"sensors": {}}}
    assert rec.header["format"] == "stage-recording" and rec.header["version"] == 1
    assert list(rec) == records
    assert rec.ignored_bytes == 0 and rec.damaged == 0
    assert list(rec) == records  # iterating twice reads the file again
    summary = rec.scan()
    assert summary["records"] == 200 and summary["duration_s"] == pytest.approx(199 * 0.033)


def test_header_is_self_describing_json(tmp_path):
    path = tmp_path / "a.rec"
    _write(path, _records(1), {"who": "test"})
    raw = path.read_bytes()
    assert raw.startswith(MAGIC)
    hlen = int.from_bytes(raw[10:14], "big")
    header = json.loads(raw[14:14 + hlen])
    assert "record_layout" in header and "arrival" in header["clock"]


def test_a_file_cut_anywhere_reads_up_to_its_last_whole_record(tmp_path, caplog):
    path = tmp_path / "a.rec"
    records = _records(12)
    ends = _write(path, records)
    data = path.read_bytes()
    _write(tmp_path / "empty.rec", [])
    header_end = os.path.getsize(tmp_path / "empty.rec")
    cut_path = tmp_path / "cut.rec"
    for cut in range(header_end, len(data) + 1):
        cut_path.write_bytes(data[:cut])
        rec = read_recording(cut_path)
        got = list(rec)
        whole = sum(1 for e in ends if e <= cut)
        assert got == records[:whole], cut
        last_end = ends[whole - 1] if whole else header_end
        assert rec.ignored_bytes == cut - last_end, cut
    assert "not a whole record" in caplog.text


def test_damage_in_the_middle_loses_only_the_damaged_record(tmp_path):
    path = tmp_path / "a.rec"
    records = _records(50)
    ends = _write(path, records)
    data = bytearray(path.read_bytes())
    k = 20  # flip a byte inside record 21 (index 20)
    data[ends[k - 1] + 30] ^= 0x5A
    damaged = tmp_path / "damaged.rec"
    damaged.write_bytes(bytes(data))
    rec = read_recording(damaged)
    got = list(rec)
    assert got == records[:k] + records[k + 1:]
    assert rec.damaged == 1 and rec.ignored_bytes == ends[k] - ends[k - 1]


def test_a_corrupt_length_field_does_not_swallow_the_rest(tmp_path):
    path = tmp_path / "a.rec"
    records = _records(30)
    ends = _write(path, records)
    data = bytearray(path.read_bytes())
    data[ends[9] + 3] = 0x07  # length of record 10 now points far past the end of file
    bad = tmp_path / "bad.rec"
    bad.write_bytes(bytes(data))
    got = list(read_recording(bad))
    assert got == records[:10] + records[11:]


def test_not_a_recording_is_a_one_line_error(tmp_path):
    other = tmp_path / "notes.txt"
    other.write_text("hello\n")
    with pytest.raises(RecordingError, match="not a stage recording"):
        read_recording(other)
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "missing.rec")
    broken = tmp_path / "broken.rec"
    _write(broken, _records(2))
    raw = bytearray(broken.read_bytes())
    raw[16] ^= 1  # inside the JSON header
    broken.write_bytes(bytes(raw))
    with pytest.raises(RecordingError, match="header is damaged"):
        read_recording(broken)


def test_writer_flushes_on_write_once_flush_interval_passed(tmp_path):
    now = [0.0]
    path = tmp_path / "a.rec"
    w = RecordingWriter(path, flush_s=1.0, clock=lambda: now[0], background=False)
    header_size = os.path.getsize(path)
    w.write(0.0, ("h", 1), b"x" * 40)
    assert os.path.getsize(path) == header_size  # still in the process's buffer
    now[0] = 0.5
    w.write(0.5, ("h", 1), b"y" * 40)
    assert os.path.getsize(path) == header_size
    now[0] = 1.0
    w.write(1.0, ("h", 1), b"z" * 40)
    assert len(list(read_recording(path))) == 3  # all on disk without close()
    w.close()
    with pytest.raises(RecordingError, match="closed"):
        w.write(2.0, ("h", 1), b"late")


def test_background_timer_flushes_when_writes_stop(tmp_path):
    path = tmp_path / "a.rec"
    w = RecordingWriter(path, flush_s=0.05)
    try:
        w.write(0.0, ("h", 1), b"only one")
        deadline = time.monotonic() + 5.0
        while not list(read_recording(path)) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [r.data for r in read_recording(path)] == [b"only one"]
    finally:
        w.close()


def test_meta_must_be_json_and_path_must_be_writable(tmp_path):
    with pytest.raises(RecordingError, match="JSON"):
        RecordingWriter(tmp_path / "a.rec", {"bad": object()}, background=False)
    with pytest.raises(RecordingError, match="cannot create"):
        RecordingWriter(tmp_path / "no" / "such" / "a.rec", background=False)
