"""The client registry: which sensors (clients) the engine knows, and the reference among them.

A ``ClientState`` is one sensor client as the engine sees it: where it sends
from, when it was last heard, its users' tracks, its clock offset and the
transform into stage space in use. ``ClientRegistry`` finds or creates the
state for each inbound message (the rig's allow-list by id), elects the
reference sensor, maps a client's timetags onto the engine clock and times
out silent clients. The engine thread owns every object here.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from ..rig import Rig
from ..sensors.protocol import Inbound, Message, RegisterDevice
from ..stats import DropCounter
from .tracking import OffsetEstimator, Track

log = logging.getLogger("stage.engine")


class ClientState:
    def __init__(self, client: str, sensor_type: str, source: tuple[str, int], now: float,
                 offset: OffsetEstimator) -> None:
        self.id, self.type, self.source = client, sensor_type, source
        self.registered = now
        self.last_seen = now
        self.frames = 0
        self.tracks: dict[int, Track] = {}
        self.offset = offset
        self.transform: np.ndarray | None = None
        self.warned_uncalibrated = False
        self.floor: np.ndarray | None = None
        self.active = True


class ClientRegistry:
    """The engine's clients by id, the reference sensor and the clients' clocks.

    ``drop_track(track, t)`` is the engine's: it unbinds a track from its person.
    """

    def __init__(self, rig: Rig, drops: DropCounter,
                 drop_track: Callable[[Track, float], None]) -> None:
        self.rig = rig
        self.drops = drops
        self._drop_track = drop_track
        self.clients: dict[str, ClientState] = {}
        self._offsets: dict[str, OffsetEstimator] = {}  # per client id, kept across silences
        self.reference = rig.reference

    def capture_time(self, item: Inbound) -> float:
        msg = item.message
        client = getattr(msg, "client", None)
        if item.timetag is None or client is None:
            return item.arrival
        estimator = self._offsets.get(client)
        if estimator is None:
            estimator = self._offsets[client] = OffsetEstimator()
        offset = estimator.update(item.arrival, item.timetag)
        return min(item.timetag + offset, item.arrival)

    def client(self, msg: Message, item: Inbound) -> ClientState | None:
        cid = msg.client  # type: ignore[union-attr]
        now = item.arrival
        if (not self.rig.allow_unknown_sensors and self.rig.sensors
                and cid not in self.rig.sensors):
            self.drops.add(cid, "not_allowed")
            return None
        state = self.clients.get(cid)
        if isinstance(msg, RegisterDevice):
            if state is None:
                log.info("sensor %s (%s) registered from %s:%d", cid, msg.sensor_type, *item.source)
            else:
                log.info("sensor %s re-registered from %s:%d", cid, *item.source)
        if state is None:
            state = ClientState(cid, getattr(msg, "sensor_type", "unknown"), item.source, now,
                                self._offsets.setdefault(cid, OffsetEstimator()))
            self.clients[cid] = state
            if not isinstance(msg, RegisterDevice):
                log.info("sensor %s sending from %s:%d without /registerDevice; accepted",
                         cid, *item.source)
            self.set_transform(state)
        elif not state.active:
            log.info("sensor %s is back after %.1f s of silence", cid, now - state.last_seen)
            state.active = True
        if isinstance(msg, RegisterDevice):
            state.type, state.source = msg.sensor_type, item.source
        state.last_seen = max(state.last_seen, now)
        return state

    def set_transform(self, state: ClientState) -> None:
        if self.reference is None:
            self.reference = state.id
            log.info("sensor %s is the reference: its space is stage space", state.id)
        state.transform = (self.rig.stage_frame.copy() if state.id == self.reference
                           else self.rig.transform_for(state.id))

    def timeouts(self, now: float) -> None:
        """Clients silent for ``timeout_s`` lose their users; so do users a client forgot."""
        timeout = self.rig.clients.timeout_s
        for client in self.clients.values():
            if client.active and now - client.last_seen > timeout:
                client.active = False
                n = len(client.tracks)
                log.warning("sensor %s silent for %.1f s%s", client.id, now - client.last_seen,
                            f": lost its {n} user(s)" if n else "")
                for track in client.tracks.values():
                    self._drop_track(track, now)
                client.tracks.clear()
            for user, track in list(client.tracks.items()):
                if track.t != float("-inf") and now - track.t > timeout:
                    del client.tracks[user]  # the client is alive but forgot /lostUser
                    self._drop_track(track, now)
