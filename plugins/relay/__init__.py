"""The relay view: our fused bodies to another stage server, as one more sensor there.

Two rooms performing together (the K-Multiscope paper's telematic future
work): each server relays its people to the other, speaking the
Client-to-Server API exactly like a Kinect client (``/registerDevice``,
``/newUser``, ``/jointCoordinates``, ``/handState``, ``/lostUser``), every
frame in one bundle whose timetag is its capture time, so the remote server
estimates our clock offset like any client's.

On the remote side the relay is a sensor named ``relay-<host>-<port>`` (or
``client_id``) of type ``stage-relay``. Its coordinates are our stage space:
the remote rig places our room in theirs with that sensor's calibration
matrix, or makes it the reference. Fused ids are mapped onto the user ids
0-5 a client may use; a seventh person is not relayed (counted).

People who are only on our stage because another server relayed them (all
their sensors are relays) are not relayed back, so two rooms relaying to each
other do not echo.
"""

from __future__ import annotations

import socket
from typing import Any

from stage.frames import FusedFrame
from stage.errors import ConfigError
from stage.sensors.protocol import MAX_USER_ID, encode_bundle, encode_client_joints, encode_message
from stage.network import parse_hostport
from stage.views import Status, View, ViewContext

SENSOR_TYPE = "stage-relay"
#: Resend a person's hand states this often even unchanged (UDP may lose the change).
HANDS_REFRESH_S = 1.0


class RelayView(View):
    """Relay: fused bodies to another stage server, as one more sensor (Client-to-Server API)."""

    description = "relay: fused bodies to another stage server as one more sensor"
    autostart = False
    max_pending_frames = 8

    def __init__(self, target: Any = None, client_id: str | None = None,
                 register_every_s: float = 5.0) -> None:
        if target is None:
            raise ConfigError("the relay needs a target server HOST:PORT")
        try:
            self.target = parse_hostport(target) if isinstance(target, str) else (
                str(target[0]), int(target[1]))
        except (ValueError, TypeError, IndexError) as exc:
            raise ConfigError(f"relay target {target!r}: {exc}") from None
        self.client_id = client_id or f"relay-{socket.gethostname()}-{self.target[1]}"
        self.register_every_s = register_every_s
        self._slots: dict[int, int] = {}           # fused id -> user id 0-5
        self._hands_sent: dict[int, tuple[tuple[int, int], float]] = {}
        self._relay_sensors: set[str] = set()
        self._sock: socket.socket | None = None
        self._ctx: ViewContext | None = None
        self._next_register = 0.0
        self.counts = {"frames": 0, "datagrams": 0, "send_errors": 0, "persons_over_6": 0,
                       "echo_skipped": 0}
        self.summary = ""

    def start(self, ctx: ViewContext) -> None:
        self._ctx = ctx
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("0.0.0.0", 0))
        self.summary = f"to {self.target[0]}:{self.target[1]} as sensor '{self.client_id}'"
        self._register(ctx.now())
        ctx.log.info("relay %s", self.summary)

    def stop(self) -> None:
        if self._sock is None:
            return
        # the remote must not keep our people as ghosts
        gone = [encode_message("/lostUser", self.client_id, user) for user in self._slots.values()]
        self._slots.clear()
        if gone:
            self._send(gone, None)
        self._sock.close()
        self._sock = None

    def on_status(self, status: Status) -> None:
        self._relay_sensors = {cid for cid, c in status.engine.get("clients", {}).items()
                               if c.get("type") == SENSOR_TYPE}

    def _is_relayed_here(self, sensors: tuple[str, ...]) -> bool:
        return bool(sensors) and all(s in self._relay_sensors or s.startswith("relay-")
                                     for s in sensors)

    def on_frame(self, frame: FusedFrame) -> None:
        if frame.t >= self._next_register:
            self._register(frame.t)
        messages: list[bytes] = []
        for pid in frame.lost:
            user = self._slots.pop(pid, None)
            self._hands_sent.pop(pid, None)
            if user is not None:
                messages.append(encode_message("/lostUser", self.client_id, user))
        for pid in frame.updated:
            body = frame.bodies.get(pid)
            if body is None or not body.sensors:
                continue
            if self._is_relayed_here(body.sensors):
                self.counts["echo_skipped"] += 1
                continue
            user = self._slots.get(pid)
            if user is None:
                free = sorted(set(range(MAX_USER_ID + 1)) - set(self._slots.values()))
                if not free:
                    self.counts["persons_over_6"] += 1
                    continue
                user = self._slots[pid] = free[0]
                messages.append(encode_message("/newUser", self.client_id, user,
                                               *(float(v) for v in body.position)))
            messages.append(encode_client_joints(self.client_id, user, body.joints, body.conf))
            hands = (int(body.hands[0]), int(body.hands[1]))
            last = self._hands_sent.get(pid)
            if last is None or last[0] != hands or frame.t - last[1] >= HANDS_REFRESH_S:
                self._hands_sent[pid] = (hands, frame.t)
                for hand in (0, 1):
                    messages.append(encode_message("/handState", self.client_id, user,
                                                   ("left", "right")[hand],
                                                   body.hands[hand].wire_name))
        if messages:
            self.counts["frames"] += 1
            self._send(messages, frame.t)

    def _register(self, now: float) -> None:
        self._next_register = now + self.register_every_s
        self._send([encode_message("/registerDevice", self.client_id, SENSOR_TYPE)], None)

    def _send(self, messages: list[bytes], t: float | None) -> None:
        if self._sock is None:
            return
        wall = None if t is None or self._ctx is None else t + self._ctx.wall_minus_clock
        # one bundle per frame; a frame of six people is about 6 kB, well within a datagram
        try:
            self._sock.sendto(encode_bundle(messages, wall), self.target)
            self.counts["datagrams"] += 1
        except OSError:  # the remote is down or unreachable: keep going, counted
            self.counts["send_errors"] += 1

    def stats(self) -> dict[str, Any]:
        return {**self.counts, "relayed_now": len(self._slots), "summary": self.summary}
