"""The OSC wire API (K-Multiscope paper, section 4.1), decoded and encoded.

Pure functions over bytes: no sockets here. ``decode_datagram`` turns one
UDP datagram into validated message objects plus a list of drops (client,
reason); it never raises. The encoders build the Server-to-View messages
and the Client-to-Server messages (for the demo, the simulator and tests).

Client-to-Server (4.1.1)::

    /registerDevice  clientID sensorType
    /newUser         clientID userID x y z
    /lostUser        clientID userID
    /jointCoordinates clientID userID (jointName x y z confidence)*
    /handState       clientID userID hand state

View-to-Server (4.1.2): ``/registerView ip port``. Server-to-View (4.1.3):
the same addresses without the clientID. Our additions are new addresses
only (``/floorPlane clientID a b c d``, ``/unregisterView ip port``,
``/stage/stats [port]``, ``/stage/health [port]``), so a Kuatro client works unchanged. See docs/osc-api.md.
"""

from __future__ import annotations

import math
import struct
import threading
from typing import Iterable, Iterator

import numpy as np
from pythonosc import osc_message
from pythonosc.parsing import ntp

from ..joints import JOINT_INDEX, N_JOINTS, HandState, parse_hand, parse_hand_state
from . import scan
# The message types and the encoders live in their own modules; they are re-exported
# here because ``protocol`` is the wire API's one import for views, clients and tests.
from .encode import (_pad, encode_bundle, encode_client_joints, encode_message,  # noqa: F401
                     encode_view_hand_state, encode_view_joints, encode_view_lost_user,
                     encode_view_new_user)
from .fastdecode import (_fast_hand_state,  # noqa: F401
                         _fast_joint_coordinates, canonical_head, canonical_joints_batch)
from .messages import (DROP_REASONS, MAX_COORD_M, MAX_TEXT, MAX_USER_ID,  # noqa: F401
                       ClientMessage, Decoded, FloorPlane, HandStateMsg, HealthQuery,
                       Inbound, JointCoordinates, LostUser, Message, NewUser, RegisterDevice,
                       RegisterView, StatsQuery, ViewUnreachable)

class _Drop(Exception):
    def __init__(self, reason: str) -> None:
        self.reason = reason


def decode_datagram(data: bytes, source: str = "?") -> Decoded:
    """Decode and validate one UDP datagram; never raises.

    ``source`` ("ip:port") names the drop when no client id can be read.
    Timetags are Unix seconds (float) from the innermost enclosing bundle,
    or None when the message was not in a bundle or the bundle is
    "immediately".
    """
    out = Decoded()
    try:
        if data.startswith(b"#bundle\0"):
            if _scanner is not None and _decode_scanned(data, out, source):
                return out
            canonical: list = []
            _walk_bundle(data, out, source, canonical)
            if canonical:
                _decode_canonical(canonical, out, source)
        elif osc_message.OscMessage.dgram_is_message(data):
            _decode_element(data, None, out, source)
        else:
            out.drops.append((source, "malformed"))
    except Exception:  # python-osc raises several types on garbage; all mean the same here
        # the whole datagram is one drop: what its first elements gave counts no more
        # (found by tests/test_fuzz.py: a bundle whose last size lies counted twice)
        out.messages.clear()
        out.drops.clear()
        out.drops.append((source, "malformed"))
    return out


def decode_records(records: Iterable[tuple[float, bytes, float | None]], drops: dict[str, int],
                   ) -> Iterator[tuple[float, float | None, Message, float | None]]:
    """Decode recorded datagrams: (arrival s, datagram, capture s or None) records ->
    (arrival, capture, message, timetag) per valid message; every drop is counted in
    ``drops`` by reason (never fatal). The offline readers (calibration, analysis) share it."""
    for arrival, data, capture in records:
        decoded = decode_datagram(bytes(data))
        for _, reason in decoded.drops:
            drops[reason] = drops.get(reason, 0) + 1
        for msg, timetag in decoded.messages:
            yield arrival, capture, msg, timetag


#: ``scan.scan`` compiled (``use_scanner``); None: bundles are walked in Python
_scanner = None
_STATES = tuple(HandState(code) for code in range(len(HandState)))


def use_scanner(scanner) -> None:
    """Walk sensor bundles with ``scanner`` (``scan.scan`` compiled; the engine installs it
    when it compiles its kernels), or in Python (None)."""
    global _scanner
    _scanner = scanner


#: each thread's scanner output arrays (``_decode_scanned``), the largest it asks for:
#: made once, not for every datagram
_SCRATCH = threading.local()


def _decode_scanned(data: bytes, out: Decoded, source: str) -> bool:
    """``decode_datagram`` of a bundle by the scanner: the same messages and drops as
    ``_walk_bundle`` gives (elements the scanner does not read are decoded here as there);
    False, having added nothing, where the bundle needs the Python walker (nested).

    The scanner writes into arrays this thread keeps from datagram to datagram, and what
    the messages hold is copied out of them before anything else runs. Live, the receiver
    thread wakes for every datagram and finds its caches cold: with three allocations and
    a numpy comparison, count and slice fewer, a 6x6 datagram took 50-70 us less then
    (issue 10, stop 37, ``bench/bench_wakeup.py``), so the skeletons are also counted
    from the rows rather than with a numpy reduction."""
    scratch = getattr(_SCRATCH, "arrays", None)
    if scratch is None:
        scratch = _SCRATCH.arrays = (np.empty((128, scan.COLUMNS), dtype=np.int64),
                                     np.empty((64, N_JOINTS, 3)), np.empty((64, N_JOINTS)))
    # whole: a datagram of n bytes holds at most n // 8 elements and n // 60 + 1 skeletons,
    # so only the 128 elements and 64 skeletons of the arrays bound what the scanner takes
    info, joints, conf = scratch
    if type(data) is not bytes:      # a bytearray: hashable client names, a read-only view
        data = bytes(data)
    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        count = _scanner(buf, info, joints, conf)
    except TypeError:       # a buffer the compiled scanner does not take: the Python walker
        return False
    if count == scan.USE_WALKER:
        return False
    if count == scan.MALFORMED:
        raise ValueError("bundle element size out of bounds")
    (stamp,) = struct.unpack_from(">Q", data, 8)
    timetag = None if stamp == 1 else ntp.ntp_to_system_time(data[8:16])
    elements = info[:count].tolist()
    skeletons = 0
    for element in elements:
        if element[0] == scan.SKELETON:
            skeletons += 1
    # the messages' arrays are views of these copies (never of the scratch arrays, which
    # the next datagram overwrites), of the skeletons' size only: a view keeps its whole
    # base alive, and the calibrator buffers seconds of frames
    joints, conf = joints[:skeletons].copy(), conf[:skeletons].copy()
    messages = out.messages
    clients: dict[bytes, str] = {}
    for kind, start, end, c0, c1, c_int, user, hand, state, row in elements:
        if kind == scan.OTHER:
            _decode_element(data[start:end], timetag, out, source)
            continue
        if c0 < 0:
            client = str(c_int)
        else:
            raw = data[c0:c1]
            client = clients.get(raw)
            if client is None:
                try:
                    client = clients[raw] = raw.decode("utf-8")
                except UnicodeDecodeError:   # the Python path names the drop
                    _decode_element(data[start:end], timetag, out, source)
                    continue
        if kind == scan.SKELETON:
            messages.append((JointCoordinates(client, user, joints[row], conf[row]), timetag))
        else:
            messages.append((HandStateMsg(client, user, hand, _STATES[state]), timetag))
    return True


def _walk_bundle(data: bytes, out: Decoded, source: str, canonical: list,
                 depth: int = 0) -> None:
    """Walk a bundle strictly: every element's size must fit, or the whole datagram is malformed.

    python-osc's OscBundle slices past the end of a truncated element and
    skips unknown content with a log line; on a stage a truncated datagram
    must count as one drop instead. Skeletons that may be canonical (``fastdecode``) keep
    their place in ``out.messages`` and are listed in ``canonical`` (place, element, client,
    user, offset of the joints), to be decoded together by ``_decode_canonical``.
    """
    if len(data) < 16 or depth > 8:
        raise ValueError("truncated or too deeply nested bundle")
    (stamp,) = struct.unpack_from(">Q", data, 8)
    timetag = None if stamp == 1 else ntp.ntp_to_system_time(data[8:16])
    index = 16
    while index < len(data):
        if index + 4 > len(data):
            raise ValueError("truncated bundle element size")
        (size,) = struct.unpack_from(">i", data, index)
        index += 4
        if size <= 0 or size % 4 or index + size > len(data):
            raise ValueError("bundle element size out of bounds")
        element = data[index:index + size]
        index += size
        if element.startswith(b"#bundle\0"):
            _walk_bundle(element, out, source, canonical, depth + 1)
        elif element.startswith(b"/"):
            head = canonical_head(element)
            if head is not None:
                canonical.append((len(out.messages), element, *head))
                out.messages.append((None, timetag))  # type: ignore[arg-type]
            else:
                _decode_element(element, timetag, out, source)
        else:
            raise ValueError("bundle element is neither a message nor a bundle")


_FIXED_SIZES = {"i": 4, "f": 4, "c": 4, "r": 4, "m": 4, "d": 8, "h": 8, "t": 8,
                "T": 0, "F": 0, "N": 0, "I": 0}
#: the type tags python-osc parses (arrays and exotic tags are refused as malformed)
_PARSED_TAGS = b"ifcrmdhtTFNsb"


def _parse_message(data: bytes) -> osc_message.OscMessage:
    """python-osc's parser, made strict about length.

    It zero-pads a float cut short at the end of a datagram (a courtesy to
    one synth), so a truncated skeleton would decode with a wrong last value;
    here the arguments must fill the datagram exactly.
    """
    # type tags python-osc does not know make it log a warning on the root logger per
    # datagram (a flood of them would fill the log): refuse them before it parses
    end = data.find(b"\0")
    start = (end // 4 + 1) * 4 if end >= 0 else -1
    stop = data.find(b"\0", start) if start >= 0 else -1
    if stop < 0 or not data.startswith(b",", start) or \
            data[start + 1:stop].strip(_PARSED_TAGS):
        raise ValueError("type tags missing or not supported")
    msg = osc_message.OscMessage(data)
    tags = msg.dgram[len(_pad(msg.address.encode())):].split(b"\0", 1)[0].decode("ascii")
    size = len(_pad(msg.address.encode())) + len(_pad(tags.encode()))
    params = iter(msg.params)
    for tag in tags[1:]:
        if tag in _FIXED_SIZES:
            next(params)  # python-osc yields a value for every tag, T/F/N/I included
            size += _FIXED_SIZES[tag]
        elif tag == "s":
            size += len(_pad(next(params).encode()))
        elif tag == "b":
            n = len(next(params))
            size += 4 + n + (-n % 4)
        else:  # arrays and exotic tags are not part of this API
            raise ValueError(f"unsupported OSC type tag {tag!r}")
    if size != len(data):
        raise ValueError("arguments do not fill the datagram exactly")
    return msg


def _decode_canonical(canonical: list, out: Decoded, source: str) -> None:
    """Fill in the places ``_walk_bundle`` kept for possibly canonical skeletons: all checked
    and converted at once; one that is not (other names, an invalid value) is decoded alone,
    as any other element, and its place takes what that gives (a message, or nothing and a
    drop)."""
    ok, joints, conf = canonical_joints_batch([e[pos:] for _, e, _, _, pos in canonical])
    redo = False
    for k, (place, element, client, user, _) in enumerate(canonical):
        timetag = out.messages[place][1]
        if ok[k]:
            out.messages[place] = (JointCoordinates(client, user, joints[k], conf[k]), timetag)
            continue
        alone = Decoded()
        _decode_element(element, timetag, alone, source)
        out.drops.extend(alone.drops)
        out.messages[place] = alone.messages[0] if alone.messages else None  # type: ignore
        redo = redo or not alone.messages
    if redo:
        out.messages[:] = [m for m in out.messages if m is not None]


def _decode_element(data: bytes, timetag: float | None, out: Decoded, source: str) -> None:
    fast = _fast_joint_coordinates(data) or _fast_hand_state(data)
    if fast is not None:
        out.messages.append((fast, timetag))
    else:
        _decode_message(_parse_message(data), timetag, out, source)


def _decode_message(msg: osc_message.OscMessage, timetag: float | None, out: Decoded,
                    source: str) -> None:
    params = msg.params
    client = _client_of(params, source)
    handler = _HANDLERS.get(msg.address)
    if handler is None:
        out.drops.append((client, "unknown_address"))
        return
    try:
        out.messages.append((handler(params, source), timetag))
    except _Drop as drop:
        out.drops.append((client, drop.reason))


def _client_of(params: list, source: str) -> str:
    if params and isinstance(params[0], (str, int)) and not isinstance(params[0], bool):
        return str(params[0])
    return source


def _is_int(v: object) -> bool:
    return (isinstance(v, int) and not isinstance(v, bool)) or (
        isinstance(v, float) and math.isfinite(v) and v.is_integer())


def _client(v: object) -> str:
    if isinstance(v, bool) or not isinstance(v, (str, int)):
        raise _Drop("bad_types")
    text = str(v)
    if not text or len(text) > 64:
        raise _Drop("bad_types")
    return text


def _user(v: object) -> int:
    if isinstance(v, str) and v.strip().isdigit():
        v = int(v)
    if not _is_int(v):
        raise _Drop("bad_types" if not isinstance(v, (int, float)) else "bad_user_id")
    user = int(v)
    if not 0 <= user <= MAX_USER_ID:
        raise _Drop("bad_user_id")
    return user


def _number(v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Drop("bad_types")
    f = float(v)
    if not math.isfinite(f):
        raise _Drop("non_finite")
    return f


def _coord(v: object) -> float:
    f = _number(v)
    if abs(f) > MAX_COORD_M:
        raise _Drop("out_of_range")
    return f


def _arity(params: list, n: int) -> None:
    if len(params) != n:
        raise _Drop("bad_arity")


def _h_register_device(params: list, source: str) -> RegisterDevice:
    if len(params) not in (1, 2):
        raise _Drop("bad_arity")
    sensor_type = params[1] if len(params) == 2 else "unknown"
    if not isinstance(sensor_type, str):
        raise _Drop("bad_types")
    if len(sensor_type) > MAX_TEXT:  # it goes into logs and stats: never 60 KB of it
        sensor_type = sensor_type[:MAX_TEXT - 1] + "~"
    return RegisterDevice(_client(params[0]), sensor_type)


def _h_new_user(params: list, source: str) -> NewUser:
    _arity(params, 5)
    pos = np.array([_coord(params[2]), _coord(params[3]), _coord(params[4])])
    return NewUser(_client(params[0]), _user(params[1]), pos)


def _h_lost_user(params: list, source: str) -> LostUser:
    _arity(params, 2)
    return LostUser(_client(params[0]), _user(params[1]))


def _h_joint_coordinates(params: list, source: str) -> JointCoordinates:
    n = len(params) - 2
    if n < 0 or n % 5 != 0 or n // 5 > N_JOINTS:
        raise _Drop("bad_arity")
    client, user = _client(params[0]), _user(params[1])
    joints = np.zeros((N_JOINTS, 3))
    conf = np.zeros(N_JOINTS)
    seen = 0
    for k in range(2, len(params), 5):
        name = params[k]
        if not isinstance(name, str):
            raise _Drop("bad_types")
        index = JOINT_INDEX.get(name)
        if index is None:
            raise _Drop("unknown_joint")
        if seen >> index & 1:
            raise _Drop("duplicate_joint")
        seen |= 1 << index
        x, y, z = _coord(params[k + 1]), _coord(params[k + 2]), _coord(params[k + 3])
        c = _number(params[k + 4])
        if not 0.0 <= c <= 1.0:
            raise _Drop("out_of_range")
        joints[index] = (x, y, z)
        conf[index] = c
    return JointCoordinates(client, user, joints, conf)


def _h_hand_state(params: list, source: str) -> HandStateMsg:
    _arity(params, 4)
    client, user = _client(params[0]), _user(params[1])
    hand = parse_hand(params[2])
    if hand is None:
        raise _Drop("bad_hand" if isinstance(params[2], (str, int)) else "bad_types")
    state = parse_hand_state(params[3])
    if state is None:
        raise _Drop("bad_hand_state")
    return HandStateMsg(client, user, hand, state)


def _h_floor_plane(params: list, source: str) -> FloorPlane:
    _arity(params, 5)
    plane = np.array([_number(v) for v in params[1:5]])
    norm = float(np.linalg.norm(plane[:3]))
    if norm < 1e-6 or abs(plane[3]) / norm > MAX_COORD_M:
        raise _Drop("out_of_range")
    return FloorPlane(_client(params[0]), plane / norm)


def _port(v: object) -> int:
    if isinstance(v, str) and v.strip().isdigit():
        v = int(v)
    if not _is_int(v):
        raise _Drop("bad_types")
    port = int(v)
    if not 1 <= port <= 65535:
        raise _Drop("out_of_range")
    return port


def _h_register_view(params: list, source: str, register: bool = True) -> RegisterView:
    rate = forecast = None
    if register and len(params) == 4 and isinstance(params[3], float):
        # rate (0: every update) and forecast in seconds (a float): stage additions
        forecast = params[3]
        if not (math.isfinite(forecast) and 0 <= forecast <= 1.0):
            raise _Drop("out_of_range")
        params = params[:3]
        if params[2] == 0 and not isinstance(params[2], bool):
            params = params[:2]
    if register and len(params) == 3:  # trailing rate in Hz: a stage addition
        rate = params[2]
        if isinstance(rate, bool) or not isinstance(rate, (int, float)):
            raise _Drop("bad_types")
        if not (math.isfinite(rate) and 0 < rate <= 1000):
            raise _Drop("out_of_range")
        params = params[:2]
    _arity(params, 2)
    host = params[0]
    if not isinstance(host, str) or not host or len(host) > 255:
        raise _Drop("bad_types")
    return RegisterView(host, _port(params[1]), register, None if rate is None else float(rate),
                        None if forecast is None else round(float(forecast), 6))  # float32 on the wire


def _h_unregister_view(params: list, source: str) -> RegisterView:
    return _h_register_view(params, source, register=False)


def _h_stats(params: list, source: str) -> StatsQuery:
    if len(params) > 1:
        raise _Drop("bad_arity")
    return StatsQuery(_port(params[0]) if params else None)


def _h_health(params: list, source: str) -> HealthQuery:
    if len(params) > 1:
        raise _Drop("bad_arity")
    return HealthQuery(_port(params[0]) if params else None)


_HANDLERS = {
    "/registerDevice": _h_register_device,
    "/newUser": _h_new_user,
    "/lostUser": _h_lost_user,
    "/jointCoordinates": _h_joint_coordinates,
    "/handState": _h_hand_state,
    "/floorPlane": _h_floor_plane,
    "/registerView": _h_register_view,
    "/unregisterView": _h_unregister_view,
    "/stage/stats": _h_stats,
    "/stage/health": _h_health,
}
