"""The live calibrator's checks of every frame: a bumped sensor, a copied stream.

A ``healing`` part (mixin of ``LiveCalibrator``, whose state it uses). Every
frame of a trusted sensor puts its view's tracked torso joints, in stage space,
into the jump gate (``gate.JumpGate``): one view at a time inline (offline, tests:
``threaded=False``); on the worker, one datagram's views at a time (one sensor,
one capture time: the gate's ``check_many``), the same check with a handful of
numpy calls per datagram instead of per skeleton. Two sensors sending
bit-identical skeletons (``gate.CopyDetector``): the copy is left out.
"""

from __future__ import annotations

import logging

import numpy as np

from ..engine import jit
from ..frames import SensorFrame
from ..joints import TORSO
from .livestate import LiveEvent, SensorState

log = logging.getLogger("stage.calibration")
_TORSO = np.array(TORSO)


class FrameChecks:
    """Mixin of ``LiveCalibrator`` (its state lives there)."""

    def _check_jump(self, frame: SensorFrame, st: SensorState) -> None:
        """Quarantine at once a sensor whose views jumped away from sensors they agreed with.

        One view jumping is a bump only when it is all the sensor sees; with
        several people, a bump moves every view of the sensor in the same
        frame, while one view alone jumping is the sensor giving a freed user
        id to another person (a Kinect reuses its body indices): that view's
        old agreements are forgotten instead.
        """
        m = frame.transform
        # tracked torso joints only: a torso the sensor only infers (a person hidden in a
        # crowd) is a guess, 10-30 cm off now and then, not evidence that the sensor moved;
        # the gate compares two views on the joints both track (see gate.JumpGate)
        tracked = frame.conf[_TORSO] >= 1.0
        if m is None or not tracked.any():
            return
        sid, user, t = frame.sensor, frame.user, frame.t - st.lag_s  # on stage time
        jumped = self._gate.check(sid, user, t, frame.joints[_TORSO] @ m[:3, :3].T + m[:3, 3],
                                  tracked)
        if jumped is not None:
            self._jumped(st, user, t, jumped)

    def _check_jumps(self, group: list[tuple[SensorFrame, SensorState]]) -> None:
        """``_check_jump`` for one datagram's frames: one sensor, one capture time, distinct
        users, in the engine's order (caller holds the lock)."""
        if len(group) == 1:
            self._check_jump(*group[0])
            return
        first, st = group[0]
        # the usual datagram: every skeleton of it, as decoded (rows of its own two arrays,
        # in order: the engine applies a datagram's skeletons in the order they came): judged
        # in one compiled call, without stacking what the decoder had stacked already
        joints, conf, m = first.joints.base, first.conf.base, first.transform
        if (joints is not None and conf is not None and len(joints) == len(group) == len(conf)
                and jit.ready()
                and all(f.joints.base is joints and f.conf.base is conf and f.transform is m
                        for f, _ in group)):
            t = first.t - st.lag_s  # on stage time
            try:
                jumps = self._gate.check_frames(st.sensor, tuple(f.user for f, _ in group), t,
                                                joints, conf, m)
            except TypeError:   # arrays the kernel does not take (not C-ordered float64)
                pass
            else:
                for r, jumped in jumps:
                    if st.state != "ok":
                        break  # left out by an earlier view of this datagram
                    self._jumped(st, group[r][0].user, t, jumped)
                return
        frames = [f for f, _ in group if f.transform is not None]
        if not frames:
            return
        tracked = np.array([f.conf for f in frames])[:, _TORSO] >= 1.0      # (k, P)
        seen = np.flatnonzero(tracked.any(axis=1))
        if not len(seen):
            return
        if len(seen) < len(frames):
            frames = [frames[k] for k in seen]
            tracked = tracked[seen]
        c = np.array([f.joints for f in frames])[:, _TORSO]                  # (k, P, 3)
        m = frames[0].transform
        if all(f.transform is m for f in frames):  # frames of one datagram share it
            placed = c @ m[:3, :3].T + m[:3, 3]
        else:
            placed = np.array([p @ f.transform[:3, :3].T + f.transform[:3, 3]
                               for f, p in zip(frames, c)])
        t = frames[0].t - st.lag_s  # on stage time
        results = self._gate.check_many(st.sensor, [f.user for f in frames], t, placed,
                                        tracked)
        for frame, jumped in zip(frames, results):
            if st.state != "ok":
                break  # left out by an earlier view of this datagram: the rest are not judged
            if jumped is not None:
                self._jumped(st, frame.user, t, jumped)

    def _jumped(self, st: SensorState, user: int, t: float,
                jumped: tuple[list[str], float]) -> None:
        """A view of ``st``'s sensor jumped: a bump when every view of it did (see
        ``_check_jump``), else that view's old agreements are forgotten."""
        sid = st.sensor
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
            st.reset_pairs()
            self._note(st)

    def _expire_duplicates(self, now: float) -> None:
        for pair in self._copies.expired(now):
            for sid in pair:
                st = self._states.get(sid)
                if st is not None and st.duplicate_of in pair:
                    st.duplicate_of = None
                    st.collect_from = st.collected_to = now
                    st.reason = "no longer a copy: checking and re-calibrating"
                    st.reset_pairs()
                    st.epoch += 1
                    self._note(st)
