"""The person bank (stage/engine/bank.py): persons' output and settle arrays as rows of one
array per kind, and the compiled settle of a whole batch on it (``jit.settle_many``)."""

from __future__ import annotations

import numpy as np
import pytest

from stage.engine import jit
from stage.engine.bank import PersonBank
from stage.engine.fusion import _CHILDREN, _PARENTS
from stage.engine.people import INFERRED, _TORSO
from stage.engine.tracking import Person
from stage.settings import FusionSettings

needs_jit = pytest.mark.skipif(not jit.ready(), reason=f"no compiled kernels: {jit.why_not()}")


def _person(pid: int, rng: np.random.Generator, views: int = 2) -> Person:
    """A person with random output, tracked joints, hold offsets and ``views`` recent views."""
    p = Person.new(pid, 0.0, FusionSettings())
    p.joints = rng.normal(0.0, 1.0, (25, 3))
    p.velocity = rng.normal(0.0, 1.0, (25, 3))
    p.conf = rng.uniform(0.0, 1.0, 25)
    p.known = rng.random(25) < 0.7
    p.tracked = rng.random(25) < 0.5
    p.hold = np.where(rng.random((25, 1)) < 0.5, rng.normal(0.0, 0.3, (25, 3)), np.nan)
    for v in range(views):
        conf = np.where(rng.random(25) < 0.3, 0.0, rng.uniform(0.0, 1.2, 25))
        p.remember((f"s{v}", 0), float(rng.uniform(0.0, 1.0)), conf)
    if rng.random() < 0.5:
        p.centre = rng.normal(0.0, 1.0, 3)
    return p


_ARRAYS = ("joints", "velocity", "conf", "known", "carried", "tracked", "hold", "recent_conf",
           "recent_t")


def _values(p: Person) -> dict:
    return {name: np.array(getattr(p, name)) for name in _ARRAYS}


def _same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_binding_keeps_every_value_and_hands_out_views_of_the_rows():
    rng = np.random.default_rng(1)
    bank = PersonBank(slots=2, rows=2)
    persons = {pid: _person(pid, rng, views=1 + pid % 4) for pid in range(1, 12)}
    before = {pid: _values(p) for pid, p in persons.items()}
    centres = {pid: None if p.centre is None else p.centre.copy() for pid, p in persons.items()}
    slots = [bank.slot(p, persons) for p in persons.values()]
    assert sorted(slots) == list(range(11))            # grew from 2 slots, none shared
    assert bank.rows >= 4                              # and to the most views a person has
    for pid, p in persons.items():
        got = _values(p)
        t = before[pid]["recent_t"]
        for name in ("recent_conf", "recent_t"):        # a person's rows first, free rows after
            np.testing.assert_array_equal(got[name][:len(t)], before[pid][name])
        assert (got["recent_t"][len(t):] == -np.inf).all()
        _same({k: v for k, v in got.items() if not k.startswith("recent")},
              {k: v for k, v in before[pid].items() if not k.startswith("recent")})
        s = p.slot
        assert p.joints.base is bank.joints and np.shares_memory(p.hold, bank.hold[s])
        if centres[pid] is None:
            assert p.centre is None
        else:
            np.testing.assert_array_equal(p.centre, centres[pid])
            assert p.centre is bank.centre_of(s)


def test_an_attribute_replaced_after_binding_is_copied_in_at_the_next_slot_call():
    rng = np.random.default_rng(2)
    bank = PersonBank()
    p = _person(1, rng)
    persons = {1: p}
    bank.slot(p, persons)
    kept = _values(p)
    p.joints = np.full((25, 3), 7.0)                   # as a new person's first view does
    p.known = np.ones(25, dtype=bool)
    p.hold = p.hold.astype(np.float32)                 # even of another dtype
    hold = np.array(p.hold, dtype=float)
    assert bank.slot(p, persons) == p.slot
    assert (bank.joints[p.slot] == 7.0).all() and bank.known[p.slot].all()
    np.testing.assert_array_equal(bank.hold[p.slot], hold)
    assert p.joints.base is bank.joints and p.hold.dtype == np.float64
    got = _values(p)                                   # the rest as it was
    for name in ("velocity", "conf", "carried", "tracked", "recent_conf", "recent_t"):
        np.testing.assert_array_equal(got[name], kept[name], err_msg=name)


def test_remember_beyond_the_rows_grows_every_persons_rows_and_keeps_them():
    rng = np.random.default_rng(3)
    bank = PersonBank(slots=4, rows=2)
    persons = {pid: _person(pid, rng, views=2) for pid in (1, 2, 3)}
    for p in persons.values():
        bank.slot(p, persons)
    other = _values(persons[2])
    p = persons[1]
    p.joints = np.zeros((25, 3))                       # replaced and not yet copied in: kept
    for v in range(2, 7):
        p.remember((f"s{v}", 0), 1.0 + v, np.full(25, 0.1 * v))
    assert bank.rows >= 7 and p.recent_t.base is bank.recent_t
    assert sorted(p.recent.values()) == list(range(7))
    np.testing.assert_array_equal(p.recent_t[:7][[p.recent[(f"s{v}", 0)] for v in range(2, 7)]],
                                  [3.0, 4.0, 5.0, 6.0, 7.0])
    assert (p.joints == 0.0).all() and (bank.joints[p.slot] == 0.0).all()
    got = _values(persons[2])
    np.testing.assert_array_equal(got["recent_t"][:2], other["recent_t"])
    np.testing.assert_array_equal(got["hold"], other["hold"])


def test_a_slot_of_a_person_the_tracker_forgot_is_reused_and_its_owner_keeps_copies():
    rng = np.random.default_rng(4)
    bank = PersonBank(slots=2)
    a, b = _person(1, rng), _person(2, rng)
    persons = {1: a, 2: b}
    bank.slot(a, persons)
    bank.slot(b, persons)
    kept = _values(a)
    del persons[1]                                     # lost
    c = _person(3, rng)
    persons[3] = c
    assert bank.slot(c, persons) == 0 and len(bank.owners) == 2
    assert a.slot == -1 and a.bank is None and not np.shares_memory(a.joints, bank.joints)
    _same(_values(a), kept)
    bank.joints[0] = 99.0                              # the new owner's rows change: not a's
    _same(_values(a), kept)


@needs_jit
def test_settle_many_is_settle_person_by_person():
    """The batch kernel on the bank gives, person by person, the floats the single-person
    kernel gives, and changes the same arrays (tracked, hold) the same way."""
    rng = np.random.default_rng(5)
    for trial in range(40):
        n = int(rng.integers(1, 9))
        persons = {pid: _person(pid, rng, views=int(rng.integers(0, 5))) for pid in range(n)}
        bank = PersonBank(slots=int(rng.integers(1, 4)), rows=2)
        order = list(persons.values())
        rng.shuffle(order)
        pos = rng.normal(0.0, 1.0, (n, 25, 3))
        pos[rng.random((n, 25)) < 0.05] = np.nan
        vel = rng.normal(0.0, 1.0, (n, 25, 3))
        row_t = rng.uniform(0.0, 1.2, (n, 25))
        t = rng.uniform(0.5, 1.5, n)
        stale = 0.25
        carry, hold_back = bool(trial % 2), bool(trial % 3)
        want = []
        for k, p in enumerate(order):
            tracked, hold = p.tracked.copy(), p.hold.copy()
            out = jit.settle(pos[k], vel[k], row_t[k], t[k], stale, p.recent_conf.copy(),
                             p.recent_t.copy(), p.joints.copy(), p.known.copy(), tracked, hold,
                             carry, hold_back, INFERRED, _PARENTS, _CHILDREN, _TORSO)
            want.append((out, tracked, hold))
        slots = np.array([bank.slot(p, persons) for p in order], dtype=np.int64)
        counts = jit.settle_many(slots, pos, vel, row_t, t, stale, bank, carry, hold_back,
                                 INFERRED, _PARENTS, _CHILDREN, _TORSO)
        for k, p in enumerate(order):
            (joints, velocity, conf, known, carried, centre), tracked, hold = want[k]
            np.testing.assert_array_equal(p.joints, joints)
            np.testing.assert_array_equal(p.velocity, velocity)
            np.testing.assert_array_equal(p.conf, conf)
            np.testing.assert_array_equal(p.known, known)
            if carry:
                np.testing.assert_array_equal(p.carried, carried)
            np.testing.assert_array_equal(p.tracked, tracked)
            np.testing.assert_array_equal(p.hold, hold)
            assert bool(counts[k]) == (centre is not None)
            if centre is not None:
                np.testing.assert_array_equal(bank.centre_of(p.slot), centre)


def test_persons_coming_and_going_for_weeks_do_not_grow_the_bank():
    """An installation sees thousands of persons over weeks, a few at a time: the bank keeps
    as many slots as were ever on stage at once (rounded up to its doubling), not one per
    person ever seen."""
    rng = np.random.default_rng(6)
    bank = PersonBank()
    persons: dict = {}
    most = 0
    for pid in range(1, 3001):
        if len(persons) >= int(rng.integers(1, 12)):           # someone leaves
            del persons[int(rng.choice(list(persons)))]
        p = Person.new(pid, 0.0, FusionSettings())
        persons[pid] = p
        most = max(most, len(persons))
        for q in persons.values():
            bank.slot(q, persons)
        assert len({q.slot for q in persons.values()}) == len(persons)   # none shared
    assert most <= 12 and len(bank.owners) <= 16
