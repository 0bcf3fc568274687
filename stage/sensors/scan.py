"""A sensor bundle's skeletons and hand states read in one pass, for compiling (numba).

Every sensor datagram is a bundle of ``/jointCoordinates`` and ``/handState`` messages,
one of each per person and hand. Decoding them element by element in Python costs
about 25 us a message on the machines we measure on (a sixth of the engine's CPU at six
sensors and six people, docs/reports/issue-10.md, stop 26). ``scan`` walks the whole
bundle in one call: it checks every element's size as ``protocol._walk_bundle`` does,
and reads each skeleton and hand state that ``fastdecode``'s fast paths would accept,
to the same values. Everything else -- other addresses, unusual types, any doubt -- is
marked for ``protocol._decode_element``, which decodes it as it always has (the fast
paths, then python-osc), so the result is exactly what the Python walker gives
(tests/test_protocol.py compares both on every kind of datagram and on fuzzed ones).

This module is plain Python and imports no compiler: the engine compiles ``scan`` with
its other kernels (``stage.engine.jit``) and hands it to ``protocol.use_scanner``. Run
uncompiled it gives the same result, slowly (the tests run it both ways).
"""

from __future__ import annotations

import numpy as np

from ..joints import HAND_STATE_NAMES, JOINTS, N_JOINTS
from .messages import MAX_COORD_M, MAX_USER_ID

#: what ``scan`` found in an element (``info[:, KIND]``)
OTHER, SKELETON, HAND = 0, 1, 2
#: the columns of ``info``: kind, the element's first and end byte, the client's first and
#: end byte (-1, -1: an integer client, in CLIENT_INT), user, hand, state code, skeleton row
KIND, START, END, CLIENT_START, CLIENT_END, CLIENT_INT, USER, HAND_, STATE, ROW = range(10)
COLUMNS = 10
#: ``scan``'s status besides an element count: the datagram is malformed (one drop), or it
#: holds a nested bundle or more elements than the arrays have room for (the Python walker)
MALFORMED, USE_WALKER = -1, -2


def _table(names: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Names concatenated (uint8) and where each ends (int64)."""
    ends = np.cumsum([len(n) for n in names]).astype(np.int64)
    return np.frombuffer(b"".join(names), dtype=np.uint8).copy(), ends


#: joint names (unpadded), hand names (left, right), hand state names by code
JOINT_NAMES, JOINT_ENDS = _table([name.encode() for name in JOINTS])
HAND_NAMES, HAND_ENDS = _table([b"left", b"right"])
STATE_NAMES, STATE_ENDS = _table([HAND_STATE_NAMES[code].encode()
                                  for code in sorted(HAND_STATE_NAMES)])
#: the smallest possible skeleton element, for sizing the skeleton rows
SMALLEST_SKELETON = 60
_JC = np.frombuffer(b"/jointCoordinates\0\0\0", dtype=np.uint8).copy()
_HS = np.frombuffer(b"/handState\0\0,siss\0\0\0", dtype=np.uint8).copy()
_BUNDLE = np.frombuffer(b"#bundle\0", dtype=np.uint8).copy()


def _starts(data, at, end, prefix):  # pragma: no cover (compiled; tested uncompiled too)
    """Whether data[at:end] starts with ``prefix``."""
    if end - at < prefix.shape[0]:
        return False
    for k in range(prefix.shape[0]):
        if data[at + k] != prefix[k]:
            return False
    return True


def _nul(data, at, end):  # pragma: no cover
    """The first zero byte in data[at:end], or -1."""
    for k in range(at, end):
        if data[k] == 0:
            return k
    return -1


def _find(data, at, stop, names, ends, first):  # pragma: no cover
    """Which of ``names`` data[at:stop] is exactly (trying ``first`` before the others), or -1."""
    n = ends.shape[0]
    for m in range(n):
        k = (first + m) % n
        begin = ends[k - 1] if k else 0
        if ends[k] - begin != stop - at:
            continue
        same = True
        for b in range(stop - at):
            if data[at + b] != names[begin + b]:
                same = False
                break
        if same:
            return k
    return -1


def _int(data, at):  # pragma: no cover
    """The big-endian int32 at ``at``."""
    v = (np.int64(data[at]) << 24) | (np.int64(data[at + 1]) << 16) | \
        (np.int64(data[at + 2]) << 8) | np.int64(data[at + 3])
    return v - (np.int64(1) << 32) if v >= (np.int64(1) << 31) else v


def _client(data, at, end, row):  # pragma: no cover
    """A string client at ``at`` (zero-terminated, padded): its bytes into ``row``; the offset
    after it, or -1 when ``fastdecode`` would not take it (no end, empty, over 64 bytes:
    a longer one may still be 64 characters, which the Python path decides)."""
    stop = _nul(data, at, end)
    if stop < 0 or stop == at or stop - at > 64:
        return -1
    row[CLIENT_START], row[CLIENT_END], row[CLIENT_INT] = at, stop, 0
    return at + ((stop - at + 4) & ~3)


def _skeleton(data, at, end, row, joints, conf, value, bits):  # pragma: no cover
    """``fastdecode._fast_joint_coordinates`` of data[at:end], into ``row`` and
    joints/conf; False where it would not take the element."""
    pos = at + 20
    stop = _nul(data, pos, end)
    if stop < 0 or stop - pos < 3 or data[pos] != 44 or data[pos + 2] != 105:   # ',' 'i'
        return False
    stringy = data[pos + 1] == 115                                               # 's'
    if not stringy and data[pos + 1] != 105:
        return False
    body = stop - pos - 3
    if body <= 0 or body % 5 or body // 5 > N_JOINTS:
        return False
    k = body // 5
    for m in range(k):
        b = pos + 3 + 5 * m
        if data[b] != 115 or data[b + 1] != 102 or data[b + 2] != 102 or \
                data[b + 3] != 102 or data[b + 4] != 102:
            return False
    pos += (stop - pos + 4) & ~3
    if stringy:
        pos = _client(data, pos, end, row)
        if pos < 0:
            return False
    else:
        if pos + 4 > end:
            return False
        row[CLIENT_START], row[CLIENT_END], row[CLIENT_INT] = -1, -1, _int(data, pos)
        pos += 4
    if pos + 4 > end:
        return False
    user = _int(data, pos)
    pos += 4
    if user < 0 or user > MAX_USER_ID:
        return False
    r = row[ROW]
    for j in range(N_JOINTS):
        conf[r, j] = 0.0
        for a in range(3):
            joints[r, j, a] = 0.0
    seen = np.zeros(N_JOINTS, dtype=np.bool_)
    for m in range(k):
        stop = _nul(data, pos, end)
        if stop < 0:
            return False
        j = _find(data, pos, stop, JOINT_NAMES, JOINT_ENDS, m)
        if j < 0 or seen[j]:
            return False
        seen[j] = True
        pos += (stop - pos + 4) & ~3
        if pos + 16 > end:
            return False
        for a in range(4):
            b = pos + 4 * a
            bits[a] = (np.uint32(data[b]) << np.uint32(24)) | \
                (np.uint32(data[b + 1]) << np.uint32(16)) | \
                (np.uint32(data[b + 2]) << np.uint32(8)) | np.uint32(data[b + 3])
        for a in range(3):
            v = np.float64(value[a])
            if not (v >= -MAX_COORD_M and v <= MAX_COORD_M):      # NaN fails too
                return False
            joints[r, j, a] = v
        c = np.float64(value[3])
        if not (c >= 0.0 and c <= 1.0):
            return False
        conf[r, j] = c
        pos += 16
    if pos != end:
        return False
    row[USER] = user
    return True


def _hand(data, at, end, row):  # pragma: no cover
    """``fastdecode._fast_hand_state`` of data[at:end] (``/handState ,siss``), into ``row``;
    False where it would not take the element."""
    pos = _client(data, at + 20, end, row)
    if pos < 0 or pos + 4 > end:
        return False
    user = _int(data, pos)
    pos += 4
    stop = _nul(data, pos, end)
    if stop < 0:
        return False
    hand = _find(data, pos, stop, HAND_NAMES, HAND_ENDS, 0)
    pos += (stop - pos + 4) & ~3
    stop = _nul(data, pos, end)
    if stop < 0 or hand < 0:
        return False
    state = _find(data, pos, stop, STATE_NAMES, STATE_ENDS, 2)
    pos += (stop - pos + 4) & ~3
    if state < 0 or pos != end or user < 0 or user > MAX_USER_ID:
        return False
    row[USER], row[HAND_], row[STATE] = user, hand, state
    return True


def scan(data, info, joints, conf):  # pragma: no cover (compiled; tested uncompiled too)
    """Walk the bundle ``data`` (uint8): per element a row of ``info`` (see ``COLUMNS``); the
    skeletons' joints and confidences in ``joints`` (S, 25, 3) and ``conf`` (S, 25), zeros
    where a joint was not sent. Returns the number of elements, ``MALFORMED`` (an element's
    size does not fit: the whole datagram is one drop, as with the Python walker) or
    ``USE_WALKER`` (a nested bundle, or more elements or skeletons than the arrays hold)."""
    n = data.shape[0]
    if n < 16 or not _starts(data, 0, n, _BUNDLE):
        return MALFORMED
    value = np.empty(4, dtype=np.float32)
    bits = value.view(np.uint32)
    index = 16
    count = 0
    rows = 0
    while index < n:
        if index + 4 > n:
            return MALFORMED
        size = _int(data, index)
        index += 4
        if size <= 0 or size % 4 or index + size > n:
            return MALFORMED
        start, end = index, index + size
        index = end
        if data[start] == 35 and _starts(data, start, end, _BUNDLE):            # '#'
            return USE_WALKER
        if data[start] != 47:                                                  # '/'
            return MALFORMED
        if count == info.shape[0]:
            return USE_WALKER
        row = info[count]
        count += 1
        row[KIND], row[START], row[END] = OTHER, start, end
        if _starts(data, start, end, _JC):
            if rows == joints.shape[0]:
                return USE_WALKER
            row[ROW] = rows
            if _skeleton(data, start, end, row, joints, conf, value, bits):
                row[KIND] = SKELETON
                rows += 1
        elif _starts(data, start, end, _HS):
            if _hand(data, start, end, row):
                row[KIND] = HAND
    return count
