"""Server-to-View output: the registered views and the datagrams each fused person sends them.

The paper's Server-to-View API (section 4.1): ``/newUser id x y z`` when a
person is found, ``/jointCoordinates id (jointName x y z confidence)*`` per
fused frame, ``/handState id hand state`` when a hand's vote changes and
``/lostUser id``. Ids are the fused persons', never the clients'. Runs on the
engine thread; the transport must not block.

By default a view gets every update of every person as it is fused. A view
that registers with a rate (``/registerView ip port rateHz``) instead gets
``/jointCoordinates`` of every person at that rate, each predicted to the
moment it is sent (``due``, called by the engine's timer).
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
        #: views that asked for a fixed rate: address -> (rate Hz, next send time or None)
        self.rates: dict[tuple[str, int], tuple[float, float | None]] = {}
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
            self.rates.pop(target, None)
            if target in self.views:
                self.views.remove(target)
                log.info("view %s:%d unregistered", *target)
            return
        if target not in self.views:
            self.views.append(target)
            log.info("view %s:%d registered%s", *target,
                     f" at {msg.rate_hz:g} Hz" if msg.rate_hz else "")
        if msg.rate_hz:
            self.rates[target] = (msg.rate_hz, None)
        else:
            self.rates.pop(target, None)
        for pid, centre, hands in announced:
            self.send(encode_view_new_user(pid, centre), target)
            for hand in (0, 1):
                self.send(encode_view_hand_state(pid, hand, hands[hand]), target)

    # ------------------------------------------------------------ messages
    def new_user(self, pid: int, centre: np.ndarray) -> None:
        self.broadcast(encode_view_new_user(pid, centre))

    def joints(self, pid: int, joints: np.ndarray, conf: np.ndarray,
               targets: list[tuple[str, int]] | None = None) -> None:
        """To every view that takes every update (default), or to ``targets``."""
        if targets is not None:
            data = encode_view_joints(pid, joints, conf)
            for view in targets:
                self.send(data, view)
            return
        if not self.rates:
            self.broadcast(encode_view_joints(pid, joints, conf))
            return
        data = encode_view_joints(pid, joints, conf)
        for view in self.views:
            if view not in self.rates:
                self.send(data, view)

    # ------------------------------------------------------------ fixed rates
    def due(self, now: float) -> list[tuple[str, int]]:
        """The fixed-rate views whose next send is due at ``now`` (and schedule the next)."""
        out = []
        for view, (rate, next_t) in self.rates.items():
            if next_t is None or now >= next_t:
                out.append(view)
                period = 1.0 / rate
                # keep the grid; after a stall, start again from now
                following = now + period if next_t is None or now - next_t > period \
                    else next_t + period
                self.rates[view] = (rate, following)
        return out

    def next_due(self) -> float | None:
        """When the next fixed-rate send is due (None: no such view)."""
        times = [t for _, t in self.rates.values()]
        if not times:
            return None
        return min(float("-inf") if t is None else t for t in times)

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
