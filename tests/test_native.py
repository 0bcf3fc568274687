"""The native core (``stage.engine.native``) held to the engine's Python path, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from stage.engine import jit
from stage.testing.native_shadow import replay, shadow_engine
from stage.testing.shows import three_dancers

needs_jit = pytest.mark.skipif(not jit.ready(), reason=f"no compiled kernels: {jit.why_not()}")
pytestmark = needs_jit


@pytest.fixture(scope="module")
def spread():
    return three_dancers()


def _count_starts(core) -> dict:
    """Rows the core restarts and starts in the datagrams it accepts, counted from now on."""
    seen = {"restarted": 0, "started": 0}
    fold = core.fold

    def counted(*args, **kwargs):
        out = fold(*args, **kwargs)
        if out is not None:
            seen["restarted"] += core.totals[0]
            seen["started"] += core.totals[1]
        return out
    core.fold = counted
    return seen


def test_the_core_sends_and_keeps_what_the_engine_does(spread):
    """Three dancers walking to the edge of three Kinects' range (joints rejected,
    restarted, started, inferred and carried): every datagram the core accepts gives the
    engine's encoded skeletons and leaves the engine's filter states and output rows, to the
    bit, rows restarted after two rejections and rows seen for the first time included."""
    poses, data = spread
    shadow = shadow_engine(poses)
    starts = _count_starts(shadow.core)
    replay(shadow, data)
    stats = shadow.engine.people.stats()
    assert stats["joints_restarted"] > 0 and stats["joints_rejected"] > 0   # not only easy rows
    assert shadow.mismatches == []
    assert shadow.accepted > 0.95 * len(data)
    assert shadow.compared >= 2.5 * shadow.accepted         # (three persons a datagram)
    assert starts["restarted"] > 0.5 * stats["joints_restarted"] and starts["started"] > 0


def test_sensors_in_step_the_core_chooses_and_replays_as_the_engine_does():
    """Aligned sensors on the simulated Kinects' errors: each person's views of a frame form
    an instant whose views often disagree. The core chooses each instant's joints as the
    Python path does, folds the instant again when a later view changes the choice, and
    what it folds is the engine's, to the bit."""
    poses, data = three_dancers(seconds=3.0, aligned=True)
    shadow = replay(shadow_engine(poses), data)
    stats = shadow.engine.people.stats()
    assert stats["joints_disagreeing"] > 0 and stats["replays"] > 0
    assert shadow.mismatches == []
    assert shadow.accepted > 0.8 * len(data)
    assert shadow.core.replayed > 0.1 * shadow.accepted


def test_datagrams_out_of_order_are_replayed_by_the_core_as_the_engine_does():
    """Datagrams arriving after later ones (their timetags unchanged): the core inserts each
    view in capture order and folds the rest of its span again, as the engine does."""
    poses, data = three_dancers(seconds=3.0, timetags=True)
    shadow = replay(shadow_engine(poses), _late(data, every=5))
    assert shadow.engine.people.stats()["replays"] > 0
    assert shadow.mismatches == []
    assert shadow.accepted > 0.8 * len(data)
    assert shadow.core.replayed > 0


def test_a_small_ring_and_one_slot_to_start_with_change_nothing(spread):
    """A ring of three states wraps every other step; one slot grows to hold everyone."""
    poses, data = spread
    shadow = replay(shadow_engine(poses, depth=3, slots=1), data[:240])
    assert shadow.mismatches == [] and shadow.accepted > 200
    assert len(shadow.core.owners) >= 3


@pytest.mark.parametrize("what", ["state", "bytes"])
def test_the_comparison_sees_a_core_that_differs(spread, what):
    """The shadow's comparison is not blind: a core whose process noise is 1 % higher, or
    whose joint names are spelt wrong, is caught."""
    poses, data = spread
    shadow = shadow_engine(poses)
    if what == "state":
        shadow.core.q = shadow.core.q * 1.01
    else:
        shadow.core.names = shadow.core.names.copy()
        shadow.core.names[0] ^= 0x20
    replay(shadow, data[:120])
    assert shadow.accepted > 50
    wanted = "state differs" if what == "state" else "encoded skeleton differs"
    assert any(wanted in m for m in shadow.mismatches)


def _arrays(core) -> dict:
    out = {n: getattr(core, n).copy() for n in core._arrays()}
    for name in [n for n in out if n.startswith("ring")]:
        for s in range(len(core.owners)):    # the entries after the newest kept are scratch
            for e in range(core.depth - 1 - int(core.valid[s])):
                out[name][s, (core.head[s] + 1 + e) % core.depth] = 0.0
    out["recent"] = [dict(rows) for rows in core.recent]     # view key -> row
    return out


def _same(a: dict, b: dict) -> bool:
    return a["recent"] == b["recent"] and all(
        np.array_equal(a[n], b[n], equal_nan=True) for n in a if n != "recent")


_TAKEN = ("nothing amiss", "joins an instant, agreeing", "joins an instant, disagreeing",
          "out of order", "row to start", "row to restart", "a new view")


@pytest.mark.parametrize("case", [*_TAKEN, "one person twice", "before the history",
                                  "a new view, declined"])
def test_a_declined_datagram_changes_nothing(spread, case):
    """What the core leaves to Python it declines before changing anything (but the ring's
    scratch entries): the heads, states, output rows and views' rows stay as they were.
    (The same views with nothing amiss are taken, and so are a view joining an instant, one
    captured before the person's newest, within its history, a step with a joint to
    start or to restart, and a person's first view from a sensor, whose row a declined
    datagram gives up again.)"""
    poses, data = spread
    shadow = replay(shadow_engine(poses), data[:90])
    core = shadow.core
    persons = shadow.engine.persons
    pids = [pid for pid in core.slot_of if pid in persons][:2]
    assert len(pids) == 2
    keys = [next(iter(core.recent[core.slot_of[pid]])) for pid in pids]
    s0 = core.slot_of[pids[0]]
    t = np.array([core.newest[core.slot_of[pid]] + 0.02 for pid in pids])
    z = np.array([core.joints[core.slot_of[pid]] for pid in pids])
    r = np.full((2, 25), 1e-4)
    conf = np.ones((2, 25))
    if case.startswith("joins an instant"):
        t[0] = core.newest[s0] + 0.5 * shadow.engine.rig.fusion.group_s
        z[0] = core.ring_z[s0, core.head[s0]]               # the instant's view...
        if case.endswith("disagreeing"):
            z[0, 3] += 0.3                                   # ... but for its head
    elif case == "out of order":
        t[0] = core.newest[s0] - 0.2 * shadow.engine.rig.fusion.replay_s
    elif case == "before the history":
        t[0] = core.newest[s0] - 2.0 * shadow.engine.rig.fusion.replay_s
    elif case == "one person twice":
        pids[1], keys[1] = pids[0], keys[0]
    elif case.startswith("a new view"):
        keys[1] = ("nobody", 9)                  # the person's first view from a sensor
        if case.endswith("declined"):             # ... in a datagram the core declines
            t[0] = core.newest[s0] - 2.0 * shadow.engine.rig.fusion.replay_s
    elif case == "nothing amiss":
        pass
    elif case == "row to start":
        core.ring[s0, core.head[s0], :, :, 7] = np.nan
        core.ring_t[s0, core.head[s0], 7] = np.nan
    else:                                            # one rejection held, a second far off
        core.ring_ht[s0, core.head[s0], 7] = core.newest[s0]
        z[0, 7] += 3.0
    before = _arrays(core)
    valid = core.valid.copy()
    out = core.fold(pids, keys, t, z, r, conf)
    if case in _TAKEN:
        assert out is not None and len(out) == 2
        assert not _same(before, _arrays(core))
        if case == "a new view":
            s1 = core.slot_of[pids[1]]
            row = core.recent[s1][keys[1]]
            assert core.recent_t[s1, row] == t[1]
            np.testing.assert_array_equal(core.recent_conf[s1, row], conf[1])
        return
    assert out is None
    core.valid[:] = valid          # (a replay declined leaves fewer steps to trust, no more)
    assert _same(before, _arrays(core))
    assert core.declined >= 1


def test_the_core_refuses_to_start_without_kernels():
    from stage.engine.native import NativeCore
    from stage.settings import FusionSettings, KalmanSettings
    with jit.disabled():
        with pytest.raises(RuntimeError, match="compiled kernels"):
            NativeCore(KalmanSettings(), FusionSettings())


# ---------------------------------------------------------------- in the engine (fusion.native)
def _engine(poses, native: bool):
    import dataclasses

    from stage.clock import ManualClock
    from stage.engine.engine import Engine
    from stage.rig import Rig, set_calibration
    from stage.testing.native_shadow import Recorder
    rig = Rig(reference="s0", views=[("127.0.0.1", 9)])
    rig.fusion = dataclasses.replace(rig.fusion, native=native)
    rig.stage_frame = poses[0].to_stage
    inverse = np.linalg.inv(poses[0].to_stage)
    for k, p in enumerate(poses):
        set_calibration(rig, f"s{k}", inverse @ p.to_stage, "test")
    recorder = Recorder()
    engine = Engine(rig, ManualClock(0.0), recorder)
    frames: list = []
    engine.listeners.append(lambda frame: frames.append(
        {pid: (b.joints, b.conf, b.velocity, b.position, b.hands)
         for pid, b in frame.bodies.items()}))
    return engine, recorder, frames


def _late(data, every: int = 7):
    """``data`` with every ``every``-th datagram arriving after the next one (its capture time,
    in its timetag, unchanged): the engine replays it into its persons."""
    out = list(data)
    for k in range(5, len(out) - 1, every):
        (ta, a), (tb, b) = out[k], out[k + 1]
        out[k], out[k + 1] = (ta, b), (tb, a)
    return out


def _play(engine, recorder, data, extra: dict | None = None) -> list[list[bytes]]:
    sent = []
    last = 0.0
    for n, (t, d) in enumerate(data):
        engine.clock.set(t)
        engine.handle_datagram(d, ("127.0.0.1", 7000), arrival=t)
        for datagram in (extra or {}).get(n, ()):
            engine.handle_datagram(datagram, ("127.0.0.1", 9100), arrival=t)
        if t - last >= 0.02:
            engine.tick(t)
            last = t
        sent.append(list(recorder.sent))
        recorder.sent.clear()
    return sent


def test_an_instant_chosen_again_steps_again_only_the_rows_its_choice_changes(monkeypatch):
    """When a view joining an instant changes which joints the instant's earlier views give,
    the core steps again only the rows whose masks changed (a row is independent of the
    others in a step, so the rest are the same floats as before) and the new view in full;
    what it keeps is still the engine's to the bit. (The kernel run uncompiled here, so
    that its helpers can be watched.)"""
    poses, data = three_dancers(seconds=3.0, aligned=True)
    shadow = replay(shadow_engine(poses), data[:150])
    rows_again: list[int] = []          # rows each partial step stepped again
    inside = [False]
    step_rows = jit._step_rows

    def watched_step(S, *args):
        if inside[0]:
            rows_again.append(S.shape[2])
        return step_rows(S, *args)

    def watched_again(*args):
        inside[0] = True
        try:
            return jit._PYTHON_HELPERS["_native_rows_again"](*args)
        finally:
            inside[0] = False

    monkeypatch.setitem(jit._compiled, "_native_fold", jit._PYTHON_NATIVE["_native_fold"])
    for name in ("_native_span", "_native_span_step"):
        monkeypatch.setattr(jit, name, jit._PYTHON_HELPERS[name])
    monkeypatch.setattr(jit, "_native_rows_again", watched_again)
    monkeypatch.setattr(jit, "_step_rows", watched_step)
    replayed = shadow.core.replayed
    replay(shadow, data[150:210])
    assert shadow.core.replayed > replayed
    assert rows_again and max(rows_again) < 25
    assert shadow.mismatches == []


#: simulated Kinects whose views of an instant agree (a few mm of noise, no bias, no swaps)
_AGREEING = dict(noise_m=0.002, noise_per_m=0.0, fit_bias_m=0.0, surface_bias_m=0.0,
                 occlusion_bias_m=0.0, swap_per_s=0.0, inferred_off_m=(0.0, 0.0))


@pytest.mark.parametrize("show", ["spread", "aligned", "aligned, agreeing", "late"])
def test_the_engine_with_the_native_core_sends_what_its_python_path_sends(show):
    """Whole shows through two engines, ``fusion.native`` on and off: every datagram sent to
    the views and every body handed to listeners the same, to the bit, and the same fold
    statistics. Spread, the core folds most datagrams, rows to restart included; sensors
    in step, it folds views joining an instant, choosing
    between views that disagree and folding an instant again when its choice changes;
    with datagrams arriving late, it replays them into the history it keeps. A view asking
    for a fixed rate with a forecast reads the filter the core holds."""
    from stage.sensors.protocol import encode_message
    poses, data = three_dancers(seconds=4.0, aligned=show.startswith("aligned"),
                                timetags=show == "late",
                                kinect=_AGREEING if show.endswith("agreeing") else None)
    if show == "late":
        data = _late(data)
    extra = {60: [encode_message("/registerView", "127.0.0.1", 9100, 20.0)],
             200: [encode_message("/registerView", "127.0.0.1", 9101, 0, 0.05)]}
    runs = []
    for native in (False, True):
        engine, recorder, frames = _engine(poses, native)
        starts = _count_starts(engine.people.core) if native else None
        runs.append((_play(engine, recorder, data, extra), frames, engine.people.stats(),
                     engine))
    (sent_a, frames_a, stats_a, _), (sent_b, frames_b, stats_b, engine) = runs
    core = engine.people.core
    assert core is not None
    native_stats = stats_b.pop("native")
    assert stats_a == stats_b
    assert native_stats["folded"] == engine.people.core.folded
    assert sent_a == sent_b
    assert len(frames_a) == len(frames_b)
    for a, b in zip(frames_a, frames_b):
        assert a.keys() == b.keys()
        for pid in a:
            for x, y in zip(a[pid], b[pid]):
                np.testing.assert_array_equal(x, y)
    assert core.folded > 0.8 * len(data)
    if show in ("aligned", "late"):     # instants chosen again, views out of order
        assert stats_b["replays"] > 0 and core.replayed > 0.5 * stats_b["replays"]
    if show == "spread":                # rows restarted, by the core too
        assert stats_b["joints_restarted"] > 0 and starts["restarted"] > 0


def test_a_ring_too_short_for_the_replay_window_is_counted():
    """Given back with more steps than its ring holds, a person gets the steps it still has
    and the core counts the short history (the engine runs on; ``DEPTH`` is sized so that
    this does not happen at six sensors)."""
    from stage.engine.native import NativeCore
    poses, data = three_dancers(seconds=3.0, timetags=True)
    engine, recorder, _ = _engine(poses, True)
    people = engine.people
    people.core = NativeCore(people.smoothing, engine.rig.fusion, people.fuser.q_scale, depth=4)
    _play(engine, recorder, _late(data, every=13))
    assert people.core.given_back > 0 and people.core.short_histories > 0


def test_persons_lost_leave_the_core_with_copies_of_their_rows(spread):
    poses, data = spread
    engine, recorder, _ = _engine(poses, True)
    _play(engine, recorder, data[:150])
    core = engine.people.core
    held = [engine.persons[pid] for pid in core.slot_of]
    assert held
    before = [p.joints.copy() for p in held]
    t = data[149][0]
    for k in range(1, 100):                              # 2 s of silence: every person lost
        engine.clock.set(t + 0.02 * k)
        engine.tick()
    assert not engine.persons and not core.slot_of
    for p, joints in zip(held, before):
        assert not np.shares_memory(p.joints, core.joints) and p.filter.native is None
        np.testing.assert_array_equal(p.joints, joints)


def test_native_on_without_kernels_runs_the_python_path(caplog):
    caplog.set_level("INFO")
    poses, data = three_dancers(seconds=0.5)
    with jit.disabled():
        engine, recorder, _ = _engine(poses, True)
        assert engine.people.core is None
        _play(engine, recorder, data)
    assert any("native is on but" in r.message for r in caplog.records)


_VISITORS = """
name: visitors
duration: 9
sensors:
  ring: {count: 3, radius: 2.5, height: 1.0}
performers:
  - name: a
    present: false
    position: [-1.0, 0.0]
    timeline:
      - {enter: [-1.0, 0.0], facing: 0, at: 0.3}
      - {circle: [-0.5, 0.0], turns: 1, speed: 0.6}
      - {leave: true, at: 6.5}
  - name: b
    present: false
    position: [1.0, -0.5]
    timeline:
      - {enter: [1.0, -0.5], facing: 180, at: 1.5}
      - {raise: both, to: 150, over: 1}
      - {walk: [0.0, 0.8], speed: 0.8}
  - name: c
    present: false
    position: [0.0, 1.0]
    timeline:
      - {enter: [0.0, 1.0], facing: 270, at: 3.0}
      - {crouch: 0.3, over: 1}
      - {stand: true, over: 1}
events:
  - {at: 2.5, unplug: kinect-b}
  - {at: 4.5, replug: kinect-b}
"""


def test_visitors_coming_and_going_through_both_paths_send_the_same(tmp_path):
    """The soak's kind of stage in 9 s: simulated Kinects at their own phases and latencies
    (views late, instants that disagree), visitors entering and leaving, a sensor unplugged
    and back. Engines with the core on and off send the same datagrams and keep the same
    statistics, and the core folds most of it."""
    import dataclasses

    from stage.clock import ManualClock
    from stage.engine.engine import Engine
    from stage.sensors.sim import Simulator
    from stage.testing.native_shadow import Recorder
    path = tmp_path / "visitors.yaml"
    path.write_text(_VISITORS)
    sim = Simulator(str(path), seed=3)
    items = list(sim.stream(9.0))
    runs = []
    for native in (False, True):
        rig = sim.rig()
        rig.views = [("127.0.0.1", 9)]
        rig.fusion = dataclasses.replace(rig.fusion, native=native)
        recorder = Recorder()
        engine = Engine(rig, ManualClock(0.0), recorder)
        engine.rig_store.threaded = False
        last = 0.0
        for d in items:
            engine.clock.set(max(engine.clock.now(), d.arrival))
            engine.handle_datagram(d.data, d.source, engine.clock.now())
            if engine.clock.now() - last >= 0.02:
                engine.tick(engine.clock.now())
                last = engine.clock.now()
        runs.append((recorder.sent, engine.people.stats(), engine.tracker._next_id))
    (sent_a, stats_a, ids_a), (sent_b, stats_b, ids_b) = runs
    native = stats_b.pop("native")
    assert stats_a == stats_b and ids_a == ids_b > 3
    assert stats_a["replays"] > 0 and stats_a["joints_disagreeing"] > 0
    assert sent_a == sent_b and len(sent_a) > 500
    assert native["folded"] > 0.6 * len(items) and native["replayed"] > 0


def _elements(bundle: bytes) -> list[bytes]:
    """A flat bundle's elements, in order."""
    out, k = [], 16
    while k < len(bundle):
        size = int.from_bytes(bundle[k:k + 4], "big")
        out.append(bundle[k + 4:k + 4 + size])
        k += 4 + size
    return out


def test_the_cores_view_offsets_are_learned_as_the_python_path_learns_them():
    """The view offsets of the core's persons are learned on its rows, for a batch's frames in
    one call before the fold (``People._offsets_held``). Engines with the core on and off
    send the same datagrams when the frames are rows of the batch's arrays, when a datagram
    holds one skeleton (its frame is no such row: corrected in a copy and written back),
    and when a ``/lostUser`` follows a frame in its datagram (the offsets are learned
    before the view is forgotten); the core's persons have offsets learned."""
    from stage.engine.people import People
    from stage.sensors.protocol import encode_bundle, encode_message
    poses, data = three_dancers(seconds=3.0)
    shaped, lost = [], 0
    for n, (t, d) in enumerate(data):
        parts = _elements(d)
        if 120 <= n < 150 and n % 3 == 0 and len(parts) == 9:   # s0: a skeleton a datagram
            shaped += [(t, encode_bundle(parts[k:k + 3])) for k in (0, 3, 6)]
        elif n in (181, 211) and len(parts) == 9:                # s1: user 0 lost after its frame
            shaped.append((t, encode_bundle(parts + [encode_message("/lostUser", "s1", 0)])))
            lost += 1
        else:
            shaped.append((t, d))
    assert lost == 2
    calls = {"batch": 0, "copies": 0, "dropping": 0}
    learn, drop = People._offsets_held, People.drop_track

    def counted(self):
        calls["batch" if all(h[0][0] >= 0 for h in self._held_offsets) else "copies"] += 1
        return learn(self)

    def dropping(self, track, t):
        calls["dropping"] += bool(self._held_offsets)
        return drop(self, track, t)
    runs = []
    People._offsets_held, People.drop_track = counted, dropping
    try:
        for native in (False, True):
            engine, recorder, frames = _engine(poses, native)
            runs.append((_play(engine, recorder, shaped), frames, engine.people.stats(), engine))
    finally:
        People._offsets_held, People.drop_track = learn, drop
    (sent_a, frames_a, stats_a, _), (sent_b, frames_b, stats_b, engine) = runs
    stats_b.pop("native")
    assert stats_a == stats_b
    assert sent_a == sent_b
    for a, b in zip(frames_a, frames_b, strict=True):
        assert a.keys() == b.keys()
        for pid in a:
            for x, y in zip(a[pid], b[pid]):
                np.testing.assert_array_equal(x, y)
    core = engine.people.core
    assert core.folded > 0.8 * len(data)
    assert calls["batch"] > 100 and calls["copies"] >= 5 and calls["dropping"] >= 1
    assert np.abs(core.offsets).max() > 0.001            # learned, in the core's rows


def test_a_backlog_of_several_sensors_datagrams_learns_the_same_offsets():
    """Several sensors' datagrams taken as one batch (a backlog: ``Engine.run`` takes it in
    one go): each sensor's frames are prepared in their own call, so the batch's arrays are
    the last sensor's, and a frame of another sensor (here one of three, where the last
    sensor's datagram holds two skeletons) is corrected in a copy. Engines with the core on
    and off send the same."""
    from stage.sensors.messages import Inbound
    from stage.sensors.protocol import decode_datagram, encode_bundle
    poses, data = three_dancers(seconds=3.0)
    trimmed = []
    for n, (t, d) in enumerate(data):
        parts = _elements(d)
        if n % 3 == 2 and len(parts) == 9:          # s2: two skeletons (and their hands)
            d = encode_bundle(parts[:6])
        trimmed.append((t, d))
    runs = []
    for native in (False, True):
        engine, recorder, _ = _engine(poses, native)
        sent, last, n = [], 0.0, 0
        while n < len(trimmed):
            # from 1.5 s on, each frame's three datagrams as one batch
            together = 3 if n >= 135 and n % 3 == 0 else 1
            items = []
            for t, d in trimmed[n:n + together]:
                engine.clock.set(t)
                items += [Inbound(m, t, ("127.0.0.1", 7000), tt)
                          for m, tt in decode_datagram(d).messages]
            engine.process(items)
            n += together
            if engine.clock.now() - last >= 0.02:
                engine.tick(engine.clock.now())
                last = engine.clock.now()
            sent.append(list(recorder.sent))
            recorder.sent.clear()
        runs.append((sent, engine.people.stats(), engine))
    (sent_a, stats_a, _), (sent_b, stats_b, engine) = runs
    native_stats = stats_b.pop("native")
    assert stats_a == stats_b and sent_a == sent_b
    assert native_stats["folded"] > 0.5 * len(sent_b)
    assert np.abs(engine.people.core.offsets).max() > 0.001
