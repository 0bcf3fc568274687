"""The engine: one thread that owns all live state.

Input is a stream of ``Inbound`` items (decoded sensor messages with their
arrival and capture times); output is Server-to-View datagrams handed to a
``Transport`` and ``FusedFrame`` objects handed to in-process listeners.
Time comes from an injected clock, so tests and replays run with no sleeps.

Per batch of inbound items (the live thread hands over one datagram at a
time), in capture-time order:
  sensor frame -> calibration transform -> track update -> association to a
  person (``tracking``); at the end of the batch every frame is one
  measurement update of its person's filter (``fuser``, ``kalman``), all
  persons at once, and every updated person is sent to views (``output``) and
  in-process listeners (``people``). No frame waits for another.

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
from ..frames import Body, SensorFrame
from ..rig import Rig, store_stage_transform
from ..sensors.protocol import (FloorPlane, HandStateMsg, HealthQuery, Inbound, JointCoordinates,
                                LostUser, NewUser, RegisterView, StatsQuery, ViewUnreachable,
                                decode_datagram)
from ..stats import DropCounter, LatencyWindow, format_drops
from . import jit
from .callbacks import Callbacks
from .output import Transport, ViewOutput, encode_stats
from .people import People, fused_persons_stats
from .rigstore import RigStore
from .clients import ClientRegistry, ClientState
from .hands import CadenceWatch
from .tracking import Person, Track, Tracker

log = logging.getLogger("stage.engine")

#: seconds between the engine thread's ticks (timeouts, expiry, merging); offline
#: runs tick on the same grid so they give what a live run gives
TICK_S = 0.02
#: more datagrams than this waiting at once is a backlog: processed as one batch
BACKLOG_DATAGRAMS = 12


class _Prepared(list):
    """One datagram's messages as ``submit_batch`` queues them, with its sensor's frames
    already computed in stage space on the receiver's thread (``Engine._prepared``): the
    frames, the transform and settings they were computed with, the kernel's results."""

    __slots__ = ("frames", "transform", "settings", "out")

    def holds(self, frames: list) -> bool:
        """Whether these are results for ``frames``, the very messages (a backlog fused as one
        batch computes several datagrams' frames of a sensor together: not these)."""
        return len(frames) == len(self.frames) and all(a is b for a, b in
                                                       zip(frames, self.frames))

    def current(self, transform: np.ndarray, settings: tuple) -> bool:
        """Whether they were computed with the transform and the settings
        (``Engine._frame_settings``) the engine would compute them with now."""
        return (transform is self.transform and settings[0] == self.settings[0]
                and settings[1] is self.settings[1])


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
        # the compiled kernels now, before any frame: compiling (or loading numba's cache)
        # must not fall in the middle of a show
        jit.warm()
        self.drops = drops or DropCounter(self.rig.limits.max_drop_keys)
        #: items and whole datagrams (lists of items, ``submit_batch``) for the engine thread
        self.queue: queue.Queue[Inbound | list[Inbound]] = queue.Queue(maxsize=8192)
        #: the clients (sensors) by id, the reference sensor, the clients' clocks
        self.registry = ClientRegistry(self.rig, self.drops, self._drop_track)
        self.output = ViewOutput(transport, self.rig.views, self.rig.limits,
                                 self.rig.allow_views if transport is not None else None,
                                 self.drops, self.rig.forecast.views_s, self.rig.forecast.max_s)
        #: called on the engine thread with every fused frame (copy-on-write: add and
        #: remove from any thread)
        self.listeners = Callbacks("listener")
        #: called on the engine thread with every valid sensor frame, calibrated or not, as
        #: it comes (what they do to the engine applies to the frames after it)
        self.frame_observers = Callbacks("frame observer")
        #: the same, once the datagrams taken with the frame are fused and sent (``_observe``):
        #: for observers that only hand frames to another thread (the live calibrator's)
        self.late_frame_observers = Callbacks("late frame observer")
        #: the batch's frames for ``late_frame_observers``, built as each came
        self._observed: list[SensorFrame] = []
        #: a datagram's frames are computed in stage space by the receiver's thread as it
        #: queues them (``submit_batch``), while the engine thread fuses those ahead
        self.prepare_on_receipt = True
        #: the datagrams taken with their frames computed, by their first frame (``_take``)
        self._ready: dict[int, _Prepared] = {}
        self._prepare_failed = False
        #: writes the rig file off the engine thread (see ``apply_calibration``)
        self.rig_store = RigStore()
        #: per input frame: its datagram's arrival -> the first datagram out that includes it
        self.latency = LatencyWindow(32768)
        #: seconds the engine spent on each batch (health: frame time p99)
        self.batch_time = LatencyWindow(1024)
        #: the app's health messages for ``/stage/health`` (set by the app; engine thread)
        self.health_messages: Callable[[], list[bytes]] | None = None
        #: (prepared: datagrams whose frames the receiver computed and the engine took; stale:
        #: computed for a transform or settings no longer in use when the engine came to them)
        self.counts = {"messages": 0, "frames": 0, "fused_frames": 0, "prepared": 0,
                       "prepared_stale": 0}
        #: the fusion path: persons, their filters and hand votes, emission to views
        self.people = People(self.rig, self.clock, self.output, self.listeners, self.drops,
                             self.latency, self.counts)
        #: set while the live engine thread waits with nothing queued (and while it is not
        #: running at all); a receiver clears it with each datagram it queues. The live
        #: calibrator's worker waits for it between chunks of its searches, so that it does
        #: not compete for the GIL while the engine has datagrams to fuse (EngineWorker._yield)
        self.idle = threading.Event()
        self.idle.set()
        self._stats_replies: list[tuple[str, int]] = []
        self._health_replies: list[tuple[str, int]] = []
        self._latency_marks: dict[tuple[str, int], int] = {}   # stats asker -> latency.count
        #: per sensor, what calibration says of it (e.g. {"fitness": 0.97, "state": "ok"});
        #: written on the engine thread (via call_soon), shown in stats and monitors
        self.sensor_notes: dict[str, dict] = {}
        #: more sections of ``stats()``: name -> a callable giving a JSON-able dict, called on
        #: the engine thread (the live calibrator adds ``calibrator``)
        self.stats_sections: dict[str, Callable[[], dict]] = {}
        # engine clock -> wall clock, to report client clocks against ours in seconds
        self._wall_minus_clock = time.time() - self.clock.now()
        if isinstance(self.clock, MonotonicClock):  # live: timetags can be judged against it
            self.registry.wall_minus_clock = self._wall_minus_clock
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
    def tracker(self) -> Tracker:
        return self.people.tracker

    @property
    def persons(self) -> dict[int, Person]:
        """Fused persons by id (the tracker's; engine thread only)."""
        return self.people.persons

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
        self.idle.clear()
        try:
            self.queue.put_nowait(item)
            return True
        except queue.Full:
            self.drops.add(_client_key(item), "queue_full")
            return False

    def submit_batch(self, items: list[Inbound]) -> bool:
        """Thread-safe enqueue of one datagram's messages as one queue entry (a receiver):
        one lock round trip and one wake-up of the engine thread per datagram, not per
        message, and the engine always sees the whole datagram at once. A full queue counts
        a drop per message."""
        if not items:
            return True
        # (only while the engine thread is busy: an idle one starts on them at once)
        if self.prepare_on_receipt and len(items) > 3 and not self.idle.is_set():
            items = self._prepared(items)
        self.idle.clear()
        try:
            self.queue.put_nowait(items)
            return True
        except queue.Full:
            for item in items:
                self.drops.add(_client_key(item), "queue_full")
            return False

    def _prepared(self, items: list[Inbound]) -> list[Inbound]:
        """Receiver thread (``submit_batch``): the datagram with its skeletons computed in
        stage space (``People.computed_frames``: transform, swapped limbs, variances; one
        compiled call) when they are two or more of one known, calibrated sensor; else as it
        came. What the engine would do first with them, done while the engine thread fuses
        the datagrams queued ahead (sensors in step send theirs together); ``submit_batch``
        does not call it while the engine waits idle (done here, the work would only come
        between the datagram and the engine). It reads the sensor's transform and the
        fusion settings as they are now, each one Python object read once; the engine takes
        the results only where its own are still those very objects (``_prepare_frames``),
        and computes them itself otherwise."""
        frames = [i.message for i in items if type(i.message) is JointCoordinates]
        if len(frames) < 2:
            return items
        cid = frames[0].client
        client = self.registry.clients.get(cid)
        transform = None if client is None else client.transform
        if transform is None or any(m.client != cid for m in frames):
            return items
        settings = self._frame_settings()
        try:
            out = self.people.computed_frames(transform, frames, *settings)
        except Exception:  # only a head start: the engine computes them itself
            if not self._prepare_failed:
                self._prepare_failed = True
                log.exception("error while preparing a datagram's frames on receipt (logged "
                              "once; the engine thread computes them)")
            return items
        if out is None:
            return items
        entry = _Prepared(items)
        entry.frames, entry.transform, entry.settings, entry.out = frames, transform, settings, out
        return entry

    def _frame_settings(self) -> tuple:
        """What a frame's stage-space computation reads besides its transform: the rig's
        ``unswap_limbs`` and the smoothing settings (each read once: any thread)."""
        return self.rig.fusion.unswap_limbs, self.people.smoothing

    def call_soon(self, fn: Callable[["Engine"], None]) -> None:
        """Run ``fn(engine)`` on the engine thread, in order with the data (thread-safe).

        The only way another thread (a calibration worker, a UI) may change
        engine state. In-process users call ``drain()`` to run what is queued.
        """
        self.queue.put(Inbound(Call(fn), self.clock.now(), ("engine", 0)), timeout=1.0)  # type: ignore[arg-type]

    def drain(self) -> None:
        """Process everything queued so far, on the calling thread (tests, offline replay)."""
        batch = self._take([])
        try:
            if batch:
                self.process(batch)
        finally:
            self._ready.clear()

    def _take(self, batch: list[Inbound], limit: int | None = None,
              first: Inbound | list[Inbound] | None = None) -> list[Inbound]:
        """``batch`` with ``first`` and what is queued now appended, up to ``limit`` items in
        all (a datagram's frames computed on receipt noted for ``_prepare_frames``)."""
        entry = first
        while True:
            if entry is not None:
                if isinstance(entry, list):
                    if type(entry) is _Prepared:
                        self._ready[id(entry.frames[0])] = entry
                    batch.extend(entry)
                else:
                    batch.append(entry)
            if limit is not None and len(batch) >= limit:
                break
            try:
                entry = self.queue.get_nowait()
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

    def process(self, batch: list[Inbound], votes: bool = True) -> None:
        """Apply a batch of inbound items in capture-time order, then emit once (``votes``
        False: the skeletons alone, the rest with the next batch: ``People.flush``)."""
        started = time.perf_counter()
        # None: a timetag far from the real time (counted: bad_time)
        timed = [(t, k, item) for k, (t, item) in
                 enumerate(zip(self.registry.capture_times(batch), batch)) if t is not None]
        # (by time, then place: k is unique, so the items themselves are never compared; no
        # key function, which cost a call and a tuple per message)
        timed.sort()
        self.counts["messages"] += len(timed)
        # (a Kinect's skeleton comes with its two hand states: fewer than four messages
        # hold at most one skeleton, and are not worth grouping)
        if len(timed) > 3 and jit.ready():
            try:
                self._prepare_frames(timed)
            except Exception:  # only a head start: each frame is then computed on its own
                log.exception("error while preparing a batch's frames")
        for t, item, hands in _with_hands(timed):
            try:
                if hands:
                    self._apply_frame(item, t, hands)
                else:
                    self._apply(item, t)
            except Exception:  # a bug must not end the show: log it, drop the item
                log.exception("error while handling %s; item dropped", type(item.message).__name__)
                for _ in range(1 + len(hands)):
                    self.drops.add(_client_key(item), "internal_error")
        try:
            self.people.flush(votes)
        except Exception:  # a bug must not end the show: log it, lose this batch's frames
            log.exception("error while fusing a batch; its frames are dropped")
        if votes and self._observed:
            self._observe()
        if self._stats_replies:
            stats = self.stats()
            for address in self._stats_replies:
                # latency since this asker's previous query: a benchmark's own window
                stats["latency_since_last_query_ms"] = self.latency.summary_ms(
                    self._latency_marks.get(address, 0))
                if len(self._latency_marks) > 256:   # spoofed addresses must not grow memory
                    self._latency_marks.clear()
                self._latency_marks[address] = self.latency.count
                # one datagram whatever the stats hold; only to addresses views may be at
                self.output.send(encode_stats(stats, self.rig.limits.stats_reply_bytes), address)
            self._stats_replies.clear()
        if self._health_replies:
            messages = self.health_messages() if self.health_messages is not None else []
            for address in self._health_replies:
                for data in messages:
                    self.output.send(data, address)
            self._health_replies.clear()
        self.batch_time.add(time.perf_counter() - started)

    def _observe(self) -> None:
        """The late frame observers, with the frames of the batch (and of the datagrams taken
        with it, ``process_taken``) in the order they came, once those frames are fused and
        sent: such an observer (the threaded live calibrator's, some 1.5 us a frame and a
        wake-up of its worker every 0.1 s) does not delay the skeletons of the datagrams
        queued behind. The frame holds what it came with (its sensor's transform and floor
        as they were); what an observer looks up in the engine (the frame's track, its
        person) it finds as the batch left it. One that raises is logged and removed."""
        frames, self._observed = self._observed, []
        call = self.late_frame_observers.call
        for frame in frames:
            call(frame)

    def _prepare_frames(self, timed: list[tuple[float, int, Inbound]]) -> None:
        """Each known, calibrated sensor's frames of the batch computed together, in one
        compiled call (``People.prepare_frames``): a datagram holds a sensor's skeletons of
        one instant. Nothing else is judged here: a frame the sensor's checks then refuse
        was computed for nothing, and a sensor whose transform changes within the batch has
        its later frames computed again, on their own."""
        groups: dict[str, list] = {}
        for _, _, item in timed:
            msg = item.message
            if type(msg) is JointCoordinates:
                frames = groups.get(msg.client)
                if frames is None:
                    groups[msg.client] = [msg]
                else:
                    frames.append(msg)
        clients, ready = self.registry.clients, self._ready
        for cid, frames in groups.items():
            client = clients.get(cid)
            if len(frames) > 1 and client is not None and client.transform is not None:
                got = ready.pop(id(frames[0]), None) if ready else None
                if got is not None and got.holds(frames):
                    if got.current(client.transform, self._frame_settings()):
                        self.people.take_frames(got.transform, frames, got.out)
                        self.counts["prepared"] += 1
                        continue
                    self.counts["prepared_stale"] += 1
                self.people.prepare_frames(client.transform, frames)

    def _apply(self, item: Inbound, t: float) -> None:
        msg = item.message
        kind = type(msg)
        if kind is JointCoordinates or kind is HandStateMsg:
            # the stream itself (three messages a skeleton): straight to its handler
            client = self.registry.client(msg, item)
            if client is not None:
                self._on_data(client, msg, item, t)
            return
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
        if isinstance(msg, (JointCoordinates, HandStateMsg)):
            self._on_data(client, msg, item, t)
        elif isinstance(msg, FloorPlane):
            client.floor = msg.plane
        elif isinstance(msg, NewUser):
            old = client.tracks.pop(msg.user, None)
            if old is not None:
                self._drop_track(old, t)
            client.new_track(msg.user)
        elif isinstance(msg, LostUser):
            track = client.tracks.pop(msg.user, None)
            if track is not None:
                self._drop_track(track, t)

    def _apply_frame(self, item: Inbound, t: float, hands: list[Inbound]) -> None:
        """A skeleton with the ``/handState`` of its user that followed it in its bundle
        (``_with_hands``): the frame is applied with them, as if each were applied after it
        (its hand votes take the new states at once, so none is voted twice). Where the
        frame goes no further than the hand states would, they are applied on their own."""
        msg = item.message
        client = self.registry.client(msg, item)
        if client is None:         # refused: the hand states are judged on their own
            for hand in hands:
                self._apply(hand, t)
            return
        # (what registry.client does for a hand state it did for the frame: same client,
        # same source, which the frame's stricter check passed, same arrival)
        stamp = item.arrival if item.timetag is None else item.timetag
        if not self._on_frame(client, msg, t, item.arrival, stamp, hands):
            for hand in hands:
                self._on_data(client, hand.message, hand, t)

    def _on_data(self, client: ClientState, msg: JointCoordinates | HandStateMsg, item: Inbound,
                 t: float) -> None:
        if isinstance(msg, JointCoordinates):
            stamp = item.arrival if item.timetag is None else item.timetag
            self._on_frame(client, msg, t, item.arrival, stamp)
            return
        track = client.tracks.get(msg.user)
        if track is None:
            track = client.new_track(msg.user)
        self.people.hand(track, msg.hand, msg.state, t)

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
                  arrival: float, stamp: float, hands: list[Inbound] | None = None) -> bool:
        """Whether the frame reached its person with ``hands`` (``_apply_frame``)."""
        client.frames += 1
        self.counts["frames"] += 1
        if self.frame_observers or self.late_frame_observers:
            frame = SensorFrame(client.id, msg.user, t, msg.joints, msg.conf, client.transform,
                                client.floor)
            if self.frame_observers:
                self.frame_observers.call(frame)
            if self.late_frame_observers:
                self._observed.append(frame)
        if client.transform is None:
            if not client.warned_uncalibrated:
                log.warning("sensor %s has no calibration in use: its frames are not fused "
                            "until it is calibrated", client.id)
                client.warned_uncalibrated = True
            return False
        track = client.tracks.get(msg.user)
        if track is None:
            track = client.new_track(msg.user)
        # "late" is judged on the client's own clock: the offset estimate only
        # improves (decreases) over time, so engine-clock capture times of two
        # frames can cross even though the client sent them in order
        if stamp <= track.stamp:
            self.drops.add(client.id, "late")
            return False
        track.stamp = stamp
        if t < track.t:
            # captured before the track's last frame by our clock, though after it by the
            # client's: the frame goes in at that frame's time, its hand states at their own
            # (older) one, on their own
            self.people.frame(track, client.transform, msg.joints, msg.conf, track.t, arrival)
            return False
        fused = self.people.frame(track, client.transform, msg.joints, msg.conf, t, arrival,
                                  hands)
        watch = client.hand_watch
        if fused and watch.verdict is None and watch.frame(track.hand_run, track.hands):
            self._hand_cadence(client, watch)
        return fused

    def _hand_cadence(self, client: ClientState, watch: CadenceWatch) -> None:
        """The sensor's hand states said how it reads them (hands.CadenceWatch, whose figures
        the stats show): taken when its cadence was a guess, else logged when they contradict
        the cadence its reports are counted by."""
        seen = (f"{watch.even} of its first {watch.runs} short hand-state runs were an even "
                f"number of frames")
        if watch.verdict in (1, 2) and watch.verdict != client.hand_frames \
                and client.hand_frames_guessed:
            # a type whose cadence nobody gave: its own runs tell, better than the guess
            log.info("sensor %s (%s): %s, so its hand-state readings are taken to last %d "
                     "frame%s from now on ('sensors: %s: hand_reading_frames' in the rig "
                     "fixes it)", client.id, client.type, seen, watch.verdict,
                     "" if watch.verdict == 1 else "s", client.id)
            client.set_hand_frames(watch.verdict)
        elif watch.verdict == 2 and client.hand_frames == 1:
            log.warning("sensor %s (%s) seems to repeat each hand-state reading over two frames "
                        "(%s) but its reports count as whole readings: its misreads count "
                        "twice and hands may flicker; set 'sensors: %s: hand_reading_frames: 2' "
                        "in the rig", client.id, client.type, seen, client.id)
        elif watch.verdict == 1 and client.hand_frames >= 2:
            log.info("sensor %s (%s) seems to read hand states every frame (%s) but its "
                     "reports count as 1/%d of a reading: its hand changes go out later than "
                     "they could; 'sensors: %s: hand_reading_frames: 1' in the rig counts them "
                     "whole", client.id, client.type, seen, client.hand_frames, client.id)
        else:
            log.debug("sensor %s: %s (verdict %d)", client.id, seen, watch.verdict)

    def _drop_track(self, track: Track, t: float) -> None:
        self.people.drop_track(track, t)

    def bodies(self) -> dict[int, Body]:
        """Every announced person's fused body now (engine thread only)."""
        return self.people.bodies()

    # ------------------------------------------------------------ housekeeping
    def tick(self, now: float | None = None) -> None:
        """Timeouts, person expiry and merging, the per-minute drop report."""
        now = self.clock.now() if now is None else now
        self._last_tick = now
        self.registry.timeouts(now)
        self.output.expire(now)
        if now - self._last_drop_report >= 60.0:
            self._last_drop_report = now
            recent = self.drops.since_last_report()
            if recent:
                log.warning("dropped in the last minute: %s", format_drops(recent))
        self.people.tick(now)

    # ------------------------------------------------------------ thread
    def run(self, stop: threading.Event, tick_s: float = TICK_S) -> None:
        """The engine thread: drain the queue in batches, tick between them."""
        while not stop.is_set():
            timeout = tick_s
            due = self.output.next_due()
            if due is not None:  # a view that asked for a fixed rate
                timeout = min(timeout, max(due - self.clock.now(), 0.0))
            try:
                try:
                    first = self.queue.get_nowait()
                except queue.Empty:
                    self.idle.set()   # nothing to do: the calibrator may run
                    first = self.queue.get(timeout=timeout)
                self.idle.clear()
                batch = self._take([], limit=512, first=first)
            except queue.Empty:
                batch = []
            self.process_taken(batch)
            now = self.clock.now()
            if now - self._last_tick >= tick_s:
                self.tick(now)
            elif due is not None:
                self.people.serve_fixed_rate(now)

    def process_taken(self, batch: list[Inbound]) -> None:
        """What the engine thread took from the queue at once (``run``): one datagram at a
        time, so that its frames go out as soon as they are folded in and not after
        everything else that came at the same instant (sensors in step); the hand votes and
        the listeners' frame (a piece) once, after the last, so that the later datagrams do
        not wait for them. A backlog is taken in one go, sending each person once, to catch
        up."""
        chunks = list(_by_datagram(batch))
        if len(chunks) > BACKLOG_DATAGRAMS:
            chunks = [batch]
        last = len(chunks) - 1
        try:
            for k, chunk in enumerate(chunks):
                self.process(chunk, votes=k == last)
        finally:
            self._ready.clear()

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
                              "hand_reading_frames": c.hand_frames,
                              "hand_runs": c.hand_watch.stats(),
                              "drops": drops.get(cid, {})}
                        for cid, c in self.clients.items()},
            "persons": fused_persons_stats(self.people),
            "views": [f"{h}:{p}" for h, p in self.views],
            "counts": {**self.counts, "datagrams_out": self.output.datagrams_out,
                       "send_errors": self.output.send_errors,
                       "views_expired": self.output.expired,
                       "views_unreachable": self.output.dropped_unreachable,
                       "clients_forgotten": self.registry.evicted},
            "drops": drops,
            "drops_total": sum(n for r in drops.values() for n in r.values()),
            "latency_ms": self.latency.summary_ms(),
            "fusion": self.people.stats(),
            "forecast": self.people.forecast_stats(),
            # the process's threads by name -> the kernel's thread id, so that a benchmark or
            # an operator can read each one's CPU in /proc/PID/task/TID (Python 3.11 does not
            # give the kernel its thread names)
            "threads": {t.name: t.native_id for t in threading.enumerate()
                        if t.native_id is not None},
            **{name: section() for name, section in list(self.stats_sections.items())},
        }


def _with_hands(timed: list[tuple[float, int, Inbound]]) -> list[list]:
    """[t, item, hand states] in order: each skeleton with the ``/handState`` of its client
    and user that follow it in its datagram (same arrival, sender and timetag) at its
    capture time (a skeleton refused by its source's port has its arrival as its time, its
    hand states need not), with no other kind of message in between (a ``/lostUser``, say),
    taken out of the sequence; an empty list for other items. Every sensor sends its users'
    hand states with their skeleton; applied with it, they cost no message of their own
    (``Engine._apply_frame``)."""
    out: list[list] = []
    frames: dict = {}
    for t, _, item in timed:
        msg = item.message
        kind = type(msg)
        if kind is HandStateMsg:
            entry = frames.get((msg.client, msg.user))
            if entry is not None:
                frame = entry[1]
                if (entry[0] == t and frame.arrival == item.arrival
                        and frame.timetag == item.timetag and frame.source == item.source):
                    entry[2].append(item)
                    continue
        elif kind is JointCoordinates:
            entry = [t, item, []]
            frames[(msg.client, msg.user)] = entry
            out.append(entry)
            continue
        elif frames:
            frames.clear()
        out.append([t, item, _NO_HANDS])
    return out


#: (never appended to)
_NO_HANDS: list = []


def _by_datagram(batch: list[Inbound]):
    """The batch in runs of items from one datagram (same arrival and sender), in order."""
    start = 0
    for k in range(1, len(batch) + 1):
        if k == len(batch) or (batch[k].arrival, batch[k].source) != (batch[start].arrival,
                                                                        batch[start].source):
            yield batch[start:k]
            start = k


def _client_key(item: Inbound) -> str:
    client = getattr(item.message, "client", None)
    return client if client is not None else f"{item.source[0]}:{item.source[1]}"
