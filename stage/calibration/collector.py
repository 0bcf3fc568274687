"""The live calibrator's collecting side: lags, pairs, fits, acceptance (a ``healing`` part).

- LAG: before collecting pairs for a sensor, and every ``lag_every_s`` for
  every calibrated one (twice as long after each search that moved nothing, up to
  ``lag_every_max_s``), its clock is searched against a trusted sensor that
  sees the same person (``pairs.find_lag`` on the buffered frames: the one
  person both see alone, or, for a calibrated sensor, the person the engine
  bound both views to). ``SensorState.lag_s`` shifts that sensor's frames for
  the monitor and for pairing; the engine's fusion is not changed by it.
- PAIRS: collected while exactly one person is seen by the sensor and a
  trusted one; enough when they reach ``pairs`` (``heal_pairs``), or sooner
  when they hold ``poses`` (``heal_poses``) distinct poses (coverage.py).
- ACCEPTANCE: the fit passes the gates (``min_pairs``, ``min_poses``,
  ``min_fitness``, as offline), and is good (fitness ``accept_above``), or
  as close as the trusted sensors agree among themselves (``accept_ratio``
  times their median distance), or, for a first calibration with nobody to
  compare with, merely passes the gates. A rejection keeps the newer half of
  the pairs and says why in the sensor's note, where ``stage stats`` shows it.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import CalibrationError
from .coverage import Gates
from .live import View, new_pairs
from .livestate import LiveEvent, SensorState
from .methods import CalibrationResult, calibrate
from .pairs import LagSearch, find_lag
from .loops import fold_loops, loop_period
from .streams import Stream
from .uncertainty import Uncertainty, fit_uncertainty

log = logging.getLogger("stage.calibration")


class Collector:
    """Mixin of ``LiveCalibrator`` (its state lives there)."""

    def _gates(self) -> Gates:
        s = self.settings
        return Gates(s.min_pairs, s.min_poses, s.min_fitness, s.poor_fitness,
                     s.min_lag_confidence, s.max_rot_deg, s.max_far_m, s.edge_m)

    # ------------------------------------------------------------ lags
    def _lag_due(self, st: SensorState, now: float) -> bool:
        s = self.settings
        if not s.lag_search or st.sensor == self._reference or st.duplicate_of is not None:
            return False
        if st.state == "ok":  # tracking: only while self-healing watches the sensors
            # the next search is due sooner while a sure one waits for another to agree; a
            # search that had nothing to compare waits for its retry time (_search_lag)
            every = (self._lag_every(st) if st.lag_candidate is None
                     else min(2.0, s.lag_every_s))
            return (s.heal and s.lag_every_s > 0 and now - st.lag_searched >= every
                    and now >= self._lag_retry.get(st.sensor, -np.inf))
        # a sensor to calibrate: every second, also once two searches agreed: the timing's
        # confidence judges a poor fit (Gates.too_poor), and it should be the confidence of
        # a search on what is buffered now, not of the first, short one
        return now - st.lag_searched >= 1.0

    def _lag_every(self, st: SensorState) -> float:
        """How long a tracked sensor waits for its next lag search: ``lag_every_s``, doubled
        for every search in a row that moved and proposed nothing, up to ``lag_every_max_s``.

        A crowd's searches are unsure (confidence 0.02-0.07 at 6 sensors x 6 people, where a
        tracked lag moves only at 0.3) and one person's confirm the lag in use; either way the
        next search most likely says the same. Measured at 6 x 6: the searches were a fifth
        of the calibrator's CPU (docs/reports/issue-10.md, stop 32). A search that proposes
        a lag starts the count over (and the next one is due in 2 s to confirm it)."""
        s = self.settings
        return min(s.lag_every_s * 2.0 ** min(st.lag_quiet, 16),
                   max(s.lag_every_max_s, s.lag_every_s))

    def _search_lag(self, sid: str, views: dict[str, list[View]], trusted: list[str],
                    now: float, since: float) -> LagSearch | None:
        """The sensor's remaining lag against a trusted sensor seeing the same person, on
        its frames after ``since`` (a suspect's frames from before it moved would mix two
        placements)."""
        s = self.settings
        mine = [v.after(since) for v in views.get(sid, []) if v.t[-1] > now - 1.0]
        mine = [v for v in mine if v is not None and len(v.t) >= 3]
        pairs: list[tuple[View, View]] = []
        for r in trusted:
            if r == sid:
                continue
            theirs = [v for v in views.get(r, []) if v.t[-1] > now - 1.0 and len(v.t) >= 3]
            if len(mine) == 1 and len(theirs) == 1:
                pairs.append((mine[0], theirs[0]))
            else:  # the same person, as the engine bound the views (calibrated sensors only)
                pairs += [(a, b) for a in mine for b in theirs
                          if a.person is not None and a.person == b.person]
        known = self._states.get(sid)  # the engine thread may have forgotten it
        if known is None:
            return None
        tracking = known.state == "ok"
        if not pairs:
            if tracking:  # nobody to compare with: a due search made every poll snapshot and
                # rebuild every buffered frame (a third of a core at 6 x 6); look again in 1 s
                self._lag_retry[sid] = now + 1.0
            return None
        # the longest common stretch, the reference first
        def common(p: tuple[View, View]) -> float:
            return min(p[0].t[-1], p[1].t[-1]) - max(p[0].t[0], p[1].t[0])
        a, b = max(pairs, key=lambda p: (common(p), p[1].sensor == self._reference))
        span = min(a.t[-1] - a.t[0], b.t[-1] - b.t[0])
        need = 4 * s.lag_min_s if tracking else s.lag_min_s
        if span < need:
            if tracking:  # not before both views can have grown long enough
                self._lag_retry[sid] = now + (need - span)
            return None  # too little to say yet: try again at the next poll
        ok = np.isfinite(b.stage).all(axis=(1, 2))
        ref = Stream(b.sensor, b.t[ok], np.zeros(int(ok.sum()), int), b.stage[ok], b.conf[ok])
        other = Stream(sid, a.t, np.zeros(len(a.t), int), a.raw, a.conf)
        try:
            # tracking: the lag in use is known; a small correction is all a search can
            # find that the monitor would not already see as a misfit (a quarter of the lags)
            if tracking:  # and it moves only by two frames or more (_update_lag): a finer
                # grid than half a frame around the best one decides nothing
                return find_lag(ref, other, min(s.max_lag_s, s.track_lag_s), fine_steps=2,
                                min_pairs=s.min_pairs, pause=self._yield)
            return find_lag(ref, other, s.max_lag_s, min_pairs=s.min_pairs, pause=self._yield)
        except CalibrationError:
            return LagSearch(0.0, np.zeros(0), np.zeros(0), 0)  # searched: no overlap

    def _update_lag(self, st: SensorState, search: LagSearch | None, now: float) -> None:
        """Apply a search's result (caller holds the lock), and count a tracked sensor's
        searches in a row that moved and proposed nothing (``_lag_every``)."""
        if search is None:
            return
        tracking, before = st.state == "ok", (st.lag_s, st.lag_candidate)
        self._move_lag(st, search, now)
        quiet = tracking and before == (st.lag_s, st.lag_candidate)
        st.lag_quiet = st.lag_quiet + 1 if quiet else 0

    def _move_lag(self, st: SensorState, search: LagSearch, now: float) -> None:
        """Apply a search's result (caller holds the lock).

        A calibrated sensor's lag (tracking) is what every judgement of it rests on, so it
        moves only on a sure search (``lag_track_confidence``), to a lag that fits clearly
        better than the one in use on the same frames (``lag_hysteresis``), and only when
        the next search agrees within two frames: in a crowd, searches on a few seconds of
        one person read confidences of 0.05-0.1 and land anywhere in the window (a
        synchronised simulated sensor was moved by -0.997 s on confidence 0.09)."""
        s = self.settings
        st.lag_searched = now
        st.lag_last = search.confidence
        tracking = st.state == "ok"
        # a sensor being re-calibrated after it was suspected had a lag that held while it
        # agreed: a bump moves a sensor, not its clock, so its lag moves only on the grounds a
        # tracked one needs (a sure search that fits clearly better), though at once; a clock
        # that really jumped gives such a search. (A 10-degree bump on the ring moved a
        # synchronised sensor 0.8 frame on confidence 0.23 and re-calibrated it 2.2 degrees
        # and 55 mm off, where keeping the lag gives 0.8 degrees and 34 mm.)
        held = tracking or st.last_good is not None
        if search.confidence < (s.lag_track_confidence if tracking else s.lag_min_confidence):
            st.lag_candidate = None  # an unsure search breaks a run of agreeing ones
            return  # nothing moved enough to say: keep the lag we have
        st.lag_confidence = search.confidence
        if abs(search.lag_s) < 1.0 / 30:
            st.lag_settled = True  # this search agrees with the lag in use
            st.lag_candidate = None
        if not tracking and search.confidence < (s.lag_track_confidence if held
                                                 else s.lag_move_confidence):
            # too unsure to move a new sensor's lag (its first searches see little), or one
            # that held: that one stays, as settled as the search can tell
            st.lag_settled = st.lag_settled or held
            return
        # a calibrated sensor's lag moves only by two frames or more (a tracked lag is a
        # correction, and noise in it would shake every judgement); a new sensor's by half
        if abs(search.lag_s) < (2.0 if held else 0.5) / 30:
            st.lag_settled = st.lag_settled or held
            return
        # hysteresis: short or periodic takes have near-equal minima; move only to a lag that
        # fits clearly better than the one in use, on the same frames -- unless this search,
        # for a sensor still to calibrate, saw much more than the one that set it (a first
        # search sees little); a lag that held always needs it
        here = np.flatnonzero(np.abs(search.lags) <= 1e-6)
        judged = len(here) > 0 and bool(np.isfinite(search.residual[here[0]]))
        more = search.overlap > 1.5 * st.lag_overlap and not held
        if st.lag_overlap:
            st.lag_overlap = max(st.lag_overlap, search.overlap) if not more else st.lag_overlap
        if tracking and not judged:
            return  # the lag in use could not be judged on these frames: no grounds to move
        if not more and judged:
            best = float(np.nanmin(search.residual))
            if best > (1.0 - s.lag_hysteresis) * float(search.residual[here[0]]):
                st.lag_settled = True  # the lag in use fits about as well: keep it
                st.lag_candidate = None
                return
        before = st.lag_s
        lag = float(np.clip(st.lag_s + search.lag_s, -s.max_lag_s, s.max_lag_s))
        if st.loop_s and not st.loop_folded:  # a looped take's lag searched on the loops is
            # only defined modulo its period: keep it near 0
            lag = float((lag + 0.5 * st.loop_s) % st.loop_s - 0.5 * st.loop_s)
        if abs(lag - before) < 0.5 / 30:
            return
        if tracking:  # one sure search proposes; the next one (due soon) must agree
            if st.lag_candidate is None or abs(lag - st.lag_candidate) > 2.0 / 30:
                st.lag_candidate = lag
                return
            st.lag_candidate = None
        st.lag_s = round(lag, 4)
        st.lag_settled = False
        st.lag_overlap = search.overlap
        if st.pairs is not None:      # pairs taken at the old lag mean nothing now
            st.reset_pairs()
        self._window.forget(st.sensor)
        text = (f"its clock runs {st.lag_s:+.3f} s from stage time (was {before:+.3f} s; "
                f"lag search confidence {search.confidence:.2f})")
        log.info("sensor %s: %s", st.sensor, text)
        self._event(LiveEvent(now, st.sensor, "lag", text))

    def _buffered(self, sid: str, since: float, lag: float, placed: bool) -> Stream | None:
        """A sensor's buffered frames after ``since`` with one person in view, as one stream
        (caller holds the lock): on stage time (its lag taken off), one user id per
        identity run; ``placed``: in stage space with the transform each frame had (frames
        without one left out)."""
        entries = [e for key, buf in self._buffers.items() if key[0] == sid for e in buf
                   if e[0].t > since and (not placed or e[0].transform is not None)]
        if len(entries) < 3:
            return None
        entries.sort(key=lambda e: e[0].t)
        rows = [e[0] for e in entries]
        joints = np.stack([f.joints for f in rows])
        if placed:
            joints = np.stack([f.joints @ f.transform[:3, :3].T + f.transform[:3, 3]
                               for f in rows])
        t = np.array([f.t for f in rows]) - lag
        conf = np.stack([f.conf for f in rows])
        # frames with one person in view, judged on the sensor's own user ids: a person lost
        # and found again under the same id (a looped take, every loop) is still one person
        alone = Stream(sid, t, np.array([f.user for f in rows]), joints, conf).single_user()
        if alone.sum() < 3:
            return None
        # one "user" per identity run, so nothing is interpolated across a lost-and-found
        users = np.array([f.user * 100003 + e[2] for f, e in zip(rows, entries)])
        return Stream(sid, t, users, joints, conf).subset(alone)

    def _search_buffers(self, sid: str, trusted: list[str], since: float,
                        ) -> LagSearch | None:
        """A new sensor's remaining lag: its buffered frames (one person in view) against a
        trusted sensor's, the reference first. Long, uncut streams: a lag searched on a
        short stretch of a short take finds one of its near-equal minima.

        Frames with two people in view are left out by the sensor's own user ids
        (``_buffered``); the identity runs only keep interpolation within one run. Judged
        by the runs instead, a person lost and found again (``stage replay --loop`` of a
        1-2 s take: every loop) lost the frames around each loop's start and end, and the
        live search on N-UCLA read confidences of 0.08-0.14 (the poor-fit gate wants 0.15)
        where the same frames with the runs joined read 0.19-0.48. A source that loops a
        take sends the same frames again every period P, so a lag and the lag P away pair
        the same frames: the search then looks within +-P/2 (``loop_period``), and the
        period is kept to judge a stalled take after one loop (``_ready``)."""
        s = self.settings
        with self._lock:
            if sid not in self._states:   # the engine thread may have forgotten it
                return None
            mine = self._buffered(sid, since, self._states[sid].lag_s, placed=False)
            partners = [(self._buffered(r, -np.inf, self._states[r].lag_s, placed=True), r)
                        for r in sorted(trusted, key=lambda r: r != self._reference)
                        if r != sid and r in self._states]
        if mine is None or mine.t[-1] - mine.t[0] < s.lag_min_s:
            return None
        period = loop_period(mine.t, mine.joints)
        with self._lock:
            if sid in self._states:
                self._states[sid].loop_s = period
        with self._lock:
            lags = {r: st.lag_s for r, st in self._states.items()}
        for theirs, r in partners:
            if theirs is None or theirs.t[-1] - theirs.t[0] < s.lag_min_s:
                continue
            a, b, max_lag, folded = theirs, mine, s.max_lag_s, None
            if period is not None:  # one pass of the take each, as offline
                folded = fold_loops(theirs, lags.get(r, 0.0), mine, lags.get(sid, 0.0), period)
                if folded is not None:
                    a, b = folded
                else:  # a lag and the lag P away pair the same frames
                    max_lag = min(max_lag, 0.5 * period)
            with self._lock:
                st = self._states.get(sid)
                if st is not None:  # folded: the lag is that of one pass, not modulo P
                    if folded is not None and not st.loop_folded:
                        st.lag_overlap = 0  # the first search on one pass replaces those
                        # made on the loops before the loop was seen (their frames wrapped)
                    st.loop_folded = folded is not None
            try:
                return find_lag(a, b, max_lag, min_pairs=s.min_pairs, single_window_s=0.0,
                                pause=self._yield)  # _buffered kept one person's frames
            except CalibrationError:
                continue
        return None

    def _track_lags(self, now: float, views: dict[str, list[View]], states: dict,
                    epochs: dict) -> None:
        """Search the lag of every sensor it is due for (worker thread)."""
        trusted = [sid for sid, (state, *_rest) in states.items() if state == "ok"]
        with self._lock:
            due = [(sid, st.state == "ok", st.collect_from)
                   for sid, st in self._states.items() if self._lag_due(st, now)
                   and (st.state == "ok" or self._wants_pairs(st))]
        for sid, tracking, since in due:
            if tracking:
                search = self._search_lag(sid, views, trusted, now, -np.inf)
            else:
                search = self._search_buffers(sid, trusted, since)
            self._yield()
            with self._lock:
                st = self._states.get(sid)  # the engine thread may have forgotten it
                if st is not None and st.epoch == epochs.get(sid):
                    self._update_lag(st, search, now)

    # ------------------------------------------------------------ pairs
    def _wants_pairs(self, st: SensorState) -> bool:
        s = self.settings
        return st.duplicate_of is None and not st.busy and (
            st.requested or (st.state == "uncalibrated" and s.auto_calibrate)
            or (st.state == "suspect" and s.heal))

    def _ready(self, st: SensorState, now: float) -> bool:
        """Enough pairs: ``needed`` of them, or ``wanted_poses`` distinct poses, or no new
        pose for ``poses_stall_s`` (a looped take, a repeated gesture: more of the same
        adds nothing; the gates then judge what there is)."""
        s = self.settings
        if (s.lag_search and not st.lag_settled and st.state != "ok"
                and st.sensor != self._reference):  # stage time is the reference's clock
            return False  # two lag searches must agree first (short takes fool one)
        n = 0 if st.pairs is None else len(st.pairs)
        if n >= st.needed:
            return True
        if n < s.min_pairs:
            return False
        stall = s.poses_stall_s
        if st.loop_s is not None and stall > 0:  # a looped take: one loop shows all it has
            stall = min(stall, st.loop_s + 0.2)
        return len(st.poses) >= st.wanted_poses or now - st.poses_grew >= stall > 0

    def _collect(self, now: float, views: dict[str, list[View]], states: dict, epochs: dict,
                 ) -> None:
        s = self.settings
        t1 = now - s.delay_s
        trusted = [sid for sid, (state, *_rest) in states.items() if state == "ok"]
        for sid in states:
            with self._lock:
                st = self._states.get(sid)  # the engine thread may have forgotten it
                if st is None:
                    continue
                wanted = self._wants_pairs(st)
                start = max(st.collected_to, st.collect_from)
                # a lag search of this poll moved its lag: these views are on the old one
                stale = bool(views.get(sid)) and abs(views[sid][0].shift - st.lag_s) > 1e-9
            if not wanted or stale:
                continue
            # with lags, sensors' frames reach the same stage time at different moments:
            # pair only up to where the sensor and its partners all have frames
            latest = [max(v.t[-1] for v in views[r]) for r in [sid, *trusted]
                      if views.get(r) and max(v.t[-1] for v in views[r]) > now - 1.0]
            until = min([t1, *latest])
            with self._lock:  # partners that agree with the others as a good fit does
                good = {r for r in trusted if r in self._states
                        and (self._states[r].fitness or 0.0) >= s.min_fitness}
            new, waiting = new_pairs(sid, views, trusted, start, until, now, s.min_joints,
                                      self._reference, good)
            self._yield()
            with self._lock:
                st = self._states.get(sid)
                if st is None or st.epoch != epochs.get(sid):
                    continue
                if waiting is not None:
                    st.reason = waiting
                elif new is not None:
                    st.collected_to = max(st.collected_to, until)
                    before = 0 if st.pairs is None else len(st.pairs)
                    st.pairs = new if st.pairs is None else st.pairs.concat(new)
                    count = st.poses.add(new.other, new.weight)
                    if count > st.poses_count:
                        st.poses_count, st.poses_grew = count, now
                    st.reason = (f"collecting pairs with {', '.join(new.partners)}"  # type: ignore[attr-defined]
                                 + (f" at lag {st.lag_s:+.3f} s" if st.lag_s else ""))
                    quarter = max(st.needed // 4, 1)
                    if len(st.pairs) // quarter > before // quarter:
                        log.info("calibrating %s: %d/%d pairs, %d distinct poses", sid,
                                 min(len(st.pairs), st.needed), st.needed, len(st.poses))
                self._note(st)

    # ------------------------------------------------------------ fit and accept
    def _level(self, sid: str) -> float:
        """How far apart the trusted sensors other than ``sid`` see people (median, m)."""
        ok = {k for k, st in self._states.items() if st.state == "ok" and k != sid}
        keys = [k for k in self._window.keys() if k[0] in ok and k[1] in ok]
        return self._window.median(keys) if keys else float("nan")

    def _judge_fit(self, st: SensorState, result: CalibrationResult,
                   spread: Uncertainty | None = None) -> str | None:
        """Why a fit is not accepted, or None (caller holds the lock)."""
        s = self.settings
        gates = self._gates()
        why = gates.too_little(result.pairs, len(st.poses)) or gates.too_poor(
            result.fitness, result.median_m, st.lag_confidence if s.lag_search else None)
        if why is None and spread is not None:
            why = gates.too_uncertain(spread)
        if why is not None:
            return why
        if result.fitness >= s.accept_above:
            return None
        level = self._level(st.sensor)
        if np.isfinite(level):
            if result.median_m <= s.accept_ratio * level:
                return None
            return (f"fit too poor: median joint distance {result.median_m * 100:.1f} cm, more "
                    f"than {s.accept_ratio:g} x the {level * 100:.1f} cm the trusted sensors "
                    f"agree within (fitness {result.fitness:.2f} < {s.accept_above:g})")
        if st.state == "uncalibrated" or st.last_good is None:
            return None  # a first calibration with nobody to compare with: the gates decide
        return (f"fit too poor: median joint distance {result.median_m * 100:.1f} cm (fitness "
                f"{result.fitness:.2f} < {s.accept_above:g})")

    def _job(self, st: SensorState, epoch: int, now: float) -> None:
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
        spread = None  # how well the pairs determine the fit (the same tolerance as offline)
        if result is not None and self._gates().judges_uncertainty:
            spread = fit_uncertainty(pairs, result.matrix, s.edge_m, pause=self._yield)
        with self._lock:
            st.busy = False
            if st.epoch != epoch:
                return  # something happened meanwhile (quarantined again, a request)
            if st.state == "recalibrating":
                st.state = "suspect"
            was = st.state
            why = error if result is None else self._judge_fit(st, result, spread)
            if result is not None and why is None:
                m = result.matrix
                st.state, st.transform, st.last_good = "ok", m, m
                st.reset_pairs()
                st.requested, st.fitness, st.since = False, result.fitness, now
                st.residual = result.median_m
                st.baseline = _worst_window(pairs, result.matrix, s.window_s)
                st.healthy = None  # a new transform: how close it agrees is learnt anew
                st.below_since = st.above_since = None
                verb = "re-calibrated" if was == "suspect" else "calibrated"
                st.reason = (f"{verb} by {result.method}: median joint distance "
                             f"{result.median_m * 1000:.0f} mm (rms {result.rms_m * 1000:.0f} mm),"
                             f" fitness {result.fitness:.2f}, {result.pairs} pairs")
                if spread is not None:
                    st.reason += f", spread {spread.text()}"
                if st.lag_s:
                    st.reason += f", lag {st.lag_s:+.3f} s"
                st.last_attempt = st.reason
                st.epoch += 1
                st.window = None
                self._window.forget(sid)
                self._gate.trust(sid, True)
                self._act(lambda e: e.set_calibration(sid, m))
                log.info("sensor %s %s", sid, st.reason)
                self._event(LiveEvent(now, sid, "calibrated", st.reason, m, result.fitness))
            else:
                kept = pairs.subset(slice(len(pairs) // 2, None))  # keep the newer half
                st.reset_pairs()
                st.pairs = kept
                st.poses_count, st.poses_grew = st.poses.add(kept.other, kept.weight), now
                st.last_attempt = f"rejected: {why}"
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


def _worst_window(pairs, m: np.ndarray, window_s: float) -> float:
    """The largest median joint distance of ``m`` over any ``window_s`` stretch of the
    pairs (m): how far a healthy sensor's residual wanders with this kind of data."""
    from .fitness import residuals, weighted_median
    if not len(pairs):
        return float("nan")
    r = residuals(m, pairs.other, pairs.ref)
    chunk = np.floor((pairs.t - pairs.t[0]) / window_s).astype(int)
    worst = float("nan")
    for k in np.unique(chunk):
        rows = chunk == k
        if rows.sum() >= 3:
            med = weighted_median(r[rows], pairs.weight[rows])
            worst = med if not np.isfinite(worst) else max(worst, med)
    return worst
