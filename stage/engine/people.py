"""The people on stage: calibrated sensor frames in, fused persons and their messages out.

``People`` is the engine's fusion path, on the engine thread. Per batch of
inbound items (live: one datagram) the engine hands it each calibrated frame
(``frame``) and hand state (``hand``); at the end of the batch ``flush`` folds
every frame into its person's filter -- all persons of the batch in one numpy
step per wave (``fuser``) -- sends each updated person's skeleton once, at
once (nothing waits for a later frame), and then votes hands (``hands``):
the batch's hand reports go to the voters after its skeletons are out, so no
skeleton waits for hand work. ``tick`` merges and expires persons and serves
views that asked for a fixed rate.

Latency is recorded per input frame: from its datagram's arrival to the
datagram out that includes it (its person's skeleton).
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from ..clock import Clock
from ..errors import ConfigError
from ..frames import Body, Forecasts, FusedFrame
from ..joints import INFERRED, JOINT_INDEX, N_JOINTS, TORSO, HandState
from ..rig import Rig
from ..stats import DropCounter, LatencyWindow
from .bank import PersonBank
from .callbacks import Callbacks
from .forecast import Forecast, Forecaster
from .fuser import Fuser, View
from . import jit, offsets
from .fusion import (_CHILDREN, _LOOK, _PARENTS, _TRADED, ARM_TRADED, SWAP_MARGIN_M,
                     apply_transform, carry_untracked, torso_centre, unswap_limbs)
from .kalman import KalmanSettings, measurement_variance
from .native import NativeCore
from .output import ViewOutput
from .tracking import Person, Track, Tracker

log = logging.getLogger("stage.engine")
_TORSO = np.array(TORSO)
_HAND_JOINT = (JOINT_INDEX["HandLeft"], JOINT_INDEX["HandRight"])
_NO_R = np.full(25, np.nan)
#: a new person's time: it has no known joint until its first view sets its time (a
#: person's known joints only ever grow), so testing the time tells a new person cheaper
#: than counting its known joints
_NEVER = float("-inf")
#: smoothing off: a filter so loose that every joint is its latest measurement
_UNSMOOTHED = dict(quiet_noise=1e12, fast_noise=1e12)
#: a person the Python path folded this many datagrams in a row (none dropped as late) is
#: taken by the native core (``fusion.native``) ...
TAKE_AFTER = 3
#: ... and twice as many after each time it is given back having been folded fewer than
#: ``KEEP_STEPS`` times by the core, up to this many (a person whose views often need what
#: only the Python path does, rows to start or restart, would otherwise go back and forth)
TAKE_AFTER_MAX = 192
KEEP_STEPS = 200


def _variance_rows(joints: np.ndarray, conf: np.ndarray, where: np.ndarray,
                   smoothing: KalmanSettings) -> np.ndarray:
    """(K, 25) measurement variances of K views' joints (K, 25, 3) with confidences (K, 25),
    seen by sensors at ``where`` (K, 3): by confidence and distance (without the kernels;
    ``jit.frame_r`` gives the same floats per frame)."""
    offset = joints - where[:, None]
    offset *= offset
    d2 = offset[..., 0] + offset[..., 1]          # .sum(axis=2), the same floats, cheaper
    d2 += offset[..., 2]
    seen = conf > 0
    return np.where(seen, measurement_variance(np.where(seen, conf, 1.0), np.sqrt(d2),
                                               smoothing), np.nan)


def _by_person(entry: tuple[Person, View]) -> int:
    return entry[0].id


class People:
    """Persons, their filters and hand votes, and what views are sent (engine thread only)."""

    def __init__(self, rig: Rig, clock: Clock, output: ViewOutput, listeners: Callbacks,
                 drops: DropCounter, latency: LatencyWindow, counts: dict[str, int]) -> None:
        self.rig, self.clock, self.output, self.listeners = rig, clock, output, listeners
        self.drops, self.latency, self.counts = drops, latency, counts
        self.tracker = Tracker(rig.fusion)
        #: the arrays persons are settled from, a row per person (for the compiled settle)
        self.bank = PersonBank()
        smoothing = rig.smoothing
        if not rig.smoothing_enabled:
            smoothing = dataclasses.replace(smoothing, **_UNSMOOTHED)
        self.smoothing: KalmanSettings = smoothing
        #: ``fusion.view_offset_s``; 0 (off) with smoothing off, where each joint is its
        #: latest measurement: a joint back from an occlusion is then its old position, and
        #: learning from it moved the views by tens of centimetres (bench_fusion.py, stop 44)
        self._offset_s = rig.fusion.view_offset_s if rig.smoothing_enabled else 0.0
        # smoothing off: each joint its latest accepted measurement, every velocity zero
        # (``fuser``); the native core, which keeps the filter's velocities, is not used
        self.fuser = Fuser(smoothing, rig.fusion, hold=not rig.smoothing_enabled)
        #: ``fusion.native``: the core that folds a datagram's usual views in one compiled
        #: call (``native``), the persons it holds bound to it; None: the Python path alone
        self.core: NativeCore | None = None
        if rig.fusion.native and rig.smoothing_enabled:
            try:
                self.core = NativeCore(smoothing, rig.fusion, self.fuser.q_scale)
            except RuntimeError as exc:
                # without any kernels (STAGE_JIT=0, no numba) the engine has said so in one
                # line already; a warning only when the core's own kernel failed
                (log.warning if jit.ready() else log.info)(
                    "fusion: native is on but %s; the Python path folds every datagram", exc)
        #: with the core: the last ``prepare_frames`` call's arrays (joints, conf, variances)
        #: and their rows as handed to the views, which the core then takes as they are
        self._batch: tuple | None = None
        #: this batch's frames of persons the core holds whose view offsets are still to be
        #: learned (``_offsets_held``): ((row in the batch's arrays or -1, slot, view row),
        #: (capture time, the person's newest time), joints, confidences)
        self._held_offsets: list[tuple] = []
        #: person id -> its skeleton as the core encoded it in this batch
        self._encoded: dict[int, bytes] = {}
        #: person id -> datagrams in a row the Python path folded it with no view dropped late
        self._python_run: dict[int, int] = {}
        #: person id -> the run it needs to be taken (TAKE_AFTER unless given back lately)
        self._take_after: dict[int, int] = {}
        #: bodies predicted ahead of their capture time (docs/anticipation.md): the
        #: horizons listeners asked for (horizon -> how many asked), and the views'
        self.forecaster = Forecaster(smoothing, rig.forecast)
        self.horizons: dict[float, int] = {}
        self._eager: dict[float, int] = {}        # (those asked for not lazily)
        self._forecasts: dict[tuple[int, float], Forecast] = {}   # this emission's
        #: the batch's views, each with its sensor's transform (whose translation is where
        #: the sensor is: the variances without the kernels, ``_variances``)
        self._views: list[tuple[Person, View, np.ndarray]] = []
        self._dirty: dict[int, list[float]] = {}   # person id -> arrivals of frames folded in
        self._hands_dirty: set[int] = set()         # persons whose hand vote may have changed
        #: the batch's hand reports, in the order they came, each the voter's method and its
        #: arguments: a frame's ``add_frame``, a /handState's ``add``; given to the voters
        #: after the batch's skeletons are sent (``_emit``)
        self._reports: list[tuple] = []
        self._lost: list[int] = []
        #: persons whose skeletons went out in a burst's earlier datagrams, their hand votes
        #: and listeners' frame held for its last (``flush(votes=False)``), and of those
        #: the ones first announced then
        self._held: dict[int, None] = {}
        self._held_new: list[int] = []
        #: this batch's frames computed together (``prepare_frames``): id of the frame's
        #: joints array -> (joints, conf, transform, then what ``jit.frame_r`` gives for it:
        #: stage-space joints, conf, traded bits, variances, trunk length, joints seen)
        self._framed: dict[int, tuple] = {}

    @property
    def persons(self) -> dict[int, Person]:
        return self.tracker.persons

    # ------------------------------------------------------------ input
    def frame(self, track: Track, transform: np.ndarray, joints: np.ndarray, conf: np.ndarray,
              t: float, arrival: float, hands: list | None = None) -> bool:
        """One calibrated sensor frame of ``track``: sensor-space ``joints`` (25, 3), ``conf``
        (25,), captured at ``t``; its datagram arrived at ``arrival`` (engine clock).

        ``hands``: the ``/handState`` items that followed the frame in its datagram at ``t``
        (``engine._with_hands``). The frame's hand votes take their states, which is what
        ``hand`` for each of them after the frame would leave. Returns whether the frame
        reached a person; if not, nothing was done with ``hands`` (the caller gives each
        to ``hand``)."""
        r = _NO_R          # the variances: here with the kernels, else for the batch in _fold
        size = None        # the trunk: here with the kernels, else in _fold
        pos = -1           # the frame's row in the batch's arrays (``prepare_frames``)
        framed = self._framed.get(id(joints)) if self._framed else None
        if framed is not None and framed[0] is joints and framed[1] is conf \
                and framed[2] is transform:
            _, _, _, track.joints, conf, traded, r, size, n_seen, pos = framed
        elif jit.ready():
            track.joints, conf, traded, r, size, n_seen = jit.frame_r(
                transform, joints, conf, self.rig.fusion.unswap_limbs, _LOOK, _TRADED,
                SWAP_MARGIN_M, self.smoothing, INFERRED)
        else:
            track.joints = apply_transform(transform, joints)
            traded = 0
            if self.rig.fusion.unswap_limbs:
                track.joints, conf, traded = unswap_limbs(track.joints, conf)
            n_seen = np.count_nonzero(conf > 0)   # (count_nonzero: cheaper than a reduction)
        if self.rig.fusion.unswap_limbs:
            # the sensor's hand states follow its arms: its "left" hand is the right one
            # while it has the arms swapped (kept until a frame says otherwise, so a
            # /handState sent before the frame of its datagram reads the last frame's)
            track.arms_traded = 1 if traded & ARM_TRADED else 0
            if traded:
                self.counts["limbs_unswapped"] = (self.counts.get("limbs_unswapped", 0)
                                                  + bin(traded).count("1"))
        track.conf = conf
        track.t = t
        if not n_seen:
            return False  # nothing tracked in this frame: no position to associate or fuse
        person = self.tracker.associate(track, t)
        if self._offset_s > 0.0 and person.t != _NEVER:
            held = person.filter.native
            if held is not None and r is not _NO_R:
                # the core's person: its offsets are learned on the core's rows, for the
                # batch's frames in one call before the fold (``_offsets_held``)
                # (a person that remembers one view has no offsets; a view it does not
                # remember yet is left as it is: ``_offset``)
                recent = person.recent
                row = recent.get(track.key, -1) if len(recent) > 1 else -1
                if row >= 0:
                    self._held_offsets.append(((pos, held[1], row), (t, person.t),
                                               track.joints, conf))
            else:
                r = self._offset(track, person, transform, conf, r, t)
        if person.t == _NEVER:
            # a person found in this batch: later views of the batch associate against this
            # view until its filter is folded in at the end of the batch
            known = conf > 0
            person.joints = np.where(known[:, None], track.joints, person.joints)
            person.known = known
            person.t = t
        # without the kernels, the measurement variances are computed for the batch in _fold
        view = View(track.key, t, track.joints, conf, r, arrival, size=size)
        self._views.append((person, view, transform))
        if hands:
            for item in hands:
                track.hands[item.message.hand] = item.message.state
            self._hands_dirty.add(person.id)
        weighted = self.rig.fusion.hand_vote == "confidence"
        traded = track.arms_traded
        self._reports.append((person.voter.add_frame, track.key, track.hands[traded],
                              float(conf[_HAND_JOINT[0]]) if weighted else 1.0,
                              track.hands[1 ^ traded],
                              float(conf[_HAND_JOINT[1]]) if weighted else 1.0, t,
                              track.hand_step))
        return True

    def _offset(self, track: Track, person: Person, transform: np.ndarray, conf: np.ndarray,
                r: np.ndarray, t: float) -> np.ndarray:
        """``track.joints`` corrected, in place, by its view's learned offset minus the mean
        of the person's views' offsets; then the view's offset learns from this frame
        (``offsets``). A view the person does not remember yet (its first frame with them)
        is left as it is; a person who remembers one view has no offsets (a second view
        starts them from nothing). In place, so that the arrays ``prepare_frames`` handed
        over (which the native core takes as they are) hold the corrected joints too.

        Returns the frame's variances ``r``: without the kernels (``_NO_R``) they are
        computed here, by where the sensor saw the joints before they move, as
        ``jit.frame_r`` gives them with the kernels."""
        recent = person.recent
        if len(recent) < 2:          # one view: nothing to learn against, nothing to correct
            person.offsets = None
            return r
        row = recent.get(track.key)
        if row is None:
            return r
        if r is _NO_R:
            r = _variance_rows(track.joints[None], conf[None], transform[None, :3, 3],
                               self.smoothing)[0]
        live = person.recent_t
        table = person.offsets
        if table is None or len(table) != len(live):  # (rows added for more views)
            grown = np.zeros((len(live), N_JOINTS, 3))
            if table is not None:
                keep = min(len(table), len(live))
                grown[:keep] = table[:keep]
            table = person.offsets = grown
        gap = min(max(t - float(live[row]), 0.0), offsets.GAP_MAX_S)
        alpha = -math.expm1(-gap / self._offset_s)
        dt = min(max(t - person.t, -offsets.GAP_MAX_S), offsets.GAP_MAX_S)
        try:
            if jit.ready():
                jit.offsets(track.joints, conf, person.joints, person.velocity, person.known,
                            dt, table, live, row, alpha, INFERRED)
                return r
        except TypeError:   # arrays the kernel does not take (not float64, not contiguous)
            pass
        offsets.learn(track.joints, conf, person.joints, person.velocity, person.known, dt,
                      table, live, row, alpha, INFERRED)
        return r

    def prepare_frames(self, transform: np.ndarray, frames: list) -> None:
        """What ``frame`` computes first for each frame (stage-space joints, swapped limbs,
        variances, trunk), for ``frames`` (messages with ``joints`` (25, 3) and ``conf``
        (25,)) of one sensor whose ``transform`` is this, all in one compiled call
        (``jit.frame_r_many``): a datagram's frames, before they are applied. ``frame``
        takes a frame's results from here when it is given these very arrays and
        transform; they are forgotten at the end of the batch (``flush``)."""
        out = self.computed_frames(transform, frames)
        if out is not None:
            self.take_frames(transform, frames, out)

    def computed_frames(self, transform: np.ndarray, frames: list, unswap: bool | None = None,
                        smoothing: KalmanSettings | None = None) -> tuple | None:
        """``jit.frame_r_many`` of ``frames`` (``prepare_frames``), or None where the kernels
        are off, there are fewer than two frames or the kernel does not take them; with the
        rig's ``unswap_limbs`` and the smoothing settings unless given. Reads nothing else
        of the engine's state: the receiver's thread calls it (``Engine._prepared``)."""
        if len(frames) < 2 or not jit.ready():
            return None
        try:
            return jit.frame_r_many(transform, np.array([m.joints for m in frames], dtype=float),
                                    np.array([m.conf for m in frames], dtype=float),
                                    self.rig.fusion.unswap_limbs if unswap is None else unswap,
                                    _LOOK, _TRADED, SWAP_MARGIN_M,
                                    self.smoothing if smoothing is None else smoothing,
                                    INFERRED)
        except (TypeError, ValueError):   # frames the kernel does not take: one by one
            return None

    def take_frames(self, transform: np.ndarray, frames: list, out: tuple) -> None:
        """``computed_frames``' ``out`` for ``frames`` kept for ``frame`` until the batch
        ends (``prepare_frames``)."""
        # each frame's results as Python objects now, for the whole datagram in C (rows of
        # the arrays by iterating them, the small ones as lists), not indexed per frame
        j_out, c_out, bits, r_out, sizes = out
        framed = self._framed
        js, cs, rs = list(j_out), list(c_out), list(r_out)
        for k, (m, j, c, b, r, size, n) in enumerate(zip(frames, js, cs, bits.tolist(), rs,
                                                      sizes[:, 0].tolist(),
                                                      sizes[:, 1].tolist())):
            framed[id(m.joints)] = (m.joints, m.conf, transform, j, c, b, r, size, int(n), k)
        if self.core is not None:
            self._batch = (j_out, c_out, r_out, js, cs, rs)

    def hand(self, track: Track, hand: int, state: HandState, t: float) -> None:
        """A ``/handState`` of ``track`` captured at ``t`` (``hand`` as the sensor names it)."""
        track.hands[hand] = state
        person = self.persons.get(track.person) if track.person is not None else None
        if person is None:
            return
        hand ^= track.arms_traded                   # the sensor's arms traded back
        weighted = self.rig.fusion.hand_vote == "confidence"
        weight = float(track.conf[_HAND_JOINT[hand]]) if weighted else 1.0
        self._reports.append((person.voter.add, track.key, hand, state, weight, t,
                              track.hand_step))
        self._hands_dirty.add(person.id)

    def _give_reports(self) -> None:
        """The batch's hand reports to their voters, in the order they came."""
        reports, self._reports = self._reports, []
        for give, *args in reports:
            give(*args)

    def drop_track(self, track: Track, t: float) -> None:
        self._give_reports()       # (its reports before it is forgotten, as they came)
        if self._held_offsets:     # (learned from the person's views as they were)
            self._offsets_held()
        pid = self.tracker.unbind(track, t)
        person = self.persons.get(pid) if pid is not None else None
        if person is not None:
            person.voter.forget(track.key)
            person.forget(track.key)
            self._hands_dirty.add(pid)  # one voter fewer

    # ------------------------------------------------------------ fusion
    def flush(self, votes: bool = True) -> None:
        """Fold the batch's frames into their persons, then send what changed.

        ``votes`` False (a datagram of a burst with more of it waiting,
        ``Engine.process_taken``): the skeletons alone; the hand votes, lost persons and the
        listeners' frame wait for the next flush with ``votes``, so that the burst's later
        datagrams do not wait for them."""
        if self._views:
            self._fold()
        if self._framed:
            # (after the fold: the core takes the batch's arrays as they are, ``_fold_core``)
            self._framed.clear()
            self._batch = None
        if votes:
            self._emit()
        elif self._dirty:
            self._send_joints(self._held_new)
            self._held.update(dict.fromkeys(self._dirty))
            self._dirty = {}
            self._forecasts.clear()

    def _offsets_held(self) -> None:
        """The view offsets of the batch's frames of persons the native core holds, in one
        compiled call (``jit._native_offsets``), as ``_offset`` would have done them frame
        by frame, in their order: before anything reads the frames' joints or changes the
        persons' views (the fold, a track dropped mid-batch). Frames that are rows of the
        batch's arrays (``prepare_frames``) are corrected there, others in copies written
        back."""
        held, self._held_offsets = self._held_offsets, []
        core = self.core
        batch = self._batch
        ints = [h[0] for h in held]
        # (the rows of the batch's last ``prepare_frames`` call: with several sensors' frames
        # in one batch, a backlog, the others' rows are another call's)
        rows = batch[3] if batch is not None else ()
        if rows and all(0 <= i[0] < len(rows) and rows[i[0]] is h[2]
                        for i, h in zip(ints, held)):
            z, conf, copies = batch[0], batch[1], False
        else:
            z = np.array([h[2] for h in held])
            conf = np.array([h[3] for h in held])
            ints = [(k, s, row) for k, (_, s, row) in enumerate(ints)]
            copies = True
        jit._compiled["_native_offsets"](
            np.array(ints, dtype=np.int64), np.array([h[1] for h in held]), z, conf,
            core.recent_t, core.joints, core.velocity, core.known, core.offsets,
            self._offset_s, offsets.GAP_MAX_S, INFERRED, offsets.CAP_M * offsets.CAP_M)
        if copies:
            for k, h in enumerate(held):
                h[2][...] = z[k]

    def _fold(self) -> None:
        if self._held_offsets:
            self._offsets_held()
        views, self._views = self._views, []
        everyone, core = views, self.core
        if core is not None and views:
            views = self._fold_native(core, views)     # what the core leaves to Python
            if not views:
                return
        live = [(p, v) for p, v, _ in views if self.persons.get(p.id) is p]
        missing = [(v, transform[:3, 3]) for _, v, transform in views if v.r is _NO_R]
        if missing:
            self._variances(missing)
        # in the order of the persons' ids (each person's views in their own order), so that
        # sensors naming the same persons with other user ids fold them in the same order,
        # and a fold can start from the one before's arrays (FilterState.concat)
        ordered = sorted(live, key=_by_person) if len(live) > 1 else live
        late = {id(v) for v in self.fuser.fold([(p.filter, v) for p, v in ordered])}
        for person, view in live:
            if id(view) in late:
                self.drops.add(view.key[0], "late")
                continue
            if view.size is None:
                person.measure_size(view.joints, view.conf)
            elif view.size == view.size:                      # (NaN: not measurable)
                person.add_size(view.size)
            person.remember(view.key, view.t, view.conf)
            self._dirty.setdefault(person.id, []).append(view.arrival)
        # settled in the fold's order (each person on its own: the order changes no value),
        # so that a fold of one plain wave hands its arrays over as they are
        touched: dict[int, Person] = {}
        for person, view in ordered:
            if id(view) not in late:
                touched[person.id] = person
        if touched:
            self._update(list(touched.values()))
            self.counts["fused_frames"] += len(touched)
        if core is not None:
            self._take_steady(core, ordered, late)
            if len(views) < len(everyone):        # both paths: sent in the views' order
                dirty = self._dirty
                order = dict.fromkeys(p.id for p, _, _ in everyone)
                self._dirty = {**{k: d for k, d in dirty.items() if k not in order},
                               **{k: dirty[k] for k in order if k in dirty}}

    def _fold_native(self, core: NativeCore, views: list) -> list:
        """The views of persons the native core holds folded, settled and encoded by it
        (``NativeCore.fold``); returns the others, for the Python path, in their order. A
        person whose view the core will not take is given back to Python first (the rest
        are tried again without it). What the Python path records of a fold is recorded
        the same."""
        persons = self.persons
        mine, rest = [], []
        for item in views:
            p, v, _ = item
            if p.filter.native is not None and persons.get(p.id) is p and v.r is not _NO_R:
                mine.append(item)
            else:
                rest.append(item)
        while mine and not self._fold_core(core, mine, len(mine) == len(views)):
            person = mine[core.refused][0]
            self._give_back(core, person)
            rest += [item for item in mine if item[0] is person]
            mine = [item for item in mine if item[0] is not person]
        for p, _, _ in rest:               # (a held person's view the core was not given)
            if p.filter.native is not None:
                self._give_back(core, p)
        if len(rest) > 1:                   # (those given back were added at the end)
            left = {id(item) for item in rest}
            rest = [item for item in views if id(item) in left]
        return rest

    def _give_back(self, core: NativeCore, person: Person) -> None:
        """``person`` back to the Python path (``NativeCore.give_back``), its history trimmed
        as that path keeps it; taken again after a longer run if it was not kept long."""
        kept = int(core.steps[core.slot_of[person.id]])
        core.give_back(person)
        self.fuser._trim(person.filter)
        self._python_run[person.id] = 0
        need = self._take_after.get(person.id, TAKE_AFTER)
        self._take_after[person.id] = (TAKE_AFTER if kept >= KEEP_STEPS
                                       else min(2 * need, TAKE_AFTER_MAX))

    def _fold_core(self, core: NativeCore, views: list, whole: bool) -> bool:
        """``views`` (of persons the core holds) folded by the core; False if it declined
        (nothing done). ``whole``: they are all of the batch's views."""
        pids, keys, t, arrival, size = [], [], [], [], []
        for p, v, _ in views:
            pids.append(p.id)
            keys.append(v.key)
            t.append(v.t)
            arrival.append(v.arrival)
            size.append(np.nan if v.size is None else v.size)
        batch = self._batch
        if (whole and batch is not None and len(batch[3]) == len(views)
                and all(v.joints is j and v.conf is c and v.r is r for (_, v, _), j, c, r
                        in zip(views, batch[3], batch[4], batch[5]))):
            z, conf, r = batch[0], batch[1], batch[2]    # the datagram's frames, in order
        else:
            z = np.array([v.joints for _, v, _ in views])
            conf = np.array([v.conf for _, v, _ in views])
            r = np.array([v.r for _, v, _ in views])
        out = core.fold(pids, keys, np.array(t), z, r, conf, np.array(arrival), np.array(size))
        if out is None:
            return False
        st = self.fuser.stats
        st.views += len(views)
        counts = core.totals
        st.restarted += counts[0]
        st.downweighted += counts[2]
        st.rejected += counts[3]
        st.replays += counts[4]
        st.disagreeing += counts[5]
        self.fuser.plain_wave = None
        person_t = core.person_t[core.slots].tolist()
        dirty, encoded = self._dirty, self._encoded
        for (p, v, _), data, t in zip(views, out, person_t):
            p.t = t
            if v.size is None:
                p.measure_size(v.joints, v.conf)
            elif v.size == v.size:                            # (NaN: not measurable)
                p.add_size(v.size)
            dirty.setdefault(p.id, []).append(v.arrival)
            encoded[p.id] = data
        self.counts["fused_frames"] += len(views)
        return True

    def _take_steady(self, core: NativeCore, ordered: list, late: set) -> None:
        """Persons the Python path has folded ``TAKE_AFTER`` datagrams in a row (more after
        being given back), none of their views dropped as late, are taken by the native
        core."""
        runs, persons, need = self._python_run, self.persons, self._take_after
        for person, view in ordered:
            pid = person.id
            if id(view) in late or not person.filter.history:
                runs[pid] = 0
                continue
            n = runs[pid] = runs.get(pid, 0) + 1
            if (n >= need.get(pid, TAKE_AFTER) and person.centre is not None and person.tracks
                    and persons.get(pid) is person and person.filter.native is None):
                core.take(person, bind=True)      # (copies the bank's rows first)
                self.bank.unbind(person)

    def _variances(self, views: list[tuple[View, np.ndarray]]) -> None:
        """Each joint's variance from its confidence and its distance from the sensor (whose
        position in stage space is the translation of its transform), all views at once
        (without the kernels; ``jit.frame_r`` gives the same floats per frame)."""
        r = _variance_rows(np.array([v.joints for v, _ in views]),
                           np.array([v.conf for v, _ in views]),
                           np.array([where for _, where in views]), self.smoothing)
        for k, (view, _) in enumerate(views):
            view.r = r[k]

    def _update(self, persons: list[Person]) -> None:
        """Each person's output skeleton from its filter at its newest frame's capture time,
        for all persons of a batch at once."""
        stale = self.rig.fusion.stale_s
        if jit.ready():
            self._update_compiled(persons, stale)
        else:
            self._update_numpy(persons, stale)

    def _update_numpy(self, persons: list[Person], stale: float) -> None:
        """``_update`` in numpy, all persons at once (the kernels' reference)."""
        t = np.array([max(p.t, p.filter.output[0]) for p in persons])
        pos = np.array([p.filter.output[1] for p in persons])           # (P, 25, 3)
        vel = np.array([p.filter.output[2] for p in persons])
        row_t = np.array([p.filter.state.t for p in persons])           # (P, 25)
        conf = np.array([self._recent_conf(p, tp, stale) for p, tp in zip(persons, t)])
        # a joint a sensor sees whose filter has had a measurement lately: one whose
        # latest frames were gated out is sent where the filter predicts it
        seen = (conf > 0) & (t[:, None] - row_t <= stale) & np.isfinite(pos).all(axis=2)
        joints = np.where(seen[..., None], pos, np.array([p.joints for p in persons]))
        known = np.array([p.known for p in persons]) | seen
        conf = np.where(seen, np.minimum(conf, 1.0), 0.0)
        for k, p in enumerate(persons):
            self._untracked(p, joints[k], conf[k])
        vel = np.where(np.isfinite(vel), vel, 0.0)
        # the centre uses every torso joint ever seen, not just this frame's, so it
        # does not jump when occlusion changes which joints a view reports
        torso = known[:, _TORSO]
        n_torso = torso.sum(axis=1)
        centres = (joints[:, _TORSO] * torso[..., None]).sum(axis=1) / np.maximum(n_torso, 1)[:, None]
        for k, p in enumerate(persons):
            p.joints, p.velocity, p.conf, p.known, p.t = joints[k], vel[k], conf[k], known[k], t[k]
            p.centre = centres[k] if n_torso[k] else torso_centre(joints[k], known[k].astype(float))

    def _update_compiled(self, persons: list[Person], stale: float) -> None:
        """``_update`` for all persons of the batch in one compiled call (``jit.settle_many``)
        on the person bank (``bank.PersonBank``), which holds their outputs: their arrays
        change in place."""
        fusion = self.rig.fusion
        bank, alive = self.bank, self.persons
        slots = np.array([bank.slot(p, alive) for p in persons], dtype=np.int64)
        outputs = [p.filter.output for p in persons]
        t = [max(p.t, o[0]) for p, o in zip(persons, outputs)]
        wave = self.fuser.plain_wave
        if (wave is not None and len(wave[0]) == len(persons)
                and all(p.filter is b for p, b in zip(persons, wave[0]))):
            _, pos, vel, row_t = wave      # the fold's own arrays: these very outputs
        else:
            # (np.array of a list: a new C-ordered array, several times cheaper than np.stack)
            pos, vel = np.array([o[1] for o in outputs]), np.array([o[2] for o in outputs])
            row_t = np.array([p.filter.state.t for p in persons])
        try:
            counts = jit.settle_many(slots, pos, vel, row_t, np.array(t), stale, bank,
                                     fusion.carry_untracked, fusion.hold_back_inferred, INFERRED,
                                     _PARENTS, _CHILDREN, _TORSO)
        except TypeError:    # arrays the kernel does not take: the batch in numpy
            self._update_numpy(persons, stale)
            return
        for k, p in enumerate(persons):
            p.t = t[k]
            p.centre = (bank.centre_of(slots[k]) if counts[k]
                        else torso_centre(p.joints, p.known.astype(float)))

    def _untracked(self, p: Person, joints: np.ndarray, conf: np.ndarray) -> None:
        """Joints no sensor tracks now (confidence at most ``INFERRED`` in every view: a guess;
        Kinect sends 0.5, a client with continuous confidences anything up to it), in
        place: carried by their parent joint as last tracked (``carry_untracked``), and not
        reported at all while no sensor has tracked them since ``p`` was found."""
        now = conf > INFERRED
        p.tracked |= now
        if self.rig.fusion.carry_untracked:
            p.carried = carry_untracked(joints, conf > 0, now, p.hold)
        if self.rig.fusion.hold_back_inferred:
            conf[~p.tracked] = 0.0

    @staticmethod
    def _recent_conf(person: Person, t: float, stale: float) -> np.ndarray:
        """(25,) the best confidence of each joint among the person's views of the last
        ``stale`` seconds (views that left the person are forgotten), 0 without one."""
        live = ~(t - person.recent_t > stale)
        if not np.count_nonzero(live):
            return np.zeros(person.conf.shape)
        return np.maximum.reduce(person.recent_conf[live], axis=0)

    # ------------------------------------------------------------ forecasts
    def want_forecast(self, horizon: float, lazy: bool = False) -> None:
        """From now on every ``FusedFrame`` carries its bodies predicted ``horizon`` s ahead
        (``frame.forecasts[horizon]``); engine thread. 0 asks for nothing. ``lazy``: made
        only when a listener reads them while the engine calls it (``frames.Forecasts``; a
        listener that reads them later, from another thread, must not ask so), unless
        someone else asked for them as they are."""
        horizon = self.check_horizon(horizon)
        if horizon > 0:
            self.horizons[horizon] = self.horizons.get(horizon, 0) + 1
            if not lazy:
                self._eager[horizon] = self._eager.get(horizon, 0) + 1

    def drop_forecast(self, horizon: float, lazy: bool = False) -> None:
        for counts in (self.horizons,) if lazy else (self.horizons, self._eager):
            n = counts.get(horizon, 0) - 1
            if n > 0:
                counts[horizon] = n
            else:
                counts.pop(horizon, None)

    def check_horizon(self, horizon: float) -> float:
        """``horizon`` as a float, or a ConfigError naming the rig's limit."""
        h = float(horizon)
        if not (0.0 <= h <= self.rig.forecast.max_s):
            raise ConfigError(f"forecast {horizon!r} s: must be between 0 and the rig's "
                              f"forecast: max_s ({self.rig.forecast.max_s:g} s)")
        return h

    def forecast(self, person: Person, horizon: float) -> Forecast:
        """``person`` predicted ``horizon`` s past its capture time (cached per emission)."""
        key = (person.id, horizon)
        fc = self._forecasts.get(key)
        if fc is None:
            block, row_t = person.filter.peek()
            fc = self._forecasts[key] = self.forecaster.predict_block(
                block, row_t, person.t, person.joints, person.conf > 0, horizon)
        return fc

    def _forecast_bodies(self, horizon: float) -> dict[int, Body]:
        """Every announced person predicted ``horizon`` s past its capture time, as bodies.
        With the kernels, all in one compiled call (``Forecaster.predict_many``: a body cost
        about 36 us one by one, 9 of them in the kernel; issue 10, stop 54), the same floats
        as one by one; one by one where a view's forecast made some of them already in this
        emission (they are kept until it ends)."""
        persons = [p for p in self.persons.values() if p.announced and p.centre is not None]
        if not jit.ready() or len(persons) < 2:
            return self._forecast_each(persons, horizon)
        cached = self._forecasts
        if cached and any((p.id, horizon) in cached for p in persons):
            return self._forecast_each(persons, horizon)
        peeked = [p.filter.peek() for p in persons]
        conf = np.array([p.conf for p in persons])
        joints, vel, sd = self.forecaster.predict_many(
            np.array([b for b, _ in peeked]), np.array([t for _, t in peeked]),
            np.array([p.t for p in persons]), np.array([p.joints for p in persons]), conf > 0,
            horizon)
        torso = np.array([p.known for p in persons])[:, _TORSO]
        n_torso = torso.sum(axis=1)
        centres = ((joints[:, _TORSO] * torso[..., None]).sum(axis=1)
                   / np.maximum(n_torso, 1)[:, None])
        return {p.id: Body(p.id, joints[k], conf[k], vel[k], (p.hands[0], p.hands[1]),
                           centres[k] if n_torso[k] else p.centre.copy(), p.sensors(), p.t,
                           horizon, sd[k])
                for k, p in enumerate(persons)}

    def _forecast_each(self, persons: list[Person], horizon: float) -> dict[int, Body]:
        """``_forecast_bodies`` one person at a time (without the kernels; and where a view's
        forecast of some persons was made already in this emission)."""
        out = {}
        for p in persons:
            pid = p.id
            fc = self.forecast(p, horizon)
            known = p.known
            torso = known[_TORSO]
            centre = (fc.joints[_TORSO] * torso[:, None]).sum(axis=0) / max(int(torso.sum()), 1) \
                if torso.any() else p.centre.copy()
            out[pid] = Body(pid, fc.joints, p.conf.copy(), fc.velocity, (p.hands[0], p.hands[1]),
                            centre, p.sensors(), p.t, horizon, fc.sd)
        return out

    # ------------------------------------------------------------ output
    def _emit(self) -> None:
        """Send what the batch changed: every updated person's skeleton first, then the hand
        votes (the batch's hand reports are given to the voters only now), so that no
        skeleton waits for hand work. A frame's latency ends when its person's skeleton is
        sent: the first datagram out that includes it."""
        if not self._dirty and not self._lost and not self._hands_dirty and not self._held:
            self._give_reports()     # (a late frame's: its vote comes with the next change)
            return
        now = self.clock.now()
        new, self._held_new = self._held_new, []
        sent_joints = self._send_joints(new)
        if self._held:               # (a burst's earlier datagrams' persons, in their order)
            held = [self.persons.get(pid) for pid in self._held if pid not in self._dirty]
            sent_joints = [p for p in held if p is not None] + sent_joints
            sent_ids = self._dirty.keys() | self._held.keys()
            self._held = {}
        else:
            sent_ids = self._dirty.keys()
        self._give_reports()
        updated: list[int] = []
        for pid in sorted(self._hands_dirty - sent_ids):
            # a hand message alone re-sends no joints: only a changed vote goes out
            person = self.persons.get(pid)
            if person is None or not person.announced:
                continue
            if self._send_hands(person, person.voter.update(max(person.t, person.voter.newest))):
                updated.append(pid)
        for person in sent_joints:
            self._send_hands(person, person.voter.update(person.t))
            updated.append(person.id)
        lost = self._lost
        for pid in lost:
            self.output.lost_user(pid)
        self._dirty, self._lost = {}, []
        self._hands_dirty.clear()
        if self.listeners and (updated or lost):
            eager = self._eager
            forecasts = {h: self._forecast_bodies(h) for h in self.horizons if h in eager}
            lazy = tuple(h for h in self.horizons if h not in eager)
            if lazy:
                forecasts = Forecasts(forecasts, lazy, self._forecast_bodies)
            self.listeners.call(FusedFrame(now, self.bodies(), tuple(updated), tuple(new),
                                           tuple(lost), forecasts))
            if lazy:
                forecasts.seal()
        self._forecasts.clear()

    def _send_joints(self, new: list[int]) -> list[Person]:
        """Every updated person's skeleton (and forecasts) to the views, a person found
        announced first (its id added to ``new``); each frame's latency ends here. Returns
        the persons sent."""
        sent_joints: list[Person] = []
        for pid, arrivals in self._dirty.items():
            person = self.persons.get(pid)
            if person is None or person.centre is None:
                continue
            if not person.announced:
                person.announced = True
                new.append(pid)
                log.info("person %d found (seen by %s)", pid, ", ".join(person.sensors()))
                self.output.new_user(pid, person.centre)
            if person.tracks:
                self.output.joints(pid, person.joints, person.conf,
                                   encoded=self._encoded.get(pid))
                for horizon, targets in self.output.forecast_targets().items():
                    self.output.joints(pid, self.forecast(person, horizon).joints, person.conf,
                                       targets)
            sent = self.clock.now()
            for arrival in arrivals:
                self.latency.add(sent - arrival)
            sent_joints.append(person)
        if self._encoded:
            self._encoded.clear()
        return sent_joints

    def _send_hands(self, person: Person, changed: list[int]) -> bool:
        for hand in changed:
            person.hands[hand] = person.voter.reported[hand]
        sent = False
        for hand in (0, 1):
            if person.hands[hand] != person.sent_hands[hand]:
                person.sent_hands[hand] = person.hands[hand]
                self.output.hand(person.id, hand, person.hands[hand])
                sent = True
        return sent

    def bodies(self) -> dict[int, Body]:
        return {pid: Body(pid, p.joints.copy(), p.conf.copy(), p.velocity.copy(),
                          (p.hands[0], p.hands[1]), p.centre.copy(), p.sensors(), p.t)
                for pid, p in self.persons.items() if p.announced and p.centre is not None}

    # ------------------------------------------------------------ housekeeping
    def tick(self, now: float) -> None:
        """Merging and expiry of persons, then what is due to views."""
        self.tracker.merge_close(now)
        self._lost.extend(self.tracker.expire(now))
        core = self.core
        if core is not None:                 # persons gone: their slots free, their runs ended
            persons = self.persons
            for pid in [pid for pid in core.slot_of if pid not in persons]:
                core.release(pid)
            if len(self._python_run) > len(persons):
                self._python_run = {k: n for k, n in self._python_run.items() if k in persons}
            if len(self._take_after) > len(persons):
                self._take_after = {k: n for k, n in self._take_after.items() if k in persons}
        self._emit()
        self.serve_fixed_rate(now)

    def serve_fixed_rate(self, now: float) -> None:
        """Views that asked for a fixed rate get every person predicted to ``now`` (plus
        their forecast, if they asked for one: bounded as every forecast is)."""
        due = self.output.due(now)
        if not due:
            return
        ahead: dict[float, list[tuple[str, int]]] = {}
        for view in due:
            ahead.setdefault(self.output.forecasts.get(view, 0.0), []).append(view)
        for pid, person in self.persons.items():
            if not person.announced or person.centre is None or not person.tracks:
                continue
            for horizon, views in ahead.items():
                if horizon > 0:
                    block, row_t = person.filter.peek()
                    fc = self.forecaster.predict_block(block, row_t, person.t, person.joints,
                                                       person.conf > 0,
                                                       max(now - person.t, 0) + horizon)
                    self.output.joints(pid, fc.joints, person.conf, views)
                    continue
                pos, _ = person.filter.estimate(now)
                reported = person.conf > 0
                joints = np.where((reported & ~person.carried)[:, None] & np.isfinite(pos),
                                  pos, person.joints)
                if person.carried.any():     # carried joints follow their parents' estimate
                    carry_untracked(joints, reported, ~person.carried, person.hold.copy())
                self.output.joints(pid, joints, person.conf, views)

    def stats(self) -> dict:
        f = self.fuser.stats
        out = {"views": f.views, "late": f.late, "replays": f.replays,
               "joints_disagreeing": f.disagreeing, "joints_downweighted": f.downweighted,
               "joints_rejected": f.rejected, "joints_restarted": f.restarted}
        core = self.core
        if core is not None:
            out["native"] = {"held": len(core.slot_of), "folded": core.folded,
                             "replayed": core.replayed, "declined": core.declined,
                             "given_back": core.given_back,
                             "short_histories": core.short_histories}
        return out

    def forecast_stats(self) -> dict:
        """What ``/stage/stats`` says of forecasts: who asks for which horizon, how many were
        made and bounded, and the latest mean s.d. per horizon."""
        views = {f"{h}:{p}": s for (h, p), s in self.output.forecasts.items()}
        return {"horizons_s": sorted(self.horizons), "views_s": views,
                **self.forecaster.stats()}


def fused_persons_stats(people: People) -> dict[int, dict]:
    """Per announced person: sensors, position, trunk length (for ``/stage/stats``)."""
    return {pid: {"sensors": list(p.sensors()),
                  "position": None if p.centre is None else [round(float(v), 4) for v in p.centre],
                  "size_m": None if p.size is None else round(p.size, 3)}
            for pid, p in people.persons.items() if p.announced}

