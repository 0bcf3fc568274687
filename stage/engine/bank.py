"""The person bank: each person's settled output and the arrays it is settled from, one row
(slot) per person.

Settling a person's output skeleton (``people.People._update``) reads and writes arrays of
that person's own: its output (``joints``, ``velocity``, ``conf``, ``known``, ``carried``,
the torso ``centre``), which joints some view has tracked (``tracked``), each joint's
offset from its parent when last tracked (``hold``), and each view's latest confidences
and capture time (``recent_conf``, ``recent_t``). With each person holding its own arrays
the compiled settle had to be called once per person, and at six people a datagram the
calls cost more than the arithmetic; gathering the arrays into one call and handing new
ones back cost as much again (issue 10, stop 35). Here they are rows of one array per
kind, indexed by the person's slot, and the compiled settle (``jit.settle_many``) updates
a batch of persons' rows in place in one call.

A bound ``Person``'s attributes are views of its rows (made once, when it is bound), so
the rest of the engine reads them as before. They change in place at every update: code
that keeps a person's arrays past the batch copies them (``Body`` does, and so did every
such reader before). A person whose attribute was replaced by another array since it
was bound (a new person's first view, the numpy code) is bound again, its values copied
in, before the kernel reads the bank: nothing is lost and nothing goes stale. Slots of
persons the tracker no longer has are given to new persons; the old owner keeps copies.
The bank grows by doubling (slots, or rows of views per person). Engine thread only.
"""

from __future__ import annotations

import numpy as np

from ..joints import N_JOINTS

#: the per-person arrays: name, shape of one row, dtype, value of a free row
_FIELDS = (
    ("joints", (N_JOINTS, 3), float, 0.0),
    ("velocity", (N_JOINTS, 3), float, 0.0),
    ("conf", (N_JOINTS,), float, 0.0),
    ("known", (N_JOINTS,), bool, False),
    ("carried", (N_JOINTS,), bool, False),
    ("tracked", (N_JOINTS,), bool, False),
    ("hold", (N_JOINTS, 3), float, np.nan),
)
_NAMES = tuple(f[0] for f in _FIELDS)


class PersonBank:
    """Slot-indexed arrays (see the module docstring): each of ``_FIELDS`` (S, ...), the
    torso ``centre`` (S, 3), ``recent_conf`` (S, R, 25) and ``recent_t`` (S, R) (-inf: a
    free row), for the persons bound to it."""

    def __init__(self, slots: int = 8, rows: int = 4) -> None:
        self.owners: list = [None] * slots
        for name, shape, dtype, free in _FIELDS:
            setattr(self, name, np.full((slots, *shape), free, dtype=dtype))
        self.centre = np.zeros((slots, 3))
        self.recent_conf = np.zeros((slots, rows, N_JOINTS))
        self.recent_t = np.full((slots, rows), -np.inf)
        #: per slot, the views handed to its owner (to see whether it still holds them)
        self._views: list[tuple | None] = [None] * slots
        self._centres: list[np.ndarray | None] = [None] * slots

    @property
    def rows(self) -> int:
        return self.recent_t.shape[1]

    def slot(self, person, persons: dict) -> int:
        """``person``'s slot, binding it (or binding it again) if need be; ``persons`` is the
        tracker's: a slot whose owner is no longer there is free."""
        s = person.slot
        if s >= 0 and self.owners[s] is person:
            v = self._views[s]
            if not (person.joints is v[0] and person.velocity is v[1] and person.conf is v[2]
                    and person.known is v[3] and person.carried is v[4]
                    and person.tracked is v[5] and person.hold is v[6]
                    and person.recent_conf is v[7] and person.recent_t is v[8]):
                self._fill(s, person)      # an attribute was replaced: its values copied in
            return s
        s = self._free(persons)
        self.owners[s] = person
        person.slot, person.bank = s, self
        self._fill(s, person)
        return s

    def unbind(self, person) -> None:
        """Free ``person``'s slot without handing it copies: it has been bound elsewhere (the
        native core took it, ``native.NativeCore.take``, copying its values first). Until it
        is bound here again its attributes are not this bank's."""
        s = person.slot
        if s >= 0 and self.owners[s] is person:
            self._clear(s)
        person.slot, person.bank = -1, None

    def centre_of(self, s: int) -> np.ndarray:
        """Slot ``s``'s row of ``centre`` (the same view object each time)."""
        return self._centres[s]

    def grow_rows_for(self, person) -> bool:
        """Twice as many rows of views per person, for ``person`` (whose ``remember`` ran out
        of them), if it is bound here (False: it is not; it grows its own arrays)."""
        s = person.slot
        if s < 0 or self.owners[s] is not person:
            return False
        self.grow_rows()
        return True

    def grow_rows(self) -> None:
        """Twice as many rows of views per person."""
        grow = max(self.rows, 2)
        n = len(self.owners)
        self.recent_conf = np.concatenate((self.recent_conf, np.zeros((n, grow, N_JOINTS))),
                                          axis=1)
        self.recent_t = np.concatenate((self.recent_t, np.full((n, grow), -np.inf)), axis=1)
        self._rebind_all()

    # ------------------------------------------------------------ internals
    def _free(self, persons: dict) -> int:
        for s, owner in enumerate(self.owners):
            if owner is None:
                return s
            if persons.get(owner.id) is not owner:
                self._release(s)
                return s
        n = len(self.owners)                                # every slot taken: twice as many
        self.owners.extend([None] * n)
        self._views.extend([None] * n)
        self._centres.extend([None] * n)
        for name, _, _, free in _FIELDS:
            old = getattr(self, name)
            setattr(self, name, np.concatenate((old, np.full_like(old, free))))
        self.centre = np.concatenate((self.centre, np.zeros_like(self.centre)))
        self.recent_conf = np.concatenate((self.recent_conf, np.zeros_like(self.recent_conf)))
        self.recent_t = np.concatenate((self.recent_t, np.full_like(self.recent_t, -np.inf)))
        self._rebind_all()
        return n

    def _release(self, s: int) -> None:
        """Slot ``s``'s owner is gone: it keeps copies, the slot is cleared."""
        owner = self.owners[s]
        if owner is not None:
            for name in (*_NAMES, "recent_conf", "recent_t"):
                setattr(owner, name, getattr(owner, name).copy())
            if owner.centre is not None and owner.centre is self._centres[s]:
                owner.centre = owner.centre.copy()
            owner.slot, owner.bank = -1, None
        self._clear(s)

    def _clear(self, s: int) -> None:
        """Slot ``s`` free, its rows as a free row's."""
        self.owners[s] = None
        self._views[s] = self._centres[s] = None
        for name, _, _, free in _FIELDS:
            getattr(self, name)[s] = free
        self.centre[s] = 0.0
        self.recent_conf[s] = 0.0
        self.recent_t[s] = -np.inf

    def _fill(self, s: int, person) -> None:
        """Copy ``person``'s own arrays into slot ``s`` and hand it the views."""
        # (all copied first: some may be views of this very row, and growing the rows binds
        # every owner's views again)
        values = [np.array(getattr(person, name)) for name in _NAMES]
        conf, t = np.array(person.recent_conf), np.array(person.recent_t)
        while len(t) > self.rows:
            self.grow_rows()
        for name, value in zip(_NAMES, values):
            getattr(self, name)[s] = value
        self.recent_conf[s] = 0.0
        self.recent_t[s] = -np.inf
        self.recent_conf[s, :len(t)] = conf
        self.recent_t[s, :len(t)] = t
        self._bind(s, person)

    def _bind(self, s: int, person) -> None:
        views = tuple(getattr(self, name)[s] for name in (*_NAMES, "recent_conf", "recent_t"))
        (person.joints, person.velocity, person.conf, person.known, person.carried,
         person.tracked, person.hold, person.recent_conf, person.recent_t) = views
        self._views[s] = views
        centre = self._centres[s] = self.centre[s]
        if person.centre is not None and person.centre is not centre:
            centre[:] = person.centre
            person.centre = centre

    def _rebind_all(self) -> None:
        """After the arrays were made anew: every owner's values (from what it holds now:
        the old arrays' views, or arrays of its own) copied in, and new views handed out."""
        for s, owner in enumerate(self.owners):
            if owner is not None:
                self._fill(s, owner)
