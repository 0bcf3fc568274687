"""The tracking layer: which sensor views are which person.

``Track`` is one sensor's view of one user; ``Person`` a fused person with the
views bound to it; ``Tracker`` decides the binding -- association against
the predicted person with hysteresis, merging of two persons no sensor sees
together, expiry after a grace period, and person ids (a person who comes
back soon after being lost, near where they went and with the same body
size, gets their id back). ``OffsetEstimator`` follows a client's clock. The
engine thread owns every object here.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..joints import JOINT_INDEX, N_JOINTS, TORSO, HandState
from ..settings import FusionSettings
from . import handbank, jit
from .fuser import BodyFilter
from .fusion import torso_centre
from .handbank import ArrayHandVoter
from .hands import HandVoter

log = logging.getLogger("stage.engine")

#: "person N picked up again" is logged at most once in this many seconds per person
PICKED_UP_LOG_S = 1.0


_TORSO_IDX = np.array(TORSO)
_NECK, _BASE = JOINT_INDEX["Neck"], JOINT_INDEX["SpineBase"]


def body_size(joints: np.ndarray, conf: np.ndarray) -> float | None:
    """Trunk length (m): SpineBase to Neck, which no pose stretches; None if either is unseen."""
    if conf[_NECK] <= 0 or conf[_BASE] <= 0:
        return None
    d = joints[_NECK] - joints[_BASE]
    # (summed in this order, as the frame kernel does: the same float either way)
    return math.sqrt(float(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))


class OffsetEstimator:
    """Estimates ``engine_time - client_time`` from (arrival, timetag) pairs.

    Network delay only ever adds to ``arrival - timetag``, so the minimum
    over a sliding window is the offset plus the smallest delay seen — the
    usual one-way estimate when clocks cannot be asked. The window lets a
    client whose clock was reset be followed within ``window_s``.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self._mins: deque[tuple[float, float]] = deque()  # increasing values: monotonic min-queue

    def update(self, arrival: float, timetag: float) -> float:
        value = arrival - timetag
        while self._mins and self._mins[-1][1] >= value:
            self._mins.pop()
        self._mins.append((arrival, value))
        while self._mins[0][0] < arrival - self.window_s:
            self._mins.popleft()
        return self._mins[0][1]

    @property
    def offset(self) -> float | None:
        return self._mins[0][1] if self._mins else None


@dataclass(eq=False)
class Track:
    """One sensor's view of one user (client id, user id 0-5), in stage space."""

    client: str
    user: int
    joints: np.ndarray = field(default_factory=lambda: np.zeros((N_JOINTS, 3)))
    conf: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS))
    t: float = float("-inf")            # capture time of the latest frame (engine clock)
    stamp: float = float("-inf")        # the same on the client's clock (timetag or arrival)
    hands: list[HandState] = field(default_factory=lambda: [HandState.UNKNOWN] * 2)
    arms_traded: int = 0                # 1 while its latest frame had the arms swapped back
    #: the part of a hand-state reading each of its reports is: 1 / the frames its sensor
    #: repeats a reading over (``hands.reading_frames``; ``ClientState.hand_frames``)
    hand_step: float = 0.5
    #: its hand states' current runs, for the sensor's ``hands.CadenceWatch``: [left state,
    #: right state, left run's frames, right's] (None, -1: none yet / begun with the track)
    hand_run: list = field(default_factory=lambda: [None, None, -1, -1])
    person: int | None = None
    far_frames: int = 0                 # consecutive frames beyond release distance

    @property
    def key(self) -> tuple[str, int]:
        return self.client, self.user


@dataclass(eq=False)
class Person:
    """A fused person: the views bound to it, its filter and its smoothed skeleton.

    ``filter`` (``fuser.BodyFilter``) holds the joint filters' full state (position,
    velocity, covariance and motion-mode probabilities per joint and axis);
    ``joints``/``velocity`` are its estimate at ``t``, the capture time of the newest
    frame folded in.
    """

    id: int
    filter: BodyFilter
    voter: HandVoter | ArrayHandVoter
    created: float
    tracks: set = field(default_factory=set)   # of Track
    joints: np.ndarray = field(default_factory=lambda: np.zeros((N_JOINTS, 3)))
    conf: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros((N_JOINTS, 3)))
    centre: np.ndarray | None = None
    known: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS, dtype=bool))
    t: float = float("-inf")
    hands: list[HandState] = field(default_factory=lambda: [HandState.UNKNOWN] * 2)
    announced: bool = False
    orphan_since: float | None = None       # when its last view went away
    sent_hands: list[HandState | None] = field(default_factory=lambda: [None, None])
    size: float | None = None               # trunk length, m (mean of the frames seen)
    size_n: int = 0
    merged: bool = False                    # folded into another person: never comes back
    #: ``sensors()`` as last made (None: to be made again; ``Tracker`` resets it when it
    #: changes ``tracks``)
    _sensors: tuple | None = field(default=None, repr=False)
    #: (client, user) -> its row of ``recent_conf``/``recent_t``: each view's latest frame's
    #: (25,) confidence and capture time (-inf: a free row)
    recent: dict = field(default_factory=dict)
    recent_conf: np.ndarray = field(default_factory=lambda: np.zeros((0, N_JOINTS)))
    recent_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: (rows, 25, 3): each remembered view's learned offset, in the rows of ``recent``
    #: (``offsets``; None: none learned yet)
    offsets: np.ndarray | None = None
    #: (25,) bool: joints some view has tracked (confidence above the inferred level) since
    #: the person was found
    tracked: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS, dtype=bool))
    #: (25, 3) each joint's offset from its parent joint (``forecast.BONES``) in the output
    #: the last time a view tracked it; NaN before that
    hold: np.ndarray = field(default_factory=lambda: np.full((N_JOINTS, 3), np.nan))
    #: (25,) bool: the joints of the latest output placed by their parent (none tracked them)
    carried: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS, dtype=bool))
    #: its slot in the engine's ``bank.PersonBank`` (-1: none) and that bank: while bound,
    #: ``joints``, ``velocity``, ``conf``, ``known``, ``carried``, ``tracked``, ``hold``,
    #: ``recent_conf`` and ``recent_t`` are views of its rows there, changed in place
    slot: int = -1
    bank: object = field(default=None, repr=False)

    @classmethod
    def new(cls, pid: int, t: float, settings: FusionSettings) -> "Person":
        # the hand votes compiled when the engine's kernels are (the same states, cheaper)
        voter = (ArrayHandVoter if handbank.compiled() else HandVoter)(
            settings.hand_memory_s, settings.hand_hold_s)
        return cls(pid, BodyFilter(), voter, t)

    def remember(self, key: tuple[str, int], t: float, conf: np.ndarray) -> None:
        """The latest frame of the view ``key``: its capture time and confidences."""
        row = self.recent.get(key)
        if row is None:
            free = np.flatnonzero(self.recent_t == -np.inf)
            if len(free):
                row = int(free[0])
            else:               # room for more views (a few per person: a row per sensor)
                row = len(self.recent_t)
                # (a person bound to the engine's bank: every person's rows, one array)
                if self.bank is None or not self.bank.grow_rows_for(self):
                    grow = max(row, 2)
                    self.recent_conf = np.concatenate((self.recent_conf,
                                                       np.zeros((grow, N_JOINTS))))
                    self.recent_t = np.concatenate((self.recent_t, np.full(grow, -np.inf)))
            self.recent[key] = row
        self.recent_conf[row] = conf
        self.recent_t[row] = t

    def forget(self, key: tuple[str, int]) -> None:
        """The view ``key`` left this person: its confidences no longer count."""
        row = self.recent.pop(key, None)
        if row is not None:
            self.recent_t[row] = -np.inf
            if self.offsets is not None:
                if len(self.recent) < 2:
                    # one view left: it has no offset (``People._offset`` forgets the table
                    # at its next frame; the native core's persons keep theirs, zeroed here)
                    self.offsets[...] = 0.0
                elif row < len(self.offsets):
                    self.offsets[row] = 0.0      # (the row's next view starts from nothing)

    def measure_size(self, joints: np.ndarray, conf: np.ndarray) -> None:
        """Fold one view's trunk length into the running mean."""
        self.add_size(body_size(joints, conf))

    def add_size(self, size: float | None) -> None:
        """Fold a trunk length (``body_size``; None: not measured) into the running mean."""
        if size is not None:
            self.size_n += 1
            self.size = size if self.size is None else self.size + (size - self.size) / self.size_n

    def distance(self, joints: np.ndarray, conf: np.ndarray, t: float) -> float | None:
        """Mean distance (m) from a view's joints to this person predicted at ``t``.

        Compared on the torso joints both have (all shared joints if no torso),
        so a view that sees only part of the body is not judged by a centre
        that jumps with what happens to be occluded.
        """
        dt = min(max(t - self.t, 0.0), 0.5)
        if jit.ready():
            try:
                return jit.distance(joints, conf, self.joints, self.velocity, self.known, dt,
                                    _TORSO_IDX)
            except TypeError:   # arrays the kernel does not take (not float64, not contiguous)
                pass
        on_torso = (conf[_TORSO_IDX] > 0) & self.known[_TORSO_IDX]
        n = np.count_nonzero(on_torso)                 # (not .any(): a reduction costs more)
        if n == len(_TORSO_IDX):
            idx = _TORSO_IDX
        elif n:
            idx = _TORSO_IDX[on_torso]
        else:
            idx = np.flatnonzero((conf > 0) & self.known)
            if not len(idx):
                return None
        diff = joints[idx] - self.joints[idx] - self.velocity[idx] * dt
        diff *= diff
        # sum / count is what .mean() computes, without its Python-level wrapper (this runs
        # for every view and candidate person); the columns added as .sum(axis=1) does
        d2 = diff[:, 0] + diff[:, 1]
        d2 += diff[:, 2]
        return float(np.sqrt(d2, out=d2).sum() / len(idx))

    def sensors(self) -> tuple[str, ...]:
        """The ids of the sensors that see it, sorted (made again after ``tracks`` changed:
        ``Tracker`` is the one that changes them, and says so)."""
        made = self._sensors
        if made is None:
            made = self._sensors = tuple(sorted({tr.client for tr in self.tracks}))
        return made


class Tracker:
    """Binds sensor views (``Track``) to fused persons (``Person``).

    A bound view stays with its person until it is beyond ``release_m`` for
    ``release_frames`` frames in a row (hysteresis); an unbound view joins the
    nearest person within ``associate_m`` that no view of the same sensor is
    bound to, else starts a new person. Two persons closer than ``merge_m``
    for ``merge_s`` that no sensor sees together are one. A person with no
    views is kept ``lost_grace_s`` before it is lost. A new person whose torso
    is within ``rejoin_m`` of where a person was lost less than ``rejoin_s``
    ago, with a trunk length within ``rejoin_size_m`` of theirs, is that
    person back: they get the old id (the nearest such, once).
    """

    def __init__(self, fusion: FusionSettings) -> None:
        self.fusion = fusion
        self.persons: dict[int, Person] = {}
        self._next_id = 1
        self._close_since: dict[tuple[int, int], float] = {}
        #: persons lost recently: (id, torso centre (3,), trunk length m, when lost)
        self.departed: list[tuple[int, np.ndarray, float, float]] = []
        #: person id -> (when "picked up again" was last logged, picks since not logged)
        self._picked_said: dict[int, tuple[float, int]] = {}

    def associate(self, track: Track, t: float) -> Person:
        """The person ``track`` (a view with fresh joints at time ``t``) belongs to."""
        fs = self.fusion
        if track.person is not None:
            person = self.persons[track.person]
            # a person's only view stays with it: no distance needed (this runs per view)
            d = None if len(person.tracks) == 1 else person.distance(track.joints, track.conf, t)
            if d is None or d <= fs.release_m:
                track.far_frames = 0
                return person
            track.far_frames += 1
            if track.far_frames < fs.release_frames:
                return person
            log.info("sensor %s user %d left person %d (%.2f m away)", track.client, track.user,
                     person.id, d)
            self.unbind(track, t)
        best, best_d = None, fs.associate_m
        for person in self.persons.values():
            if any(other.client == track.client for other in person.tracks):
                continue  # one sensor never sees one person twice
            d = person.distance(track.joints, track.conf, t)
            if d is not None and d <= best_d:
                best, best_d = person, d
        if best is None:
            pid = self._rejoin(track, t)
            if pid is None:
                pid = self._next_id
                self._next_id += 1
            best = self.persons[pid] = Person.new(pid, t, fs)
        elif best.orphan_since is not None:
            self._say_picked_up(best.id, track.client, t)
        best.tracks.add(track)
        best._sensors = None
        best.orphan_since = None
        track.person, track.far_frames = best.id, 0
        return best

    def _say_picked_up(self, pid: int, client: str, t: float) -> None:
        """Log that a person was picked up again, at most once a second per person. An
        engine that fell behind drops and picks up views every frame: 745 such lines in 5 s
        once (bench_soak live, issue 10, stop 33), each one slowing it further."""
        said = self._picked_said
        last, quiet = said.get(pid, (-math.inf, 0))
        if t - last < PICKED_UP_LOG_S:
            said[pid] = (last, quiet + 1)
            return
        more = f" (and {quiet} more time(s) since the last such line)" if quiet else ""
        log.info("person %d picked up again by sensor %s%s", pid, client, more)
        said[pid] = (t, 0)
        if len(said) > 64:    # persons come and go for weeks: keep the recent ones only
            self._picked_said = {k: v for k, v in said.items() if t - v[0] < PICKED_UP_LOG_S}

    def _rejoin(self, track: Track, t: float) -> int | None:
        """The id of a recently lost person this view is (see the class docstring), or None."""
        fs = self.fusion
        self.departed = [d for d in self.departed if t - d[3] <= fs.rejoin_s]
        size = body_size(track.joints, track.conf)
        centre = torso_centre(track.joints, track.conf)
        if size is None or centre is None or not self.departed:
            return None
        best, best_d = None, fs.rejoin_m
        for k, (pid, where, old_size, _) in enumerate(self.departed):
            d = float(np.linalg.norm(centre - where))
            if d <= best_d and abs(size - old_size) <= fs.rejoin_size_m and pid not in self.persons:
                best, best_d = k, d
        if best is None:
            return None
        pid, _, _, lost_at = self.departed.pop(best)
        log.info("person %d is back after %.1f s (%.2f m from where they were lost)", pid,
                 t - lost_at, best_d)
        return pid

    def unbind(self, track: Track, t: float) -> int | None:
        """Detach ``track`` from its person; returns that person's id (None if unbound)."""
        pid = track.person
        person = self.persons.get(pid) if pid is not None else None
        track.person = None
        if person is not None:
            person.tracks.discard(track)
            person._sensors = None
            if not person.tracks:
                person.orphan_since = t
        return pid

    def merge_close(self, now: float) -> None:
        """Merge persons that stayed within ``merge_m`` for ``merge_s`` and share no sensor."""
        fs = self.fusion
        live = [p for p in self.persons.values() if p.centre is not None and p.tracks]
        close_now: set[tuple[int, int]] = set()
        if len(live) < 2:
            self._close_since.clear()
            return
        # every pair, in floats: a handful of persons, at every tick (numpy's arrays cost
        # more to build than these few sums; the same floats, as dx * dx + dy * dy + dz * dz
        # is the order numpy sums three terms in)
        limit = fs.merge_m ** 2
        centres = [p.centre.tolist() for p in live]
        near = []
        for i, (xi, yi, zi) in enumerate(centres):
            for j in range(i + 1, len(centres)):
                xj, yj, zj = centres[j]
                dx, dy, dz = xi - xj, yi - yj, zi - zj
                if dx * dx + dy * dy + dz * dz <= limit:
                    near.append((i, j))
        if not near:    # no pair: the usual
            self._close_since.clear()
            return
        for i, j in near:
            a, b = live[i], live[j]
            if a.tracks and b.tracks:
                if {t.client for t in a.tracks} & {t.client for t in b.tracks}:
                    continue  # one sensor sees both: two people
                key = (min(a.id, b.id), max(a.id, b.id))
                close_now.add(key)
                since = self._close_since.setdefault(key, now)
                if now - since >= fs.merge_s:
                    keep, gone = (a, b) if a.id < b.id else (b, a)
                    log.info("person %d and %d are one person: keeping %d", keep.id, gone.id,
                             keep.id)
                    for track in list(gone.tracks):
                        track.person = keep.id
                        keep.tracks.add(track)
                    gone.tracks.clear()
                    keep._sensors = gone._sensors = None
                    gone.merged = True
                    gone.orphan_since = now - fs.lost_grace_s  # lost at once
                    close_now.discard(key)
        self._close_since = {k: v for k, v in self._close_since.items() if k in close_now}

    def expire(self, now: float) -> list[int]:
        """Forget persons without views for ``lost_grace_s``; returns the announced ones."""
        grace = self.fusion.lost_grace_s
        lost = []
        for pid, person in list(self.persons.items()):
            if person.orphan_since is not None and now - person.orphan_since >= grace:
                del self.persons[pid]
                if person.announced:
                    log.info("person %d lost", pid)
                    lost.append(pid)
                    if not person.merged and person.centre is not None and person.size:
                        self.departed.append((pid, person.centre.copy(), person.size,
                                              person.orphan_since))
        return lost
