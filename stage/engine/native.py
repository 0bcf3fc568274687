"""The native core: a datagram's usual fusion work in one compiled call (issue 10, stop 41).

What a 6 x 6 datagram costs the engine is mostly the Python between its compiled
kernels, not the kernels (docs/reports/issue-10.md, stops 34-40): about three quarters
of it live on the machines we measure on. Moving one kind of call at a time into one
call per datagram gained nothing (stop 40), because gathering each person's arrays for
the call cost what the calls saved. The only way left is a path on which a datagram's
data stays in arrays from its frames to its encoded output. This module is that path's
core, built beside the Python one and held to it bit for bit:

- every person's filter state is a *ring* of states in one array per kind, indexed by
  its slot: a step reads the newest entry and writes the next, so the state before each
  step stays in place (what a replay starts from) and nothing is allocated or freed;
- the person's settled output (joints, velocity, confidences and the rest of
  ``bank.PersonBank``'s rows) lives beside it, indexed by the same slot;
- ``fold`` takes a datagram's views of persons it holds -- one sensor's frames of one
  instant, in stage space -- and in one compiled call (``jit._native_fold``) folds them
  in, remembers each view's confidences, settles each person and encodes the
  ``/jointCoordinates`` the views receive, into one buffer.

It does only the usual case: every view a plain update of a person it holds (after the
person's newest view, not within ``group_s`` of its instant), no joint to start or to
restart, every view already remembered by its person. Anything else is *declined*:
nothing is changed, and the caller folds the datagram by the Python path
(``fuser.Fuser``), then hands the persons over again (``take``).

This stop it runs beside the engine, not in it: ``bench/bench_native.py`` and
tests/test_native.py feed the engine the simulator's datagrams, give the core each
datagram's views as the engine made them, and compare what both send and keep. Wiring it
into the engine (behind a rig switch, the persons handed back to the Python path when a
datagram is declined) is the next step.
"""

from __future__ import annotations

import numpy as np

from ..joints import INFERRED, N_JOINTS
from ..settings import FusionSettings, KalmanSettings
from . import jit
from .fusion import _CHILDREN, _PARENTS
from .people import _TORSO

#: states kept per person: at 6 sensors x 30 Hz, 27 steps in ``replay_s`` (0.15 s)
DEPTH = 48

_FIELDS = (
    ("joints", (N_JOINTS, 3), float, 0.0),
    ("velocity", (N_JOINTS, 3), float, 0.0),
    ("conf", (N_JOINTS,), float, 0.0),
    ("known", (N_JOINTS,), bool, False),
    ("carried", (N_JOINTS,), bool, False),
    ("tracked", (N_JOINTS,), bool, False),
    ("hold", (N_JOINTS, 3), float, np.nan),
)


class NativeCore:
    """Persons held in slots (see the module docstring); engine thread only."""

    def __init__(self, smoothing: KalmanSettings, fusion: FusionSettings,
                 q_scale: np.ndarray | None = None, slots: int = 8, rows: int = 8,
                 depth: int = DEPTH) -> None:
        if not jit.warm_native():
            raise RuntimeError("the native core needs the compiled kernels ("
                               f"{jit.why_not() or 'its own failed to compile: logged'})")
        self.s, self.f = smoothing, fusion
        self.q_scale = (np.empty(0) if q_scale is None
                        else np.ascontiguousarray(q_scale, dtype=float))
        self.q, self.rates = jit._flat(smoothing)
        self.depth = depth
        self.slot_of: dict[int, int] = {}             # person id -> slot
        self.owners: list[int | None] = []
        #: per slot: view key -> its row of recent_conf/recent_t (Person.recent)
        self.recent: list[dict] = []
        self._rows = rows
        self._alloc(slots)
        self.names, self.name_end, self.longest = jit._NAMES, jit._NAME_END, jit._LONGEST
        self.declined = 0
        self.folded = 0
        #: per view of the last accepted fold: the step's counts (K, 4), outcome, used
        self.counts = np.zeros((0, 4), dtype=np.int64)
        self._scratch: dict[int, tuple] = {}
        self._tg = np.empty(N_JOINTS)

    # ------------------------------------------------------------ slots
    def _alloc(self, n: int) -> None:
        d, r = self.depth, self._rows
        self.ring = np.full((n, d, 6, 2, N_JOINTS, 3), np.nan)
        self.ring_t = np.full((n, d, N_JOINTS), np.nan)
        self.ring_hz = np.full((n, d, N_JOINTS, 3), np.nan)
        self.ring_ht = np.full((n, d, N_JOINTS), np.nan)
        self.head = np.zeros(n, dtype=np.int64)
        self.newest = np.full(n, -np.inf)
        self.anchor = np.full(n, -np.inf)
        self.person_t = np.full(n, -np.inf)
        for name, shape, dtype, free in _FIELDS:
            setattr(self, name, np.full((n, *shape), free, dtype=dtype))
        self.centre = np.zeros((n, 3))
        self.recent_conf = np.zeros((n, r, N_JOINTS))
        self.recent_t = np.full((n, r), -np.inf)
        self.owners = [None] * n
        self.recent = [{} for _ in range(n)]

    def _grow(self) -> None:
        """Twice as many slots, every held person's rows kept."""
        n = len(self.owners)
        old = {name: getattr(self, name) for name in self._arrays()}
        owners, recent = self.owners, self.recent
        self._alloc(2 * n)
        for name, value in old.items():
            getattr(self, name)[:n] = value
        self.owners[:n] = owners
        self.recent[:n] = recent

    def _grow_rows(self) -> None:
        """Twice as many rows of views per person."""
        n, r = self.recent_t.shape
        self.recent_conf = np.concatenate((self.recent_conf, np.zeros((n, r, N_JOINTS))), axis=1)
        self.recent_t = np.concatenate((self.recent_t, np.full((n, r), -np.inf)), axis=1)
        self._rows = 2 * r

    @staticmethod
    def _arrays() -> tuple[str, ...]:
        return ("ring", "ring_t", "ring_hz", "ring_ht", "head", "newest", "anchor", "person_t",
                *(f[0] for f in _FIELDS), "centre", "recent_conf", "recent_t")

    def take(self, person) -> int:
        """Take ``person`` (a ``tracking.Person`` the Python path has folded, with a centre)
        into a slot, as it is now: its filter's state, newest view and instant, its output
        rows and its views' recent confidences (copies). Returns the slot."""
        s = self.slot_of.get(person.id)
        if s is None:
            try:
                s = self.owners.index(None)
            except ValueError:
                s = len(self.owners)
                self._grow()
            self.slot_of[person.id] = s
            self.owners[s] = person.id
        st = person.filter.state
        while len(person.recent_t) > self.recent_t.shape[1]:
            self._grow_rows()
        self.head[s] = 0
        self.ring[s, 0] = st.stacked()
        self.ring_t[s, 0] = st.t
        self.ring_hz[s, 0] = st.held_z
        self.ring_ht[s, 0] = st.held_t
        hist = person.filter.history
        self.newest[s] = person.filter.newest
        self.anchor[s] = hist[-1].anchor if hist else -np.inf
        self.person_t[s] = person.t
        for name, *_ in _FIELDS:
            getattr(self, name)[s] = getattr(person, name)
        self.centre[s] = person.centre
        self.recent_conf[s] = 0.0
        self.recent_t[s] = -np.inf
        n = len(person.recent_t)
        self.recent_conf[s, :n] = person.recent_conf
        self.recent_t[s, :n] = person.recent_t
        self.recent[s] = dict(person.recent)
        return s

    def release(self, pid: int) -> None:
        """Forget the person ``pid`` (its slot is free for another)."""
        s = self.slot_of.pop(pid, None)
        if s is not None:
            self.owners[s] = None
            self.recent[s] = {}

    def state(self, pid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The person's filter state now: ((6, 2, 25, 3) block, t, held_z, held_t), views."""
        s = self.slot_of[pid]
        h = self.head[s]
        return self.ring[s, h], self.ring_t[s, h], self.ring_hz[s, h], self.ring_ht[s, h]

    # ------------------------------------------------------------ the datagram
    def _buffers(self, k: int) -> tuple:
        b = self._scratch.get(k)
        if b is None:
            b = self._scratch[k] = (
                np.empty((k, N_JOINTS), dtype=np.int8), np.empty((k, N_JOINTS), dtype=np.bool_),
                np.empty((k, 4), dtype=np.int64), np.empty((k, N_JOINTS, 3)),
                np.empty((k, N_JOINTS, 3)), np.empty(k * self.longest, dtype=np.uint8),
                np.empty(k + 1, dtype=np.int64), np.empty(k, dtype=np.int64))
        return b

    def fold(self, pids: list[int], keys: list[tuple[str, int]], t: np.ndarray, z: np.ndarray,
             r: np.ndarray, conf: np.ndarray) -> list[bytes] | None:
        """Fold K views (view i of person ``pids[i]``, from view ``keys[i]``, captured at
        t[i], joints z (K, 25, 3), variances r (K, 25), confidences conf (K, 25); C-ordered
        float64) in; returns each person's encoded ``/jointCoordinates``, or None if the
        core declines the datagram (nothing changed: see the module docstring)."""
        k = len(pids)
        slot_of, recent = self.slot_of, self.recent
        slots = np.empty(k, dtype=np.int64)
        rows = np.empty(k, dtype=np.int64)
        for i in range(k):
            s = slot_of.get(pids[i])
            row = None if s is None else recent[s].get(keys[i])
            if row is None:
                self.declined += 1
                return None
            slots[i] = s
            rows[i] = row
        outcome, used, counts, pos, vel, buf, offsets, centred = self._buffers(k)
        s, f = self.s, self.f
        done = jit._compiled["_native_fold"](
            slots, t, z, r, conf, rows, np.asarray(pids, dtype=np.int64), self.ring,
            self.ring_t, self.ring_hz, self.ring_ht, self.head, self.newest, self.anchor,
            self.person_t, self.q, self.q_scale, self.rates, float(s.gate_sigma ** 2),
            float(s.reject_sigma ** 2), float(f.group_s), self._tg, outcome, used, counts, pos,
            vel, float(f.stale_s), self.recent_conf, self.recent_t, self.joints, self.velocity,
            self.conf, self.known, self.carried, self.tracked, self.hold, self.centre,
            bool(f.carry_untracked), bool(f.hold_back_inferred), float(INFERRED), _PARENTS,
            _CHILDREN, _TORSO, self.names, self.name_end, buf, offsets, centred)
        if done < 0:
            self.declined += 1
            return None
        self.folded += 1
        self.counts = counts
        out = []
        for i in range(k):
            if not centred[i]:
                self._centre_otherwise(slots[i])
            out.append(buf[offsets[i]:offsets[i + 1]].tobytes())
        return out

    def _centre_otherwise(self, s: int) -> None:
        """A person with no torso joint known: the centre of its known joints (as
        ``fusion.torso_centre`` of the joints and ``known``), else left as it was."""
        known = self.known[s]
        if known.any():
            self.centre[s] = self.joints[s][known].mean(axis=0)
