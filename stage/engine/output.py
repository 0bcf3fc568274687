"""Server-to-View output: the registered views and the datagrams each fused person sends them.

The paper's Server-to-View API (section 4.1): ``/newUser id x y z`` when a
person is found, ``/jointCoordinates id (jointName x y z confidence)*`` per
fused frame, ``/handState id hand state`` when a hand's vote changes and
``/lostUser id``. Ids are the fused persons', never the clients'. Runs on the
engine thread; the transport must not block.
"""

from __future__ import annotations

import logging
from typing import Iterable, Protocol

import numpy as np

from ..joints import HandState
from ..sensors.protocol import (RegisterView, encode_view_hand_state, encode_view_joints,
                                encode_view_lost_user, encode_view_new_user)

log = logging.getLogger("stage.engine")


class Transport(Protocol):
    def send(self, data: bytes, address: tuple[str, int]) -> None:
        """Send one datagram; must not block and must not raise."""


class ViewOutput:
    """The views registered with the server and what is sent to them."""

    def __init__(self, transport: Transport | None, views: Iterable[tuple[str, int]] = ()) -> None:
        self.transport = transport
        self.views: list[tuple[str, int]] = list(dict.fromkeys(views))
        self.datagrams_out = 0
        self.send_errors = 0

    # ------------------------------------------------------------ registration
    def register(self, msg: RegisterView, announced: Iterable[tuple[int, np.ndarray,
                                                                    tuple[HandState, HandState]]]
                 ) -> None:
        """``/registerView`` or ``/unregisterView``; a new view learns who is on stage.

        announced: (person id, centre (3,), hands) of every person already found.
        """
        target = (msg.host, msg.port)
        if not msg.register:
            if target in self.views:
                self.views.remove(target)
                log.info("view %s:%d unregistered", *target)
            return
        if target not in self.views:
            self.views.append(target)
            log.info("view %s:%d registered", *target)
        for pid, centre, hands in announced:
            self.send(encode_view_new_user(pid, centre), target)
            for hand in (0, 1):
                self.send(encode_view_hand_state(pid, hand, hands[hand]), target)

    # ------------------------------------------------------------ messages
    def new_user(self, pid: int, centre: np.ndarray) -> None:
        self.broadcast(encode_view_new_user(pid, centre))

    def joints(self, pid: int, joints: np.ndarray, conf: np.ndarray) -> None:
        self.broadcast(encode_view_joints(pid, joints, conf))

    def hand(self, pid: int, hand: int, state: HandState) -> None:
        self.broadcast(encode_view_hand_state(pid, hand, state))

    def lost_user(self, pid: int) -> None:
        self.broadcast(encode_view_lost_user(pid))

    # ------------------------------------------------------------ sending
    def broadcast(self, data: bytes) -> None:
        for view in self.views:
            self.send(data, view)

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        if self.transport is None:
            return
        try:
            self.transport.send(data, address)
            self.datagrams_out += 1
        except OSError:
            self.send_errors += 1
