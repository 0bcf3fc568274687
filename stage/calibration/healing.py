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

Threads: the observer runs on the engine thread and only appends to
bounded buffers, hashes the frame and checks the torso gate (a few
microseconds); everything else runs on the calibrator's worker thread,
which changes engine state only through ``engine.call_soon``. With
``threaded=False`` the same work runs inline on the engine thread at the
frames' own times: deterministic, for tests and offline replays.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from ..engine.engine import Engine
from ..frames import SensorFrame
from ..errors import CalibrationError
from .fitness import fitness_from_mse
from .gate import CopyDetector, JumpGate
from .live import LiveSettings, View, new_pairs, torso_centre
from .methods import CalibrationResult, calibrate
from .scoring import grid, score
from .pairs import PairSet
from .worker import EngineWorker

log = logging.getLogger("stage.calibration")
INF = float("inf")
#: sensors the calibrator keeps state for; beyond, those the engine forgot are dropped
MAX_SENSORS = 128


@dataclass(frozen=True)
class LiveEvent:
    """Something the calibrator did, at engine time ``t``."""

    t: float
    sensor: str
    kind: str       # suspect | restored | calibrated | rejected | identical | failed
    detail: str
    matrix: np.ndarray | None = None   # sensor -> stage, for calibrated
    fitness: float | None = None


@dataclass
class _State:
    sensor: str
    state: str                          # ok | suspect | recalibrating | uncalibrated
    reason: str = ""
    transform: np.ndarray | None = None  # what the engine uses now (None: not fused)
    last_good: np.ndarray | None = None
    fitness: float | None = None
    since: float = -INF
    below_since: float | None = None
    above_since: float | None = None
    pairs: PairSet | None = None
    needed: int = 0
    collect_from: float = -INF
    collected_to: float = -INF
    duplicate_of: str | None = None
    requested: bool = False
    busy: bool = False
    epoch: int = 0                      # bumped on every state change (stale decisions lose)
    noted: dict | None = None
    history: deque = field(default_factory=deque)   # (t, sum w d^2, sum w) per poll


class LiveCalibrator(EngineWorker):
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
        self._buffers: dict[tuple[str, int], deque] = {}   # of (frame, person id)
        self._states: dict[str, _State] = {}
        self._order: list[str] = []
        s = self.settings
        self._gate = JumpGate(s.agree_m, s.gate_m, s.link_s)
        self._monitored_to = -INF
        self._copies = CopyDetector(self.settings.identical_frames)
        self._pending: dict[str, int] = {}  # requested before the sensor was seen
        self._request_all: int | None = None
        self._latest = -INF
        self._next_poll = -INF
        #: times the calibrator failed and was restarted, and the last failure (health)
        self.crashes = 0
        self.last_crash = ""

    # ------------------------------------------------------------ lifecycle
    def start(self) -> "LiveCalibrator":
        self.engine.frame_observers.append(self._observe)
        self._start_worker()
        return self

    def stop(self) -> None:
        """Detach from the engine and end the worker (waits for a running job)."""
        try:
            self.engine.frame_observers.remove(self._observe)
        except ValueError:
            pass
        self._stop_worker()

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
                st.requested, st.pairs, st.epoch = True, None, st.epoch + 1
                st.needed = pairs or self.settings.pairs
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
            self._gate = JumpGate(s.agree_m, s.gate_m, s.link_s)
            self._copies = CopyDetector(s.identical_frames)
            self._buffers.clear()
            self._states.clear()
            self._order.clear()
            self._monitored_to = -INF

    def _forget_gone(self) -> None:
        """Sensors the engine no longer knows are forgotten (caller holds the lock), so
        ever new sensor ids cannot grow the calibrator's tables."""
        gone = [sid for sid in self._states if sid not in self.engine.clients]
        for sid in gone:
            del self._states[sid]
        self._order = [sid for sid in self._order if sid in self._states]
        s = self.settings
        self._gate = JumpGate(s.agree_m, s.gate_m, s.link_s)
        for sid, st in self._states.items():
            self._gate.trust(sid, st.state == "ok")

    # ------------------------------------------------------------ engine thread
    def _observe(self, frame: SensorFrame) -> None:
        try:
            self._observe_frame(frame)
        except Exception as exc:  # never let the engine's callback list disable us
            self._crashed(f"frame of {frame.sensor[:64]}", exc)

    def _observe_frame(self, frame: SensorFrame) -> None:
        s = self.settings
        self._engine_thread = threading.current_thread()
        with self._lock:
            self._reference = self.engine.reference
            if frame.sensor not in self._states and len(self._states) >= MAX_SENSORS:
                self._forget_gone()
            st = self._states.get(frame.sensor) or self._new_state(frame)
            self._follow_reference(st, frame)
            st.transform = frame.transform
            key = (frame.sensor, frame.user)
            buf = self._buffers.get(key)
            if buf is None:
                buf = self._buffers[key] = deque(maxlen=int(s.buffer_s * 60))
            client = self.engine.clients.get(frame.sensor)
            track = client.tracks.get(frame.user) if client is not None else None
            buf.append((frame, None if track is None else track.person))
            self._latest = max(self._latest, frame.t)
            if s.identical_frames > 0:
                pair = self._copies.check(frame.sensor, frame.t, frame.joints, frame.conf)
                if pair is not None:
                    self._flag_identical(pair, frame.t)
            if s.heal and st.state == "ok" and frame.transform is not None:
                self._check_jump(frame, st)
            due = frame.t >= self._next_poll
            if due:
                self._next_poll = frame.t + s.poll_s
        if due:
            if self.threaded:
                self._wake.set()
            else:
                self._poll()

    def _new_state(self, frame: SensorFrame) -> _State:
        sid = frame.sensor
        if sid == self._reference:
            st = _State(sid, "ok", "reference: its space is stage space")
        elif frame.transform is None:
            st = _State(sid, "uncalibrated", "no calibration yet" + (
                ": waiting for exactly one person seen by it and a calibrated sensor"
                if self.settings.auto_calibrate else ""))
        else:
            st = _State(sid, "ok", "calibrated")
        st.transform = st.last_good = frame.transform
        pending = self._pending.pop(sid, None)
        if pending is None and self._request_all and sid != self._reference:
            pending = self._request_all
        st.needed = pending or self.settings.pairs
        st.requested = pending is not None
        self._gate.trust(sid, st.state == "ok")
        self._states[sid] = st
        self._order.append(sid)
        self._note(st)
        return st

    def _follow_reference(self, st: _State, frame: SensorFrame) -> None:
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

    def _check_jump(self, frame: SensorFrame, st: _State) -> None:
        """Quarantine at once a sensor whose torso jumped away from sensors it agreed with."""
        m = frame.transform
        c = torso_centre(frame.joints, frame.conf)
        if c is None or m is None:
            return
        jumped = self._gate.check(frame.sensor, frame.user, frame.t, m[:3, :3] @ c + m[:3, 3])
        if jumped is not None:
            sensors, distance = jumped
            self._quarantine(st, frame.t, f"its view jumped {distance:.2f} m away from "
                                          f"{', '.join(sensors)} (moved or bumped?)")

    def _flag_identical(self, pair: tuple[str, str], t: float) -> None:
        a, b = pair
        ref = self._reference
        if a == ref or (b != ref and self._order.index(a) < self._order.index(b)):
            original, copy = a, b
        else:
            original, copy = b, a
        st = self._states[copy]
        st.duplicate_of = original
        reason = (f"sends skeletons bit-identical to {original}'s: a copied stream, not a "
                  "sensor; left out")
        log.warning("sensor %s %s", copy, reason)
        self._event(LiveEvent(t, copy, "identical", reason))
        if st.state == "ok":
            self._quarantine(st, t, reason)
        else:
            st.reason = reason
            st.epoch += 1
            st.pairs = None
            self._note(st)

    def _quarantine(self, st: _State, t: float, reason: str) -> None:
        """Leave a sensor out of fusion (caller holds the lock)."""
        if st.transform is not None:
            st.last_good = st.transform
        st.state, st.reason, st.since = "suspect", reason, t
        st.transform, st.pairs, st.busy = None, None, False
        st.needed = self.settings.heal_pairs
        st.collect_from = st.collected_to = t
        st.below_since = st.above_since = None
        st.epoch += 1
        st.history.clear()
        sid = st.sensor
        self._gate.trust(sid, False)
        self._act(lambda e: e.set_calibration(sid, None))
        log.warning("sensor %s is suspect: %s; left out of fusion until it is re-calibrated",
                    sid, reason)
        self._event(LiveEvent(t, sid, "suspect", reason, fitness=st.fitness))
        self._note(st)

    # ------------------------------------------------------------ helpers
    def _note_of(self, st: _State) -> dict:
        note = {"state": st.state, "fitness": None if st.fitness is None else round(st.fitness, 3),
                "reason": st.reason}
        if st.pairs is not None or st.state in ("uncalibrated", "suspect") or st.requested:
            note["progress"] = f"{0 if st.pairs is None else len(st.pairs)}/{st.needed} pairs"
        return note

    def _note(self, st: _State) -> None:
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
        with self._lock:
            now = self._latest
            t1 = now - s.delay_s
            t0 = max(self._monitored_to, t1 - s.window_s)
            oldest = min([t0] + [max(st.collected_to, st.collect_from)
                                 for st in self._states.values() if st.pairs is not None
                                 or st.state != "ok" or st.requested])
            since = max(oldest, now - s.buffer_s) - 0.25  # room to interpolate at the edges
            for key in [k for k, b in self._buffers.items() if b and b[-1][0].t < now - s.buffer_s]:
                del self._buffers[key]
            snapshot = []
            for buf in self._buffers.values():
                recent = []
                for e in reversed(buf):  # newest first; frames are nearly in time order
                    if e[0].t <= since - 0.2:
                        break
                    if e[0].t > since:
                        recent.append(e)
                if recent:
                    snapshot.append(recent)
            epochs = {sid: st.epoch for sid, st in self._states.items()}
            states = {sid: (st.state, st.transform, st.last_good, st.duplicate_of)
                      for sid, st in self._states.items()}
            self._expire_duplicates(now)
        views: dict[str, list[View]] = {}
        for entries in snapshot:
            view = View.of(entries)
            views.setdefault(view.sensor, []).append(view)
        self._yield()
        if s.heal and t1 > t0:
            self._monitor(now, t0, t1, views, states, epochs)
            self._monitored_to = t1
        self._collect(now, views, states, epochs)
        with self._lock:
            jobs = [(st, st.epoch) for st in self._states.values()
                    if st.pairs is not None and len(st.pairs) >= st.needed and not st.busy]
            for st, _ in jobs:
                st.busy = True
                if st.state == "suspect":
                    st.state = "recalibrating"
                self._note(st)
        for st, epoch in jobs:
            self._job(st, epoch, now)

    def _expire_duplicates(self, now: float) -> None:
        for pair in self._copies.expired(now):
            for sid in pair:
                st = self._states.get(sid)
                if st is not None and st.duplicate_of in pair:
                    st.duplicate_of = None
                    st.collect_from = st.collected_to = now
                    st.reason = "no longer a copy: checking and re-calibrating"
                    st.epoch += 1
                    self._note(st)

    def _monitor(self, now: float, t0: float, t1: float, views: dict[str, list[View]],
                 states: dict, epochs: dict) -> None:
        """Score every sensor on the frames of (t0, t1]; decide who is suspect or restored."""
        s = self.settings
        at = grid(t0, t1)
        if not len(at):
            return
        sums = score(views, states, at, s.match_m)
        with self._lock:
            candidates = []
            for sid, st in self._states.items():
                if st.epoch != epochs.get(sid):
                    continue
                sse, w = sums.get(sid, (0.0, 0.0))
                if w > 0:
                    st.history.append((t1, sse, w))
                while st.history and st.history[0][0] <= t1 - s.window_s:
                    st.history.popleft()
                total_w = sum(h[2] for h in st.history)
                if total_w <= 0:
                    continue  # nobody to compare with: no verdict
                st.fitness = float(fitness_from_mse(sum(h[1] for h in st.history) / total_w))
                if st.state == "ok":
                    if st.fitness < s.suspect_below:
                        st.below_since = now if st.below_since is None else st.below_since
                        if now - st.below_since >= s.hold_s:
                            candidates.append(st)
                    else:
                        st.below_since = None
                elif (st.state == "suspect" and st.last_good is not None and not st.busy
                      and st.duplicate_of is None):
                    if st.fitness >= s.restore_above:
                        st.above_since = now if st.above_since is None else st.above_since
                        if now - st.above_since >= s.restore_s:
                            self._restore(st, now)
                    else:
                        st.above_since = None
                self._note(st)
            if candidates:
                # with two sensors both look wrong to each other: blame the lowest, and on a
                # near tie not the reference (stage space is its space)
                worst = min(candidates, key=lambda c: (round(c.fitness / 0.05),
                                                       c.sensor == self._reference))
                self._quarantine(worst, now, f"fitness {worst.fitness:.2f} stayed below "
                                             f"{s.suspect_below} for {s.hold_s:g} s")

    def _restore(self, st: _State, now: float) -> None:
        m = st.last_good
        st.state, st.transform, st.pairs, st.since = "ok", m, None, now
        st.reason = f"its old transform fits again (fitness {st.fitness:.2f}): restored"
        st.above_since = st.below_since = None
        st.epoch += 1
        st.history.clear()
        sid = st.sensor
        self._gate.trust(sid, True)
        self._act(lambda e: e.set_calibration(sid, m))
        log.info("sensor %s: %s", sid, st.reason)
        self._event(LiveEvent(now, sid, "restored", st.reason, m, st.fitness))

    def _collect(self, now: float, views: dict[str, list[View]], states: dict, epochs: dict,
                 ) -> None:
        s = self.settings
        t1 = now - s.delay_s
        trusted = [sid for sid, (state, *_rest) in states.items() if state == "ok"]
        for sid, (state, *_rest) in states.items():
            with self._lock:
                st = self._states.get(sid)  # the engine thread may have forgotten it
                if st is None:
                    continue
                wanted = st.duplicate_of is None and not st.busy and (
                    st.requested or (state == "uncalibrated" and s.auto_calibrate)
                    or (state == "suspect" and s.heal))
                start = max(st.collected_to, st.collect_from)
            if not wanted:
                continue
            new, waiting = new_pairs(sid, views, trusted, start, t1, now, s.min_joints)
            self._yield()
            with self._lock:
                st = self._states.get(sid)
                if st is None or st.epoch != epochs.get(sid):
                    continue
                if waiting is not None:
                    st.reason = waiting
                elif new is not None:
                    st.collected_to = t1
                    before = 0 if st.pairs is None else len(st.pairs)
                    st.pairs = new if st.pairs is None else st.pairs.concat(new)
                    st.reason = f"collecting pairs with {', '.join(new.partners)}"  # type: ignore[attr-defined]
                    quarter = max(st.needed // 4, 1)
                    if len(st.pairs) // quarter > before // quarter:
                        log.info("calibrating %s: %d/%d pairs", sid, min(len(st.pairs), st.needed),
                                 st.needed)
                self._note(st)

    def _job(self, st: _State, epoch: int, now: float) -> None:
        """Fit, check, and accept or reject (worker thread, or inline)."""
        s = self.settings
        pairs = st.pairs
        sid = st.sensor
        assert pairs is not None
        try:
            result: CalibrationResult | None = calibrate(pairs, s.method)
            error = None
        except CalibrationError as exc:
            result, error = None, str(exc)
        with self._lock:
            st.busy = False
            if st.epoch != epoch:
                return  # something happened meanwhile (quarantined again, a request)
            if st.state == "recalibrating":
                st.state = "suspect"
            was = st.state
            if result is not None and result.fitness >= s.accept_above:
                m = result.matrix
                st.state, st.transform, st.last_good, st.pairs = "ok", m, m, None
                st.requested, st.fitness, st.since = False, result.fitness, now
                st.below_since = st.above_since = None
                verb = "re-calibrated" if was == "suspect" else "calibrated"
                st.reason = (f"{verb} by {result.method}: fitness {result.fitness:.2f}, rms "
                             f"{result.rms_m * 1000:.0f} mm, {result.pairs} pairs")
                st.epoch += 1
                st.history.clear()
                self._gate.trust(sid, True)
                self._act(lambda e: e.set_calibration(sid, m))
                log.info("sensor %s %s", sid, st.reason)
                self._event(LiveEvent(now, sid, "calibrated", st.reason, m, result.fitness))
            else:
                why = error or (f"fit too poor (fitness {result.fitness:.2f} < "  # type: ignore[union-attr]
                                f"{s.accept_above})")
                st.pairs = pairs.subset(slice(len(pairs) // 2, None))  # keep the newer half
                st.reason = f"calibration rejected: {why}; collecting more pairs"
                log.warning("sensor %s: %s", sid, st.reason)
                self._event(LiveEvent(now, sid, "rejected", st.reason,
                                      fitness=None if result is None else result.fitness))
            self._note(st)
            accepted = st.state == "ok"
        if accepted and result is not None:
            self._save(sid, result)

    def _save(self, sid: str, result: CalibrationResult) -> None:
        """Hand an accepted calibration to the engine thread, which owns the rig and saves it."""
        path = self.rig_path if self.settings.save else None
        if self.settings.save and not self.rig_path:
            log.info("%s's calibration is in use but not saved: no rig file (--rig)", sid)
        matrix, method = result.matrix, f"{result.method} (live)"
        fitness, rms, wait = result.fitness, result.rms_m, not self.threaded
        self._act(lambda e: e.record_calibration(sid, matrix, method, fitness, rms, path, wait))


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
