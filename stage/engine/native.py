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

It folds a view as ``fuser.Fuser.fold`` does: after the person's newest view, beginning an
instant or joining one (whose joints are chosen again, as ``Fuser._choose`` does, when
its views do not all agree, and the instant folded again when the choice changes), or
before it, within the history the Python path would keep (inserted in capture order and
the span from its instant folded again, as ``Fuser._replay``). It declines, before
anything changes (``refused`` names the view), a view the Python path would drop as late
or fit before its history, a replay reaching past the steps the ring still holds and a
person twice in a datagram. A joint to start or to restart (rejected twice in a row) is
started as the Python path starts it, and a person's first view from a sensor is given
the row ``Person.remember`` would give it (stop 43; before, the core declined both).

In the engine (``people.People``, with ``fusion: native: true``) a person the Python path
has folded a few datagrams in a row is taken (``take(bind=True)``, its history put in the
ring); a person whose view the core declines is given back first (``give_back``: its
history rebuilt from the ring, as if the Python path had folded every view) and that view
folded by the Python path, the others by the core. tests/test_native.py plays whole shows through
engines with the switch on and off and compares every datagram sent;
``stage.testing.native_shadow`` runs a core beside an engine on the same datagrams and
compares every float it keeps (``bench/bench_native.py``).
"""

from __future__ import annotations

import numpy as np

from ..joints import INFERRED, N_JOINTS, TORSO
from ..settings import FusionSettings, KalmanSettings
from . import jit
from .bank import _FIELDS
from .fuser import View, _Step
from .fusion import _CHILDREN, _PARENTS
from .kalman import FilterState, initial_mu

_TORSO = np.array(TORSO)

#: states kept per person: the newest, the entry the next step writes, and DEPTH - 2 before
#: them (at 6 sensors x 30 Hz, ``replay_s``'s 0.15 s is 27 steps); a replay writes its span
#: after the head first, so spans up to a third of the ring are folded by the core
DEPTH = 64

#: the arrays a bound person's attributes are views of
_BOUND = (*(f[0] for f in _FIELDS), "recent_conf", "recent_t", "offsets")


class NativeCore:
    """Persons held in slots (see the module docstring); engine thread only."""

    def __init__(self, smoothing: KalmanSettings, fusion: FusionSettings,
                 q_scale: np.ndarray | None = None, slots: int = 8, rows: int = 8,
                 depth: int = DEPTH) -> None:
        if not jit.warm_native():
            raise RuntimeError("the native core needs the compiled kernels ("
                               f"{jit.why_not() or 'its own failed to compile: logged'})")
        if depth < 3:
            raise ValueError(f"a ring of {depth} states: at least 3")
        self.s, self.f = smoothing, fusion
        self.q_scale = (np.empty(0) if q_scale is None
                        else np.ascontiguousarray(q_scale, dtype=float))
        self.q, self.rates = jit._flat(smoothing)
        self.depth = depth
        self.slot_of: dict[int, int] = {}             # person id -> slot
        #: per slot: the person held there (None: free) and whether its attributes are
        #: views of the slot's rows (``take(bind=True)``)
        self.owners: list = []
        self.bound: list[bool] = []
        #: per slot: view key -> its row of recent_conf/recent_t (the bound person's own
        #: ``Person.recent``, else a copy of it)
        self.recent: list[dict] = []
        self._rows = rows
        self._alloc(slots)
        self.names, self.name_end, self.longest = jit._NAMES, jit._NAME_END, jit._LONGEST
        self.declined = 0
        self.folded = 0
        self.given_back = 0
        #: views the core folded in again from where they belong (late, or an instant's
        #: choice changed: ``fuser.Fuser._replay``)
        self.replayed = 0
        #: after a declined fold: the index of the view the core could not take
        self.refused = -1
        #: persons given back whose history lost steps the ring no longer held (see
        #: ``give_back``)
        self.short_histories = 0
        #: per view of the last accepted fold (K, 6): rows restarted, rows started, joints
        #: downweighted, joints rejected, 1 if replayed, the change in joints left out by
        #: instants' choices (``jit._native_fold``)
        self.counts = np.zeros((0, 6), dtype=np.int64)
        #: ``counts`` summed over the views, as a list
        self.totals = [0] * 6
        #: the slots of the last accepted fold's views, in order
        self.slots = np.zeros(0, dtype=np.int64)
        self._scratch: dict[int, tuple] = {}
        self._tg = np.empty(N_JOINTS)
        #: what a row started afresh begins with (``jit._native_start``)
        self._init = np.array([smoothing.initial_velocity_var, *initial_mu(smoothing)],
                              dtype=float)
        #: an instant's joints chosen again (``jit._native_fold``'s scratch)
        self._given = np.empty((self.depth, N_JOINTS), dtype=bool)

    # ------------------------------------------------------------ slots
    def _alloc(self, n: int) -> None:
        self._args = None
        d, r = self.depth, self._rows
        self.ring = np.full((n, d, 6, 2, N_JOINTS, 3), np.nan)
        self.ring_t = np.full((n, d, N_JOINTS), np.nan)
        self.ring_hz = np.full((n, d, N_JOINTS, 3), np.nan)
        self.ring_ht = np.full((n, d, N_JOINTS), np.nan)
        self.ring_z = np.full((n, d, N_JOINTS, 3), np.nan)
        self.ring_r = np.full((n, d, N_JOINTS), np.nan)
        self.ring_conf = np.zeros((n, d, N_JOINTS))
        self.ring_used = np.zeros((n, d, N_JOINTS), dtype=bool)
        self.ring_mask = np.zeros((n, d, N_JOINTS), dtype=bool)
        # t, recent row, arrival, size, anchor, joints its instant's choice left out
        self.ring_view = np.full((n, d, 6), np.nan)
        # each row's outcome in the step that made the entry (``jit._step_rows``), -1 where
        # not known (steps put in by ``take``): a changed choice steps only the rows it
        # changes and counts the others' outcomes from here (``jit._native_rows_again``)
        self.ring_out = np.full((n, d, N_JOINTS), -1, dtype=np.int8)
        self.head = np.zeros(n, dtype=np.int64)
        self.steps = np.zeros(n, dtype=np.int64)
        self.valid = np.zeros(n, dtype=np.int64)       # steps whose state before is kept
        self.seeded = np.zeros(n, dtype=np.int64)      # of those, put in by ``take``
        self.newest = np.full(n, -np.inf)
        self.anchor = np.full(n, -np.inf)
        self.person_t = np.full(n, -np.inf)
        for name, shape, dtype, free in _FIELDS:
            setattr(self, name, np.full((n, *shape), free, dtype=dtype))
        self.centre = np.zeros((n, 3))
        self.recent_conf = np.zeros((n, r, N_JOINTS))
        self.recent_t = np.full((n, r), -np.inf)
        #: each view's learned offset (``offsets``), a row per row of ``recent_t``: the
        #: person's ``offsets`` (zeros where the Python path has none yet; learned by
        #: ``jit._native_offsets``, ``people.People._offsets_held``)
        self.offsets = np.zeros((n, r, N_JOINTS, 3))
        self.owners = [None] * n
        self.bound = [False] * n
        self.recent = [{} for _ in range(n)]

    def _grow(self) -> None:
        """Twice as many slots, every held person's rows kept (bound persons' views made
        again)."""
        n = len(self.owners)
        old = {name: getattr(self, name) for name in self._arrays()}
        owners, bound, recent = self.owners, self.bound, self.recent
        self._alloc(2 * n)
        for name, value in old.items():
            getattr(self, name)[:n] = value
        self.owners[:n], self.bound[:n], self.recent[:n] = owners, bound, recent
        self._rebind()

    def _grow_rows(self) -> None:
        """Twice as many rows of views per person."""
        n, r = self.recent_t.shape
        self.recent_conf = np.concatenate((self.recent_conf, np.zeros((n, r, N_JOINTS))), axis=1)
        self.recent_t = np.concatenate((self.recent_t, np.full((n, r), -np.inf)), axis=1)
        self.offsets = np.concatenate((self.offsets, np.zeros((n, r, N_JOINTS, 3))), axis=1)
        self._rows = 2 * r
        self._args = None
        self._rebind()

    def _rebind(self) -> None:
        for s, person in enumerate(self.owners):
            if person is not None and self.bound[s]:
                self._bind(s, person)

    def _bind(self, s: int, person) -> None:
        for name in _BOUND:
            setattr(person, name, getattr(self, name)[s])
        person.centre = self.centre[s]

    @staticmethod
    def _arrays() -> tuple[str, ...]:
        return ("ring", "ring_t", "ring_hz", "ring_ht", "ring_z", "ring_r", "ring_conf",
                "ring_used", "ring_mask", "ring_view", "ring_out", "head", "steps", "valid",
                "seeded", "newest", "anchor",
                "person_t",
                *(f[0] for f in _FIELDS), "centre", "recent_conf", "recent_t", "offsets")

    def take(self, person, bind: bool = False) -> int:
        """Take ``person`` (a ``tracking.Person`` the Python path has folded, with a centre)
        into a slot, as it is now: its filter's state, newest view and instant, its output
        rows and its views' recent confidences (copies). Returns the slot.

        ``bind``: the engine's own persons. The person's output attributes become views of
        the slot's rows (as ``bank.PersonBank`` binds them), its ``recent`` dict is the
        core's, and its filter reads its state from here (``fuser.BodyFilter``), until
        ``give_back``. Else (a shadow beside an engine) the person is left as it is."""
        s = self.slot_of.get(person.id)
        if s is None:
            try:
                s = self.owners.index(None)
            except ValueError:
                s = len(self.owners)
                self._grow()
            self.slot_of[person.id] = s
        self.owners[s] = person
        self.bound[s] = bind
        body = person.filter
        st = body.state
        while len(person.recent_t) > self.recent_t.shape[1]:
            self._grow_rows()
        hist = body.history
        # the history goes into the ring as steps, each with the state before it, so that
        # a view joining its newest instant is checked against all of its views and a late
        # view folded in again from where it belongs (the Python path's history begins an
        # instant; one too long for the ring: the newest instant alone)
        members: list = list(hist)
        if len(members) > self.depth - 3:
            k = len(hist)
            while k > 0 and hist[k - 1].anchor == hist[-1].anchor:
                k -= 1
            members = hist[k:] if len(hist) - k <= self.depth - 3 else []
        self.seeded[s] = len(members)
        self.ring_out[s] = -1
        states = [m.before for m in members[1:]] + [st]
        self._put(s, 0, members[0].before if members else st)
        for j, (m, after) in enumerate(zip(members, states), start=1):
            self._put(s, j, after)
            v = m.view
            self.ring_z[s, j] = v.joints
            self.ring_r[s, j] = v.r
            self.ring_conf[s, j] = v.conf
            self.ring_used[s, j] = v.used
            self.ring_mask[s, j] = m.mask
            row = person.recent.get(v.key, -1)
            self.ring_view[s, j] = (v.t, row, v.arrival, np.nan if v.size is None else v.size,
                                    m.anchor, v.excluded)
        self.head[s] = len(members)
        self.steps[s] = len(members)
        self.valid[s] = len(members)
        self.newest[s] = body.newest
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
        self.offsets[s] = 0.0         # (none learned: the Python path's None)
        if person.offsets is not None:
            n = min(len(person.offsets), self.offsets.shape[1])
            self.offsets[s, :n] = person.offsets[:n]
        if bind:
            self.recent[s] = person.recent
            self._bind(s, person)
            body.native = (self, s)
        else:
            self.recent[s] = dict(person.recent)
        return s

    def _put(self, s: int, e: int, st) -> None:
        """A ``FilterState`` into ring entry ``e`` of slot ``s``."""
        self.ring[s, e] = st.stacked()
        self.ring_t[s, e] = st.t
        self.ring_hz[s, e] = st.held_z
        self.ring_ht[s, e] = st.held_t

    def give_back(self, person) -> None:
        """A bound person back to the Python path, as if that path had folded every view the
        core did (``fuser`` then trims its history as it would have): its filter's state and
        history -- the steps since ``take``, each with its view and the state before it,
        after the history it had then -- and its output rows as arrays of its own. A person
        with more steps than the ring holds gets the steps it still holds (``valid``: up to
        ``DEPTH`` - 2 of them, fewer after a replay; counted in ``short_histories`` when
        those do not reach back ``replay_s``)."""
        s = self.slot_of[person.id]
        body = person.filter
        d, h, n = self.depth, int(self.head[s]), int(self.steps[s])
        keep = min(n, int(self.valid[s]))
        steps = []
        if keep:
            key_of = {row: key for key, row in person.recent.items()}
            for back in range(keep - 1, -1, -1):
                e = (h - back) % d
                b = (e - 1) % d
                t, row, arrival, size, anchor, left = self.ring_view[s, e].tolist()
                view = View(key_of.get(int(row), ("?", -1)), t, self.ring_z[s, e].copy(),
                            self.ring_conf[s, e].copy(), self.ring_r[s, e].copy(), arrival,
                            self.ring_used[s, e].copy(), int(left), size)
                before = FilterState.of_block(self.ring[s, b].copy(), self.ring_t[s, b].copy(),
                                              self.ring_hz[s, b].copy(),
                                              self.ring_ht[s, b].copy())
                steps.append(_Step(view, before, anchor, self.ring_mask[s, e].copy(),
                                   left == 0))
        if keep < n:
            if steps and steps[0].anchor >= self.newest[s] - self.f.replay_s:
                self.short_histories += 1
            history = steps
        else:              # (the steps seeded at ``take`` are the history's last ones)
            history = body.history[:len(body.history) - int(self.seeded[s])] + steps
        self.given_back += 1
        body.native = None
        body.history = history
        body.state = self.state_copy(s)
        self.release(person.id)

    def release(self, pid: int) -> None:
        """Forget the person ``pid`` (its slot is free for another); a bound person keeps
        copies of its rows and reads its filter from them."""
        s = self.slot_of.pop(pid, None)
        if s is None:
            return
        person = self.owners[s]
        if person is not None and self.bound[s]:
            for name in _BOUND:
                setattr(person, name, getattr(self, name)[s].copy())
            person.centre = self.centre[s].copy()
            if person.filter.native is not None:
                person.filter.native = None
                person.filter.state = self.state_copy(s)
        self.owners[s] = None
        self.bound[s] = False
        self.recent[s] = {}

    def state(self, pid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The person's filter state now: ((6, 2, 25, 3) block, t, held_z, held_t), views."""
        return self.state_of(self.slot_of[pid])

    def state_of(self, s: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        h = self.head[s]
        return self.ring[s, h], self.ring_t[s, h], self.ring_hz[s, h], self.ring_ht[s, h]

    def state_copy(self, s: int) -> FilterState:
        """Slot ``s``'s filter state now, as a ``FilterState`` of its own (the ring's entries
        are written over in turn)."""
        block, t, held_z, held_t = self.state_of(s)
        return FilterState.of_block(block.copy(), t.copy(), held_z.copy(), held_t.copy())

    # ------------------------------------------------------------ the datagram
    def _buffers(self, k: int) -> tuple:
        b = self._scratch.get(k)
        if b is None:
            b = self._scratch[k] = (
                np.empty((k, N_JOINTS), dtype=np.int8), np.empty((k, 6), dtype=np.int64),
                np.empty((k, N_JOINTS, 3)), np.empty((k, N_JOINTS, 3)),
                np.empty((k, 2), dtype=np.int64),
                np.empty(k * self.longest, dtype=np.uint8), np.empty(k + 1, dtype=np.int64),
                np.empty(k, dtype=np.int64))
        return b

    def fold(self, pids: list[int], keys: list[tuple[str, int]], t: np.ndarray, z: np.ndarray,
             r: np.ndarray, conf: np.ndarray, arrival: np.ndarray | None = None,
             size: np.ndarray | None = None) -> list[bytes] | None:
        """Fold K views (view i of person ``pids[i]``, from view ``keys[i]``, captured at
        t[i], joints z (K, 25, 3), variances r (K, 25), confidences conf (K, 25); its
        datagram's ``arrival`` and its trunk ``size`` (K,), kept for a replay; C-ordered
        float64) in; returns each person's encoded ``/jointCoordinates``, or None if the
        core declines the datagram (nothing changed: see the module docstring; ``refused``
        is then the index of the first view it could not take)."""
        k = len(pids)
        slot_of, recent = self.slot_of, self.recent
        slots, rows = [], []
        added = None
        for pid, key in zip(pids, keys):
            s = slot_of.get(pid)
            if s is None:
                return self._decline(len(slots), added)
            row = recent[s].get(key)
            if row is None:               # the person's first view from this sensor
                row = self._new_row(s, key)
                added = [(s, key)] if added is None else added + [(s, key)]
            slots.append(s)
            rows.append(row)
        if arrival is None:
            arrival = np.full(k, np.nan)
        if size is None:
            size = np.full(k, np.nan)
        outcome, counts, pos, vel, plan, buf, offsets, centred = self._buffers(k)
        args = self._args
        if args is None:
            args = self._args = self._arguments()
        slots_a = np.array(slots, dtype=np.int64)
        done = jit._compiled["_native_fold"](
            slots_a, t, z, r, conf, np.array(rows, dtype=np.int64),
            np.array(pids, dtype=np.int64), arrival, size, *args[0], outcome, counts, pos, vel,
            plan, *args[1], buf, offsets, centred)
        if done < 0:
            return self._decline(-1 - done, added)
        self.folded += 1
        self.counts = counts
        totals = self.totals = counts.sum(axis=0).tolist()
        self.replayed += totals[4]
        self.slots = slots_a
        ends = offsets.tolist()
        data = buf[:ends[k]].tobytes()
        out = [data[ends[i]:ends[i + 1]] for i in range(k)]
        centred_l = centred.tolist()
        if not all(centred_l):
            for i in range(k):
                if not centred_l[i]:
                    self._centre_otherwise(slots[i])
        return out

    def _decline(self, refused: int, added: list | None) -> None:
        """``fold`` declines (``refused``: the view it could not take); the rows it gave new
        views are given up again."""
        for s, key in added or ():
            del self.recent[s][key]
        self.declined += 1
        self.refused = refused
        return None

    def _new_row(self, s: int, key: tuple[str, int]) -> int:
        """A row of slot ``s``'s recent confidences and times for the view ``key``, which
        its person has not remembered yet: the first free one, as ``Person.remember`` takes
        it (the rows grow first when none is free). The kernel writes the view into it."""
        free = np.flatnonzero(self.recent_t[s] == -np.inf)
        if not len(free):
            row = self.recent_t.shape[1]
            self._grow_rows()
        else:
            row = int(free[0])
        self.recent[s][key] = row
        return row

    def _arguments(self) -> tuple[tuple, tuple]:
        """The kernel's arguments that are the same from datagram to datagram (made again
        after the arrays grow)."""
        s, f = self.s, self.f
        return ((self.ring, self.ring_t, self.ring_hz, self.ring_ht, self.ring_z, self.ring_r,
                 self.ring_conf, self.ring_used, self.ring_mask, self.ring_view, self.ring_out,
                 self.head, self.steps, self.valid, self.newest, self.anchor, self.person_t, self.q,
                 self.q_scale, self.rates, float(s.gate_sigma ** 2), float(s.reject_sigma ** 2),
                 float(f.group_s), float(2.0 * f.view_bias_m ** 2), float(f.replay_s),
                 float(INFERRED), self._tg, self._init, self._given),
                (float(f.stale_s), self.recent_conf, self.recent_t, self.joints, self.velocity,
                 self.conf, self.known, self.carried, self.tracked, self.hold, self.centre,
                 bool(f.carry_untracked), bool(f.hold_back_inferred), _PARENTS,
                 _CHILDREN, _TORSO, self.names, self.name_end))

    def _centre_otherwise(self, s: int) -> None:
        """A person with no torso joint known: the centre of its known joints (as
        ``fusion.torso_centre`` of the joints and ``known``), else left as it was."""
        known = self.known[s]
        if known.any():
            self.centre[s] = self.joints[s][known].mean(axis=0)
