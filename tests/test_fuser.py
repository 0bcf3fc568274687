"""stage.engine.fuser: views folded in at once, in capture order, replays, instants, waves."""

from __future__ import annotations

import numpy as np

from stage.engine.fuser import BodyFilter, Fuser, View
from stage.engine.kalman import FilterState, step
from stage.settings import FusionSettings, KalmanSettings

S = KalmanSettings()
F = FusionSettings()
R = 1e-4


def walk(seed: int, frames: int, sensors: int = 3, jitter: float = 0.0):
    """Views of one person walking at 1 m/s, waving; sensors 11 ms apart, 1 cm noise."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(-0.5, 0.5, size=(25, 3)) + [0.0, 1.0, 0.0]
    out = []
    for k in range(frames):
        for s in range(sensors):
            t = k / 30 + s / (30 * sensors) + rng.uniform(-jitter, jitter)
            truth = base + [t, 0.0, 0.0] + 0.2 * np.sin(4 * t + np.arange(25))[:, None]
            z = truth + rng.normal(0, 0.01, size=(25, 3))
            r = np.full(25, R)
            r[rng.random(25) < 0.1] = np.nan
            out.append(View((f"s{s}", 0), t, z, np.where(np.isnan(r), 0.0, 1.0), r, t + 0.01))
    return out


def fold_all(views, one_by_one=True) -> BodyFilter:
    body = BodyFilter()
    fuser = Fuser(S, F)
    if one_by_one:
        for v in views:
            fuser.fold([(body, v)])
    else:
        fuser.fold([(body, v) for v in views])
    return body


def copy_views(views):
    return [View(v.key, v.t, v.joints, v.conf, v.r, v.arrival) for v in views]


def test_in_order_views_are_one_filter_update_each():
    views = walk(1, 20)
    body = fold_all(copy_views(views))
    state = FilterState.empty(25)
    for v in views:
        step(state, np.full(25, v.t), v.joints, v.r, S)
    np.testing.assert_array_equal(body.state.x, state.x)
    np.testing.assert_array_equal(body.state.P, state.P)
    assert body.history[-1].view.used.any()


def test_a_view_that_comes_late_is_replayed_into_place_exactly():
    views = walk(2, 30)
    in_order = fold_all(copy_views(views))
    shuffled = copy_views(views)
    # sensor 2's frames reach the engine two frames late
    late = [v for v in shuffled if v.key[0] == "s2"]
    rest = [v for v in shuffled if v.key[0] != "s2"]
    arrival = sorted(rest + late, key=lambda v: v.t + (0.07 if v.key[0] == "s2" else 0.0))
    body = BodyFilter()
    fuser = Fuser(S, F)
    for v in arrival:
        fuser.fold([(body, v)])
    assert fuser.stats.replays > 20 and fuser.stats.late == 0
    np.testing.assert_allclose(body.state.x, in_order.state.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(body.state.P, in_order.state.P, rtol=0, atol=1e-15)
    # every view went into the filter once: the history holds each of the last ones once
    keys = [(s.view.key, s.view.t) for s in body.history]
    assert len(keys) == len(set(keys))


def test_a_view_older_than_the_history_is_dropped_as_late():
    views = walk(3, 20)
    body = BodyFilter()
    fuser = Fuser(S, F)
    for v in views[3:]:
        fuser.fold([(body, v)])
    before = body.state
    late = fuser.fold([(body, views[0])])
    assert late == [views[0]] and fuser.stats.late == 1
    assert body.state is before


def test_one_wave_for_many_people_equals_folding_each_alone():
    people = [walk(10 + p, 10) for p in range(4)]
    alone = [fold_all(copy_views(v)) for v in people]
    bodies = [BodyFilter() for _ in people]
    fuser = Fuser(S, F)
    for k in range(len(people[0])):
        fuser.fold([(bodies[p], people[p][k]) for p in range(4)])   # one wave of four
    for body, ref in zip(bodies, alone):
        np.testing.assert_array_equal(body.state.x, ref.state.x)
    # two frames of one person in one batch are two waves, in order
    batch = fold_all(copy_views(people[0]), one_by_one=False)
    np.testing.assert_array_equal(batch.state.x, alone[0].state.x)


def instant(body: BodyFilter, fuser: Fuser, t: float, truth: np.ndarray, bad: int, order):
    rng = np.random.default_rng(int(t * 1000))
    views = []
    for s in range(3):
        z = truth + rng.normal(0, 0.005, size=(25, 3))
        if s == bad:
            z[7] += [0.25, 0.0, 0.0]          # this sensor's left hand is 25 cm off
        views.append(View((f"s{s}", 0), t + 0.001 * s, z, np.ones(25), np.full(25, R), t))
    for s in order:
        fuser.fold([(body, views[s])])
    return views


def test_views_of_one_instant_that_disagree_keep_the_consistent_ones_whatever_comes_first():
    truth = np.zeros((25, 3)) + [0.0, 1.0, 2.0]
    results = []
    for order in ([0, 1, 2], [2, 0, 1], [1, 2, 0]):   # sensor 0, the odd one, first to last
        body, fuser = BodyFilter(), Fuser(S, F)
        # the first instant: the filter knows nothing yet, only the views can judge
        views = instant(body, fuser, 0.0, truth, bad=0, order=order)
        assert not views[0].used[7]                          # the odd one out...
        assert views[1].used[7] and views[2].used[7]         # ...and the two that agree
        assert np.linalg.norm(body.estimate(0.002)[0][7] - truth[7]) < 0.02
        for k in range(1, 5):
            instant(body, fuser, k / 30, truth, bad=0, order=order)
        results.append(body.estimate(4 / 30 + 0.002)[0])
        assert fuser.stats.disagreeing == 5                 # one joint per instant
    for other in results[1:]:
        np.testing.assert_allclose(other, results[0], atol=1e-9)


def test_a_disagreeing_view_that_leaves_the_instants_choice_alone_needs_no_replay():
    """The first views of an instant agree, one of them not seeing a joint; a third view is
    off on another joint. The choice for the first two does not change (the first's mask
    is every joint it sees: a plain step's mask, made only when read), so the third is
    folded in without a replay."""
    truth = np.zeros((25, 3)) + [0.0, 1.0, 2.0]
    body, fuser = BodyFilter(), Fuser(S, F)
    rng = np.random.default_rng(5)
    for k in range(5):
        t = k / 30
        for s in range(3):
            z = truth + rng.normal(0, 0.005, size=(25, 3))
            r = np.full(25, R)
            if s == 0:
                r[3] = np.nan                       # the first view does not see joint 3
            if s == 2:
                z[7] += [0.25, 0.0, 0.0]            # the last one's joint 7 is 25 cm off
            view = View((f"s{s}", 0), t + 0.001 * s, z, np.where(np.isnan(r), 0.0, 1.0), r, t)
            fuser.fold([(body, view)])
        assert not view.used[7] and view.used[6]
    assert fuser.stats.disagreeing == 5
    assert fuser.stats.replays == 0


def test_a_wave_of_the_same_people_starts_from_the_last_waves_arrays_and_folds_the_same(
        monkeypatch):
    """A fold starts from the previous fold's arrays when it takes the same bodies in the
    same order (``Fuser._wave_before`` for filters whose rows were not cut out since,
    ``FilterState.concat`` for states that were); the result, replays of late views
    included, is the same as with copies, and no history entry is changed by a later fold."""
    def run(reuse: bool):
        whole, wave = FilterState._whole, Fuser._wave_before
        hits = [0]

        def counted(states):
            found = whole(states) if reuse else None
            hits[0] += found is not None
            return found

        def counted_wave(items):
            found = wave(items) if reuse else None
            hits[0] += found is not None
            return found
        monkeypatch.setattr(FilterState, "_whole", staticmethod(counted))
        monkeypatch.setattr(Fuser, "_wave_before", staticmethod(counted_wave))
        people = [walk(20 + p, 30) for p in range(3)]
        # sensor 2's frames come two frames late: replays into waves of the others
        for views in people:
            views.sort(key=lambda v: v.t + (0.07 if v.key[0] == "s2" else 0.0))
        bodies = [BodyFilter() for _ in people]
        fuser = Fuser(S, F)
        snapshots = []
        for k in range(len(people[0])):
            fuser.fold([(bodies[p], people[p][k]) for p in range(3)])
            step = bodies[0].history[-1]
            snapshots.append((step, step.before.stacked().copy()))
        for step, saved in snapshots:   # a history entry's state before never changes
            np.testing.assert_array_equal(step.before.stacked(), saved)
        monkeypatch.undo()
        return bodies, fuser, hits[0]

    copied, fuser_c, none = run(False)
    shared, fuser_s, hits = run(True)
    assert none == 0 and hits > 20 and fuser_s.stats.replays > 20
    assert fuser_s.stats == fuser_c.stats
    for a, b in zip(shared, copied):
        for name in ("x", "P", "mu", "t", "held_z", "held_t"):
            np.testing.assert_array_equal(getattr(a.state, name), getattr(b.state, name))
    # a state whose arrays were replaced since is copied, not taken whole
    rows = [shared[p].state for p in range(3)]
    rows[1].t = rows[1].t.copy()
    assert FilterState._whole(rows) is None


def test_concat_takes_a_state_whole_only_for_all_its_rows_in_order():
    rng = np.random.default_rng(5)
    owner = FilterState.of_block(rng.normal(size=(6, 2, 75, 3)), rng.normal(size=75),
                                 rng.normal(size=(75, 3)), rng.normal(size=75))
    rows = [owner.view_rows(a, a + 25) for a in (0, 25, 50)]
    whole = FilterState.concat(rows)
    assert whole.x is owner.x and whole.t is owner.t and whole.held_z is owner.held_z
    for order in (rows[::-1], rows[:2], rows[1:], [rows[0], rows[2], rows[1]], [rows[0], rows[2]]):
        joined = FilterState.concat(order)
        assert not np.shares_memory(joined.stacked(), owner.stacked())
        np.testing.assert_array_equal(
            joined.stacked(), np.concatenate([s.stacked() for s in order], axis=2))
        np.testing.assert_array_equal(joined.t, np.concatenate([s.t for s in order]))
