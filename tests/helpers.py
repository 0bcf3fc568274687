"""Shared helpers for the integration tests: free ports and OSC peers on loopback UDP.

A plain module (not a conftest): tests import it as ``from helpers import ...``,
which works because pytest's default "prepend" import mode puts ``tests/``
(a folder without ``__init__.py``) on ``sys.path``.

Nothing here sleeps to "let things happen": a ``Peer`` waits for the message
it needs with a deadline, and ``sync`` uses the server's own ``/stage/stats``
reply as a barrier (the engine handles its queue in order, so once the reply
to a query sent after some datagrams is back, those datagrams are handled and
everything the engine sent because of them is already in our socket buffers;
see ``sync`` for why that takes two queries).
"""

from __future__ import annotations

import json
import re
import socket
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from pythonosc import osc_bundle, osc_message

from stage.sensors.protocol import encode_bundle, encode_client_joints, encode_message

LOCALHOST = "127.0.0.1"
TIMEOUT_S = 5.0


def free_udp_port(host: str = LOCALHOST) -> int:
    """A UDP port nobody listens on right now (the kernel's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def typetags_of(dgram: bytes) -> str:
    """The OSC type tags of one message datagram, without the leading comma."""
    end = dgram.index(b"\0")
    start = (end // 4 + 1) * 4
    tags = dgram[start:dgram.index(b"\0", start)].decode()
    assert tags.startswith(","), f"no type tag string in {dgram!r}"
    return tags[1:]


@dataclass(frozen=True)
class Msg:
    """One OSC message as a peer received it."""

    address: str
    typetags: str
    params: tuple
    t: float                    # time.monotonic() when the test read it
    source: tuple[str, int]


class Peer:
    """A UDP socket on loopback that sends OSC and keeps every OSC message it gets."""

    def __init__(self, host: str = LOCALHOST) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.received: list[Msg] = []
        self.undecodable: list[bytes] = []

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def send(self, data: bytes, target: tuple[str, int]) -> None:
        self.sock.sendto(data, target)

    def send_message(self, target: tuple[str, int], address: str, *args: object) -> None:
        self.send(encode_message(address, *args), target)

    def _store(self, data: bytes, source: tuple[str, int]) -> None:
        now = time.monotonic()
        try:
            if osc_bundle.OscBundle.dgram_is_bundle(data):
                items = [m.dgram for m in _flatten(osc_bundle.OscBundle(data))]
            else:
                items = [data]
            for item in items:
                msg = osc_message.OscMessage(item)
                self.received.append(Msg(msg.address, typetags_of(item), tuple(msg.params),
                                         now, source))
        except Exception:  # a view must report garbage, not crash on it
            self.undecodable.append(data)

    def _receive(self, timeout: float) -> bool:
        """Read one datagram, waiting at most ``timeout`` seconds (0: do not wait)."""
        if timeout <= 0:
            self.sock.setblocking(False)
        else:
            self.sock.settimeout(timeout)
        try:
            data, source = self.sock.recvfrom(1 << 20)
        except (BlockingIOError, socket.timeout):
            return False
        self._store(data, source)
        return True

    def drain(self) -> list[Msg]:
        """Read whatever is already waiting in the socket buffer; never blocks."""
        before = len(self.received)
        while self._receive(0):
            pass
        return self.received[before:]

    def wait_for(self, predicate: Callable[[Msg], bool], timeout: float = TIMEOUT_S,
                 start: int = 0, what: str = "a message") -> Msg:
        """The first message from index ``start`` on that satisfies ``predicate``.

        Raises AssertionError (listing what did arrive) when none came within ``timeout``.
        """
        deadline = time.monotonic() + timeout
        i = start
        while True:
            while i < len(self.received):
                msg = self.received[i]
                i += 1
                if predicate(msg):
                    return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                seen = "\n  ".join(f"{m.address} {m.typetags} {m.params[:6]}"
                                   for m in self.received[start:][-20:])
                raise AssertionError(f"no {what} within {timeout} s; received since "
                                     f"#{start}:\n  {seen or '(nothing)'}")
            self._receive(remaining)

    def messages(self, address: str | None = None, start: int = 0) -> list[Msg]:
        return [m for m in self.received[start:] if address is None or m.address == address]

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> "Peer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _flatten(bundle: osc_bundle.OscBundle):
    for item in bundle:
        if isinstance(item, osc_bundle.OscBundle):
            yield from _flatten(item)
        else:
            yield item


class Sensor(Peer):
    """A fake Kinect client: speaks the Client-to-Server API from its own socket."""

    def __init__(self, client: str, server: tuple[str, int], host: str = LOCALHOST) -> None:
        super().__init__(host)
        self.client, self.server = client, server

    def register(self, sensor_type: str = "kinect2") -> None:
        self.send_message(self.server, "/registerDevice", self.client, sensor_type)

    def new_user(self, user: int, position: np.ndarray) -> None:
        self.send_message(self.server, "/newUser", self.client, user,
                          *(float(v) for v in position))

    def lost_user(self, user: int) -> None:
        self.send_message(self.server, "/lostUser", self.client, user)

    def joints_message(self, user: int, joints: np.ndarray,
                       conf: np.ndarray | None = None) -> bytes:
        conf = np.ones(len(joints)) if conf is None else conf
        return encode_client_joints(self.client, user, joints, conf)

    def frame(self, user: int, joints: np.ndarray, conf: np.ndarray | None = None) -> None:
        self.send(self.joints_message(user, joints, conf), self.server)

    def hand_message(self, user: int, hand: str, state: str) -> bytes:
        return encode_message("/handState", self.client, user, hand, state)

    def hand(self, user: int, hand: str, state: str) -> None:
        self.send(self.hand_message(user, hand, state), self.server)

    def bundle(self, messages: list[bytes], timetag: float | None) -> None:
        self.send(encode_bundle(messages, timetag), self.server)


def query_stats(server: tuple[str, int], timeout: float = TIMEOUT_S) -> dict:
    """Ask a server for ``/stage/stats`` from a fresh socket; the decoded JSON."""
    with Peer() as peer:
        peer.send_message(server, "/stage/stats")
        reply = peer.wait_for(lambda m: m.address == "/stage/stats", timeout,
                              what="/stage/stats reply")
    assert reply.typetags == "s", reply
    return json.loads(reply.params[0])


def sync(server: tuple[str, int], *views: Peer) -> dict:
    """Barrier: every datagram sent to ``server`` before this call has been handled.

    Returns the stats; the views' buffers are drained into ``.received``.

    Two queries, because the engine answers a query while it applies its batch
    but sends view output at the end of the batch: the first reply can overtake
    the view datagrams of the frames batched with it. The second query is sent
    only after the first reply, so it lands in a later batch, after that emit.
    """
    query_stats(server)
    stats = query_stats(server)
    for view in views:
        view.drain()
    return stats


def register_view(server: tuple[str, int], view: Peer) -> None:
    view.send_message(server, "/registerView", LOCALHOST, view.port)
    stats = query_stats(server)
    assert f"{LOCALHOST}:{view.port}" in stats["views"], stats["views"]


def joint_groups(msg: Msg) -> dict[str, tuple[np.ndarray, float]]:
    """A view's ``/jointCoordinates id (name x y z conf)*`` as {name: (xyz, conf)}."""
    assert msg.address == "/jointCoordinates", msg
    assert re.fullmatch(r"i(sffff)*", msg.typetags), msg.typetags
    rest = msg.params[1:]
    return {rest[k]: (np.array(rest[k + 1:k + 4], dtype=float), float(rest[k + 4]))
            for k in range(0, len(rest), 5)}
