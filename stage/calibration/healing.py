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
from .fitness import fitness_from_median
from .gate import CopyDetector, JumpGate
from .judge import PairWindow, Verdict, judge, judge_suspect
from .live import LiveSettings, View, new_pairs, torso_centre
from .methods import CalibrationResult, calibrate
from .scoring import distances, grid
from .pairs import PairSet
from .worker import EngineWorker

log = logging.getLogger("stage.calibration")
INF = float("inf")


@dataclass(frozen=True)
class LiveEvent:
    """Something the calibrator did, at engine time ``t``."""

    t: float
    sensor: str
    kind: str       # suspect | restored | calibrated | rejected | identical | held
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
    window: PairWindow | None = None    # a suspect's distances with its last good transform
    residual: float | None = None       # m, the robust residual behind ``fitness``


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
        self._window = PairWindow(s.window_s)   # trusted pairs' joint distances
        self._held_since: float | None = None   # everything looked wrong at once since then
        self._jumps: dict[str, tuple[float, set]] = {}   # sensor -> (frame time, users jumped)
        self._copies = CopyDetector(self.settings.identical_frames)
        self._pending: dict[str, int] = {}  # requested before the sensor was seen
        self._request_all: int | None = None
        self._latest = -INF
        self._next_poll = -INF

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

    # ------------------------------------------------------------ engine thread
    def _observe(self, frame: SensorFrame) -> None:
        s = self.settings
        self._engine_thread = threading.current_thread()
        with self._lock:
            self._reference = self.engine.reference
            st = self._states.get(frame.sensor) or self._new_state(frame)
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

    def _check_jump(self, frame: SensorFrame, st: _State) -> None:
        """Quarantine at once a sensor whose views jumped away from sensors they agreed with.

        One view jumping is a bump only when it is all the sensor sees; with
        several people, a bump moves every view of the sensor in the same
        frame, while one view alone jumping is the sensor giving a freed user
        id to another person (a Kinect reuses its body indices): that view's
        old agreements are forgotten instead.
        """
        m = frame.transform
        c = torso_centre(frame.joints, frame.conf)
        if c is None or m is None:
            return
        sid, user, t = frame.sensor, frame.user, frame.t
        jumped = self._gate.check(sid, user, t, m[:3, :3] @ c + m[:3, 3])
        if jumped is None:
            return
        others = [u for (s2, u), buf in self._buffers.items()
                  if s2 == sid and u != user and buf and t - buf[-1][0].t <= 0.1]
        first, users = self._jumps.get(sid, (t, set()))
        if abs(t - first) > 0.02:        # a jump of an earlier frame: start counting again
            first, users = t, set()
        users.add(user)
        self._jumps[sid] = (first, users)
        if others and len(users) < 2:
            self._gate.forget(sid, user)  # one view of several: another person took its id
            return
        sensors, distance = jumped
        self._quarantine(st, t, f"{'its view' if not others else f'{len(users)} of its views'} "
                                f"jumped {distance:.2f} m away from {', '.join(sensors)} "
                                "(moved or bumped?)")

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
            self._quarantine(st, t, reason, force=True)
        else:
            st.reason = reason
            st.epoch += 1
            st.pairs = None
            self._note(st)

    def _quarantine(self, st: _State, t: float, reason: str, force: bool = False) -> bool:
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
        st.transform, st.pairs, st.busy = None, None, False
        st.needed = self.settings.heal_pairs
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

    def _calibrated(self) -> list[_State]:
        """Sensors with a calibration, in use or last good (copies are not sensors)."""
        return [st for st in self._states.values() if st.duplicate_of is None and (
            st.state == "ok" and st.transform is not None
            or st.state in ("suspect", "recalibrating") and st.last_good is not None)]

    def _room_for_suspect(self, more: int = 1) -> bool:
        """Whether ``more`` sensors can be left out with at least half still trusted."""
        cal = self._calibrated()
        trusted = sum(st.state == "ok" for st in cal)
        return trusted - more >= (len(cal) + 1) // 2 and trusted - more >= 1

    def _hold(self, t: float, states: list[_State], why: str) -> None:
        """Everything looks wrong at once: keep the last good calibrations, and say so."""
        names = ", ".join(st.sensor for st in states)
        text = (f"keeping the last good calibrations: {names} disagree{'s' if len(states) == 1 else ''}"
                f" too ({why}), but leaving {'it' if len(states) == 1 else 'them'} out would "
                "leave less than half of the sensors trusted (a crowd hiding everybody, or the "
                "reference moved?)")
        for st in states:
            st.reason = text
            self._note(st)
        if self._held_since is None:
            self._held_since = t
            log.warning("%s", text)
            self._event(LiveEvent(t, states[0].sensor, "held", text))

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
        """Judge every sensor on the frames of (t0, t1]; decide who is suspect or restored.

        See ``judge``: a sensor is suspect when it disagrees with the others
        while they agree among themselves, for ``hold_s``; never more than
        half of the calibrated sensors at once.
        """
        s = self.settings
        at = grid(t0, t1)
        if not len(at):
            return
        trusted, suspects = distances(views, states, at, s.match_m)
        with self._lock:
            changed = {sid for sid, st in self._states.items() if st.epoch != epochs.get(sid)}
            self._window.add(t1, {k: v for k, v in trusted.items() if not set(k) & changed})
            ok = [sid for sid, st in self._states.items() if st.state == "ok"
                  and st.transform is not None and st.duplicate_of is None]
            verdict = judge(self._window, ok, self._reference, s.suspect_below, s.suspect_ratio)
            candidates = []
            for sid in ok:
                st = self._states[sid]
                if sid not in verdict.fitness:
                    continue  # nobody to compare with: no verdict
                st.fitness, st.residual = verdict.fitness[sid], verdict.residual[sid]
                if sid in verdict.outliers:
                    st.below_since = now if st.below_since is None else st.below_since
                    if now - st.below_since >= s.hold_s:
                        candidates.append(st)
                else:
                    st.below_since = None
                    if st.reason.startswith("keeping the last good"):
                        st.reason = "calibrated; agrees with the others again"
                self._note(st)
            for sid, st in self._states.items():
                if (st.state != "suspect" or st.last_good is None or st.busy
                        or st.duplicate_of is not None or sid in changed or st.window is None):
                    continue
                st.window.add(t1, {k: v for k, v in suspects.items() if k[0] == sid})
                r, lvl = judge_suspect(st.window, sid, self._window, ok, verdict.outliers)
                if not np.isfinite(r):
                    continue
                st.residual, st.fitness = r, float(fitness_from_median(r))
                if st.fitness >= s.restore_above or (np.isfinite(lvl)
                                                     and r <= s.restore_ratio * lvl):
                    st.above_since = now if st.above_since is None else st.above_since
                    if now - st.above_since >= s.restore_s:
                        self._restore(st, now, lvl)
                else:
                    st.above_since = None
                self._note(st)
            self._decide(now, candidates, verdict)

    def _decide(self, now: float, candidates: list[_State], verdict: Verdict) -> None:
        """Quarantine the worst candidate, or hold everything when too many look wrong."""
        s = self.settings
        if not candidates:
            if not verdict.outliers:
                self._held_since = None
            return
        if not self._room_for_suspect(len(verdict.outliers)):
            self._hold(now, candidates, "; ".join(verdict.why(c.sensor) for c in candidates))
            return
        worst = max(candidates, key=lambda c: (verdict.residual.get(c.sensor, 0.0),
                                               c.sensor != self._reference))
        self._quarantine(worst, now, f"fitness {worst.fitness:.2f} stayed below "
                                     f"{s.suspect_below} for {s.hold_s:g} s: "
                                     f"{verdict.why(worst.sensor)}")

    def _restore(self, st: _State, now: float, level: float = float("nan")) -> None:
        m = st.last_good
        st.state, st.transform, st.pairs, st.since = "ok", m, None, now
        like = (f", as close as the others agree ({level * 100:.0f} cm)"
                if np.isfinite(level) else "")
        st.reason = (f"its old transform fits again (fitness {st.fitness:.2f}, median "
                     f"{(st.residual or 0) * 100:.0f} cm{like}): restored")
        st.above_since = st.below_since = None
        st.epoch += 1
        st.window = None
        sid = st.sensor
        self._window.forget(sid)
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
                st = self._states[sid]
                wanted = st.duplicate_of is None and not st.busy and (
                    st.requested or (state == "uncalibrated" and s.auto_calibrate)
                    or (state == "suspect" and s.heal))
                start = max(st.collected_to, st.collect_from)
            if not wanted:
                continue
            new, waiting = new_pairs(sid, views, trusted, start, t1, now, s.min_joints)
            self._yield()
            with self._lock:
                st = self._states[sid]
                if st.epoch != epochs.get(sid):
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
                st.window = None
                self._window.forget(sid)
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
