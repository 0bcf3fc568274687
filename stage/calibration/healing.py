"""Live calibration and self-healing (K-Multiscope, end of section 3.4).

``attach_live(engine, rig_path)`` plugs a ``LiveCalibrator`` into a
running engine:

- a sensor the rig has no calibration for is calibrated as soon as exactly
  one person is seen by it and by a calibrated sensor (``pairs`` pairs);
- every calibrated sensor's fitness is computed over the last ``window_s``
  against the other trusted sensors; when it stays below ``suspect_below``
  for ``hold_s``, or at once when its torso jumps ``gate_m`` away from
  sensors it agreed with a moment ago (a bumped sensor), the sensor is
  marked suspect and left out of fusion (no wrong notes), fresh pairs are
  collected, it is re-calibrated on a worker thread and the new transform
  is accepted only if its fitness is at least ``accept_above``; a sensor
  whose old transform fits again (hysteresis: above ``restore_above`` for
  ``restore_s``) is simply restored;
- two sensors sending bit-identical skeletons are flagged, the copy left out;
- every change is logged, shown in ``engine.sensor_notes`` (stats, monitor)
  and handed to the engine thread, which owns the rig, records it there and
  writes the rig file atomically (``Engine.record_calibration``).

Threads: the observer runs on the engine thread and only notes what the
engine knows of the frame (its track and person, the reference) in an
inbox; everything else -- the buffers, the copy check, the jump gate, the
monitor, lags, pairs and fits -- runs on the calibrator's worker thread,
every ``poll_s``, which changes engine state only through
``engine.call_soon``. With ``threaded=False`` the same work runs inline on
the engine thread at the frames' own times: deterministic, for tests and
offline replays.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import replace
from typing import Callable

import numpy as np

from ..engine.callbacks import Callbacks
from ..engine.engine import Engine
from ..frames import SensorFrame
from .checks import FrameChecks
from .collector import Collector
from .gate import CopyDetector, JumpGate
from .judge import PairWindow
from .live import LiveSettings, View
from .livestate import LiveEvent, SensorState
from .monitor import Monitor
from .worker import EngineWorker

log = logging.getLogger("stage.calibration")
INF = float("inf")
#: sensors the calibrator keeps state for; beyond, those the engine forgot are dropped
MAX_SENSORS = 128
#: frames the worker ingests between two yields to the engine (``_drain``): each one holds
#: the GIL for ~30-40 us a frame at 6x6, and a datagram that comes meanwhile waits. With
#: 72 a chunk, 4.5-4.9 % of the engine's batches spent over 1 ms not running at 6x6 spread
#: on a quiet VM; with 12, and a yield before the first, 2.3-2.6 % (docs/reports/issue-10.md,
#: stop 31)
DRAIN_CHUNK = 12

#: at most one log line per this many seconds (capture time) about frames dropped from the
#: worker's full inbox
INBOX_LOG_S = 10.0

__all__ = ["LiveCalibrator", "LiveEvent", "attach_live"]


class LiveCalibrator(Monitor, Collector, FrameChecks, EngineWorker):
    """See the module docstring. Build with ``attach_live``."""

    name = "stage-calibration"

    def __init__(self, engine: Engine, rig_path: str | None,
                 settings: LiveSettings | None = None, threaded: bool = True,
                 on_event: Callable[[LiveEvent], None] | None = None) -> None:
        super().__init__(engine, threaded)
        self.rig_path = rig_path
        self.settings = settings or LiveSettings()
        self.on_event = on_event
        self.events: list[LiveEvent] = []
        self._lock = threading.Lock()
        # the engine's reference sensor, as last seen on the engine thread (read under _lock)
        self._reference: str | None = engine.reference
        self._buffers: dict[tuple[str, int], deque] = {}   # of (frame, person id, run)
        self._runs: dict[tuple[str, int], int] = {}        # identities a user id has had
        self._tracks_seen: dict[tuple[str, int], object] = {}  # the engine's track, last frame
        self._states: dict[str, SensorState] = {}
        self._order: list[str] = []
        s = self.settings
        self._gate = self._new_gate()
        self._monitored_to = -INF
        self._window = PairWindow(s.window_s)   # trusted pairs' joint distances
        self._held_since: float | None = None   # everything looked wrong at once since then
        self._jumps: dict[str, tuple[float, set]] = {}   # sensor -> (frame time, users jumped)
        self._copies = CopyDetector(self.settings.identical_frames)
        self._pending: dict[str, int] = {}  # requested before the sensor was seen
        self._request_all: int | None = None
        self._latest = -INF
        self._next_poll = -INF
        self._idle = False   # every sensor calibrated and trusted, nothing collected (lock)
        self._lag_retry: dict[str, float] = {}   # tracked sensor -> no lag search before then
        # threaded: (frame, track, person, reference) the engine thread saw, for the worker
        self._inbox: deque[tuple] = deque()
        self._inbox_max = 1 << 16
        #: frames the worker could not keep up with (dropped from the inbox, oldest first;
        #: logged at the first and then at most every ``INBOX_LOG_S`` of capture time)
        self.inbox_dropped = 0
        self._inbox_said = (0, -INF)     # (inbox_dropped, frame time) at the last log line
        # ``frame_budget`` (lock): frames ingested since ``_budget_from``, the seconds between
        # two frames kept of one view (0: every frame) and each view's last time bin kept
        self._budget_from, self._budget_count = -INF, 0
        self._keep_every = 0.0
        self._kept_bin: dict[tuple[str, int], int] = {}
        self._rate: float | None = None   # frames ingested a second, last measured
        #: frames left out of the buffers by ``frame_budget`` (copy-checked all the same)
        self.frames_thinned = 0
        #: the monitor's judgements, and those of them the jump gate brought forward (a
        #: sensor's views drifted ``idle_wake_m`` from the others within a chunk)
        self.judgements = self.woken = 0
        #: times the calibrator failed and was restarted, and the last failure (health)
        self.crashes = 0
        self.last_crash = ""

    # ------------------------------------------------------------ lifecycle
    def start(self) -> "LiveCalibrator":
        self._observers().append(self._observe)
        self.engine.stats_sections["calibrator"] = self.stats
        self._start_worker()
        return self

    def stop(self) -> None:
        """Detach from the engine and end the worker (waits for a running job)."""
        try:
            self._observers().remove(self._observe)
        except ValueError:
            pass
        if self.engine.stats_sections.get("calibrator") == self.stats:
            del self.engine.stats_sections["calibrator"]
        self._stop_worker()

    def _observers(self) -> Callbacks:
        """Where the engine calls ``_observe``: threaded, once the frame's batch is fused and
        sent (the observer only queues it for the worker, and the skeletons queued behind
        it need not wait); inline, as each frame comes, so that a bump the jump gate catches
        leaves the sensor out of the very next frame."""
        return self.engine.late_frame_observers if self.threaded else self.engine.frame_observers

    def stats(self) -> dict:
        """The ``calibrator`` section of ``/stage/stats`` (any thread; counters only):
        frames ingested a second (null before the first second), the frame budget, the
        rate each view is kept at while over it (null: every frame kept), the frames left
        out by the budget and dropped from a full inbox, the monitor's judgements and those
        the jump gate brought forward, and the restarts after a failure."""
        every, rate = self._keep_every, self._rate
        return {"frames_per_s": None if rate is None else round(rate, 1),
                "frame_budget": self.settings.frame_budget,
                "kept_hz": round(1.0 / every, 2) if every else None,
                "frames_thinned": self.frames_thinned,
                "inbox_dropped": self.inbox_dropped,
                "judgements": self.judgements,
                "woken": self.woken,
                "crashes": self.crashes}

    def request(self, sensors: list[str] | None = None, pairs: int | None = None) -> list[str]:
        """Re-calibrate now (on demand): the sensors keep being fused meanwhile.

        Default: every sensor but the reference, including those that appear
        later. Named sensors not seen yet are calibrated when they appear.
        Returns the sensors seen so far that were asked for.
        """
        with self._lock:
            if sensors is None:
                self._request_all = pairs or self.settings.pairs
            targets = sensors or [s for s in self._order if s != self._reference]
            seen = []
            for sid in targets:
                st = self._states.get(sid)
                if st is None:
                    self._pending[sid] = pairs or self.settings.pairs
                    continue
                seen.append(sid)
                st.requested, st.epoch = True, st.epoch + 1
                st.reset_pairs()
                st.needed = pairs or self.settings.pairs
                st.wanted_poses = self.settings.poses if not pairs else pairs
                st.collect_from = st.collected_to = self._latest
                st.reason = "calibration requested: collecting pairs"
                self._note(st)
        self._send()
        return seen

    @property
    def reference(self) -> str | None:
        """The engine's reference sensor, as last seen on the engine thread (any thread)."""
        with self._lock:
            return self._reference

    def states(self) -> dict[str, dict]:
        """sensor -> {state, fitness, reason, progress} (a copy, any thread)."""
        with self._lock:
            return {sid: self._note_of(st) for sid, st in self._states.items()}

    # ------------------------------------------------------------ failures
    def _crashed(self, where: str, exc: BaseException) -> None:
        """A bug must not end self-healing for the rest of the run: log it, start afresh."""
        self.crashes += 1
        self.last_crash = f"{where}: {type(exc).__name__}: {str(exc)[:200]}"
        log.error("the live calibrator failed (%s); restarted with fresh state (failure %d)",
                  self.last_crash, self.crashes, exc_info=exc)
        with self._lock:
            s = self.settings
            self._gate = self._new_gate()
            self._copies = CopyDetector(s.identical_frames)
            self._buffers.clear()
            self._kept_bin.clear()
            self._keep_every, self._budget_from, self._budget_count = 0.0, -INF, 0
            self._inbox.clear()
            self._runs.clear()
            self._tracks_seen.clear()
            self._states.clear()
            self._order.clear()
            self._monitored_to = -INF
            self._window = PairWindow(s.window_s)
            self._held_since = None
            self._jumps.clear()

    def _new_gate(self) -> JumpGate:
        s = self.settings
        return JumpGate(s.agree_m, s.gate_m, s.link_s, same_m=s.match_m)

    def _forget_gone(self) -> None:
        """Sensors the engine no longer knows are forgotten (caller holds the lock), so
        ever new sensor ids cannot grow the calibrator's tables."""
        gone = [sid for sid in self._states if sid not in self.engine.clients]
        for sid in gone:
            del self._states[sid]
        self._order = [sid for sid in self._order if sid in self._states]
        self._gate = self._new_gate()
        for sid, st in self._states.items():
            self._gate.trust(sid, st.state == "ok")

    # ------------------------------------------------------------ engine thread
    def _observe(self, frame: SensorFrame) -> None:
        try:
            self._observe_frame(frame)
        except Exception as exc:  # never let the engine's callback list disable us
            self._crashed(f"frame of {frame.sensor[:64]}", exc)

    def _observe_frame(self, frame: SensorFrame) -> None:
        """Engine thread, every frame (threaded: once its batch is fused, ``_observers``):
        what the engine knows of it then (its track, the person it is bound to, the
        reference), then -- threaded -- a reference appended to the inbox and nothing more:
        the buffers, the copy and jump checks run on the worker at its next poll (every
        ``poll_s``), in the engine's order. They cost the engine thread 30-40 us a frame (a
        fifth of its time at 6 sensors x 6 people), and a bump caught 0.1 s later is still
        left out long before anyone hears it. Inline (``threaded=False``) they run at once,
        as before, so offline runs are unchanged."""
        self._engine_thread = threading.current_thread()
        client = self.engine.clients.get(frame.sensor)
        track = client.tracks.get(frame.user) if client is not None else None
        entry = (frame, track, None if track is None else track.person, self.engine.reference)
        due = frame.t >= self._next_poll
        if due:
            self._next_poll = frame.t + self.settings.poll_s
        if self.threaded:
            if len(self._inbox) >= self._inbox_max:  # the worker is stuck: keep the newest
                try:
                    self._inbox.popleft()
                    self.inbox_dropped += 1
                except IndexError:  # the worker emptied it meanwhile
                    pass
                else:
                    said, at = self._inbox_said
                    if frame.t - at >= INBOX_LOG_S:
                        log.warning("calibrator: its worker is behind: %d frame(s) dropped "
                                    "from its inbox since the last report (%d in all)",
                                    self.inbox_dropped - said, self.inbox_dropped)
                        self._inbox_said = (self.inbox_dropped, frame.t)
            self._inbox.append(entry)
            if due:
                self._wake.set()
            return
        with self._lock:
            self._ingest(*entry)
        if due:
            self._poll()

    def _drain(self) -> None:
        """Worker: ingest the frames the engine thread queued, a chunk at a time (the lock
        and the GIL are let go before and between chunks: the engine thread woke the worker
        from within a datagram, whose frames would otherwise wait for the first chunk)."""
        drained = False
        while self._inbox:
            # behind by more than an eighth of the inbox (seconds of frames): catch up
            # rather than wait for the engine to be idle
            self._yield(wait=len(self._inbox) < self._inbox_max // 8)
            drained = True
            with self._lock:
                group: list[tuple[SensorFrame, SensorState]] = []  # one datagram's, to judge
                users: set[int] = set()         # ... their users, its sensor and time
                sensor, t = None, None
                pop, keep = self._inbox.popleft, self._keep
                for _ in range(min(DRAIN_CHUNK, len(self._inbox))):
                    entry = pop()
                    frame = entry[0]
                    if group and (frame.t != t or frame.sensor != sensor or frame.user in users):
                        self._check_jumps(group)
                        group = []
                        users = set()
                    st = keep(*entry)
                    if st is not None:
                        if not group:
                            sensor, t = frame.sensor, frame.t
                        group.append((frame, st))
                        users.add(frame.user)
                if group:
                    self._check_jumps(group)
        if drained:
            self._yield()

    def _ingest(self, frame: SensorFrame, track: object, person: int | None,
                reference: str | None) -> None:
        """One frame into the buffers, the copy detector and the jump gate (caller holds
        the lock). ``track``, ``person``, ``reference``: as the engine had them when the
        frame came."""
        st = self._keep(frame, track, person, reference)
        if st is not None:
            self._check_jump(frame, st)

    def _keep(self, frame: SensorFrame, track: object, person: int | None,
              reference: str | None) -> SensorState | None:
        """``_ingest`` but the jump check: the frame's state when the check is due, else None."""
        s = self.settings
        self._reference = reference
        if frame.sensor not in self._states and len(self._states) >= MAX_SENSORS:
            self._forget_gone()
        st = self._states.get(frame.sensor) or self._new_state(frame)
        self._follow_reference(st, frame)
        st.transform = frame.transform
        key = (frame.sensor, frame.user)
        buf = self._buffers.get(key)
        if buf is None:
            buf = self._buffers[key] = deque(maxlen=int(s.buffer_s * 60))
        if track is not None and self._tracks_seen.get(key) is not track:
            # a new user, or one lost and found (the engine has a new track for it):
            # nothing it agreed with before counts
            self._tracks_seen[key] = track
            self._gate.forget(frame.sensor, frame.user)
            self._runs[key] = self._runs.get(key, 0) + 1
        if frame.t > self._latest:
            self._latest = frame.t
        if s.identical_frames > 0:
            pair = self._copies.check(frame.sensor, frame.t, frame.joints, frame.conf)
            if pair is not None:
                self._flag_identical(pair, frame.t)
        self._budget_count += 1
        if self._keep_every:
            # the first frame of each time bin, so that a view is thinned evenly (frames at
            # 30 Hz in bins of 1/15 s: every other one)
            at = int(frame.t // self._keep_every)
            if self._kept_bin.get(key) == at:
                self.frames_thinned += 1
                return None
            self._kept_bin[key] = at
        buf.append((frame, person, self._runs.get(key, 0)))
        if s.heal and st.state == "ok" and frame.transform is not None:
            return st
        return None

    def _rebudget(self, now: float) -> None:
        """Once a second (caller holds the lock): thin the views when the frames ingested
        over the last second exceed ``frame_budget`` (until they fall under 90 % of it),
        each view then to ``frame_budget / views`` frames a second, and never under 10."""
        budget = self.settings.frame_budget
        if budget <= 0:     # (also when it is turned off while thinning: every frame at once)
            self._keep_every = 0.0
        if self._budget_from == -INF:
            self._budget_from, self._budget_count = now, 0
        span = now - self._budget_from
        if span < 1.0:
            return
        rate = self._rate = self._budget_count / span      # (the stats' frames_per_s)
        self._budget_from, self._budget_count = now, 0
        if budget <= 0:
            return
        views = sum(1 for b in self._buffers.values() if b and now - b[-1][0].t <= 1.0)
        over = rate > (0.9 if self._keep_every else 1.0) * budget
        # (never under 10 Hz: a view's frames 0.25 s apart would each start a new identity)
        every = min(views / budget, 0.1) if over and views else 0.0
        if bool(every) != bool(self._keep_every):
            if every:
                log.info("calibrator: %.0f frames a second from %d views, over its budget of "
                         "%g: each view kept at %.1f Hz", rate, views, budget, 1.0 / every)
            else:
                log.info("calibrator: %.0f frames a second, within its budget: every frame "
                         "kept", rate)
        self._keep_every = every
        for key in [k for k in self._kept_bin if k not in self._buffers]:
            del self._kept_bin[key]

    def _new_state(self, frame: SensorFrame) -> SensorState:
        sid = frame.sensor
        if sid == self._reference:
            st = SensorState(sid, "ok", "reference: its space is stage space")
        elif frame.transform is None:
            st = SensorState(sid, "uncalibrated", "no calibration yet" + (
                ": waiting for exactly one person seen by it and a calibrated sensor"
                if self.settings.auto_calibrate else ""))
        else:
            st = SensorState(sid, "ok", "calibrated")
        st.transform = st.last_good = frame.transform
        pending = self._pending.pop(sid, None)
        if pending is None and self._request_all and sid != self._reference:
            pending = self._request_all
        st.needed = pending or self.settings.pairs
        st.wanted_poses = self.settings.poses if pending in (None, self.settings.pairs) else pending
        st.requested = pending is not None
        self._gate.trust(sid, st.state == "ok")
        self._states[sid] = st
        self._order.append(sid)
        self._note(st)
        return st

    def _follow_reference(self, st: SensorState, frame: SensorFrame) -> None:
        """The engine may choose a new reference (the old one went silent before anything
        was calibrated against it): the new one is fine as it is, the old one needs a
        calibration like any other sensor."""
        sid = st.sensor
        if sid == self._reference and st.state != "ok" and frame.transform is not None:
            st.state, st.reason, st.pairs, st.epoch = "ok", "reference: its space is stage space", \
                None, st.epoch + 1
            st.transform = st.last_good = frame.transform
            self._gate.trust(sid, True)
            self._note(st)
        elif (sid != self._reference and st.state == "ok" and frame.transform is None
              and st.reason.startswith("reference")):
            st.state, st.reason, st.epoch = "uncalibrated", "no longer the reference: no " \
                "calibration yet", st.epoch + 1
            st.last_good = None
            self._gate.trust(sid, False)
            self._note(st)

    def _quarantine(self, st: SensorState, t: float, reason: str, force: bool = False) -> bool:
        """Leave a sensor out of fusion (caller holds the lock); False when held back.

        Never more than half of the calibrated sensors at once (``force``: a
        copy, which is not a sensor): when more would be suspect, everything
        looks wrong at once (a crowd hiding everybody, or the reference moved)
        and the last good calibrations stay in use, which the note says.
        """
        if not force and not self._room_for_suspect():
            self._hold(t, [st], reason)
            return False
        if st.transform is not None:
            st.last_good = st.transform
        st.state, st.reason, st.since = "suspect", reason, t
        st.transform, st.busy = None, False
        st.reset_pairs()
        st.needed, st.wanted_poses = self.settings.heal_pairs, self.settings.heal_poses
        st.collect_from = st.collected_to = t
        st.below_since = st.above_since = None
        st.epoch += 1
        st.window = PairWindow(self.settings.window_s)
        sid = st.sensor
        self._gate.trust(sid, False)
        self._act(lambda e: e.set_calibration(sid, None))
        log.warning("sensor %s is suspect: %s; left out of fusion until it is re-calibrated",
                    sid, reason)
        self._event(LiveEvent(t, sid, "suspect", reason, fitness=st.fitness))
        self._note(st)
        return True

    # ------------------------------------------------------------ helpers
    def _note_of(self, st: SensorState) -> dict:
        """What ``stage stats`` and the monitor show: state, fitness, the reason in words,
        progress while collecting, the last attempt's outcome and the lag found."""
        note = {"state": st.state, "fitness": None if st.fitness is None else round(st.fitness, 3),
                "reason": st.reason}
        if st.residual is not None and np.isfinite(st.residual):
            note["median_m"] = round(st.residual, 4)
        if st.pairs is not None or st.state in ("uncalibrated", "suspect") or st.requested:
            n = 0 if st.pairs is None else len(st.pairs)
            note["progress"] = (f"{n}/{st.needed} pairs, {len(st.poses)}/{st.wanted_poses} "
                                "distinct poses")
        if st.last_attempt is not None and st.state != "ok":
            note["last_attempt"] = st.last_attempt
        s = self.settings
        if (st.state != "ok" and s.lag_search and not st.lag_settled and st.lag_last is not None
                and st.sensor != self._reference and st.pairs is not None
                and len(st.pairs) >= s.min_pairs):
            # no fit is tried before two lag searches agree: say so, not only "collecting"
            note["waiting"] = (f"for a sure lag: no fit is tried until a lag search is sure "
                               f"(last search's confidence {st.lag_last:.2f}; a new sensor's "
                               f"lag moves at {s.lag_move_confidence:g}) and a second one "
                               "agrees; a take whose timing its frames cannot fix never is")
        if st.lag_confidence is not None:
            note["lag_s"] = round(st.lag_s, 4)
        return note

    def _note(self, st: SensorState) -> None:
        if st.state != "ok" or st.requested:  # something to do: every poll works again
            self._idle = False
        note = self._note_of(st)
        if note == st.noted:
            return
        st.noted = note
        sid = st.sensor
        self._act(lambda e: e.sensor_notes.__setitem__(sid, dict(note)))

    def _event(self, event: LiveEvent) -> None:
        self.events.append(event)
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:
                log.exception("calibration event callback failed")

    # ------------------------------------------------------------ worker
    def _poll(self) -> None:
        s = self.settings
        if self.threaded:
            self._drain()
        with self._lock:
            now = self._latest
            self._rebudget(now)
            t1 = now - s.delay_s
            if (self._idle and t1 - self._monitored_to < s.idle_poll_s
                    and not any(self._lag_due(st, now) for st in self._states.values())):
                # all calibrated and trusted: the monitor judges larger chunks, unless a
                # sensor's views drifted apart from the others' since the last judgement
                # (in the frames the jump gate compared)
                if max(self._gate.apart.values(), default=0.0) <= s.idle_wake_m:
                    return
                self.woken += 1
            self._gate.apart.clear()   # (frames drained from now on: for the next poll)
            t0 = max(self._monitored_to, t1 - s.window_s)
            oldest = min([t0] + [max(st.collected_to, st.collect_from)
                                 for st in self._states.values() if st.pairs is not None
                                 or st.state != "ok" or st.requested])
            if any(self._lag_due(st, now) for st in self._states.values()):
                oldest = -INF  # a lag search wants everything buffered
            since = max(oldest, now - s.buffer_s) - 0.25  # room to interpolate at the edges
            if any(st.pairs is not None or self._wants_pairs(st) for st in self._states.values()):
                # pairs look back up to a lag for where each view's identity run began
                since -= s.max_lag_s
            for key in [k for k, b in self._buffers.items() if b and b[-1][0].t < now - s.buffer_s]:
                del self._buffers[key]
            lags = {sid: st.lag_s for sid, st in self._states.items() if st.lag_s}
            snapshot = []
            for (sid, _user), buf in self._buffers.items():
                # ``since`` is stage time; a sensor's own clock runs lag_s from it (a clock
                # behind stage time lost its frames of the last ``lag_s`` before ``since``)
                cut = since + lags.get(sid, 0.0)
                recent = []
                for e in reversed(buf):  # newest first; frames are nearly in time order
                    if e[0].t <= cut - 0.2:
                        break
                    if e[0].t > cut:
                        recent.append(e)
                if recent:
                    snapshot.append(recent)
            epochs = {sid: st.epoch for sid, st in self._states.items()}
            states = {sid: (st.state, st.transform, st.last_good, st.duplicate_of)
                      for sid, st in self._states.items()}
            self._expire_duplicates(now)
        views: dict[str, list[View]] = {}
        # onto stage time: a sensor's clock runs lag_s from it
        for view in View.many(snapshot, [lags.get(entries[0][0].sensor, 0.0)
                                         for entries in snapshot]):
            views.setdefault(view.sensor, []).append(view)
        self._yield()
        if s.heal and t1 > t0:
            self.judgements += 1
            self._monitor(now, t0, t1, views, states, epochs)
            self._monitored_to = t1
            self._yield()
        self._track_lags(now, views, states, epochs)
        self._collect(now, views, states, epochs)
        with self._lock:
            jobs = [(st, st.epoch) for st in self._states.values()
                    if st.pairs is not None and self._ready(st, now) and not st.busy]
            for st, _ in jobs:
                st.busy = True
                if st.state == "suspect":
                    st.state = "recalibrating"
                self._note(st)
        for st, epoch in jobs:
            self._job(st, epoch, now)
        with self._lock:
            # (a sensor the monitor found off, holding, is judged every poll again, so that
            # the hold ends on time)
            self._idle = bool(self._states) and self._held_since is None and all(
                st.state == "ok" and st.pairs is None and not st.requested and not st.busy
                and st.duplicate_of is None and st.below_since is None
                for st in self._states.values())



def attach_live(engine: Engine, rig_path: str | None = None,
                settings: LiveSettings | None = None, threaded: bool = True,
                on_event: Callable[[LiveEvent], None] | None = None,
                **overrides: object) -> LiveCalibrator:
    """Start live calibration and self-healing on ``engine``; ``.stop()`` to end it.

    rig_path: where accepted calibrations are saved (atomically); None: keep
    them in memory only. ``overrides`` replace fields of ``settings``.
    """
    settings = replace(settings or LiveSettings(), **overrides)  # type: ignore[arg-type]
    return LiveCalibrator(engine, rig_path, settings, threaded, on_event).start()
