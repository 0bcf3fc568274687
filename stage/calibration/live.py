"""Pieces of the live calibrator that do not own state: settings, views, consensus.

Frames come from the engine's ``frame_observers`` (the sensor's own space,
with the transform the engine used). A ``View`` is one (sensor, user)'s
recent frames as arrays. The "consensus" for a sensor at some instants is
what the other trusted sensors say the person's joints were, in stage
space: each trusted view resampled at those instants, averaged with the
confidences as weights.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..joints import N_JOINTS, TORSO
from .coverage import Gates
from .pairs import PairSet, resample

_TORSO = np.array(TORSO)


@dataclass(frozen=True)
class LiveSettings:
    """Knobs of live calibration and self-healing (defaults suit 30 Hz Kinects).

    Every two trusted sensors that see one person are compared over
    ``window_s``; a sensor is suspect when its fitness (from the median joint
    distance) stays below ``suspect_below`` AND it is ``suspect_ratio`` times
    further from the others than they are from each other, for ``hold_s``
    (or at once, when every view of it jumps ``gate_m`` away from sensors it
    agreed with a moment ago); never more than half of the calibrated sensors
    at once. A suspect sensor is left out of fusion, and comes back either
    with its old transform (fitness back above ``restore_above``, or within
    ``restore_ratio`` of how close the others agree or of how close it agreed
    itself while healthy, for ``restore_s``: it was a glitch) or
    with a new one. The worker polls every ``poll_s``; while every sensor
    is calibrated, trusted and agrees, the monitor judges every ``idle_poll_s``.
    Pairs for a calibration are enough at ``pairs`` (``heal_pairs``) or
    sooner at ``poses`` (``heal_poses``) distinct poses;
    a fit is accepted when it passes the gates (``min_pairs``, ``min_poses``,
    ``min_fitness``, as offline) and is good (``accept_above``) or within
    ``accept_ratio`` of how close the trusted sensors agree (a first
    calibration with nobody to compare with: the gates alone). Each sensor's
    lag is searched within ``max_lag_s`` before it is calibrated and every
    ``lag_every_s`` after, within ``track_lag_s`` of the lag in use (``lag_search``); each
    such search that moves nothing doubles the wait for the next, up to ``lag_every_max_s``.
    """

    method: str = "rigid"
    pairs: int = 300              # pairs that are enough for a first calibration (~10 s)
    poses: int = 40               # ... or this many distinct poses, sooner
    heal_pairs: int = 90          # pairs that are enough for a re-calibration (~3 s)
    heal_poses: int = 20
    poses_stall_s: float = 3.0    # ... or sooner still when no new pose came for this long
    window_s: float = 0.5
    suspect_below: float = 0.35   # fitness 0.35 = core joints 12.6 cm apart (median)
    suspect_ratio: float = 2.0    # ... and twice as far as the others agree among themselves
    hold_s: float = 0.3
    restore_above: float = 0.7    # hysteresis: 0.7 = 5.8 cm (median)
    restore_ratio: float = 1.25   # ... or as close as the others agree, or as it agreed
                                  # itself while healthy (x 1.25)
    restore_s: float = 1.0
    accept_above: float = 0.7
    accept_ratio: float = 1.5
    min_pairs: int = Gates.min_pairs
    min_poses: int = Gates.min_poses
    min_fitness: float = Gates.min_fitness
    poor_fitness: float = Gates.poor_fitness
    min_lag_confidence: float = Gates.min_lag_confidence
    max_rot_deg: float = Gates.max_rot_deg   # the fit's spread over its independent poses:
    max_far_m: float = Gates.max_far_m       # the same tolerance as offline (0: off)
    edge_m: float = Gates.edge_m
    lag_search: bool = True
    max_lag_s: float = 1.0
    lag_every_s: float = 10.0     # re-search a calibrated sensor's lag this often (0: never),
    lag_every_max_s: float = 60.0  # ... twice as long after each search that moved nothing,
                                   # up to this (lag_every_s or less: always lag_every_s)
    track_lag_s: float = 0.25     # ... within this of the lag in use (a clock that jumps further
                                  # makes the sensor disagree: suspect, then a full search)
    lag_min_confidence: float = 0.05
    lag_move_confidence: float = 0.15  # a new sensor's lag moves only on searches this sure
                                       # (a first search on 0.8 s of frames can read 0.08)
    lag_track_confidence: float = 0.3  # a calibrated sensor's lag moves only on searches this
                                       # sure (a crowd's searches read 0.05-0.1 with no lag)
    lag_hysteresis: float = 0.1   # a new lag must fit 10 % better than the one in use
    lag_min_s: float = 0.8        # both views need this much buffered before a lag search
    gate_m: float = 0.30
    agree_m: float = 0.15
    link_s: float = 0.5
    match_m: float = 0.5          # views further apart than this are different people
    identical_frames: int = 5
    poll_s: float = 0.1
    idle_poll_s: float = 0.3      # ... but while every sensor is calibrated, trusted and
                                  # agrees, the monitor judges the frames in chunks this long
                                  # (polls between do nothing unless a lag search is due) ...
    idle_wake_m: float = 0.10     # ... and while, in every frame the jump gate compared since
                                  # the last judgement, each sensor's closest view was within
                                  # this of another trusted sensor's: a bump under the jump
                                  # gate moves them apart, and the next poll judges at once
                                  # (4 degrees caught as soon as judging every poll; inf: 0.1 to
                                  # 0.2 s later). Saves 1.5-2 % of a core at 6 sensors x 6
                                  # people; views further apart than this (N-UCLA's Kinect v1:
                                  # 11 cm, median) keep every poll
    delay_s: float = 0.1          # frames are judged once the partners' later frames are in
    buffer_s: float = 4.0
    frame_budget: float = 540.0   # frames a second the calibrator keeps at most: above it (more
                                  # than 18 views of 30 Hz sensors) each view is thinned evenly
                                  # in time (to budget / views a second, never under 10),
                                  # so that its cost stops growing with the crowd; every
                                  # frame is still checked for copies. 0: every frame
    auto_calibrate: bool = True   # calibrate sensors the rig has no calibration for
    heal: bool = True
    save: bool = True
    min_joints: int = 8


@dataclass
class View:
    """One (sensor, user)'s recent frames. t (n,); raw/stage (n, 25, 3); conf (n, 25).

    ``stage`` holds the frames placed with the transform the engine used
    (NaN rows where it had none).
    """

    sensor: str
    user: int
    t: np.ndarray
    raw: np.ndarray
    conf: np.ndarray
    stage: np.ndarray
    floor: np.ndarray | None = None
    transform: np.ndarray | None = None    # the newest frame's
    person: int | None = None              # the fused person the engine bound it to, if any
    run: np.ndarray | None = None          # (n,) identity run of each frame (``whole`` only)
    shift: float = 0.0                     # s taken off the frames' times (the sensor's lag)
    entries: list | None = field(default=None, repr=False, compare=False)  # all, when cut

    @classmethod
    def of(cls, entries: list[tuple], shift: float = 0.0, whole: bool = False) -> "View":
        """From (frame, person id, run) entries, as the observer buffers them.

        Only the newest run of one identity is kept: a sensor gives a freed
        user id to the next body it acquires (a Kinect's body index 0-5 does
        the same), so one (sensor, user) buffer can hold two people one after
        the other. A run ends where the frames are more than ``IDENTITY_GAP_S``
        apart, where the torso moves ``IDENTITY_JUMP_M`` between two frames
        (nobody moves 30 cm in a frame), or where the engine bound the view to
        another person. Mixing two people in one view made every sensor that
        saw either of them look wrong to the monitor. ``whole``: every run is
        kept, each frame labelled with its run (``run``); see ``whole()``.
        ``shift``: taken off every time (the sensor's lag: onto stage time).
        """
        entries = sorted(entries, key=_frame_time)  # batches may interleave slightly
        frames = [e[0] for e in entries]
        t = np.array([f.t for f in frames]) - shift
        raw = np.array([f.joints for f in frames])
        conf = np.array([f.conf for f in frames])
        cuts = _identity_cuts(t, raw, conf, [e[1] for e in entries],
                              [e[2] if len(e) > 2 else 0 for e in entries])
        run = every = None
        if whole:
            run = np.searchsorted(cuts, np.arange(len(t)), side="right")
        elif len(cuts):
            first = int(cuts[-1])
            every = entries
            entries, frames = entries[first:], frames[first:]
            t, raw, conf = t[first:], raw[first:], conf[first:]
        stage = _placed(frames, raw)
        return cls(frames[0].sensor, frames[0].user, t, raw, conf, stage,
                   frames[-1].floor, frames[-1].transform, entries[-1][1], run, shift, every)

    def whole(self) -> "View":
        """This (sensor, user)'s frames of every identity run, not only the newest, each
        labelled with its run (``run``): pairs for a calibration are taken frame by frame
        (one person in view at that instant) and interpolated within one run only, so a
        run cut at a lost-and-found person (every loop of ``stage replay --loop``, a track
        the engine confirmed a few frames late) no longer loses the frames before the cut
        that were not yet paired. On N-UCLA the live pairs of a 21-frame view held 9 of its
        frames, offline 17, and the live fit ended 28 % above the optimum."""
        if self.entries is None:  # one run only
            return self if self.run is not None else replace(
                self, run=np.zeros(len(self.t), int))
        return View.of(self.entries, self.shift, whole=True)

    @classmethod
    def many(cls, snapshot: list[list[tuple]], shifts: list[float] | None = None
             ) -> list["View"]:
        """``[View.of(entries, shift) for entries, shift in zip(snapshot, shifts)]``, the same
        views to the bit (the newest identity run, ``entries`` kept when cut, ``shift``
        taken off), with the numpy work done once for all the buffers of a poll (36 views at
        6 sensors x 6 people cost the calibrator ~4 ms a poll one at a time). The views'
        arrays are slices of shared arrays: like every ``View``'s, never written into."""
        shifts = [0.0] * len(snapshot) if shifts is None else list(shifts)
        if len(snapshot) < 2:
            return [cls.of(entries, shift) for entries, shift in zip(snapshot, shifts)]
        ordered = [sorted(entries, key=_frame_time) for entries in snapshot]
        frames = [e[0] for entries in ordered for e in entries]
        t = np.array([f.t for f in frames])
        raw = np.array([f.joints for f in frames])
        conf = np.array([f.conf for f in frames])
        centres = torso_centre(raw, conf)
        stage = _placed(frames, raw)
        sizes = [len(entries) for entries in ordered]
        persons = [e[1] for entries in ordered for e in entries]
        runs = [e[2] if len(e) > 2 else 0 for entries in ordered for e in entries]
        firsts = _identity_starts(t, centres, persons, runs, sizes)
        out = []
        a = 0
        for entries, first, shift in zip(ordered, firsts, shifts):
            b = a + len(entries)
            newest = frames[b - 1]
            out.append(cls(newest.sensor, newest.user, t[first:b] - shift, raw[first:b],
                           conf[first:b], stage[first:b], newest.floor, newest.transform,
                           entries[-1][1], None, shift, entries if first > a else None))
            a = b
        return out

    def after(self, t0: float) -> "View | None":
        """The frames after ``t0`` only (None if there are none)."""
        keep = self.t > t0
        if keep.all():
            return self
        if not keep.any():
            return None
        return replace(self, t=self.t[keep], raw=self.raw[keep], conf=self.conf[keep],
                       stage=self.stage[keep], run=None if self.run is None else self.run[keep])

    def between(self, t0: float, t1: float) -> np.ndarray:
        """Indices of frames with t0 < t <= t1."""
        return np.flatnonzero((self.t > t0) & (self.t <= t1))


#: a (sensor, user) view is a new identity after a gap this long (s) ...
IDENTITY_GAP_S = 0.25
#: ... or a torso jump this large between consecutive frames (m), see View.of
IDENTITY_JUMP_M = 0.30


def _identity_cuts(t: np.ndarray, raw: np.ndarray, conf: np.ndarray,
                   persons: list[int | None], runs: list[int]) -> np.ndarray:
    """Indices of the frames that start a new run of one identity, ascending (frames in
    time order; the first frame is not listed).

    runs: the observer's count of times the engine had no track for this user
    (it was lost, or is new): a change is a new identity whatever the gap.
    """
    n = len(t)
    if n < 2:
        return np.zeros(0, int)
    brk = np.diff(t) > IDENTITY_GAP_S                      # brk[k]: between frame k and k + 1
    brk |= np.diff(np.asarray(runs)) != 0
    c = torso_centre(raw, conf)                            # (n, 3), NaN where no torso
    seen = np.flatnonzero(np.isfinite(c[:, 0]))
    if len(seen) > 1:  # consecutive frames with a torso, however many torso-less ones between
        jump = np.linalg.norm(np.diff(c[seen], axis=0), axis=1) > IDENTITY_JUMP_M
        brk[seen[1:][jump] - 1] = True
    known = [(k, p) for k, p in enumerate(persons) if p is not None]
    for (k0, p0), (k1, p1) in zip(known, known[1:]):
        if p0 != p1:
            brk[k1 - 1] = True
    return np.flatnonzero(brk) + 1


def _identity_starts(t: np.ndarray, c: np.ndarray, persons: list[int | None], runs: list[int],
                     sizes: list[int]) -> list[int]:
    """The newest identity run's first frame of several views laid end to end (``sizes``
    frames each, none empty; ``c`` their torso centres, NaN: none), in one pass: the index
    into the whole of each one's first frame kept (``_identity_cuts``' last cut)."""
    n = len(t)
    ends = np.cumsum(sizes)
    view = np.repeat(np.arange(len(sizes)), sizes)
    same = view[1:] == view[:-1]                           # frames k and k + 1 of one view
    brk = (t[1:] - t[:-1]) > IDENTITY_GAP_S
    brk |= np.diff(np.asarray(runs)) != 0
    seen = np.flatnonzero(np.isfinite(c[:, 0]))
    if len(seen) > 1:  # consecutive frames with a torso, however many torso-less ones between
        pair = view[seen[1:]] == view[seen[:-1]]
        jump = (np.linalg.norm(np.diff(c[seen], axis=0), axis=1) > IDENTITY_JUMP_M) & pair
        brk[seen[1:][jump] - 1] = True
    known = [(k, p) for k, p in enumerate(persons) if p is not None]
    for (k0, p0), (k1, p1) in zip(known, known[1:]):
        if p0 != p1 and view[k0] == view[k1]:  # another view's person is no change of this one
            brk[k1 - 1] = True
    cut = np.flatnonzero(brk & same) if n > 1 else np.zeros(0, dtype=int)
    # each view's last break before its last frame (a break k sits between k and k + 1)
    last = np.searchsorted(cut, ends - 1) - 1
    starts = ends - np.asarray(sizes)
    return [int(cut[j]) + 1 if j >= 0 and cut[j] >= a else int(a)
            for j, a in zip(last, starts)]


def _frame_time(entry: tuple) -> float:
    return entry[0].t


def _placed(frames: list, raw: np.ndarray) -> np.ndarray:
    """(n, 25, 3) the frames' joints in stage space by each one's transform (NaN where a
    frame has none). Frames share transform objects: each run of one is placed at once."""
    stage = np.full_like(raw, np.nan)
    start = 0
    for k in range(1, len(frames) + 1):
        if k == len(frames) or frames[k].transform is not frames[start].transform:
            m = frames[start].transform
            if m is not None:
                stage[start:k] = raw[start:k] @ m[:3, :3].T + m[:3, 3]
            start = k
    return stage


@dataclass
class Consensus:
    """Trusted sensors' joints at given instants, stage space."""

    joints: np.ndarray   # (m, 25, 3)
    conf: np.ndarray     # (m, 25) 0 where nobody trusted saw the joint
    sensors: list[str] = field(default_factory=list)


def consensus(partners: list[View], at: np.ndarray,
              masks: list[np.ndarray] | None = None, first: str | None = None,
              source: tuple[np.ndarray, np.ndarray] | None = None,
              beside: set[str] | frozenset = frozenset()) -> Consensus:
    """Confidence-weighted average of the partners' stage joints at instants ``at``.

    A partner's frames are interpolated within one identity run (``View.run``) only;
    ``masks``: per partner, the instants it may be used at (one person in its view);
    ``first``: a partner (the reference) that, where it is valid, is the consensus alone
    but for the partners in ``beside``;
    ``source``: (capture time on its own clock, start of its identity run on that clock)
    of the calibrated sensor's frame at each instant: a partner's frame counts only if each
    of the two was captured after the other's run began. Two sensors with different clocks
    pair frames captured up to a lag apart; across a person lost and found, or a looped
    take's restart (``stage replay --loop`` restarts every view at once), that pairs one
    pass of the take with the next (N-UCLA: a 65-frame view 0.68 s behind the reference
    paired its last 17 frames with the reference's first ones, and fitted 41 % above the
    optimum)."""
    total = np.zeros((len(at), N_JOINTS, 3))
    weight = np.zeros((len(at), N_JOINTS))
    used = []
    taken = np.zeros(len(at), dtype=bool)
    order = sorted(range(len(partners)), key=lambda k: partners[k].sensor != first)
    for k in order:
        v = partners[k]
        ok_rows = np.isfinite(v.stage).all(axis=(1, 2))
        if not ok_rows.any():
            continue
        j, c, valid = resample(v.t[ok_rows], v.stage[ok_rows], v.conf[ok_rows], at,
                               max_gap=0.1, max_dt=0.05,
                               user=None if v.run is None else v.run[ok_rows])
        if masks is not None:
            valid &= masks[k]
        if v.run is not None and len(v.run) > 1:  # between two runs (a lost-and-found
            # person, a looped take's seam) there is no skeleton to read, not even the nearest
            t_ok, run = v.t[ok_rows], v.run[ok_rows]
            i = np.searchsorted(t_ok, at)
            inside = (i > 0) & (i < len(t_ok))
            i0, i1 = np.maximum(i - 1, 0), np.minimum(i, len(t_ok) - 1)
            valid &= ~(inside & (run[i0] != run[i1]))
            if source is not None:
                begun = _run_starts(t_ok, run)[i0]
                slack = 0.5 / 30
                valid &= source[0] >= begun + v.shift - slack    # raw time, both sides
                valid &= at + v.shift >= source[1] - slack
        if v.sensor not in beside:
            valid &= ~taken
        c = np.where(valid[:, None], c, 0.0)
        if not valid.any():
            continue
        if v.sensor == first:
            taken = valid
        used.append(v.sensor)
        total += j * c[..., None]
        weight += c
    safe = np.where(weight > 0, weight, 1.0)
    return Consensus(total / safe[..., None], np.minimum(weight, 1.0), used)


def torso_centre(joints: np.ndarray, conf: np.ndarray, tracked_only: bool = False,
                 ) -> np.ndarray | None:
    """(..., 25, 3) -> (..., 3) mean of the torso joints (None if none, for one frame).

    Tracked joints (confidence 1) only, when a frame has any: an inferred torso joint can
    be guessed 10-30 cm off, which moved the centre more than the jump gate's agreement.
    ``tracked_only``: never the inferred ones (a frame without a tracked torso joint has
    no centre).
    """
    c = conf[..., _TORSO]
    tracked = c >= 1.0
    if tracked_only:
        w = tracked.astype(float)
    else:
        w = np.where(tracked.any(axis=-1, keepdims=True), tracked, c > 0).astype(float)
    n = w.sum(axis=-1)
    if joints.ndim == 2:  # the engine-thread path: as few numpy calls as possible
        return None if n == 0 else (w @ joints[_TORSO]) / n
    out = (joints[..., _TORSO, :] * w[..., None]).sum(axis=-2) / np.maximum(n, 1)[..., None]
    out[n == 0] = np.nan
    return out


def _current(views: list[View], now: float) -> list[View]:
    """A sensor's views of people it sees now: seen within the last second (its clock may
    run up to ``LiveSettings.max_lag_s`` from stage time, hence the 2 s), and within half a
    second of its newest view (an older one is a person it lost, not a second person)."""
    recent = [v for v in views if v.t[-1] > now - 2.0]
    if not recent:
        return []
    newest = max(v.t[-1] for v in recent)
    return [v for v in recent if v.t[-1] > newest - 0.5]


def new_pairs(sensor: str, views: dict[str, list[View]], trusted: list[str], start: float,
              until: float, now: float, min_joints: int, reference: str | None = None,
              good: set[str] | frozenset = frozenset(),
              ) -> tuple["PairSet | None", str | None]:
    """Pairs for calibrating ``sensor`` from its frames in (start, until].

    Needs exactly one user in the sensor's view (last second) and at least one
    trusted sensor that also sees exactly one; the target is those sensors' consensus in
    stage space -- where the ``reference`` sees that person, only the reference's and the
    ``good`` sensors' (those that agree with the others well) -- and the source is the
    sensor's raw joints. Returns (pairs or None, why we wait or None).
    """
    from ..geometry import transform_plane
    from .pairs import PairSet
    seen = _current(views.get(sensor, []), now)
    if len(seen) != 1:
        return None, ("waiting: nobody in its view" if not seen else
                      f"waiting: {len(seen)} people in its view; calibration needs one")
    partners = []
    for r in trusted:
        rv = _current(views.get(r, []), now) if r != sensor else []
        if len(rv) == 1:
            partners.append(rv[0])
    if not partners:
        return None, "waiting for a calibrated sensor to see the same single person"
    # every identity run of the views, each instant judged on its own (see View.whole)
    v = seen[0].whole()
    idx = v.between(start, until)
    idx = idx[_alone(v.t[idx], sensor, v.user, views)]
    if not len(idx):
        return None, None
    at = v.t[idx]
    partners = [p.whole() for p in partners]
    # where the reference sees the person, only sensors that agree well join it: a consensus
    # with a sensor placed poorly a moment ago passed that one's error on (N-UCLA: a second
    # sensor fitted at 34 cm to a consensus with a first one placed 21 cm off), while on
    # the simulator a consensus of well-agreeing sensors averages their views' biases out
    began = _run_starts(v.t, v.run)[idx]
    cons = consensus(partners, at, [_alone(at, p.sensor, p.user, views) for p in partners],
                     first=reference, source=(at + v.shift, began + v.shift), beside=good)
    w = v.conf[idx] * cons.conf
    good = (w > 0).sum(axis=1) >= min_joints
    floor = next((transform_plane(p.floor, p.transform) for p in partners
                  if p.floor is not None and p.transform is not None), None)
    pairs = PairSet("stage", sensor, cons.joints[good], v.raw[idx][good], w[good], v.t[idx][good],
                    floor, v.floor)
    pairs.partners = sorted(p.sensor for p in partners)  # type: ignore[attr-defined]
    return pairs, None


def _alone(at: np.ndarray, sensor: str, user: int, views: dict[str, list[View]],
           window_s: float = 0.25) -> np.ndarray:
    """(m,) bool: no other user of ``sensor`` was in its view within ``window_s`` of each
    instant (pairs are taken only while each sensor sees exactly one person, as offline)."""
    ok = np.ones(len(at), dtype=bool)
    for o in views.get(sensor, []):
        if o.user == user or not len(at):
            continue
        ot = o.whole().t
        k = np.searchsorted(ot, at)
        before = np.abs(at - ot[np.maximum(k - 1, 0)])
        after = np.abs(ot[np.minimum(k, len(ot) - 1)] - at)
        ok &= np.minimum(before, after) > window_s
    return ok


def _run_starts(t: np.ndarray, run: np.ndarray) -> np.ndarray:
    """(n,) the time each frame's identity run began; -inf for the first run, which began
    before the frames at hand (the worker's snapshot reaches ``max_lag_s`` further back
    than any frame it pairs)."""
    first_of = np.r_[0, np.flatnonzero(np.diff(run)) + 1]
    starts = t[first_of].astype(float)
    starts[0] = -np.inf
    return starts[np.searchsorted(first_of, np.arange(len(t)), side="right") - 1]
