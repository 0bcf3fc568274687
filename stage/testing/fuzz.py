"""Hypothesis strategies for OSC datagrams, and the properties the fuzz tests check.

Shared by ``tests/test_fuzz.py`` (a short run in every test suite) and
``bench/fuzz.py`` (a long run that reports how many inputs were tried). The
datagrams are built from the wire format's own parts -- addresses the
server serves (and a few it does not), type tags, strings, numbers (NaN,
infinities, huge values), joint names, nested bundles with any timetag --
and then often damaged (cut, bytes flipped, sizes lied about), so the
decoder's and the engine's checks are reached, not only its first
``malformed``.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from hypothesis import strategies as st

from ..clock import ManualClock
from ..engine.engine import Engine
from ..joints import JOINTS
from ..rig import Rig
from ..sensors.protocol import DROP_REASONS, Inbound, decode_datagram
from ..settings import LimitSettings
from ..stats import DropCounter

ADDRESSES = ["/registerDevice", "/newUser", "/lostUser", "/jointCoordinates", "/handState",
             "/floorPlane", "/registerView", "/unregisterView", "/stage/stats", "/stage/health",
             "/nope", "/", "/jointCoordinate"]
CLIENTS = ["k1", "k2", "k3", "", "x" * 65, "k\u00e9", "1"]


def _pad(b: bytes) -> bytes:
    return b + b"\0" * (4 - len(b) % 4)


def _arg(tag: str, value: Any) -> bytes:
    if tag == "i":
        return struct.pack(">i", value)
    if tag == "f":
        return struct.pack(">f", value)
    if tag == "d":
        return struct.pack(">d", value)
    if tag == "h":
        return struct.pack(">q", value)
    if tag == "s":
        return _pad(value.encode("utf-8", "surrogatepass"))
    if tag == "b":
        return struct.pack(">i", len(value)) + value + b"\0" * (-len(value) % 4)
    return b""  # T F N I


def encode(address: str, args: list[tuple[str, Any]]) -> bytes:
    tags = "," + "".join(t for t, _ in args)
    return _pad(address.encode()) + _pad(tags.encode()) + b"".join(_arg(t, v) for t, v in args)


_floats = st.one_of(st.floats(-25, 25, width=32), st.sampled_from(
    [float("nan"), float("inf"), -float("inf"), 1e30, 0.5, 0.0, 1.0]))
_ints = st.one_of(st.integers(-3, 8), st.integers(-2**31, 2**31 - 1))
_strings = st.one_of(st.sampled_from(CLIENTS + list(JOINTS) + ["left", "right", "open", "closed",
                                                                 "lasso", "127.0.0.1", "127.1"]),
                     st.text(max_size=12))


def _value_arg():
    return st.one_of(
        st.tuples(st.just("i"), _ints), st.tuples(st.just("f"), _floats),
        st.tuples(st.just("d"), st.floats(allow_nan=True, allow_infinity=True)),
        st.tuples(st.just("s"), _strings),
        st.tuples(st.just("h"), st.integers(-2**63, 2**63 - 1)),
        st.tuples(st.just("b"), st.binary(max_size=8)),
        st.tuples(st.sampled_from("TFNI"), st.none()))


@st.composite
def skeleton_args(draw) -> list[tuple[str, Any]]:
    """A /jointCoordinates body, mostly well formed, sometimes not."""
    args = [("s", draw(st.sampled_from(CLIENTS))), ("i", draw(st.integers(-1, 7)))]
    names = draw(st.lists(st.sampled_from(list(JOINTS) + ["Nose"]), max_size=27))
    for name in names:
        args.append(("s", name))
        for _ in range(3):
            args.append(("f", draw(_floats)))
        args.append(("f", draw(st.one_of(st.floats(0, 1, width=32), _floats))))
    return args


@st.composite
def messages(draw) -> bytes:
    address = draw(st.sampled_from(ADDRESSES))
    if address == "/jointCoordinates" and draw(st.booleans()):
        args = draw(skeleton_args())
    else:
        first = [("s", draw(st.sampled_from(CLIENTS)))] if draw(st.booleans()) else []
        args = first + draw(st.lists(_value_arg(), max_size=6))
    return encode(address, args)


@st.composite
def bundles(draw, depth: int = 0) -> bytes:
    stamp = draw(st.one_of(st.just(1), st.integers(0, 2**64 - 1),
                           st.just(int((1_700_000_000 + 2208988800) * 2**32))))
    parts = draw(st.lists(st.one_of(messages(), bundles(depth + 1)) if depth < 2 else messages(),
                          max_size=4))
    body = b"".join(struct.pack(">i", len(p)) + p for p in parts)
    return b"#bundle\0" + struct.pack(">Q", stamp) + body


@st.composite
def damaged(draw, data: bytes) -> bytes:
    """``data`` cut, with bytes flipped, or with a size field lying."""
    kind = draw(st.sampled_from(["none", "none", "cut", "flip", "append"]))
    if kind == "cut" and data:
        return data[:draw(st.integers(0, len(data) - 1))]
    if kind == "flip" and data:
        buf = bytearray(data)
        for _ in range(draw(st.integers(1, 4))):
            buf[draw(st.integers(0, len(buf) - 1))] = draw(st.integers(0, 255))
        return bytes(buf)
    if kind == "append":
        return data + draw(st.binary(max_size=9))
    return data


@st.composite
def datagrams(draw) -> bytes:
    base = draw(st.one_of(messages(), bundles(), st.binary(max_size=64)))
    return draw(damaged(base))


def element_count(data: bytes) -> int | None:
    """How many OSC messages a well-formed datagram holds (None: not well formed)."""
    if data.startswith(b"#bundle\0"):
        if len(data) < 16:
            return None
        n, i = 0, 16
        while i < len(data):
            if i + 4 > len(data):
                return None
            (size,) = struct.unpack_from(">i", data, i)
            i += 4
            if size <= 0 or size % 4 or i + size > len(data):
                return None
            inner = element_count(data[i:i + size])
            if inner is None:
                return None
            n += inner
            i += size
        return n
    return 1 if data.startswith(b"/") else None


def check_decoder(data: bytes) -> None:
    """decode_datagram never raises; every message is either decoded or dropped, with a
    documented reason; a malformed datagram decodes to nothing."""
    out = decode_datagram(data, "127.0.0.1:9")
    assert all(reason in DROP_REASONS for _, reason in out.drops), out.drops
    if any(r == "malformed" for _, r in out.drops):
        assert out.messages == [] and len(out.drops) == 1
        return
    n = element_count(data)
    assert n is not None, "a datagram that is not well formed must be dropped as malformed"
    assert len(out.messages) + len(out.drops) == n


class EngineUnderTest:
    """An engine on a manual clock with small caps, fed datagrams; ``check()`` its invariants."""

    def __init__(self) -> None:
        self.clock = ManualClock(100.0)
        self.sent: list[tuple[bytes, tuple[str, int]]] = []
        rig = Rig(limits=LimitSettings(max_clients=8, max_views=4, max_drop_keys=32))
        self.engine = Engine(rig, self.clock, self, DropCounter(32))
        self.decoded = 0           # messages the decoder accepted
        self.dropped_at_decode = 0

    def send(self, data: bytes, address: tuple[str, int]) -> None:  # the engine's transport
        self.sent.append((data, address))
        del self.sent[:-100]

    def feed(self, data: bytes, source: tuple[str, int], dt: float) -> None:
        self.clock.advance(dt)
        decoded = decode_datagram(data, f"{source[0]}:{source[1]}")
        for client, reason in decoded.drops:
            self.engine.drops.add(client, reason)
        self.dropped_at_decode += len(decoded.drops)
        self.decoded += len(decoded.messages)
        self.engine.process([Inbound(m, self.clock.now(), source, tt)
                             for m, tt in decoded.messages])
        if dt > 0.02:
            self.engine.tick()

    def check(self) -> None:
        e = self.engine
        limits = e.rig.limits
        drops = e.drops.snapshot()
        assert "internal_error" not in {r for d in drops.values() for r in d}, drops
        assert len(e.clients) <= limits.max_clients
        assert len(e.output.registered) <= limits.max_views
        assert len(drops) <= limits.max_drop_keys + limits.max_clients + 1
        # every message the decoder gave the engine was applied (and then used or counted
        # as a drop by reason) or refused for its timetag (counted as bad_time)
        assert e.counts["messages"] + e.drops.total("bad_time") == self.decoded
        # and every drop the decoder reported is in the counters
        assert sum(n for d in drops.values() for n in d.values()) >= self.dropped_at_decode
        # tracks and persons agree
        for cid, client in e.clients.items():
            for track in client.tracks.values():
                if track.person is not None:
                    person = e.persons.get(track.person)
                    assert person is not None and track in person.tracks, (cid, track.user)
        for pid, person in e.persons.items():
            for track in person.tracks:
                assert track.person == pid
                assert e.clients.get(track.client) is not None
            assert np.isfinite(person.joints).all()
        if e.reference is not None:
            assert isinstance(e.reference, str)
