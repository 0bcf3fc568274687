"""Asynchronous fusion: every sensor frame is one measurement update of its person's filter.

A ``View`` is one sensor's frame of one person in stage space, with each
joint's measurement variance (confidence and distance from the sensor). A
``BodyFilter`` is one person's 25 joint filters (``kalman.FilterState``)
and a short history of the views folded into it, each with the state before
it. The ``Fuser`` folds views in, for all persons of a batch in one numpy
step per wave (a wave holds at most one view per person; a batch with two
frames of one person has two waves).

Order. A person's views are folded in in capture-time order, each exactly
once, at its own capture time. A view captured before the newest one already
folded in (sensors whose frames reach the engine out of order) is inserted
where it belongs and the views after it are folded in again from the state
stored before them: a short replay. History is kept for ``replay_s``
(``FusionSettings``); a view older than that is dropped as late (unless
nothing older than it was ever folded in: a new person's first frames). We chose
replay over an update at the past time because it is exact (the result is
what in-order arrival would have given) and cheap at this size: a few steps
of 25 rows.

Views of one instant (captured within ``group_s`` of the first of them)
are checked against each other before they reach the filter:
``fusion.consistent_views`` keeps, joint by joint, the views that agree with
the largest group, so one sensor's bad joint is dropped even when the filter
is too unsure to judge it (just after a person is found, after an
occlusion). A view that joins an instant and leaves the choice made for the
earlier ones unchanged is a plain update; otherwise the instant is replayed.

Smoothing off (``hold``): each joint is its latest accepted measurement. The filter runs
with motion noise so large that an update puts a joint at its measurement, and every
velocity is set to zero after each fold: the velocity such a filter estimates is the jump
between two sensors' views of one joint over the few milliseconds between their frames
(tens of metres a second), which carried a joint no view reports now, and the person
when views are matched to persons, metres away (two persons for one on real takes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..joints import INFERRED, N_JOINTS
from ..settings import FusionSettings, KalmanSettings
from . import jit
from .fusion import consistent_views
from .kalman import FilterState, combine, mix, predict, step_folded, step_views, transition


#: a view's ``used`` before it is folded in (or when it is dropped as late): no joint;
#: shared, so read-only (the fold hands each view its own array)
_NONE_USED = np.zeros(N_JOINTS, dtype=bool)
_NONE_USED.flags.writeable = False


class View:
    """One sensor frame of one person, ready to fuse (arrays in stage space).

    key (client, user); t: capture time, engine clock, s; joints (25, 3) metres; conf
    (25,); r (25,) per-axis variance, m^2, NaN where not seen; arrival: when its datagram
    reached the server, engine clock. After fusion, ``used`` (25,) bool: the joints that
    went into the filter (not dropped by the instant's consistency check nor rejected by
    the gate), and ``excluded``: how many joints the consistency check left out (for the
    stats). ``size``: its trunk length as the frame kernel measured it
    (``tracking.body_size``; NaN: not measurable; None: not measured, for the fold to
    measure). A plain class with slots, not a dataclass: one is made per sensor frame
    and person, and a dataclass's default factory made an array for ``used`` each time
    that the fold then replaced.
    """

    __slots__ = ("key", "t", "joints", "conf", "r", "arrival", "used", "excluded", "size")

    def __init__(self, key: tuple[str, int], t: float, joints: np.ndarray, conf: np.ndarray,
                 r: np.ndarray, arrival: float, used: np.ndarray = _NONE_USED,
                 excluded: int = 0, size: float | None = None) -> None:
        self.key, self.t, self.joints, self.conf, self.r = key, t, joints, conf, r
        self.arrival, self.used, self.excluded, self.size = arrival, used, excluded, size

    def __repr__(self) -> str:
        return f"View(key={self.key!r}, t={self.t!r}, arrival={self.arrival!r})"


class _Step:
    """One view folded in: the view; the state before it (never changed); the capture time
    of the first view of its instant (``anchor``); the (25,) joints the instant's
    consistency check let through (``mask``); whether that is every joint the view sees
    (``whole``); on the first view of an instant, the filter's prediction for the instant
    (``prior``, cached).

    ``before`` may be given as a wave's state and the first of the 25 rows of it that are
    this person's, cut out only if a replay or a consistency check reads it (most never
    are); ``mask`` as None for every joint the view sees (``np.isfinite(view.r)``, made
    when read). A fold makes one per person and keeps it for ``replay_s``: each object
    it holds is one more to make and, a second later, to free."""

    __slots__ = ("view", "_before", "_at", "anchor", "_mask", "whole", "prior")

    def __init__(self, view: View, before: FilterState, anchor: float,
                 mask: np.ndarray | None, whole: bool = True,
                 prior: tuple[np.ndarray, np.ndarray] | None = None, at: int = -1) -> None:
        self.view, self._before, self._at, self.anchor = view, before, at, anchor
        self._mask, self.whole, self.prior = mask, whole, prior

    @property
    def before(self) -> FilterState:
        at = self._at
        if at >= 0:
            self._before = self._before.view_rows(at, at + N_JOINTS)
            self._at = -1
        return self._before

    @property
    def mask(self) -> np.ndarray:
        m = self._mask
        if m is None:
            m = self._mask = np.isfinite(self.view.r)
        return m


class BodyFilter:
    """One person's joint filters and recent history (engine thread only).

    ``state`` is a ``kalman.FilterState`` of 25 rows (SpineBase ... ThumbRight): for
    each joint and axis the two modes' [position, velocity], covariances and mode
    probabilities, and the time each joint's state refers to. It is replaced, never
    changed in place, so a reference taken from it stays valid. ``estimate(t)`` is
    the usual way to read it.
    """

    def __init__(self, n: int = N_JOINTS) -> None:
        self._state = FilterState.empty(n)
        #: (wave state, start, stop): the state is those rows of a plain fold's state, cut
        #: out only when read (``state``); the next fold of the same persons in the same
        #: order starts from that wave's state itself (``Fuser._fold_plain``)
        self._rows: tuple[FilterState, int, int] | None = None
        self.history: list[_Step] = []
        #: after a fold: (t, (25, 3) position, (25, 3) velocity), the estimate at the newest
        #: view's capture time, computed for a whole wave at once
        self.output: tuple[float, np.ndarray, np.ndarray] | None = None
        #: (core, slot) while the native core holds the person (``native.NativeCore.take``):
        #: its state and newest view are read from there, its ``history`` is what it was
        #: when taken, and it must be given back before the Python path folds it
        self.native: tuple | None = None

    @property
    def state(self) -> FilterState:
        native = self.native
        if native is not None:           # a copy: the core's ring is written over in turn
            return native[0].state_copy(native[1])
        rows = self._rows
        if rows is not None:
            self._state = rows[0].view_rows(rows[1], rows[2])
            self._rows = None
        return self._state

    def peek(self) -> tuple[np.ndarray, np.ndarray]:
        """The state now as ((6, 2, N, 3) block [x; P; mu], (N,) row times), views to be read
        at once and not kept (the native core's ring is written over in turn; ``state`` is
        the copy to keep)."""
        native = self.native
        if native is not None:
            block, t, _, _ = native[0].state_of(native[1])
            return block, t
        state = self.state
        return state.stacked(), state.t

    @state.setter
    def state(self, value: FilterState) -> None:
        self._state, self._rows = value, None

    @property
    def newest(self) -> float:
        """Capture time of the newest view folded in (-inf: none yet)."""
        native = self.native
        if native is not None:
            return float(native[0].newest[native[1]])
        return self.history[-1].view.t if self.history else float("-inf")

    def estimate(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """((25, 3) position m, (25, 3) velocity m/s) predicted to ``t`` (never backwards);
        NaN for joints never measured."""
        return self.state.predicted(t)


def prior_of(st: FilterState, t: float, s: KalmanSettings) -> tuple[np.ndarray, np.ndarray]:
    """The IMM prediction of the state ``st`` for ``t``: ((25, 3) mean, (25,) per-axis
    variance, mean of the three axes); NaN for joints never measured. Compiled
    (``jit.prior``, the same floats) when the kernels are used: an instant whose views
    disagree needs it (``Fuser._choose``), 4.8 times an aligned 6x6 datagram on the
    simulated Kinects, at 281 us a call in numpy under cProfile (issue 10, stop 39)."""
    if jit.ready():
        return jit.prior(st.stacked(), st.t, t, s)
    dt = np.maximum(t - st.t, 0.0)
    dt = np.where(np.isnan(dt), 0.0, dt)
    x0, P0, cbar = mix(st.x, st.P, st.mu, *transition(dt, s))
    xp, Pp = predict(x0, P0, dt, np.array([s.quiet_noise, s.fast_noise]))
    xm, Pm = combine(xp, Pp, cbar)
    return xm[0], Pm[0].mean(axis=1)


@dataclass
class FoldStats:
    views: int = 0
    late: int = 0            # older than the replay history: dropped
    replays: int = 0         # out-of-order views and instants whose choice changed
    disagreeing: int = 0     # joints left out because other views of the instant disagreed
    downweighted: int = 0    # joints beyond the gate
    rejected: int = 0        # joints beyond reject_sigma
    restarted: int = 0       # joints started afresh after two rejections in a row


def _held(state: FilterState) -> FilterState:
    """``state`` with every velocity zero (a copy: states kept in a history are shared)."""
    held = state.copy()
    held.x[1] = 0.0
    return held


class Fuser:
    """Folds views into ``BodyFilter``s; see the module docstring."""

    def __init__(self, smoothing: KalmanSettings, fusion: FusionSettings,
                 q_scale: np.ndarray | None = None, hold: bool = False) -> None:
        self.s, self.f = smoothing, fusion
        #: smoothing off: every velocity zero after a fold (see the module docstring)
        self.hold = hold
        self.q_scale = q_scale
        self.stats = FoldStats()
        #: after a fold whose every view went in by the plain path in one wave: (the
        #: filters, in order; their outputs' (P, 25, 3) position and velocity; (P, 25) row
        #: times), so that the settle reads them as they are, not gathered person by
        #: person; else None
        self.plain_wave: tuple[list[BodyFilter], np.ndarray, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------ entry point
    def fold(self, pairs: list[tuple[BodyFilter, View]]) -> list[View]:
        """Fold views into their filters (``pairs`` in capture-time order); returns the views
        dropped as late."""
        waves: list[list[tuple[BodyFilter, View]]] = []
        depth: dict[int, int] = {}
        for body, view in pairs:
            k = depth.get(id(body), 0)
            depth[id(body)] = k + 1
            if k == len(waves):
                waves.append([])
            waves[k].append((body, view))
        late: list[View] = []
        self.plain_wave = None
        for wave in waves:
            plain: list[tuple[BodyFilter, View, np.ndarray | None, float]] = []
            for body, view in wave:
                self.stats.views += 1
                if not body.history or (view.t >= body.newest and
                                        view.t - body.history[-1].anchor > self.f.group_s):
                    plain.append((body, view, None, view.t))
                    continue
                if view.t < body.history[0].view.t and not self._fits_before(body, view.t):
                    late.append(view)
                    self.stats.late += 1
                    continue
                if view.t >= body.newest:
                    anchor = body.history[-1].anchor
                    start = self._instant_start(body, len(body.history) - 1)
                    members = body.history[start:]
                    if all(m.whole for m in members) and self._agrees(view, members):
                        # the views so far all agree and so does this one: all are used
                        plain.append((body, view, np.isfinite(view.r), anchor))
                        continue
                    mask = self._choose(body, [m.view for m in members] + [view], members[0],
                                        anchor)
                    if np.array_equal(mask[:-1], np.array([m.mask for m in members])):
                        plain.append((body, view, mask[-1], anchor))
                        continue
                    self._replay(body, view, mask)      # the instant again, with this choice
                else:
                    self._replay(body, view)
                self._trim(body)
            if plain:
                self._fold_plain(plain, len(waves) == 1 and len(plain) == len(wave))
            for body, *_ in plain:
                self._trim(body)
        return late

    # ------------------------------------------------------------ the plain path
    def _fold_plain(self, items: list[tuple[BodyFilter, View, np.ndarray | None, float]],
                    whole: bool = False) -> None:
        """Fold one wave's views that need no replay in one step; ``whole``: they are all
        of the fold's views (``plain_wave`` is set)."""
        n = N_JOINTS
        before = self._wave_before(items)
        if before is None:
            before = FilterState.concat([body.state for body, *_ in items])
        work = before.shallow()
        t = np.array([view.t for _, view, _, _ in items]).repeat(n)
        z = np.concatenate([view.joints for _, view, _, _ in items])
        r = np.concatenate([view.r if mask is None else np.where(mask, view.r, np.nan)
                            for _, view, mask, _ in items])
        q = None if self.q_scale is None else np.tile(self.q_scale, len(items))
        outcome, pos, vel, used, (down, rejected, restarted) = step_folded(work, t, z, r,
                                                                           self.s, q)
        st = self.stats
        st.downweighted += down
        st.rejected += rejected
        st.restarted += restarted
        k = len(items)
        if self.hold:
            # (new arrays: a step that changed nothing leaves the state before's own; the
            # rows not measured now were held before, so their positions are as kept)
            held = _held(work)
            work.x, work.P, work.mu, work.block = held.x, held.P, held.mu, held.block
            vel = np.zeros_like(vel)
        # each person's rows as views made by iterating the reshaped arrays (in C: cheaper
        # than slicing each in Python)
        pos, vel = pos.reshape(k, n, 3), vel.reshape(k, n, 3)
        a = 0
        for (body, view, mask, anchor), p, v, u in zip(items, pos, vel, used.reshape(k, n)):
            body._state, body._rows = None, (work, a, a + n)
            body.output = (view.t, p, v)
            view.used = u
            if mask is not None:
                view.excluded = int((np.isfinite(view.r) & ~mask).sum())
                st.disagreeing += view.excluded
            body.history.append(_Step(view, before, anchor, mask, view.excluded == 0, None, a))
            a += n
        if whole:
            self.plain_wave = ([body for body, *_ in items], pos, vel, work.t.reshape(k, n))

    @staticmethod
    def _wave_before(items: list) -> FilterState | None:
        """The state of the wave the filters of ``items`` were last folded in, when they are
        all of its rows in the same order and none has changed since (as
        ``FilterState._whole``, without cutting the rows out first); else None."""
        first = items[0][0]._rows
        if first is None:
            return None
        wave, at = first[0], 0
        for body, *_ in items:
            rows = body._rows
            if rows is None or rows[0] is not wave or rows[1] != at:
                return None
            at = rows[2]
        return wave if at == wave.n else None

    # ------------------------------------------------------------ instants and replays
    def _instant_start(self, body: BodyFilter, i: int) -> int:
        """Index of the first step of the instant that step ``i`` belongs to."""
        anchor = body.history[i].anchor
        while i > 0 and body.history[i - 1].anchor == anchor:
            i -= 1
        return i

    def _agrees(self, view: View, members: list[_Step]) -> bool:
        """Whether ``view`` agrees with every view of its instant on every joint both see
        (the test of ``fusion.consistent_views``; the prior cannot change the choice then)."""
        z = np.array([m.view.joints for m in members])
        r = np.array([m.view.r for m in members])
        d = z - view.joints
        with np.errstate(invalid="ignore"):
            d2 = (d * d).sum(axis=2) / (r + view.r + 2.0 * self.f.view_bias_m ** 2)
        return not (d2 > self.s.gate_sigma ** 2).any()       # NaN (a joint unseen): no test

    def _choose(self, body: BodyFilter, views: list[View], first: _Step,
                anchor: float) -> np.ndarray:
        """(G, 25) the joints of each view of one instant that agree with the rest; ``first``
        is the instant's first step (its state before, and the prediction cached on it)."""
        if len(views) == 1:
            return np.isfinite(views[0].r)[None]
        if first.prior is None:
            first.prior = prior_of(first.before, anchor, self.s)
        prior, var = first.prior
        z = np.array([v.joints for v in views])
        r = np.array([v.r for v in views])
        gate2 = self.s.gate_sigma ** 2
        tracked = np.array([v.conf > INFERRED for v in views])   # above the guess level
        return consistent_views(z, r, prior, var, self.f.view_bias_m ** 2, gate2, tracked)

    def _replay(self, body: BodyFilter, view: View, chosen: np.ndarray | None = None) -> None:
        """Insert ``view`` in capture order and fold in again from the instant it joins.
        ``chosen``: when ``view`` joins the newest instant, the (G, 25) choice ``_choose``
        just made for its views (the same views, prior and state before: not made again)."""
        self.stats.replays += 1
        hist = body.history
        p = len(hist)
        while p > 0 and hist[p - 1].view.t > view.t:
            p -= 1
        start = p
        if p > 0 and view.t - hist[p - 1].anchor <= self.f.group_s:
            start = self._instant_start(body, p - 1)
        state = hist[start].before if start < len(hist) else body.state
        # the first instant's prediction, when it starts from the same state and view as before
        prior = hist[start].prior if start < p else None
        views = [s.view for s in hist[start:p]] + [view] + [s.view for s in hist[p:]]
        del hist[start:]
        state = state.shallow()
        k = 0
        while k < len(views):
            anchor = views[k].t
            g = k + 1
            while g < len(views) and views[g].t - anchor <= self.f.group_s:
                g += 1
            group = views[k:g]
            first = _Step(group[0], state, anchor, np.isfinite(group[0].r), True,
                          prior if k == 0 else None)
            if k == 0 and chosen is not None and g == len(views) == len(chosen):
                masks = chosen
            else:
                masks = self._choose(body, group, first, anchor)
            # the group's views stepped in turn, in one call (kalman.step_views)
            r = np.array([v.r for v in group])
            after, outcome, used, counts, last = step_views(
                state, np.array([v.t for v in group]), np.array([v.joints for v in group]),
                np.where(masks, r, np.nan), self.s, self.q_scale)
            if self.hold:
                after = [_held(a) for a in after]
            st = self.stats
            total = counts.sum(axis=0).tolist()
            st.restarted += total[0]
            st.downweighted += total[2]
            st.rejected += total[3]
            excluded = (np.isfinite(r) & ~masks).sum(axis=1).tolist()
            before = state
            for j, v in enumerate(group):
                v.used = used[j]
                st.disagreeing += excluded[j] - v.excluded
                v.excluded = excluded[j]
                hist.append(_Step(v, before, anchor, masks[j], excluded[j] == 0,
                                  first.prior if j == 0 else None))
                before = after[j]
            state = before
            k = g
        body.state = state
        if self.hold:               # (each state was held as it was stepped)
            body.output = (body.newest, state.estimate()[0], np.zeros((N_JOINTS, 3)))
            return
        # (the newest view is the last one stepped: the kernel's estimate at its time)
        body.output = (body.newest, *(state.predicted(body.newest) if last is None else last))

    @staticmethod
    def _fits_before(body: BodyFilter, t: float) -> bool:
        """Whether a view at ``t`` can still go before the oldest step kept: the state
        before that step refers to nothing later than ``t`` (always so for a new person)."""
        times = body.history[0].before.t
        return bool(np.isnan(times).all() or np.nanmax(times) <= t)

    def _trim(self, body: BodyFilter) -> None:
        """Forget whole instants older than ``replay_s`` before the newest view."""
        hist = body.history
        horizon = body.newest - self.f.replay_s
        cut = 0
        while cut < len(hist) - 1 and hist[cut].anchor < horizon:
            cut += 1
        if cut and hist[cut].anchor == hist[cut - 1].anchor:
            cut = self._instant_start(body, cut)
        if cut:
            del hist[:cut]
