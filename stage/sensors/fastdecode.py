"""The hot path of decoding: the two messages every sensor frame carries, read by hand.

``protocol.decode_datagram`` tries these first for every bundle element; anything they do
not recognise, or find invalid, goes to the general python-osc based path, which decodes it
or names the drop, so both paths accept exactly the same messages (tests/test_protocol.py
checks them against each other, and python-osc stays the reference).

A ``/jointCoordinates`` with all 25 joints in ``JOINTS`` order (what Kinect clients send)
is *canonical*: its names and values sit at fixed offsets. The canonical skeletons of one
datagram are checked and converted together (``canonical_joints_batch``): a dozen numpy
operations for the whole datagram instead of about fifteen per skeleton.
"""

from __future__ import annotations

import struct

import numpy as np

from ..joints import JOINTS, N_JOINTS, HandState
from .messages import MAX_COORD_M, MAX_USER_ID, HandStateMsg, JointCoordinates

_HS_ADDRESS = b"/handState\0\0"
_HS_TAGS = b",siss\0\0\0"
_HS_HANDS = {b"left": 0, b"right": 1}
_HS_STATES = {name.encode(): state for state, name in
              ((s, s.wire_name) for s in HandState)}


def _fast_hand_state(data: bytes) -> HandStateMsg | None:
    """``/handState clientID userID hand state`` with string client, hand and state.

    Two per person per sensor frame; like the joint fast path, anything else
    goes to the general decoder.
    """
    if not data.startswith(_HS_ADDRESS) or data[12:20] != _HS_TAGS:
        return None
    try:
        end = data.index(b"\0", 20)
        client = data[20:end].decode("utf-8")
        pos = 20 + ((end - 20 + 4) & ~3)
        user = _INT.unpack_from(data, pos)[0]
        pos += 4
        end = data.index(b"\0", pos)
        hand = _HS_HANDS.get(data[pos:end])
        pos += (end - pos + 4) & ~3
        end = data.index(b"\0", pos)
        state = _HS_STATES.get(data[pos:end])
        pos += (end - pos + 4) & ~3
    except (ValueError, UnicodeDecodeError, struct.error):
        return None
    if (hand is None or state is None or pos != len(data) or not client or len(client) > 64
            or not 0 <= user <= MAX_USER_ID):
        return None
    return HandStateMsg(client, user, hand, state)


_JC_ADDRESS = b"/jointCoordinates\0\0\0"
_JC_BODIES = {b"sffff" * k: k for k in range(1, N_JOINTS + 1)}
_JOINT_BY_BYTES = {name.encode(): i for i, name in enumerate(JOINTS)}
_INT = struct.Struct(">i")


def _canonical_layout() -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Where the names and the values sit when all 25 joints come in ``JOINTS`` order (what
    Kinect clients send): total length, byte offsets of the padded names, the names' bytes,
    and byte offsets of the 25 x 4 float32 values."""
    name_idx, names, value_idx = [], [], []
    pos = 0
    for name in JOINTS:
        padded = name.encode() + b"\0" * (4 - len(name) % 4)
        name_idx.extend(range(pos, pos + len(padded)))
        names.extend(padded)
        pos += len(padded)
        value_idx.extend(range(pos, pos + 16))
        pos += 16
    return (pos, np.array(name_idx), np.frombuffer(bytes(names), dtype=np.uint8),
            np.array(value_idx))


_CANON_LEN, _CANON_NAME_IDX, _CANON_NAMES, _CANON_VALUE_IDX = _canonical_layout()
_CANON_NAME_BYTES = _CANON_NAMES.tobytes()


#: the valid range of each value of a joint (x, y, z metres; confidence): NaN and inf fall
#: outside it
_LOW = np.array([-MAX_COORD_M] * 3 + [0.0])
_HIGH = np.array([MAX_COORD_M] * 3 + [1.0])


def canonical_joints_batch(tails: list[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The joints of B canonical ``/jointCoordinates`` at once: ``tails`` are their bytes from
    the first joint name on (all the same length: the canonical layout's). Returns (ok (B,) bool: the names
    are the canonical ones and every value is valid, joints (B, 25, 3) m, conf (B, 25)); a
    skeleton that is not ok goes to the general path, which decodes it or names the drop."""
    b = len(tails)
    buf = np.frombuffer(b"".join(tails), dtype=np.uint8).reshape(b, _CANON_LEN)
    # (.take, not buf[:, idx]: that one is not C-ordered for several rows, so no .view)
    values = buf.take(_CANON_VALUE_IDX, axis=1).view(">f4").reshape(b, N_JOINTS, 4)
    values = values.astype(float)
    names = buf.take(_CANON_NAME_IDX, axis=1).tobytes()
    n = len(_CANON_NAME_BYTES)
    ok = np.array([names[k * n:(k + 1) * n] == _CANON_NAME_BYTES for k in range(b)])
    inside = (values >= _LOW) & (values <= _HIGH)
    if np.count_nonzero(inside) < inside.size:    # (a reduction per row only then: rare)
        ok &= inside.all(axis=(1, 2))
    return ok, np.ascontiguousarray(values[:, :, :3]), np.ascontiguousarray(values[:, :, 3])



def _head(data: bytes) -> tuple[str, int, int, int] | None:
    """A ``/jointCoordinates``'s (client, user, number of joints, offset of the first joint
    name) when its address, type tags, client and user are the usual ones, else None."""
    if not data.startswith(_JC_ADDRESS):
        return None
    pos = len(_JC_ADDRESS)
    end = data.find(b"\0", pos)
    tags = data[pos:end]
    pos += (end - pos + 4) & ~3
    k = _JC_BODIES.get(tags[3:])
    if k is None or tags[:3] not in (b",si", b",ii"):
        return None
    try:
        if tags[1] == 0x73:  # 's'
            end = data.index(b"\0", pos)
            client = data[pos:end].decode("utf-8")
            pos += (end - pos + 4) & ~3
            if not client or len(client) > 64:
                return None
        else:
            client = str(_INT.unpack_from(data, pos)[0])
            pos += 4
        user = _INT.unpack_from(data, pos)[0]
    except (ValueError, UnicodeDecodeError, struct.error):
        return None
    pos += 4
    if not 0 <= user <= MAX_USER_ID:
        return None
    return client, user, k, pos


def canonical_head(data: bytes) -> tuple[str, int, int] | None:
    """(client, user, offset of the joints) of a ``/jointCoordinates`` that may be canonical
    (usual header, 25 joints, the canonical length); its names and values are checked by
    ``canonical_joints_batch``."""
    head = _head(data)
    if head is None or head[2] != N_JOINTS or len(data) - head[3] != _CANON_LEN:
        return None
    return head[0], head[1], head[3]


def _fast_joint_coordinates(data: bytes) -> JointCoordinates | None:
    """The hot path: a well-formed ``/jointCoordinates`` in its usual types.

    Every sensor frame of every person goes through here (over a thousand a
    second with six Kinects and six people), and the general parser spends
    most of its time per argument. This reads the common layout ``,si`` or
    ``,ii`` + ``sffff`` per joint directly and validates in numpy. Anything
    unusual or invalid returns None, and the general path decodes it and
    names the drop reason, so both paths accept exactly the same messages.
    """
    head = _head(data)
    if head is None:
        return None
    client, user, k, pos = head
    if k == N_JOINTS and len(data) - pos == _CANON_LEN:
        ok, joints, conf = canonical_joints_batch([data[pos:]])
        if ok[0]:
            return JointCoordinates(client, user, joints[0], conf[0])
        if (np.frombuffer(data, np.uint8, offset=pos)[_CANON_NAME_IDX] == _CANON_NAMES).all():
            return None        # the canonical names, an invalid value: the general path
    index = [0] * k
    blocks = []
    find = data.find
    try:
        for n in range(k):
            end = find(b"\0", pos)
            j = _JOINT_BY_BYTES.get(data[pos:end])
            if j is None:
                return None
            index[n] = j
            pos += (end - pos + 4) & ~3
            blocks.append(data[pos:pos + 16])
            pos += 16
    except (ValueError, UnicodeDecodeError, struct.error):
        return None
    if pos != len(data) or len(set(index)) != k:
        return None
    values = np.frombuffer(b"".join(blocks), dtype=">f4").reshape(k, 4).astype(float)
    if not ((values >= _LOW) & (values <= _HIGH)).all():
        return None
    joints = np.zeros((N_JOINTS, 3))
    conf = np.zeros(N_JOINTS)
    joints[index] = values[:, :3]
    conf[index] = values[:, 3]
    return JointCoordinates(client, user, joints, conf)
