"""OSC encoders: the Server-to-View messages and the Client-to-Server ones (for the demo,
the simulator, the relay and tests).

Hand-rolled because the hot path sends one /jointCoordinates per person per
frame and python-osc's builder costs ~10x more; tests check python-osc
decodes these bytes to the same values.
"""

from __future__ import annotations

import functools
import struct

import numpy as np
from pythonosc.parsing import ntp

from ..joints import HANDS, JOINTS, HandState


def _pad(b: bytes) -> bytes:
    return b + b"\0" * (4 - len(b) % 4)


_NAME_BYTES = tuple(_pad(name.encode()) for name in JOINTS)
_ADDR_JOINTS = _pad(b"/jointCoordinates")


def _arg(v: object) -> tuple[bytes, bytes]:
    if isinstance(v, bool):
        raise TypeError("bool is not an OSC argument here")
    if isinstance(v, int):
        return b"i", struct.pack(">i", v)
    if isinstance(v, float):
        return b"f", struct.pack(">f", v)
    if isinstance(v, str):
        return b"s", _pad(v.encode())
    raise TypeError(f"cannot encode {type(v).__name__} as an OSC argument")


def encode_message(address: str, *args: object) -> bytes:
    """One OSC message with int (i), float (f) and str (s) arguments."""
    tags, data = [b","], []
    for a in args:
        t, d = _arg(a)
        tags.append(t)
        data.append(d)
    return _pad(address.encode()) + _pad(b"".join(tags)) + b"".join(data)


@functools.lru_cache(maxsize=256)
def _block_layout(prefix_tags: bytes, selected: bytes) -> tuple[bytes, bytes, np.ndarray, np.ndarray]:
    """The fixed part of a joint block for one set of joints: (address and type tags, the
    joint names with room for their floats, where the floats go, which joints). Cached:
    a skeleton stream uses few joint sets, and filling a template costs a fraction of
    building the message (lru_cache is thread-safe)."""
    idx = np.flatnonzero(np.frombuffer(selected, dtype=bool))
    head = _ADDR_JOINTS + _pad(b"," + prefix_tags + b"sffff" * len(idx))
    body = bytearray()
    slots = []
    for i in idx:
        body += _NAME_BYTES[i]
        slots.append(len(body))
        body += bytes(16)
    where = (np.array(slots, dtype=np.intp)[:, None] + np.arange(16)).ravel()
    where.setflags(write=False)
    idx.setflags(write=False)
    return head, bytes(body), where, idx


def _joint_block(prefix_tags: bytes, prefix: bytes, joints: np.ndarray, conf: np.ndarray,
                 mask: np.ndarray | None) -> bytes:
    selected = np.ascontiguousarray(conf > 0 if mask is None else mask, dtype=bool)
    head, template, where, idx = _block_layout(prefix_tags, selected.tobytes())
    values = np.empty((len(idx), 4), dtype=">f4")
    values[:, :3] = joints[idx]
    values[:, 3] = conf[idx]
    body = np.frombuffer(template, dtype=np.uint8).copy()
    body[where] = values.view(np.uint8).ravel()
    return head + prefix + body.tobytes()


def encode_view_joints(user: int, joints: np.ndarray, conf: np.ndarray,
                       mask: np.ndarray | None = None) -> bytes:
    """Server-to-View ``/jointCoordinates id (name x y z conf)*``.

    ``joints`` (25, 3) metres, stage space; ``conf`` (25,); joints are sent
    where ``mask`` is true (default: where conf > 0).
    """
    return _joint_block(b"i", struct.pack(">i", user), joints, conf, mask)


def encode_client_joints(client: str, user: int, joints: np.ndarray, conf: np.ndarray,
                         mask: np.ndarray | None = None) -> bytes:
    """Client-to-Server ``/jointCoordinates clientID userID (name x y z conf)*``."""
    return _joint_block(b"si", _pad(client.encode()) + struct.pack(">i", user), joints, conf,
                        mask)


def encode_view_new_user(user: int, position: np.ndarray) -> bytes:
    return encode_message("/newUser", user, *(float(v) for v in position))


def encode_view_lost_user(user: int) -> bytes:
    return encode_message("/lostUser", user)


def encode_view_hand_state(user: int, hand: int, state: HandState) -> bytes:
    return encode_message("/handState", user, HANDS[hand], state.wire_name)


def encode_bundle(messages: list[bytes], timetag: float | None = None) -> bytes:
    """An OSC bundle of encoded messages; ``timetag`` in Unix seconds, None = immediately."""
    stamp = ntp.IMMEDIATELY if timetag is None else ntp.system_time_to_ntp(timetag)
    return b"#bundle\0" + stamp + b"".join(struct.pack(">i", len(m)) + m for m in messages)
