"""The engine: one thread that owns all live state.

Input is a stream of ``Inbound`` items (decoded sensor messages with their
arrival and capture times); output is Server-to-View datagrams handed to a
``Transport`` and ``FusedFrame`` objects handed to in-process listeners.
Time comes from an injected clock, so tests and replays run with no sleeps.

Per batch of inbound items, in capture-time order:
  sensor frame -> calibration transform -> track update -> association to a
  person (``tracking``) -> confidence-weighted average with outlier rejection
  (``fusion``) -> Kalman smoothing (``kalman``) -> (end of batch) emission to
  views (``output``) and in-process listeners.

Ownership: everything here, the rig included, belongs to the engine thread.
Other threads change it only through ``call_soon`` (a calibration result,
an operator's command) or the copy-on-write callback lists; the rig is
changed and saved by ``apply_calibration`` on this thread.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..clock import Clock, MonotonicClock
from ..frames import Body, FusedFrame, SensorFrame
from .fusion import apply_transform, fuse_joints, torso_centre, vote_hand
from ..joints import TORSO
from ..rig import Rig, store_stage_transform
from ..sensors.protocol import (FloorPlane, HandStateMsg, HealthQuery, Inbound, JointCoordinates,
                                LostUser, NewUser, RegisterView, StatsQuery, ViewUnreachable,
                                decode_datagram)
from ..stats import DropCounter, LatencyWindow, format_drops
from .callbacks import Callbacks
from .output import Transport, ViewOutput, encode_stats
from .rigstore import RigStore
from .clients import ClientRegistry, ClientState
from .tracking import Person, Track, Tracker

log = logging.getLogger("stage.engine")
_TORSO = np.array(TORSO)

#: seconds between the engine thread's ticks (timeouts, expiry, merging); offline
#: runs tick on the same grid so they give what a live run gives
TICK_S = 0.02


@dataclass(slots=True)
class Call:
    """A function to run on the engine thread (see ``Engine.call_soon``)."""

    fn: Callable[["Engine"], None]


class Engine:
    """Kuatro's server core. Call ``process`` and ``tick`` from one thread only."""

    def __init__(self, rig: Rig | None = None, clock: Clock | None = None,
                 transport: Transport | None = None, drops: DropCounter | None = None) -> None:
        self.rig = rig or Rig()
        self.clock = clock or MonotonicClock()
        self.drops = drops or DropCounter(self.rig.limits.max_drop_keys)
        self.queue: queue.Queue[Inbound] = queue.Queue(maxsize=8192)
        #: the clients (sensors) by id, the reference sensor, the clients' clocks
        self.registry = ClientRegistry(self.rig, self.drops, self._drop_track)
        self.tracker = Tracker(self.rig.fusion, self.rig.smoothing)
        self.output = ViewOutput(transport, self.rig.views, self.rig.limits,
                                 self.rig.allow_views if transport is not None else None,
                                 self.drops)
        #: called on the engine thread with every fused frame (copy-on-write: add and
        #: remove from any thread)
        self.listeners = Callbacks("listener")
        #: called on the engine thread with every valid sensor frame, calibrated or not
        self.frame_observers = Callbacks("frame observer")
        #: writes the rig file off the engine thread (see ``apply_calibration``)
        self.rig_store = RigStore()
        self.latency = LatencyWindow()
        #: seconds the engine spent on each batch (health: frame time p99)
        self.batch_time = LatencyWindow(1024)
        #: the app's health messages for ``/stage/health`` (set by the app; engine thread)
        self.health_messages: Callable[[], list[bytes]] | None = None
        self.counts = {"messages": 0, "frames": 0, "fused_frames": 0}
        self._stats_replies: list[tuple[str, int]] = []
        self._health_replies: list[tuple[str, int]] = []
        #: per sensor, what calibration says of it (e.g. {"fitness": 0.97, "state": "ok"});
        #: written on the engine thread (via call_soon), shown in stats and monitors
        self.sensor_notes: dict[str, dict] = {}
        # engine clock -> wall clock, to report client clocks against ours in seconds
        self._wall_minus_clock = time.time() - self.clock.now()
        if isinstance(self.clock, MonotonicClock):  # live: timetags can be judged against it
            self.registry.wall_minus_clock = self._wall_minus_clock
        # person id -> arrival of the earliest frame whose fusion is not emitted yet
        self._dirty: dict[int, float] = {}
        self._hands_dirty: set[int] = set()  # persons whose hand vote may have changed
        # person id -> (capture, arrival) of a frame that came too soon after the last
        # fusion: it is averaged into the next one (see FusionSettings.min_interval_s)
        self._pending: dict[int, tuple[float, float]] = {}
        self._lost: list[int] = []
        self._started = self.clock.now()
        self._last_tick = self._started
        self._last_drop_report = self._started

    @property
    def clients(self) -> dict[str, ClientState]:
        """Known clients by id (the registry's; engine thread only)."""
        return self.registry.clients

    @property
    def reference(self) -> str | None:
        """The reference sensor: its space is stage space (None until one is chosen)."""
        return self.registry.reference

    @property
    def persons(self) -> dict[int, Person]:
        """Fused persons by id (the tracker's; engine thread only)."""
        return self.tracker.persons

    @property
    def views(self) -> list[tuple[str, int]]:
        """Registered Server-to-View addresses (engine thread only)."""
        return self.output.views

    def add_view(self, address: tuple[str, int]) -> None:
        """Send fused bodies to ``address`` too (before start, or on the engine thread)."""
        self.output.add_static(address)

    # ------------------------------------------------------------ input
    def submit(self, item: Inbound) -> bool:
        """Thread-safe enqueue from a receiver; a full queue counts a drop."""
        try:
            self.queue.put_nowait(item)
            return True
        except queue.Full:
            self.drops.add(_client_key(item), "queue_full")
            return False

    def call_soon(self, fn: Callable[["Engine"], None]) -> None:
        """Run ``fn(engine)`` on the engine thread, in order with the data (thread-safe).

        The only way another thread (a calibration worker, a UI) may change
        engine state. In-process users call ``drain()`` to run what is queued.
        """
        self.queue.put(Inbound(Call(fn), self.clock.now(), ("engine", 0)), timeout=1.0)  # type: ignore[arg-type]

    def drain(self) -> None:
        """Process everything queued so far, on the calling thread (tests, offline replay)."""
        batch = self._take([])
        if batch:
            self.process(batch)

    def _take(self, batch: list[Inbound], limit: int | None = None) -> list[Inbound]:
        """``batch`` with what is queued now appended, up to ``limit`` items in all."""
        while limit is None or len(batch) < limit:
            try:
                batch.append(self.queue.get_nowait())
            except queue.Empty:
                break
        return batch

    def handle_datagram(self, data: bytes, source: tuple[str, int] = ("127.0.0.1", 0),
                        arrival: float | None = None) -> None:
        """Decode one datagram and process it now (in-process use: tests, replay)."""
        arrival = self.clock.now() if arrival is None else arrival
        decoded = decode_datagram(data, f"{source[0]}:{source[1]}")
        for client, reason in decoded.drops:
            self.drops.add(client, reason)
        self.process([Inbound(m, arrival, source, tt) for m, tt in decoded.messages])

    def process(self, batch: list[Inbound]) -> None:
        """Apply a batch of inbound items in capture-time order, then emit once."""
        started = time.perf_counter()
        timed = []
        for k, item in enumerate(batch):
            t = self.registry.capture_time(item)
            if t is not None:  # None: a timetag far from the real time (counted: bad_time)
                timed.append((t, k, item))
        timed.sort(key=lambda e: (e[0], e[1]))
        for t, _, item in timed:
            self.counts["messages"] += 1
            try:
                self._apply(item, t)
            except Exception:  # a bug must not end the show: log it, drop the item
                log.exception("error while handling %s; item dropped", type(item.message).__name__)
                self.drops.add(_client_key(item), "internal_error")
        self._emit()
        if self._stats_replies:
            # one datagram whatever the stats hold; only to addresses views may be at
            reply = encode_stats(self.stats(), self.rig.limits.stats_reply_bytes)
            for address in self._stats_replies:
                self.output.send(reply, address)
            self._stats_replies.clear()
        if self._health_replies:
            messages = self.health_messages() if self.health_messages is not None else []
            for address in self._health_replies:
                for data in messages:
                    self.output.send(data, address)
            self._health_replies.clear()
        self.batch_time.add(time.perf_counter() - started)

    def _apply(self, item: Inbound, t: float) -> None:
        msg = item.message
        if isinstance(msg, Call):
            msg.fn(self)
            return
        if isinstance(msg, RegisterView):
            self.output.register(msg, ((pid, p.centre, (p.hands[0], p.hands[1]))
                                       for pid, p in self.persons.items()
                                       if p.announced and p.centre is not None),
                                 item.arrival, f"{item.source[0]}:{item.source[1]}")
            return
        if isinstance(msg, (StatsQuery, HealthQuery)):
            # answered after this batch's emission, so a reply never overtakes
            # the fused output of frames that arrived before the query; replies go only
            # to the asker's own address, and only where views may be
            if not self.output.allowed(item.source[0]):
                self.drops.add(f"{item.source[0]}:{item.source[1]}", "not_allowed")
                return
            replies = self._stats_replies if isinstance(msg, StatsQuery) else self._health_replies
            if len(replies) < 64:
                replies.append((item.source[0], msg.reply_port or item.source[1]))
            return
        if isinstance(msg, ViewUnreachable):
            self.output.unreachable(msg.host, msg.port)
            return
        client = self.registry.client(msg, item)
        if client is None:
            return
        if isinstance(msg, JointCoordinates):
            stamp = item.arrival if item.timetag is None else item.timetag
            self._on_frame(client, msg, t, item.arrival, stamp)
        elif isinstance(msg, HandStateMsg):
            track = client.tracks.get(msg.user)
            if track is None:
                track = client.tracks[msg.user] = Track(client.id, msg.user)
            track.hands[msg.hand] = msg.state
            if track.person is not None:
                self._hands_dirty.add(track.person)
        elif isinstance(msg, FloorPlane):
            client.floor = msg.plane
        elif isinstance(msg, NewUser):
            old = client.tracks.pop(msg.user, None)
            if old is not None:
                self._drop_track(old, t)
            client.tracks[msg.user] = Track(client.id, msg.user)
        elif isinstance(msg, LostUser):
            track = client.tracks.pop(msg.user, None)
            if track is not None:
                self._drop_track(track, t)

    def set_calibration(self, client: str, matrix: np.ndarray | None) -> None:
        """Use a new sensor->stage transform from now on (None: leave the sensor out)."""
        state = self.clients.get(client)
        if state is None:
            return
        state.transform = None if matrix is None else np.asarray(matrix, dtype=float)
        state.warned_uncalibrated = False
        now = self.clock.now()
        for track in state.tracks.values():  # views in the old space must not linger in fusion
            if track.person is not None:
                self._drop_track(track, now)
            track.t = track.stamp = float("-inf")

    def record_calibration(self, sensor: str, to_stage: np.ndarray, method: str,
                           fitness: float | None, rms_m: float | None, path: str | None = None,
                           wait: bool = False) -> None:
        """Engine thread: write a sensor's new sensor -> stage calibration into the rig.

        The transform in use is set separately (``set_calibration``); this
        keeps the rig, which views and status read on this thread, in step,
        and with ``path`` saves it (atomically, by the writer thread of
        ``rig_store``; ``wait``: until it is on disk).
        """
        if not self.registry.may_persist(sensor):
            log.warning("%s's calibration is in use but not written into the rig: it is not an "
                        "allowed sensor", sensor)
            return
        store_stage_transform(self.rig, sensor, to_stage, self.reference, method, fitness, rms_m)
        if self.reference is not None:
            self.registry.elected = False  # the rig now depends on it: it stays the reference
        if path is not None:
            self.rig_store.save(self.rig, path, f"{sensor}'s calibration")
            if wait:
                self.rig_store.flush()

    # ------------------------------------------------------------ fusion
    def _on_frame(self, client: ClientState, msg: JointCoordinates, t: float,
                  arrival: float, stamp: float) -> None:
        client.frames += 1
        self.counts["frames"] += 1
        if self.frame_observers:
            self.frame_observers.call(SensorFrame(client.id, msg.user, t, msg.joints, msg.conf,
                                                  client.transform, client.floor))
        if client.transform is None:
            if not client.warned_uncalibrated:
                log.warning("sensor %s has no calibration in use: its frames are not fused "
                            "until it is calibrated", client.id)
                client.warned_uncalibrated = True
            return
        track = client.tracks.get(msg.user)
        if track is None:
            track = client.tracks[msg.user] = Track(client.id, msg.user)
        # "late" is judged on the client's own clock: the offset estimate only
        # improves (decreases) over time, so engine-clock capture times of two
        # frames can cross even though the client sent them in order
        if stamp <= track.stamp:
            self.drops.add(client.id, "late")
            return
        track.stamp = stamp
        t = max(t, track.t)
        track.joints = apply_transform(client.transform, msg.joints)
        track.conf = msg.conf
        track.t = t
        if not (track.conf > 0).any():
            return  # nothing tracked in this frame: no position to associate or fuse
        person = self.tracker.associate(track, t)
        # Fuse at most once per min_interval_s per person. Every fusion averages the
        # latest view of every sensor (older ones moved forward by the filter's
        # velocity), so a frame that arrives sooner is not lost: it joins the next
        # fusion. Re-fusing on each of S sensors' frames would feed the Kalman filter
        # the same views S times a frame period as if independent, and cost S times
        # the work for output no view needs faster than the sensors' 30 Hz.
        if t - person.t >= self.rig.fusion.min_interval_s:
            self._fuse(person, t)
            self._pending.pop(person.id, None)
            self._dirty.setdefault(person.id, arrival)
        else:
            self._pending.setdefault(person.id, (t, arrival))

    def _drop_track(self, track: Track, t: float) -> None:
        pid = self.tracker.unbind(track, t)
        if pid is not None:
            self._hands_dirty.add(pid)  # one voter fewer

    def _fuse(self, person: Person, t: float) -> None:
        fs = self.rig.fusion
        # sorted: a set's order follows memory addresses, and the float sums of the
        # average must not, or a replay would differ from its live run in the last bit
        views = sorted((tr for tr in person.tracks if t - tr.t <= fs.stale_s),
                       key=lambda tr: tr.key)
        if not views:
            return
        velocity = person.velocity if person.kalman.initialised.any() else None
        positions = np.stack([tr.joints if velocity is None or tr.t >= t
                              else tr.joints + velocity * (t - tr.t) for tr in views])
        conf = np.stack([tr.conf for tr in views])
        fused, weight, used = fuse_joints(positions, conf, fs.outlier_m)
        seen = weight > 0
        if self.rig.smoothing_enabled:
            smoothed = person.kalman.step(t, fused, weight)
            # never-measured joints have NaN velocity; they must not poison compensation
            person.velocity = np.nan_to_num(person.kalman.velocities)
        else:
            smoothed = fused
        person.joints = np.where(seen[:, None], smoothed, person.joints)
        person.conf = np.minimum(np.where(used, conf, 0.0).max(axis=0), 1.0)
        person.known |= seen
        # the centre uses every torso joint ever seen, not just this frame's, so it
        # does not jump when occlusion changes which joints a view reports
        torso = person.known[_TORSO]
        person.centre = (person.joints[_TORSO][torso].mean(axis=0) if torso.any()
                         else torso_centre(person.joints, person.known.astype(float)))
        person.t = max(person.t, t)
        self.counts["fused_frames"] += 1

    def _vote_hands(self, person: Person, now: float) -> None:
        views = sorted((tr for tr in person.tracks if now - tr.t <= 1.0), key=lambda tr: tr.key)
        weighted = self.rig.fusion.hand_vote == "confidence"
        for hand, joint in ((0, 7), (1, 11)):  # HandLeft, HandRight
            states = [tr.hands[hand] for tr in views]
            weights = [float(tr.conf[joint]) for tr in views] if weighted else None
            person.hands[hand] = vote_hand(states, weights)

    # ------------------------------------------------------------ output
    def _emit(self) -> None:
        if not self._dirty and not self._lost and not self._hands_dirty:
            return
        now = self.clock.now()
        new: list[int] = []
        updated: list[int] = []
        for pid in self._hands_dirty - self._dirty.keys():
            # a hand message alone re-sends no joints: only a changed vote goes out
            person = self.persons.get(pid)
            if person is None or not person.announced:
                continue
            self._vote_hands(person, now)
            if self._send_hands(person):
                updated.append(pid)
        for pid, arrival in self._dirty.items():
            person = self.persons.get(pid)
            if person is None or person.centre is None:
                continue
            if not person.announced:
                person.announced = True
                new.append(pid)
                log.info("person %d found (seen by %s)", pid, ", ".join(person.sensors()))
                self.output.new_user(pid, person.centre)
            self._vote_hands(person, now)
            if person.tracks:
                self.output.joints(pid, person.joints, person.conf)
            self._send_hands(person)
            updated.append(pid)
            self.latency.add(self.clock.now() - arrival)
        lost = self._lost
        for pid in lost:
            self.output.lost_user(pid)
        self._dirty, self._lost = {}, []
        self._hands_dirty.clear()
        if self.listeners and (updated or lost):
            self.listeners.call(FusedFrame(now, self.bodies(), tuple(updated), tuple(new),
                                           tuple(lost)))

    def _send_hands(self, person: Person) -> bool:
        changed = False
        for hand in (0, 1):
            if person.hands[hand] != person.sent_hands[hand]:
                person.sent_hands[hand] = person.hands[hand]
                self.output.hand(person.id, hand, person.hands[hand])
                changed = True
        return changed

    def bodies(self) -> dict[int, Body]:
        return {pid: Body(pid, p.joints.copy(), p.conf.copy(), p.velocity.copy(),
                          (p.hands[0], p.hands[1]), p.centre.copy(), p.sensors())
                for pid, p in self.persons.items() if p.announced and p.centre is not None}

    # ------------------------------------------------------------ housekeeping
    def tick(self, now: float | None = None) -> None:
        """Timeouts, person expiry and merging, the per-minute drop report."""
        now = self.clock.now() if now is None else now
        self._last_tick = now
        self.registry.timeouts(now)
        self.output.expire(now)
        self._flush_pending(now)
        self.tracker.merge_close(now)
        self._lost.extend(self.tracker.expire(now))
        if now - self._last_drop_report >= 60.0:
            self._last_drop_report = now
            recent = self.drops.since_last_report()
            if recent:
                log.warning("dropped in the last minute: %s", format_drops(recent))
        self._emit()

    def _flush_pending(self, now: float) -> None:
        """Fuse frames that waited for a next fusion that did not come (a stream stopped)."""
        wait = max(2.0 * self.rig.fusion.min_interval_s, 0.05)
        for pid, (t, arrival) in list(self._pending.items()):
            person = self.persons.get(pid)
            if person is None or not person.tracks:
                del self._pending[pid]
            elif now - arrival >= wait:
                del self._pending[pid]
                self._fuse(person, max(tr.t for tr in person.tracks))
                self._dirty.setdefault(pid, arrival)

    # ------------------------------------------------------------ thread
    def run(self, stop: threading.Event, tick_s: float = TICK_S) -> None:
        """The engine thread: drain the queue in batches, tick between them."""
        while not stop.is_set():
            try:
                batch = self._take([self.queue.get(timeout=tick_s)], limit=512)
            except queue.Empty:
                batch = []
            if batch:
                self.process(batch)
            now = self.clock.now()
            if now - self._last_tick >= tick_s:
                self.tick(now)

    def stats(self) -> dict:
        now = self.clock.now()
        drops = self.drops.snapshot()
        return {
            "uptime_s": round(now - self._started, 3),
            "reference": self.reference,
            "clients": {cid: {"type": c.type, "source": f"{c.source[0]}:{c.source[1]}",
                              "active": c.active, "silent_s": round(now - c.last_seen, 3),
                              "frames": c.frames, "users": sorted(c.tracks),
                              "calibrated": c.transform is not None,
                              "clock_ahead_s": None if c.offset.offset is None else
                              round(-c.offset.offset - self._wall_minus_clock, 4),
                              "calibration": self.sensor_notes.get(cid, {}),
                              "restarts": c.restarts,
                              "drops": drops.get(cid, {})}
                        for cid, c in self.clients.items()},
            "persons": {pid: {"sensors": list(p.sensors()),
                              "position": None if p.centre is None else
                              [round(float(v), 4) for v in p.centre]}
                        for pid, p in self.persons.items() if p.announced},
            "views": [f"{h}:{p}" for h, p in self.views],
            "counts": {**self.counts, "datagrams_out": self.output.datagrams_out,
                       "send_errors": self.output.send_errors,
                       "views_expired": self.output.expired,
                       "views_unreachable": self.output.dropped_unreachable,
                       "clients_forgotten": self.registry.evicted},
            "drops": drops,
            "drops_total": sum(n for r in drops.values() for n in r.values()),
            "latency_ms": self.latency.summary_ms(),
        }


def _client_key(item: Inbound) -> str:
    client = getattr(item.message, "client", None)
    return client if client is not None else f"{item.source[0]}:{item.source[1]}"
