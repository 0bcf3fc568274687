"""The client registry: which sensors (clients) the engine knows, and the reference among them.

A ``ClientState`` is one sensor client as the engine sees it: the address it
is bound to, when it was last heard, its users' tracks, its clock and the
transform into stage space in use. ``ClientRegistry`` finds or creates the
state for each inbound message, and is where the rules of docs/security.md
about clients live:

- an id is bound to the host it sends from, and its skeletons to the one
  socket (host and port) it streams them from; the same id from elsewhere
  is dropped (``wrong_source``) unless it re-registers (from an allowed
  address) or has gone silent; a rig may pin a sensor to an address or
  network instead (``sensors: {id: {address: ...}}``);
- the table is capped (``limits.max_clients``): a new id evicts the
  longest-silent client the rig does not list, and is refused
  (``too_many_clients``) when every client is listed or live;
- the reference is the rig's, or, with none, the first sensor that sends a
  valid skeleton for ``clients.reference_after_s``; a reference chosen at
  run time that goes silent before anything is calibrated against it is
  replaced, so a stray client cannot keep the stage dark;
- a client's clock (``ClientClock``): timetags far from our wall clock are
  refused (``bad_time``), a clock going back is a restart (its users are
  dropped at once, not frozen as late), and a client sending faster than
  real time (a replay at speed) keeps its own time line.

The engine thread owns every object here.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Callable

import numpy as np

from ..joints import TORSO
from ..rig import Rig
from ..sensors.kinds import HAND_READING_FRAMES
from ..sensors.protocol import Inbound, JointCoordinates, Message, RegisterDevice
from ..stats import DropCounter
from .hands import CadenceWatch, reading_frames
from .tracking import OffsetEstimator, Track

log = logging.getLogger("stage.engine")
def _two_torso_joints(conf: np.ndarray) -> bool:
    """Whether at least two torso joints have a confidence above 0 (a Python loop that stops
    at the second: a tenth of the numpy indexing's cost on 25 joints)."""
    found = False
    for j in TORSO:
        if conf[j] > 0:
            if found:
                return True
            found = True
    return False


def _level(msg: Message) -> int:
    """How much ``ClientRegistry._may_send`` asks of a message's source, by kind: a
    registration the least, a skeleton the most (bound to its socket), anything else the host."""
    return 2 if isinstance(msg, JointCoordinates) else 0 if isinstance(msg, RegisterDevice) else 1


#: a time line this far ahead of arrival is a client sending faster than real time
FAST_LEAD_S = 0.5
#: a client's tag jumping this much further than the time that passed is a new time line
STEP_S = 1.0
#: how fast (s per s) a client's offset follows its windowed minimum: fast enough for
#: clock drift and a first datagram that came late, slow enough that a replay sent at
#: 1.05x real time or faster keeps its own time line instead of being squeezed into ours
SLEW = 0.05


class ClientClock:
    """Maps one client's timetags (its clock, Unix seconds) onto the engine clock.

    ``offset`` (engine - client) is set when the client's time line starts
    (its first timetag, a restart, a jump) and then follows the windowed
    minimum of ``arrival - timetag`` (``OffsetEstimator``) at most ``SLEW``
    seconds per second. A capture time is ``timetag + offset``.
    """

    __slots__ = ("estimator", "offset", "last_tag", "last_arrival", "latest")

    def __init__(self) -> None:
        self.estimator = OffsetEstimator()
        self.offset: float | None = None
        self.last_tag = float("-inf")
        self.last_arrival = float("-inf")
        self.latest = float("-inf")     # the latest capture time given (engine clock)

    def anchor(self, arrival: float, tag: float, base: float | None = None) -> None:
        """Start a time line: this tag is captured at ``base`` (default: its arrival)."""
        self.estimator = OffsetEstimator()
        self.estimator.update(arrival, tag)
        self.offset = (arrival if base is None else base) - tag
        self.last_tag, self.last_arrival = tag, arrival

    def follow(self, arrival: float, tag: float) -> None:
        target = self.estimator.update(arrival, tag)
        assert self.offset is not None
        step = SLEW * max(arrival - self.last_arrival, 0.0)
        self.offset += min(max(target - self.offset, -step), step)
        self.last_tag = max(self.last_tag, tag)
        self.last_arrival = max(self.last_arrival, arrival)

    def capture(self, tag: float, arrival: float) -> float:
        assert self.offset is not None
        t = tag + self.offset
        self.latest = max(self.latest, t)
        return t

    def lead(self, arrival: float) -> float:
        """How far ahead of ``arrival`` this client's time line runs now."""
        if self.latest == float("-inf"):
            return 0.0
        return self.latest + (arrival - self.last_arrival) - arrival


class ClientState:
    def __init__(self, client: str, sensor_type: str, source: tuple[str, int], now: float,
                 offset: ClientClock) -> None:
        self.id, self.type, self.source = client, sensor_type, source
        self.registered = now
        self.last_seen = now
        self.frames = 0
        self.tracks: dict[int, Track] = {}
        self.offset = offset              # the client's clock (``offset.offset``: engine - client)
        self.transform: np.ndarray | None = None
        self.warned_uncalibrated = False
        self.floor: np.ndarray | None = None
        self.active = True
        self.skeleton_since: float | None = None  # valid skeletons since (reference election)
        self.skeletons = 0
        self.streamed = 0                 # /jointCoordinates accepted from it
        self.frame_source: tuple[str, int] | None = None  # the socket its skeletons come from
        self.restarts = 0
        #: the frames its hand-state readings last (``hands.reading_frames``; set by the
        #: registry from the rig and its type): each report is 1 / this of a reading
        self.hand_frames = 2
        #: no rig key and a type of unknown cadence: ``hand_frames`` is a guess its own hand
        #: states may correct (``Engine._hand_cadence``)
        self.hand_frames_guessed = False
        #: whether its hand states change as that cadence says (it stops once decided)
        self.hand_watch = CadenceWatch()

    def new_track(self, user: int) -> Track:
        """A new view of user ``user`` (replacing any it had)."""
        track = self.tracks[user] = Track(self.id, user, hand_step=1.0 / self.hand_frames)
        return track

    def set_hand_frames(self, frames: int) -> None:
        """Its reports count as 1 / ``frames`` of a hand-state reading from now on, its users'
        tracks' too."""
        self.hand_frames = frames
        for track in self.tracks.values():
            track.hand_step = 1.0 / frames


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
        self.reference = rig.reference
        #: the reference was chosen at run time (may be replaced while nothing depends on it)
        self.elected = False
        self.evicted = 0
        # clocks of clients first seen in the batch being sorted (process() computes capture
        # times before it applies anything); handed to the state when it is created
        self._new_clocks: dict[str, ClientClock] = {}
        # engine clock -> wall clock, to judge timetags against the real time
        self.wall_minus_clock: float | None = None

    # ------------------------------------------------------------ time
    def capture_times(self, batch: list[Inbound]) -> list[float | None]:
        """Each item's capture time on the engine clock (None: refused, counted as
        ``bad_time``; an item without a timetag or a client: its arrival), worked out once
        for a bundle's messages.

        The messages of one bundle share its timetag, arrival and source: a second call
        with the same inputs gives the same time and leaves the clock as it was (the offset
        estimator keeps one entry per value, and the offset moves only with time passing),
        so a message takes the time of the one before it when they share all of these and
        its kind is allowed to speak where the one before was (``_may_send``: a
        ``/registerDevice`` asks the least, a skeleton the most). Nothing is applied while
        this runs, so no client's state changes in between."""
        out: list[float | None] = []
        last: tuple | None = None         # (timetag, arrival, source, client, level, time)
        for item in batch:
            msg = item.message
            client = getattr(msg, "client", None)
            tag = item.timetag
            if tag is None or client is None:
                out.append(item.arrival)
                continue
            level = _level(msg)
            if (last is not None and tag == last[0] and item.arrival == last[1]
                    and item.source == last[2] and client == last[3] and level <= last[4]):
                out.append(last[5])
                continue
            t, passed = self._capture(item, msg, client)
            out.append(t)
            # a time refused (None) or not from the clock (level -1) is not shared
            last = (tag, item.arrival, item.source, client, passed, t)
        return out

    def _capture(self, item: Inbound, msg: Message, client: str) -> tuple[float | None, int]:
        """(the capture time of a timetagged client message, the strictest kind of message
        (``_level``) the time holds for from this source: 2 for a new client, whose messages
        are not checked here; -1: not a time from the client's clock)."""
        tag, arrival = item.timetag, item.arrival
        assert tag is not None
        if self.wall_minus_clock is not None and (
                abs(tag - (arrival + self.wall_minus_clock)) > self.rig.clients.max_clock_skew_s):
            self.drops.add(client, "bad_time")
            return None, -1
        state = self.clients.get(client)
        if state is not None and not self._may_send(state, msg, item):
            # dropped as wrong_source when applied; the clock is untouched
            return item.arrival, -1
        passed = 2 if state is None else _level(msg)
        clock = state.offset if state is not None else self._new_clocks.get(client)
        if clock is None:
            if len(self._new_clocks) >= 1024:
                self._new_clocks.clear()
            clock = self._new_clocks[client] = ClientClock()
        if clock.offset is None:
            self._anchor(clock, client, arrival, tag)
        elif tag < clock.last_tag - self.rig.clients.restart_back_s:
            back = clock.last_tag - tag
            self._anchor(clock, client, arrival, tag)
            if state is not None:
                self._restart(state, arrival, f"its clock went back {back:.2f} s")
        elif (tag - clock.last_tag) - (arrival - clock.last_arrival) > STEP_S:
            self._anchor(clock, client, arrival, tag)  # its clock jumped ahead: a new time line
        else:
            clock.follow(arrival, tag)
        return clock.capture(tag, arrival), passed

    def _anchor(self, clock: ClientClock, client: str, arrival: float, tag: float) -> None:
        """Start a client's time line at its arrival, or on the running time line of clients
        sending faster than real time (a replay at speed), so they stay together."""
        horizon, offsets = float("-inf"), []
        for other in self.clients.values():
            if other.id == client or not other.active or other.offset.offset is None:
                continue
            lead = other.offset.lead(arrival)
            if lead > FAST_LEAD_S:
                horizon = max(horizon, arrival + lead)
                offsets.append(other.offset.offset)
        if horizon == float("-inf"):
            clock.anchor(arrival, tag)
            return
        for offset in offsets:  # one recording's clients share one clock: join it exactly
            if abs(tag + offset - horizon) <= FAST_LEAD_S:
                clock.anchor(arrival, tag, tag + offset)
                return
        clock.anchor(arrival, tag, horizon)

    def _restart(self, state: ClientState, now: float, why: str) -> None:
        state.restarts += 1
        n = len(state.tracks)
        log.warning("sensor %s restarted (%s)%s", state.id, why,
                    f": its {n} user(s) are dropped" if n else "")
        for track in state.tracks.values():
            self._drop_track(track, now)
        state.tracks.clear()

    # ------------------------------------------------------------ clients
    def _may_send(self, state: ClientState, msg: Message, item: Inbound) -> bool:
        """Whether ``item`` may speak for the client ``state`` (its address binding)."""
        config = self.rig.sensors.get(state.id)
        if config is not None and config.address is not None:
            return config.address.allows(item.source[0])
        if isinstance(msg, RegisterDevice) or not state.active:
            return True
        if item.source[0] != state.source[0]:
            return False  # another host
        # skeletons come from one socket (oscsend-style tools may send other messages from
        # a new port each time, so those are bound to the host only)
        return (not isinstance(msg, JointCoordinates) or state.frame_source is None
                or item.source == state.frame_source)

    def client(self, msg: Message, item: Inbound) -> ClientState | None:
        cid = msg.client  # type: ignore[union-attr]
        now = item.arrival
        if (not self.rig.allow_unknown_sensors and self.rig.sensors
                and cid not in self.rig.sensors):
            self.drops.add(cid, "not_allowed")
            return None
        state = self.clients.get(cid)
        if state is not None and not self._may_send(state, msg, item):
            self.drops.add(cid, "wrong_source")
            return None
        if state is None:
            config = self.rig.sensors.get(cid)
            if config is not None and config.address is not None and not config.address.allows(
                    item.source[0]):
                self.drops.add(cid, "wrong_source")
                return None
            if len(self.clients) >= self.rig.limits.max_clients and not self._evict(now):
                self.drops.add(cid, "too_many_clients")
                return None
            clock = self._new_clocks.pop(cid, None) or ClientClock()
            state = ClientState(cid, getattr(msg, "sensor_type", "unknown"), item.source, now,
                                clock)
            self.clients[cid] = state
            self._hand_frames(state)
            self.drops.keep(cid)
            if isinstance(msg, RegisterDevice):
                log.info("sensor %s (%s) registered from %s:%d", cid, msg.sensor_type,
                         *item.source)
            else:
                log.info("sensor %s sending from %s:%d without /registerDevice; accepted",
                         cid, *item.source)
            self.set_transform(state)
        else:
            if isinstance(msg, RegisterDevice):
                log.info("sensor %s re-registered from %s:%d", cid, *item.source)
            if not state.active:
                log.info("sensor %s is back after %.1f s of silence", cid, now - state.last_seen)
                state.active = True
                state.frame_source = None
            if item.source[0] != state.source[0]:
                log.warning("sensor %s now sends from %s:%d (was %s:%d)", cid, *item.source,
                            *state.source)
            state.source = item.source
        if isinstance(msg, RegisterDevice):
            if msg.sensor_type != state.type:
                state.type = msg.sensor_type
                self._hand_frames(state)
                state.hand_watch = CadenceWatch()     # watch it anew
            state.frame_source = None  # its next skeleton binds its socket afresh
        state.last_seen = max(state.last_seen, now)
        if isinstance(msg, JointCoordinates):
            state.streamed += 1
            state.frame_source = item.source
            self._skeleton(state, msg, now)
        return state

    def _evict(self, now: float) -> bool:
        """Forget one client to make room: silent first, then ones that never sent a
        skeleton, longest silent first; never the rig's sensors or the reference."""
        candidates = [c for c in self.clients.values()
                      if c.id not in self.rig.sensors and c.id != self.reference]
        if not candidates:
            return False
        victim = min(candidates, key=lambda c: (c.active, c.skeletons > 0, c.last_seen))
        if victim.active and victim.skeletons > 0:
            return False  # every one is a live sensor: the newcomer waits
        for track in victim.tracks.values():
            self._drop_track(track, now)
        del self.clients[victim.id]
        self.drops.forget(victim.id)
        self.evicted += 1
        log.debug("sensor %s forgotten to make room (%d clients)", victim.id, len(self.clients))
        return True

    def _skeleton(self, state: ClientState, msg: JointCoordinates, now: float) -> None:
        if not _two_torso_joints(msg.conf):
            return  # not a person's skeleton: does not count towards the reference
        state.skeletons += 1
        if state.skeleton_since is None:
            state.skeleton_since = now
        if self.reference is None and (now - state.skeleton_since
                                       >= self.rig.clients.reference_after_s):
            self.reference, self.elected = state.id, True
            log.info("sensor %s is the reference: its space is stage space", state.id)
            state.transform = self.rig.stage_frame.copy()
            state.warned_uncalibrated = False

    def _hand_frames(self, state: ClientState) -> None:
        """How many frames its hand-state readings last, from the rig and its type (the type
        it registered with; the rig's for it when it did not say)."""
        config = self.rig.sensors.get(state.id)
        kind = state.type if state.type != "unknown" or config is None else config.type
        setting = None if config is None else config.hand_reading_frames
        frames = reading_frames(kind, setting, self.rig.fusion.hand_reading_frames)
        state.hand_frames_guessed = (setting is None and self.rig.fusion.hand_reading_frames
                                     is None and kind not in HAND_READING_FRAMES)
        if frames != state.hand_frames:
            log.info("sensor %s (%s): a hand-state reading lasts %d frame%s", state.id,
                     state.type, frames, "" if frames == 1 else "s")
        state.set_hand_frames(frames)

    def set_transform(self, state: ClientState) -> None:
        state.transform = (self.rig.stage_frame.copy() if state.id == self.reference
                           else self.rig.transform_for(state.id))

    def may_persist(self, sensor: str) -> bool:
        """Whether a calibration of ``sensor`` may be written into the rig file: the rig's
        id allow-list (its data passed the address allow-list when it arrived)."""
        if sensor in self.rig.sensors or sensor == self.reference:
            return True
        return self.rig.allow_unknown_sensors

    # ------------------------------------------------------------ time passing
    def timeouts(self, now: float) -> None:
        """Clients silent for ``timeout_s`` lose their users; so do users a client forgot."""
        timeout = self.rig.clients.timeout_s
        self._new_clocks.clear()
        for client in self.clients.values():
            if client.active and now - client.last_seen > timeout:
                client.active = False
                client.skeleton_since = None
                n = len(client.tracks)
                log.warning("sensor %s silent for %.1f s%s", client.id, now - client.last_seen,
                            f": lost its {n} user(s)" if n else "")
                for track in client.tracks.values():
                    self._drop_track(track, now)
                client.tracks.clear()
                if client.id == self.reference:
                    self._reference_silent(client)
            stale = [user for user, track in client.tracks.items()
                     if now - track.t > timeout and track.t != -math.inf]
            for user in stale:
                track = client.tracks.pop(user)  # the client is alive but forgot /lostUser
                self._drop_track(track, now)

    def _reference_silent(self, client: ClientState) -> None:
        """A reference chosen at run time went silent: if nothing was calibrated against it
        (nothing in the rig depends on it), the next sensor with a skeleton takes over."""
        if not self.elected or self.rig.reference == client.id:
            return
        if any(cfg.calibration is not None for sid, cfg in self.rig.sensors.items()
               if sid != client.id):
            return
        if any(c.transform is not None for c in self.clients.values() if c.id != client.id):
            return  # a calibration is in use against it (live, not saved yet)
        log.warning("reference sensor %s went silent before anything was calibrated against it: "
                    "the next sensor sending a skeleton becomes the reference", client.id)
        self.reference, self.elected = None, False
        client.transform = None
        for other in self.clients.values():
            if other.active and other.skeleton_since is not None:
                other.skeleton_since = None  # a fresh claim: it must send skeletons again


def wall_minus_clock(clock_now: float) -> float:
    """Add to an engine time to get Unix time (for judging timetags)."""
    return time.time() - clock_now
