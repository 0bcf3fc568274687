"""The live calibrator's judging side: who disagrees, who is suspect, who fits again.

A ``healing`` part. Every poll the joint distances between every two
trusted sensors that see one person go into a window; ``judge`` says who
disagrees with the others by more than they agree among themselves (or, with
nobody else to compare, than the sensor did when it was calibrated here).
Such a sensor is suspect after ``hold_s`` and left out of fusion; never more
than half of the calibrated sensors at once: when more look wrong together
the last good calibrations stay in use and a ``held`` event says so. A
suspect whose last good transform fits again for ``restore_s`` (fitness above
``restore_above``, or within ``restore_ratio`` of how close the others agree
or of how close it agreed itself while healthy) is restored.
"""

from __future__ import annotations

import logging

import numpy as np

from .fitness import fitness_from_median
from .judge import Verdict, judge, judge_suspect
from .live import View
from .livestate import LiveEvent, SensorState
from .scoring import distances, grid

log = logging.getLogger("stage.calibration")


class Monitor:
    """Mixin of ``LiveCalibrator`` (its state lives there)."""

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
            self._window.add_histograms(t1, {k: v for k, v in trusted.items()
                                             if not set(k) & changed})
            ok = [sid for sid, st in self._states.items() if st.state == "ok"
                  and st.transform is not None and st.duplicate_of is None]
            baselines = {sid: self._states[sid].baseline for sid in ok}
            verdict = judge(self._window, ok, self._reference, s.suspect_below, s.suspect_ratio,
                            baselines)
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
                    r = verdict.residual[sid]
                    st.healthy = r if st.healthy is None else 0.9 * st.healthy + 0.1 * r
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
                # back as close as the others agree, or as it agreed itself before (two
                # sensors facing each other see opposite sides of a body: their healthy
                # residual can sit above restore_above for good)
                if (st.fitness >= s.restore_above
                        or np.isfinite(lvl) and r <= s.restore_ratio * lvl
                        or st.healthy is not None and r <= s.restore_ratio * st.healthy):
                    st.above_since = now if st.above_since is None else st.above_since
                    if now - st.above_since >= s.restore_s:
                        self._restore(st, now, lvl)
                else:
                    st.above_since = None
                self._note(st)
            self._decide(now, candidates, verdict)

    def _decide(self, now: float, candidates: list[SensorState], verdict: Verdict) -> None:
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

    def _restore(self, st: SensorState, now: float, level: float = float("nan")) -> None:
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

    def _calibrated(self) -> list[SensorState]:
        """Sensors with a calibration, in use or last good (copies are not sensors)."""
        return [st for st in self._states.values() if st.duplicate_of is None and (
            st.state == "ok" and st.transform is not None
            or st.state in ("suspect", "recalibrating") and st.last_good is not None)]

    def _room_for_suspect(self, more: int = 1) -> bool:
        """Whether ``more`` sensors can be left out with at least half still trusted."""
        cal = self._calibrated()
        trusted = sum(st.state == "ok" for st in cal)
        return trusted - more >= (len(cal) + 1) // 2 and trusted - more >= 1

    def _hold(self, t: float, states: list[SensorState], why: str) -> None:
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

