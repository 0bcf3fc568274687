"""Hand states voted across sensors and time, so that one sensor's misreads do not flicker.

Each sensor that sees a person reports each hand's state with every frame
(the state it last sent counts as repeated with each skeleton, so a client
that sends ``/handState`` only when it changes votes as often as one that
sends it every frame). A report's weight decays by e every
``hand_memory_s``; once it has decayed below e^-4 (four memories) it no longer
counts.

The vote for a hand at time t:

1. each sensor with recent reports has one vote, worth the hand joint's
   confidence in its newest frame (1 with ``hand_vote: plain``), shared among
   the states it reported recently in proportion to their decayed weights
   (ages counted from the sensor's own newest report, so a sensor whose frame
   is a little older than another's is not worth less): one misread frame
   among a sensor's last few counts for part of its vote only;
2. only known states (open, closed, lasso) count while any sensor gives one
   a share: ``unknown`` and ``notTracked`` never outvote a known state;
3. the known state with the largest total wins; between known states with
   exactly equal support the higher code wins (the K-Multiscope paper's tie
   rule, section 4.1.3);
4. with no known state: ``notTracked`` if any sensor said so, else ``unknown``.

A change of the vote is reported only after the new state has won the vote
for ``hand_hold_s`` (100 ms by default) -- in all, counted at the pace of its
support (``_pace``: with two or more sensors voting for known states, twice as
fast when all agree, as fast with three quarters of the votes, not at all with
half; a lone sensor as fast): a moment in which it loses counts against it
rather than starting the count again, so one misread sensor frame during the
hold delays the change by that moment only. (Until stop 50 the pace was twice
as fast when all agree and as fast with half or less, so a lone sensor always
went at double pace and two sensors of three misreading alike at 1.33: with
sensors that repeat each reading over two frames, as a Kinect v2 does, that
sent 7.5-10 false changes a minute in bench/bench_hands.py.) A wrong state
needs most sensors to misread it alike, together, for that long. A hand whose
reported state is not a known state (a new person, a hand that was not seen)
takes its first known state at once -- there is nothing to flicker from.

Besides the hold, a change is reported on the evidence of the reports themselves,
once they make a clear case for a known state (a sequential test, like a CUSUM): per
hand and state, counting every sensor report once, in capture order, weighted by its
vote weight,

- ``lead``: +1 when it says the state, -1 when it says the reported state, never
  below 0, must reach ``EVIDENCE_LEAD`` (4) readings;
- ``margin``: +1 when it says the state, -1 when it says any other known state, never
  below 0, must reach ``EVIDENCE_MARGIN`` (2.5) readings;
- a report is 1 / N of a reading, N being the frames its sensor repeats a reading over
  (``reading_frames``: by the sensor's type, a Kinect v2 2, the webcam client 1; the rig
  may say otherwise): a Kinect v2 reads hand states every second frame and repeats them
  (the NTU RGB+D samples, docs/sources.md), and a misread counted twice made a case twice
  as fast (until stop 50 the thresholds were 5 and 3 reports, whatever the sensor; until
  stop 51 N was one rig setting for all sensors, so a rig mixing Kinects and webcams was
  wrong for one of them);
- and the lead's run must have begun ``hand_hold_s`` or more ago: at the first report for
  the state after the lead last had to be held at 0 (a report against it when it was
  already 0). A lead that falls back to exactly 0 and rises again keeps its beginning:
  the lead is a CUSUM, the running sum of the reports' evidence minus its lowest value,
  and where the sum comes back to its lowest value without going under it, the earlier and
  the later moment are equally likely starts of the change (the sum is the same from
  both); the earlier is taken. Taking the later one (issue 10's first version of this
  rule) restarted the 100 ms on every old-state misread just after a change: two of
  bench/bench_hands.py's slowest changes on seeds 1-3 (162 and 165 ms; now 130 and 145 ms)
  were that. The cost: a run begun by misreads just before a change, or a burst of them,
  counts its time from there (one more false change in 18 minutes of that bench).

A misread moment during a change then costs one report of evidence instead of
interrupting the hold: with two sensors that misread a fifth of the time, the vote can
hover at a tie for 100 ms after a change, and the hold alone could not complete
(bench/bench_hands.py). The margin keeps a run of misreads into a third state, while
the reported state is no longer said, from counting as a case.
"""

from __future__ import annotations

import math

from ..joints import HandState
from ..sensors.kinds import DEFAULT_HAND_READING_FRAMES, HAND_READING_FRAMES


#: a state's decayed weight below this (one report four memories old) no longer counts
_FORGOTTEN = math.exp(-4.0)
#: the evidence that reports a change without the hold (module docstring), in readings (a
#: report is 1 / ``reading_frames`` of one): weighted readings for the new state over those
#: for the reported one, and over those for any other state
EVIDENCE_LEAD = 4.0
EVIDENCE_MARGIN = 2.5
_KNOWN = (int(HandState.OPEN), int(HandState.CLOSED), int(HandState.LASSO))
#: per reported known state: the other two, in code order
_OTHERS = {c: tuple(k for k in _KNOWN if k != c) for c in _KNOWN}
_NEVER = float("-inf")


def reading_frames(sensor_type: str, sensor_setting: int | None = None,
                   rig_setting: int | None = None) -> int:
    """The frames one hand-state reading of a sensor lasts: the rig's setting for that
    sensor (``sensors: <id>: hand_reading_frames``), else the rig's for all sensors
    (``fusion.hand_reading_frames``), else its type's (``sensors.kinds``)."""
    if sensor_setting is not None:
        return sensor_setting
    if rig_setting is not None:
        return rig_setting
    return HAND_READING_FRAMES.get(sensor_type, DEFAULT_HAND_READING_FRAMES)


def _pace(share: float, voters: int) -> float:
    """How fast a winning known state's hold counts, from its share of the known states'
    votes and the number of sensors voting for any known state (module docstring): twice
    as fast when all of two or more sensors agree, as fast with three quarters of the
    votes, not at all with half; a lone sensor, which has no one to agree with, as fast."""
    if voters < 2:
        return 1.0
    pace = 4.0 * share - 2.0
    return 2.0 if pace > 2.0 else pace if pace > 0.0 else 0.0


class HandVoter:
    """The two hands of one person (engine thread only).

    Per sensor and hand it keeps the decayed weight of each state it reported
    (``shares``), updated in O(1) per report, so a vote costs a few operations per
    sensor however often they report.
    """

    __slots__ = ("memory_s", "hold_s", "evidence", "reports", "reported",
                 "_candidate", "_last_t", "_pending", "_fresh", "_counted", "_lead", "_margin",
                 "_since")

    def __init__(self, memory_s: float, hold_s: float, evidence: bool = True) -> None:
        self.memory_s, self.hold_s = memory_s, hold_s
        #: False: the hold alone reports changes (issue 10's rule; a benchmark's reference)
        self.evidence = evidence
        #: per hand: sensor key -> [newest report time, shares per state code (5), weight,
        #: state of the newest report, its part of the vote for open, closed and lasso,
        #: whether it has a notTracked share]
        self.reports: tuple[dict, dict] = ({}, {})
        #: what was last reported per hand (None: nothing yet)
        self.reported: list[HandState | None] = [None, None]
        #: per hand: (a state that is winning but not reported yet, for how long, s)
        self._candidate: list[tuple[HandState, float] | None] = [None, None]
        self._last_t: float | None = None
        #: the evidence (module docstring), per hand: each sensor's newest report not yet
        #: counted (key -> (t, state, its weight as evidence)), the time of each sensor's
        #: last counted one, and per state code the lead, the margin and when the lead's run
        #: began (-1: none)
        self._pending: tuple[dict, dict] = ({}, {})
        #: per hand: the sensors whose pending report changed since the last count (only
        #: they can have a report not counted yet)
        self._fresh: tuple[set, set] = (set(), set())
        self._counted: tuple[dict, dict] = ({}, {})
        self._lead = ([0.0] * 5, [0.0] * 5)
        self._margin = ([0.0] * 5, [0.0] * 5)
        self._since = ([-1.0] * 5, [-1.0] * 5)    # -1: no run

    def add(self, key: tuple[str, int], hand: int, state: HandState, weight: float,
            t: float, step: float = 1.0) -> None:
        """One report; a second report by the same sensor at the same ``t`` replaces the first.
        ``step``: the part of a reading it is (1 / the sensor's ``reading_frames``), which
        scales its weight as evidence (module docstring), not its vote."""
        pending = self._pending[hand].get(key)
        if pending is None or t >= pending[0]:
            self._pending[hand][key] = (t, int(state), weight * step)
            self._fresh[hand].add(key)
        entry = self.reports[hand].get(key)
        if entry is None:
            shares = [0.0] * 5
            shares[state] = 1.0
            entry = self.reports[hand][key] = [t, shares, weight, state, 0.0, 0.0, 0.0, False]
        else:
            newest, shares = entry[0], entry[1]
            if t == newest:
                shares[entry[3]] -= 1.0
                shares[state] += 1.0
                entry[2], entry[3] = weight, state
            elif t > newest:
                decay = math.exp(-(t - newest) / self.memory_s)
                for k in range(5):
                    shares[k] *= decay
                shares[state] += 1.0
                entry[0], entry[2], entry[3] = t, weight, state
            else:  # an older report, out of order: counts as old as it is
                shares[state] += math.exp(-(newest - t) / self.memory_s)
        # the sensor's part of the vote (rule 1): it changes only here, so each vote adds
        # these up instead of working them out for every sensor (the same floats: a share
        # at or under the floor adds 0.0, where the vote used to add nothing)
        total = shares[0] + shares[1] + shares[2] + shares[3] + shares[4]
        floor = _FORGOTTEN * total
        scale = entry[2] / total
        so, sc, sl = shares[2], shares[3], shares[4]
        entry[4] = scale * so if so > floor else 0.0
        entry[5] = scale * sc if sc > floor else 0.0
        entry[6] = scale * sl if sl > floor else 0.0
        entry[7] = shares[1] > floor

    def add_frame(self, key: tuple[str, int], left: HandState, left_weight: float,
                  right: HandState, right_weight: float, t: float, step: float = 1.0) -> None:
        """Both hands' reports of one frame."""
        self.add(key, 0, left, left_weight, t, step)
        self.add(key, 1, right, right_weight, t, step)

    def forget(self, key: tuple[str, int]) -> None:
        """A sensor view left this person: its reports no longer vote."""
        for reports in (*self.reports, *self._pending, *self._counted):
            reports.pop(key, None)
        for fresh in self._fresh:
            fresh.discard(key)

    def vote(self, hand: int, t: float) -> HandState:
        """The winning state of ``hand`` at ``t`` (rules in the module docstring)."""
        return self._vote(hand, t)[0]

    def _vote(self, hand: int, t: float) -> tuple[HandState, float]:
        """(winner, the pace of its hold: ``_pace``)."""
        window = 4.0 * self.memory_s
        o = c = l = 0.0
        not_tracked = False
        voters = 0
        for newest, _, _, _, so, sc, sl, nt in self.reports[hand].values():
            if t - newest > window:
                continue
            o += so
            c += sc
            l += sl
            not_tracked = not_tracked or nt
            if so > 0.0 or sc > 0.0 or sl > 0.0:
                voters += 1
        # the largest total wins; a tie between known states goes to the higher code
        total = o + c + l
        if l > 0.0 and l >= c and l >= o:
            return HandState.LASSO, _pace(l / total, voters)
        if c > 0.0 and c >= o:
            return HandState.CLOSED, _pace(c / total, voters)
        if o > 0.0:
            return HandState.OPEN, _pace(o / total, voters)
        return (HandState.NOT_TRACKED if not_tracked else HandState.UNKNOWN), 1.0

    def update(self, t: float) -> list[int]:
        """Vote both hands at ``t``; returns the hands whose reported state changes now."""
        dt = 0.0 if self._last_t is None else max(t - self._last_t, 0.0)
        self._last_t = t if self._last_t is None else max(t, self._last_t)
        changed = []
        for hand in (0, 1):
            case = self._evidence(hand, t)
            winner, pace = self._vote(hand, t)
            current = self.reported[hand]
            cand = self._candidate[hand]
            if winner != current and (current is None or current < HandState.OPEN
                                      and winner >= HandState.OPEN):
                self._report(hand, winner, changed)
                continue
            if cand is not None and cand[0] == winner:
                # the candidate keeps winning: its time counts at the pace of its support
                cand = (winner, cand[1] + dt * pace)
            elif cand is not None and cand[1] - dt > 0.0:
                cand = (cand[0], cand[1] - dt)          # a moment lost counts against it
            else:
                cand = None if winner == current else (winner, 0.0)
            self._candidate[hand] = cand
            if cand is not None and cand[1] >= self.hold_s - 1e-9:
                self._report(hand, cand[0], changed)
            elif case is not None and self.evidence:
                self._report(hand, case, changed)
        return changed

    def _evidence(self, hand: int, t: float) -> HandState | None:
        """Count the reports not counted yet into ``hand``'s evidence; the state they make a
        clear case for at ``t`` (module docstring), or None."""
        pending, counted, fresh = self._pending[hand], self._counted[hand], self._fresh[hand]
        if not fresh:
            new = []
        elif len(fresh) == 1:             # one sensor reported since the last vote: no sort
            key = fresh.pop()
            rt, state, w = pending[key]
            new = [(rt, state, w, key)] if rt > counted.get(key, _NEVER) else []
        else:
            new = [(rt, state, w, key) for key in fresh
                   for rt, state, w in (pending[key],) if rt > counted.get(key, _NEVER)]
            fresh.clear()
            new.sort()
        current = self.reported[hand]
        if current is None or current < HandState.OPEN:
            for rt, _, _, key in new:
                counted[key] = rt         # nothing to change from: the first state goes at once
            return None
        lead, margin, since = self._lead[hand], self._margin[hand], self._since[hand]
        # the two other known states, in code order
        c1, c2 = others = _OTHERS[current]
        for rt, state, w, key in new:
            counted[key] = rt
            if state < HandState.OPEN:
                continue                  # unknown and notTracked are no evidence
            for c in others:
                step = w if state == c else -w if state == current else 0.0
                if step > 0.0 and since[c] < 0.0:
                    since[c] = rt         # a run begins
                elif lead[c] + step < -1e-9:
                    since[c] = -1.0       # held at 0 (the sum under its lowest): the run is over
                v = lead[c] + step
                lead[c] = v if v > 0.0 else 0.0                  # max(0, v), cheaper
                v = margin[c] + (w if state == c else -w)
                margin[c] = v if v > 0.0 else 0.0
        # the first of the two other known states with the largest lead
        best = c2 if lead[c2] > lead[c1] else c1
        if lead[best] >= EVIDENCE_LEAD and margin[best] >= EVIDENCE_MARGIN and \
                since[best] >= 0.0 and t - since[best] >= self.hold_s - 1e-9:
            return HandState(best)
        return None

    @property
    def newest(self) -> float:
        """The newest report's time (-inf: none)."""
        return max((e[0] for reports in self.reports for e in reports.values()),
                   default=float("-inf"))

    def _report(self, hand: int, state: HandState, changed: list[int]) -> None:
        self.reported[hand] = state
        self._candidate[hand] = None
        self._lead[hand][:] = [0.0] * 5     # the evidence was against the state reported before
        self._margin[hand][:] = [0.0] * 5
        self._since[hand][:] = [-1.0] * 5
        changed.append(hand)


class CadenceWatch:
    """Whether a sensor's hand states change the way its reading cadence says (one client).

    A sensor that repeats each reading over two frames (a Kinect v2) changes its reported
    state only every second frame, so its short runs of a state (a misread, mostly) last an
    even number of frames; one that reads every frame has runs of any length, most misreads
    one frame long. Over a sensor's first ``DECIDE_RUNS`` short runs (up to ``SHORT_RUN``
    frames, begun and ended by a change, counted in frames that reached a person) the share
    of even ones says which it is: at least ``EVEN_REPEATS`` a sensor that repeats
    readings, at most ``EVEN_EVERY_FRAME`` one that reads every frame, else nothing is said.
    ``verdict`` is then 2, 1 or 0, and the watch stops (it costs the engine nothing after);
    the engine logs a verdict that contradicts the cadence in use, or takes it for a sensor
    whose cadence was a guess (``Engine._hand_cadence``).
    A frame lost on the way ends a run one frame short, so the shares are not 100 % and 0 %.
    """

    #: the longest run counted (frames): longer ones are the hand's true states, where a
    #: lost frame would make the parity a coin toss
    SHORT_RUN = 8
    DECIDE_RUNS = 40
    #: the even share at or over which the sensor repeats readings (a Kinect-like sensor
    #: with 0.5 % of frames lost: 98-100 % in bench_hands' sensors), and at or under which
    #: it reads every frame (independent misreads: about a fifth of short runs are even)
    EVEN_REPEATS, EVEN_EVERY_FRAME = 0.8, 0.35

    __slots__ = ("runs", "even", "verdict")

    def __init__(self) -> None:
        self.runs = self.even = 0
        #: None while watching; then 2 (repeats readings over two frames), 1 (reads every
        #: frame) or 0 (neither clearly)
        self.verdict: int | None = None

    def frame(self, run: list, hands: list) -> bool:
        """A frame of a track whose hand states are now ``hands`` (left, right); ``run``:
        the track's [state, state, run length, run length] (length -1: its run began with
        the track, not with a change). True when this frame decides the verdict; once it
        is decided, frames change nothing."""
        if self.verdict is not None:
            return False
        decided = False
        for h in (0, 1):
            state = hands[h]
            if state == run[h]:
                if run[2 + h] >= 0:
                    run[2 + h] += 1
                continue
            n = run[2 + h]
            if 0 < n <= self.SHORT_RUN:
                self.runs += 1
                self.even += n % 2 == 0
                if self.runs >= self.DECIDE_RUNS and self.verdict is None:
                    share = self.even / self.runs
                    self.verdict = (2 if share >= self.EVEN_REPEATS else
                                    1 if share <= self.EVEN_EVERY_FRAME else 0)
                    decided = True
            run[2 + h] = -1 if run[h] is None else 1
            run[h] = state
        return decided

    def stats(self) -> dict:
        return {"short_runs": self.runs, "even": self.even, "looks_like": self.verdict}
