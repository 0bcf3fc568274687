"""Hand states voted across sensors and time, so that one sensor's misreads do not flicker.

Each sensor that sees a person reports each hand's state with every frame
(the state it last sent counts as repeated with each skeleton, so a client
that sends ``/handState`` only when it changes votes as often as one that
sends it every frame). Reports older than four ``hand_memory_s`` are
forgotten.

The vote for a hand at time t:

1. each sensor with recent reports has one vote, worth the hand joint's
   confidence (1 with ``hand_vote: plain``), shared among the states it
   reported recently in proportion to ``exp(-age / hand_memory_s)``: one
   misread frame among a sensor's last few counts for part of its vote only;
2. only known states (open, closed, lasso) count while any sensor gives one
   a share: ``unknown`` and ``notTracked`` never outvote a known state;
3. the known state with the largest total wins; between known states with
   exactly equal support the higher code wins (the K-Multiscope paper's tie
   rule, section 4.1.3);
4. with no known state: ``notTracked`` if any sensor said so, else ``unknown``.

A change of the vote is reported only after the new state has won every vote
for ``hand_hold_s`` (100 ms by default); a hand whose reported state is not
a known state (a new person, a hand that was not seen) takes its first known
state at once -- there is nothing to flicker from.
"""

from __future__ import annotations

import math
from collections import deque

from ..joints import HandState

_KNOWN = (HandState.OPEN, HandState.CLOSED, HandState.LASSO)


class HandVoter:
    """The two hands of one person (engine thread only)."""

    __slots__ = ("memory_s", "hold_s", "reports", "reported", "_candidate")

    def __init__(self, memory_s: float, hold_s: float) -> None:
        self.memory_s, self.hold_s = memory_s, hold_s
        #: (sensor key, hand) -> deque of [t, state, weight]
        self.reports: dict[tuple[tuple[str, int], int], deque] = {}
        #: what was last reported per hand (None: nothing yet)
        self.reported: list[HandState | None] = [None, None]
        self._candidate: list[tuple[HandState, float] | None] = [None, None]

    def add(self, key: tuple[str, int], hand: int, state: HandState, weight: float,
            t: float) -> None:
        """One report; a second report by the same sensor at the same ``t`` replaces the first."""
        q = self.reports.get((key, hand))
        if q is None:
            q = self.reports[(key, hand)] = deque()
        if q and q[-1][0] == t:
            q[-1] = [t, state, weight]
        elif not q or t > q[-1][0]:
            q.append([t, state, weight])
        else:  # out of order: keep the deque sorted
            at = len(q)
            while at > 0 and q[at - 1][0] > t:
                at -= 1
            q.insert(at, [t, state, weight])

    def forget(self, key: tuple[str, int]) -> None:
        """A sensor view left this person: its reports no longer vote."""
        for hand in (0, 1):
            self.reports.pop((key, hand), None)

    def vote(self, hand: int, t: float) -> HandState:
        """The winning state of ``hand`` at ``t`` (rules in the module docstring)."""
        window = 4.0 * self.memory_s
        tally = [0.0] * 5
        not_tracked = False
        for (_, h), q in list(self.reports.items()):
            if h != hand:
                continue
            while q and t - q[0][0] > window:
                q.popleft()
            if not q:
                continue
            shares = [0.0] * 5
            total = 0.0
            newest = q[-1][0]
            for rt, state, _ in q:
                # ages relative to this sensor's newest report: a sensor whose frame is a
                # little older than another's is not worth less for it
                w = math.exp(-(newest - rt) / self.memory_s)
                shares[state] += w
                total += w
            weight = q[-1][2]
            for state in _KNOWN:
                tally[state] += weight * shares[state] / total
            not_tracked = not_tracked or shares[HandState.NOT_TRACKED] > 0.0
        best = max(_KNOWN, key=lambda s: (tally[s], s))
        if tally[best] > 0.0:
            return best
        return HandState.NOT_TRACKED if not_tracked else HandState.UNKNOWN

    def update(self, t: float) -> list[int]:
        """Vote both hands at ``t``; returns the hands whose reported state changes now."""
        changed = []
        for hand in (0, 1):
            winner = self.vote(hand, t)
            current = self.reported[hand]
            if winner == current:
                self._candidate[hand] = None
                continue
            if current is None or current < HandState.OPEN and winner >= HandState.OPEN:
                self.reported[hand] = winner
                self._candidate[hand] = None
                changed.append(hand)
                continue
            cand = self._candidate[hand]
            if cand is None or cand[0] != winner:
                self._candidate[hand] = cand = (winner, t)
            if t - cand[1] >= self.hold_s - 1e-9:
                self.reported[hand] = winner
                self._candidate[hand] = None
                changed.append(hand)
        return changed
