"""``hands.HandVoter`` in one float array per person, for compiling (numba).

Voting both hands of a person costs about 10 us in Python with six sensors reporting, and
it runs every time the person is sent (a sixth of the engine thread's time at six sensors
and six people, docs/reports/issue-10.md, stop 29). The functions here are the same rules,
step for step and in the same floating-point order, on one flat ``float64`` array per
person (``new``), so that a report or a vote is one compiled call. ``HandVoter`` stays the
reference and the fallback: tests/test_hands_compiled.py feeds both the same reports and
compares every reported state, and the floats they keep.

This module is plain Python and imports no compiler: the engine compiles the kernels
with its others (``stage.engine.jit``) and installs them with ``use_kernels``; until then
(or without numba) ``ArrayHandVoter`` runs them uncompiled, slowly, with the same results.

The array: ``[last vote time (NaN: none), reports kept for each hand (2), each hand's
sensor slots in the order their first report came (2 x S)]``, then per hand ``H`` fields
(the evidence's lead, margin and run start per state code, the reported state (-1: none),
the candidate (-1: none) and its time), then per hand and sensor slot ``F`` fields (the
decayed shares per state code and the rest of ``HandVoter.reports``' entry, the pending
report, whether it is fresh, and the time of the last one counted). A slot is a sensor
(``ArrayHandVoter`` maps sensor keys to slots); the order in which sensors came matters,
as the vote adds their parts up in it.
"""

from __future__ import annotations

import math

import numpy as np

from ..joints import HandState

#: per hand: lead (5), margin (5), since (5), reported, candidate, candidate's time
H = 18
LEAD, MARGIN, SINCE, REPORTED, CAND, CAND_T = 0, 5, 10, 15, 16, 17
#: per hand and slot
F = 20
(HAS, NEWEST, SHARES, WEIGHT, STATE, SO, SC, SL, NT, PENDING, P_T, P_STATE, P_W, FRESH,
 COUNTED) = 0, 1, 2, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18
_FORGOTTEN = math.exp(-4.0)
EVIDENCE_LEAD = 4.0
EVIDENCE_MARGIN = 2.5
_OPEN = 2


def size(slots):  # pragma: no cover (compiled; tested uncompiled too)
    return 3 + 2 * slots + 2 * H + 2 * slots * F


def slots_of(buf):  # pragma: no cover
    return (buf.shape[0] - 3 - 2 * H) // (2 + 2 * F)


def _hand(S, hand):  # pragma: no cover
    return 3 + 2 * S + hand * H


def _slot(S, hand, k):  # pragma: no cover
    return 3 + 2 * S + 2 * H + (hand * S + k) * F


def new(slots: int) -> np.ndarray:
    """An empty voter with room for ``slots`` sensors."""
    buf = np.zeros(size(slots))
    buf[0] = np.nan
    for hand in (0, 1):
        hb = _hand(slots, hand)
        buf[hb + SINCE:hb + SINCE + 5] = -1.0
        buf[hb + REPORTED] = -1.0
        buf[hb + CAND] = -1.0
        for k in range(slots):
            buf[_slot(slots, hand, k) + COUNTED] = -np.inf
    return buf


def grow(buf: np.ndarray, slots: int) -> np.ndarray:
    """``buf`` with room for ``slots`` sensors (the slots it has keep their numbers)."""
    S = slots_of(buf)
    out = new(slots)
    out[:3] = buf[:3]
    for hand in (0, 1):
        out[3 + hand * slots:3 + hand * slots + S] = buf[3 + hand * S:3 + (hand + 1) * S]
        out[_hand(slots, hand):_hand(slots, hand) + H] = buf[_hand(S, hand):_hand(S, hand) + H]
        out[_slot(slots, hand, 0):_slot(slots, hand, S)] = buf[_slot(S, hand, 0):_slot(S, hand, S)]
    return out


def add(buf, k, hand, state, weight, t, memory, step):  # pragma: no cover
    """``HandVoter.add`` of sensor slot ``k`` (``step``: the part of a reading the report is)."""
    S = slots_of(buf)
    b = _slot(S, hand, k)
    if buf[b + PENDING] == 0.0 or t >= buf[b + P_T]:
        buf[b + PENDING] = 1.0
        buf[b + P_T] = t
        buf[b + P_STATE] = state
        buf[b + P_W] = weight * step
        buf[b + FRESH] = 1.0
    s = b + SHARES
    if buf[b + HAS] == 0.0:
        for j in range(5):
            buf[s + j] = 0.0
        buf[s + state] = 1.0
        buf[b + HAS] = 1.0
        buf[b + NEWEST] = t
        buf[b + WEIGHT] = weight
        buf[b + STATE] = state
        n = int(buf[1 + hand])
        buf[3 + hand * S + n] = k
        buf[1 + hand] = n + 1
    else:
        newest = buf[b + NEWEST]
        if t == newest:
            buf[s + int(buf[b + STATE])] -= 1.0
            buf[s + state] += 1.0
            buf[b + WEIGHT] = weight
            buf[b + STATE] = state
        elif t > newest:
            decay = math.exp(-(t - newest) / memory)
            for j in range(5):
                buf[s + j] *= decay
            buf[s + state] += 1.0
            buf[b + NEWEST] = t
            buf[b + WEIGHT] = weight
            buf[b + STATE] = state
        else:  # an older report, out of order: counts as old as it is
            buf[s + state] += math.exp(-(newest - t) / memory)
    total = buf[s] + buf[s + 1] + buf[s + 2] + buf[s + 3] + buf[s + 4]
    floor = _FORGOTTEN * total
    scale = buf[b + WEIGHT] / total
    so, sc, sl = buf[s + 2], buf[s + 3], buf[s + 4]
    buf[b + SO] = scale * so if so > floor else 0.0
    buf[b + SC] = scale * sc if sc > floor else 0.0
    buf[b + SL] = scale * sl if sl > floor else 0.0
    buf[b + NT] = 1.0 if buf[s + 1] > floor else 0.0


def add_frame(buf, k, t, left, left_w, right, right_w, memory, step):  # pragma: no cover
    """Both hands' reports of one frame of sensor slot ``k``."""
    add(buf, k, 0, left, left_w, t, memory, step)
    add(buf, k, 1, right, right_w, t, memory, step)


def forget(buf, k):  # pragma: no cover
    """``HandVoter.forget`` of sensor slot ``k``."""
    S = slots_of(buf)
    for hand in range(2):
        b = _slot(S, hand, k)
        if buf[b + HAS] != 0.0:
            n = int(buf[1 + hand])
            o = 3 + hand * S
            j = 0
            while j < n and int(buf[o + j]) != k:
                j += 1
            while j < n - 1:
                buf[o + j] = buf[o + j + 1]
                j += 1
            buf[1 + hand] = n - 1
        for f in range(F):
            buf[b + f] = 0.0
        buf[b + COUNTED] = -np.inf


def vote(buf, hand, t, memory):  # pragma: no cover
    """``HandVoter._vote``'s winner and the pace of its hold, as (code, pace)."""
    S = slots_of(buf)
    window = 4.0 * memory
    o = 0.0
    c = 0.0
    lasso = 0.0
    not_tracked = False
    voters = 0
    n = int(buf[1 + hand])
    for j in range(n):
        b = _slot(S, hand, int(buf[3 + hand * S + j]))
        if t - buf[b + NEWEST] > window:
            continue
        o += buf[b + SO]
        c += buf[b + SC]
        lasso += buf[b + SL]
        not_tracked = not_tracked or buf[b + NT] != 0.0
        if buf[b + SO] > 0.0 or buf[b + SC] > 0.0 or buf[b + SL] > 0.0:
            voters += 1
    total = o + c + lasso
    if lasso > 0.0 and lasso >= c and lasso >= o:
        return 4, pace_of(lasso / total, voters)
    if c > 0.0 and c >= o:
        return 3, pace_of(c / total, voters)
    if o > 0.0:
        return 2, pace_of(o / total, voters)
    return (1 if not_tracked else 0), 1.0


def pace_of(share, voters):  # pragma: no cover
    """``hands._pace``."""
    if voters < 2:
        return 1.0
    pace = 4.0 * share - 2.0
    return 2.0 if pace > 2.0 else pace if pace > 0.0 else 0.0


def _before(buf, a, b):  # pragma: no cover
    """Whether slot block ``a``'s pending report comes before ``b``'s in (time, state,
    weight) order (equal ones count alike in any order)."""
    ta, tb = buf[a + P_T], buf[b + P_T]
    if ta != tb:
        return ta < tb
    sa, sb = buf[a + P_STATE], buf[b + P_STATE]
    if sa != sb:
        return sa < sb
    return buf[a + P_W] < buf[b + P_W]


def _next_fresh(buf, S, hand):  # pragma: no cover
    """The slot block of the first uncounted fresh report in (time, state, weight) order,
    or -1; fresh reports already counted stop being fresh."""
    first = -1
    for k in range(S):
        b = _slot(S, hand, k)
        if buf[b + FRESH] == 0.0:
            continue
        if not buf[b + P_T] > buf[b + COUNTED]:
            buf[b + FRESH] = 0.0
        elif first < 0 or _before(buf, b, first):
            first = b
    return first


def _evidence(buf, hand, t, hold):  # pragma: no cover
    """``HandVoter._evidence``: the state the uncounted reports make a clear case for, or
    -1. The reports are taken in order by selection (a few sensors: no sort, nothing
    allocated)."""
    S = slots_of(buf)
    hb = _hand(S, hand)
    current = int(buf[hb + REPORTED])
    if current < _OPEN:
        b = _next_fresh(buf, S, hand)
        while b >= 0:
            buf[b + FRESH] = 0.0
            buf[b + COUNTED] = buf[b + P_T]
            b = _next_fresh(buf, S, hand)
        return -1
    c1 = 3 if current == 2 else 2
    c2 = 3 if current == 4 else 4
    b = _next_fresh(buf, S, hand)
    while b >= 0:
        buf[b + FRESH] = 0.0
        rt = buf[b + P_T]
        state = int(buf[b + P_STATE])
        w = buf[b + P_W]
        buf[b + COUNTED] = rt
        b = _next_fresh(buf, S, hand)
        if state < _OPEN:
            continue
        for c in (c1, c2):
            step = w if state == c else -w if state == current else 0.0
            lead = buf[hb + LEAD + c]
            if step > 0.0 and buf[hb + SINCE + c] < 0.0:
                buf[hb + SINCE + c] = rt
            elif lead + step < -1e-9:
                buf[hb + SINCE + c] = -1.0
            v = lead + step
            buf[hb + LEAD + c] = v if v > 0.0 else 0.0
            v = buf[hb + MARGIN + c] + (w if state == c else -w)
            buf[hb + MARGIN + c] = v if v > 0.0 else 0.0
    best = c2 if buf[hb + LEAD + c2] > buf[hb + LEAD + c1] else c1
    since = buf[hb + SINCE + best]
    if buf[hb + LEAD + best] >= EVIDENCE_LEAD and buf[hb + MARGIN + best] >= EVIDENCE_MARGIN \
            and since >= 0.0 and t - since >= hold - 1e-9:
        return best
    return -1


def _report(buf, hb, state):  # pragma: no cover
    buf[hb + REPORTED] = state
    buf[hb + CAND] = -1.0
    for j in range(5):
        buf[hb + LEAD + j] = 0.0
        buf[hb + MARGIN + j] = 0.0
        buf[hb + SINCE + j] = -1.0


def update(buf, t, memory, hold, evidence):  # pragma: no cover
    """``HandVoter.update``: bit 0 set if the left hand's reported state changes now, bit 1
    the right's. ``evidence``: 0 for the hold alone (``HandVoter.evidence`` False), else 1."""
    S = slots_of(buf)
    last = buf[0]
    dt = 0.0 if math.isnan(last) else max(t - last, 0.0)
    buf[0] = t if math.isnan(last) else max(t, last)
    changed = 0
    for hand in range(2):
        hb = _hand(S, hand)
        case = _evidence(buf, hand, t, hold)
        winner, pace = vote(buf, hand, t, memory)
        current = int(buf[hb + REPORTED])
        if winner != current and (current < 0 or current < _OPEN and winner >= _OPEN):
            _report(buf, hb, winner)
            changed |= 1 << hand
            continue
        cand = int(buf[hb + CAND])
        cand_t = buf[hb + CAND_T]
        if cand >= 0 and cand == winner:
            # its time counts at the pace of its support (hands._pace)
            cand_t = cand_t + dt * pace
        elif cand >= 0 and cand_t - dt > 0.0:
            cand_t = cand_t - dt                   # a moment lost counts against it
        elif winner == current:
            cand = -1
        else:
            cand = winner
            cand_t = 0.0
        buf[hb + CAND] = cand
        buf[hb + CAND_T] = cand_t
        if cand >= 0 and cand_t >= hold - 1e-9:
            _report(buf, hb, cand)
            changed |= 1 << hand
        elif case >= 0 and evidence > 0.0:
            _report(buf, hb, case)
            changed |= 1 << hand
    return changed


def newest(buf):  # pragma: no cover
    """The newest report's time (-inf: none)."""
    S = slots_of(buf)
    out = -np.inf
    for hand in range(2):
        for k in range(S):
            b = _slot(S, hand, k)
            if buf[b + HAS] != 0.0 and buf[b + NEWEST] > out:
                out = buf[b + NEWEST]
    return out


#: the kernels ``ArrayHandVoter`` calls: these functions, or their compiled versions once
#: the engine has compiled them (``use_kernels``)
_PLAIN = {"add": add, "add_frame": add_frame, "forget": forget, "update": update,
          "vote": vote, "newest": newest}
_K = dict(_PLAIN)
HELPERS = ("size", "slots_of", "_hand", "_slot", "add", "vote", "pace_of", "_before",
           "_next_fresh", "_evidence", "_report")


def compiled() -> bool:
    """Whether the compiled kernels are installed (``ArrayHandVoter`` is then the cheaper
    voter; uncompiled, ``hands.HandVoter`` is)."""
    return _K["update"] is not update


def use_kernels(kernels: dict | None) -> None:
    """Call the compiled kernels (None: the plain functions again)."""
    _K.clear()
    _K.update(_PLAIN if kernels is None else kernels)


class ArrayHandVoter:
    """``hands.HandVoter``'s interface on the array (engine thread only)."""

    __slots__ = ("memory_s", "hold_s", "evidence", "buf", "slots")

    def __init__(self, memory_s: float, hold_s: float, evidence: bool = True,
                 slots: int = 4) -> None:
        self.memory_s, self.hold_s, self.evidence = memory_s, hold_s, evidence
        self.buf = new(slots)
        self.slots: dict[tuple[str, int], int] = {}

    def slot(self, key: tuple[str, int]) -> int:
        k = self.slots.get(key)
        if k is None:
            used = set(self.slots.values())
            k = next(j for j in range(len(used) + 1) if j not in used)
            if k >= slots_of(self.buf):
                self.buf = grow(self.buf, 2 * slots_of(self.buf))
            self.slots[key] = k
        return k

    def add(self, key: tuple[str, int], hand: int, state: HandState, weight: float,
            t: float, step: float = 1.0) -> None:
        k = self.slot(key)                  # (first: it may grow the array)
        _K["add"](self.buf, k, hand, int(state), weight, t, self.memory_s, step)

    def add_frame(self, key: tuple[str, int], left: HandState, left_weight: float,
                  right: HandState, right_weight: float, t: float, step: float = 1.0) -> None:
        """Both hands of one frame (``add`` twice, in one call)."""
        k = self.slot(key)
        _K["add_frame"](self.buf, k, t, int(left), left_weight, int(right), right_weight,
                        self.memory_s, step)

    def forget(self, key: tuple[str, int]) -> None:
        k = self.slots.pop(key, None)
        if k is not None:
            _K["forget"](self.buf, k)

    def vote(self, hand: int, t: float) -> HandState:
        return HandState(_K["vote"](self.buf, hand, t, self.memory_s)[0])

    def update(self, t: float) -> list[int]:
        mask = _K["update"](self.buf, t, self.memory_s, self.hold_s,
                            1.0 if self.evidence else 0.0)
        return [] if not mask else [0] if mask == 1 else [1] if mask == 2 else [0, 1]

    @property
    def reported(self) -> list[HandState | None]:
        S = slots_of(self.buf)
        out = []
        for hand in (0, 1):
            code = int(self.buf[_hand(S, hand) + REPORTED])
            out.append(None if code < 0 else HandState(code))
        return out

    @property
    def newest(self) -> float:
        return float(_K["newest"](self.buf))
