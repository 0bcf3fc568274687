"""The one-pass bundle scanner (stage/sensors/scan.py) decodes what the Python walker does.

Every datagram is decoded three ways: the Python walker (the reference), the scanner run
uncompiled, and the scanner compiled (when numba is there); the messages, their values
and timetags, and the drops must be the same.
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest

from stage.engine import jit
from stage.joints import JOINTS
from stage.sensors import protocol, scan
from stage.sensors.encode import encode_bundle, encode_client_joints, encode_message
from stage.sensors.messages import HandStateMsg, JointCoordinates

hypothesis = pytest.importorskip("hypothesis", reason="pip install -e '.[test]' (hypothesis)")
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from stage.testing.fuzz import bundles, damaged, datagrams  # noqa: E402

FAST = settings(max_examples=400, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _scanners():
    out = [("uncompiled", scan.scan)]
    if jit.ready():
        out.append(("compiled", jit._compiled["scan"]))
    return out


def _decode(data: bytes, scanner) -> protocol.Decoded:
    saved = protocol._scanner
    protocol.use_scanner(scanner)
    try:
        return protocol.decode_datagram(data, "10.0.0.1:9000")
    finally:
        protocol.use_scanner(saved)


def _flat(decoded: protocol.Decoded) -> list:
    """Everything a decode gave, arrays as bytes (NaN-safe, bit for bit); the drops as a
    multiset (the walker lists a canonical skeleton's drop after the other elements', the
    scanner in element order; each is counted the same)."""
    out: list = [tuple(sorted(decoded.drops))]
    for msg, timetag in decoded.messages:
        fields = []
        for f in dataclasses.fields(msg):
            v = getattr(msg, f.name)
            fields.append((v.dtype.str, v.shape, v.tobytes()) if isinstance(v, np.ndarray)
                          else (type(v).__name__, v))
        out.append((type(msg).__name__, timetag, tuple(fields)))
    return out


def check_same(data: bytes) -> protocol.Decoded:
    reference = _decode(data, None)
    for name, scanner in _scanners():
        assert _flat(_decode(data, scanner)) == _flat(reference), name
    return reference


def _sensor_bundle(rng: np.random.Generator, people: int, client: str = "kinect-1",
                   stamp: float | None = 1_700_000_000.25) -> bytes:
    msgs = []
    for user in range(people):
        joints = rng.normal(0.0, 1.0, (25, 3))
        conf = rng.choice([1.0, 0.5, 0.0], size=25, p=[0.8, 0.15, 0.05])
        msgs += [encode_client_joints(client, user, joints, conf),
                 encode_message("/handState", client, user, "left", "open"),
                 encode_message("/handState", client, user, "right", "lasso")]
    return encode_bundle(msgs, stamp)


def test_sensor_bundles_decode_alike_and_the_scanner_reads_them():
    rng = np.random.default_rng(3)
    read = 0
    for k in range(60):
        data = _sensor_bundle(rng, k % 7, stamp=None if k % 3 else 1_700_000_000.5)
        decoded = check_same(data)
        assert not decoded.drops and len(decoded.messages) == 3 * (k % 7)
        info = np.empty((64, scan.COLUMNS), dtype=np.int64)
        joints, conf = np.empty((32, 25, 3)), np.empty((32, 25))
        count = scan.scan(np.frombuffer(data, dtype=np.uint8), info, joints, conf)
        assert count == 3 * (k % 7)
        assert (info[:count, scan.KIND] != scan.OTHER).all()   # none left to the Python path
        read += count
        if jit.ready():
            # a skeleton's arrays keep their base alive (the calibrator buffers frames):
            # the base holds this datagram's skeletons only, not the scanner's spare rows
            scanned = _decode(data, jit._compiled["scan"])
            for msg, _ in scanned.messages:
                if isinstance(msg, JointCoordinates):
                    assert msg.joints.base.shape == (k % 7, 25, 3)
                    assert msg.conf.base.shape == (k % 7, 25)
    assert read > 300


def _element(address: str, *args) -> bytes:
    return encode_message(address, *args)


def _bundle(*elements: bytes, stamp: int = 1) -> bytes:
    return b"#bundle\0" + struct.pack(">Q", stamp) + b"".join(
        struct.pack(">i", len(e)) + e for e in elements)


def _skeleton(client, user, names, values) -> bytes:
    args = [client, user]
    for name, v in zip(names, values):
        args += [name, *map(float, v)]
    return _element("/jointCoordinates", *args)


EDGE_CASES = {
    "int client": _bundle(_skeleton(7, 1, JOINTS[:3], np.ones((3, 4)) * 0.5)),
    "user out of range": _bundle(_skeleton("k", 9, JOINTS[:2], np.ones((2, 4)) * 0.5)),
    "negative user": _bundle(_skeleton("k", -1, JOINTS[:2], np.ones((2, 4)) * 0.5)),
    "joint twice": _bundle(_skeleton("k", 1, [JOINTS[0], JOINTS[0]], np.ones((2, 4)) * 0.5)),
    "unknown joint": _bundle(_skeleton("k", 1, ["Nose"], np.ones((1, 4)) * 0.5)),
    "far joint": _bundle(_skeleton("k", 1, JOINTS[:1], [[25.0, 0, 0, 1]])),
    "conf above 1": _bundle(_skeleton("k", 1, JOINTS[:1], [[0, 0, 0, 1.5]])),
    "NaN joint": _bundle(_skeleton("k", 1, JOINTS[:1], [[np.nan, 0, 0, 1]])),
    "reversed order": _bundle(_skeleton("k", 2, JOINTS[::-1], np.full((25, 4), 0.25))),
    "empty client": _bundle(_skeleton("", 1, JOINTS[:1], [[0, 0, 0, 1]])),
    "64-byte client": _bundle(_skeleton("x" * 64, 1, JOINTS[:1], [[0, 0, 0, 1]])),
    "65-byte client": _bundle(_skeleton("x" * 65, 1, JOINTS[:1], [[0, 0, 0, 1]])),
    "64 characters, more bytes": _bundle(_skeleton("é" * 64, 1, JOINTS[:1], [[0, 0, 0, 1]]),
                                         _element("/handState", "é" * 64, 1, "left", "open")),
    "invalid utf-8 client": _bundle(
        _element("/handState", "ab", 1, "left", "open").replace(b"ab", b"\xff\xfe")),
    "hand state typo": _bundle(_element("/handState", "k", 1, "left", "opened")),
    "hand typo": _bundle(_element("/handState", "k", 1, "middle", "open")),
    "hand state int user as float": _bundle(_element("/handState", "k", 1.0, "left", "open")),
    "other addresses": _bundle(_element("/newUser", "k", 1, 0.0, 1.0, 2.0),
                               _element("/registerDevice", "k", "kinect2"),
                               _element("/stage/stats", 9001), _element("/nope", 1)),
    "nested": _bundle(_bundle(_element("/handState", "k", 1, "left", "open")),
                      _element("/handState", "k", 2, "right", "closed")),
    "size lies": _bundle(_element("/handState", "k", 1, "left", "open"))[:-4],
    "not an element": b"#bundle\0" + struct.pack(">Q", 1) + struct.pack(">i", 4) + b"abcd",
    "header only": b"#bundle\0" + struct.pack(">Q", 5),
    "short": b"#bundle\0\0\0",
    "trailing bytes": _bundle(_element("/handState", "k", 1, "left", "open")) + b"\0\0",
    "hand state with bytes after it": _bundle(
        _element("/handState", "k", 1, "left", "open") + b"\0" * 4),
    "skeleton with bytes after it": _bundle(
        _skeleton("k", 1, JOINTS[:2], np.ones((2, 4)) * 0.5) + b"\0" * 4),
    "130 elements (more than the scanner's rows)": _bundle(
        *[_element("/handState", "k", k % 6, "left", "open") for k in range(130)]),
    "65 skeletons (more than the scanner's rows)": _bundle(
        *[_skeleton("k", k % 6, JOINTS, np.full((25, 4), 0.5)) for k in range(65)]),
    "general parse error": _bundle(b"/handState\0\0,six\0\0\0\0"),
}


@pytest.mark.parametrize("case", sorted(EDGE_CASES))
def test_edge_cases_decode_alike(case):
    check_same(EDGE_CASES[case])


def test_a_bytearray_decodes_as_its_bytes():
    """A bytearray decodes to what its bytes give (the compiled scanner takes a read-only
    buffer, and client names are looked up by their bytes: without care every such
    datagram would be 'malformed')."""
    rng = np.random.default_rng(9)
    data = _sensor_bundle(rng, 2)
    for name, scanner in _scanners():
        got = _decode(bytearray(data), scanner)
        assert _flat(got) == _flat(_decode(data, None)), name
        assert len(got.messages) == 6 and not got.drops


def test_a_datagrams_messages_keep_their_values_after_the_next_datagram():
    """The scanner writes into arrays each thread keeps from datagram to datagram; the
    messages of one datagram must hold copies, so that decoding the next (here in the same
    thread, and in another) leaves them as they were, and a message's arrays keep alive
    only its own datagram's skeletons (the calibrator buffers seconds of frames)."""
    import threading

    rng = np.random.default_rng(11)
    first, second = _sensor_bundle(rng, 3), _sensor_bundle(rng, 5)
    for name, scanner in _scanners():
        got = _decode(first, scanner)
        kept = _flat(got)
        _decode(second, scanner)
        thread = threading.Thread(target=_decode, args=(second, scanner))
        thread.start()
        thread.join()
        assert _flat(got) == kept, name
        skeletons = [m for m, _ in got.messages if isinstance(m, JointCoordinates)]
        assert len(skeletons) == 3
        for m in skeletons:
            assert m.joints.base is not None and m.joints.base.shape == (3, 25, 3), name
            assert m.conf.base.shape == (3, 25), name


def test_edge_cases_give_what_the_api_says():
    """A few of them spelled out (the reference could be wrong too)."""
    ok = check_same(EDGE_CASES["int client"]).messages
    assert isinstance(ok[0][0], JointCoordinates) and ok[0][0].client == "7"
    assert check_same(EDGE_CASES["user out of range"]).drops[0][1] == "bad_user_id"
    accents = check_same(EDGE_CASES["64 characters, more bytes"]).messages
    assert [type(m) for m, _ in accents] == [JointCoordinates, HandStateMsg]
    assert check_same(EDGE_CASES["size lies"]).drops == [("10.0.0.1:9000", "malformed")]
    assert len(check_same(EDGE_CASES["nested"]).messages) == 2
    for case, n in (("130 elements (more than the scanner's rows)", 130),
                    ("65 skeletons (more than the scanner's rows)", 65)):
        assert len(check_same(EDGE_CASES[case]).messages) == n       # by the Python walker
        data = np.frombuffer(EDGE_CASES[case], dtype=np.uint8)
        rows = len(data) // scan.SMALLEST_SKELETON + 1
        assert scan.scan(data, np.empty((min(len(data) // 8, 128), scan.COLUMNS), np.int64),
                         np.empty((min(rows, 64), 25, 3)),
                         np.empty((min(rows, 64), 25))) == scan.USE_WALKER


@FAST
@given(datagrams())
def test_fuzzed_datagrams_decode_alike(data):
    check_same(data)


@FAST
@given(st.data())
def test_damaged_sensor_bundles_decode_alike(data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 16)))
    clean = _sensor_bundle(rng, data.draw(st.integers(1, 4)))
    check_same(data.draw(damaged(clean)))


@FAST
@given(bundles())
def test_fuzzed_bundles_decode_alike(data):
    check_same(data)


def test_compiled_scanner_reads_nothing_outside_the_datagram(tmp_path):
    """numba does not check array bounds by default: a scanner that read past a damaged
    datagram would read the process's memory. Compiled with NUMBA_BOUNDSCHECK=1 (in a
    fresh process and cache), 3000 damaged sensor bundles -- cut, bytes flipped, sizes
    lying, joints' names and tags broken, the last element cut short with a size that
    fits it -- must scan without an IndexError."""
    import os
    import subprocess
    import sys

    if not jit.ready():
        pytest.skip(f"no compiled kernels: {jit.why_not()}")
    script = r'''
import numpy as np
from stage.engine import jit
from stage.sensors import protocol, scan
from stage.sensors.encode import encode_bundle, encode_client_joints, encode_message
assert jit.warm(), jit.why_not()
scanner = jit._compiled["scan"]
rng = np.random.default_rng(5)
scanned = 0
for k in range(3000):
    msgs = []
    for user in range(int(rng.integers(1, 4))):
        joints = rng.normal(0.0, 1.0, (25, 3))
        conf = rng.choice([1.0, 0.5, 0.0], size=25)
        msgs += [encode_client_joints("k", user, joints, conf),
                 encode_message("/handState", "k", user, "left", "open")]
    data = bytearray(encode_bundle(msgs, None))
    kind = k % 5
    if kind == 4:                         # the last element cut short, its size made to fit
        last = int(rng.integers(0, len(msgs)))
        cut = msgs[last][:4 * int(rng.integers(1, len(msgs[last]) // 4 + 1))]
        data = bytearray(encode_bundle(msgs[:last], None) + len(cut).to_bytes(4, "big") + cut)
    elif kind == 0:
        data = data[:int(rng.integers(0, len(data)))]
    elif kind == 1:
        for _ in range(int(rng.integers(1, 8))):
            data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
    elif kind == 2:                       # a size field that lies
        data[16:20] = int(rng.integers(-8, len(data) + 64)).to_bytes(4, "big", signed=True)
    else:                                 # zero bytes where names and tags end
        for _ in range(int(rng.integers(1, 20))):
            data[int(rng.integers(16, len(data)))] = 0
    data = bytes(data)
    n = len(data)
    info = np.empty((max(n // 8, 1), scan.COLUMNS), dtype=np.int64)
    rows = n // scan.SMALLEST_SKELETON + 1
    scanner(np.frombuffer(data, dtype=np.uint8), info, np.empty((rows, 25, 3)),
            np.empty((rows, 25)))
    protocol.decode_datagram(data)
    scanned += 1
print("scanned", scanned)
'''
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "scanned 3000" in out.stdout
