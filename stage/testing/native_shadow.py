"""The native core run beside an engine on the same datagrams, and compared with it.

``Shadow`` wraps an ``Engine`` (its clock a ``ManualClock``, its transport this module's
recorder). For every datagram the engine processes, the views its fusion path made of the
datagram's frames (``People._fold``'s input: person, view key, capture time, stage-space
joints, variances, confidences) are handed to a ``native.NativeCore`` that holds those
persons. The engine folds the datagram by its Python path as always; the core folds the
same views from its own copy of the persons' state. When the core accepts the datagram,
what it encoded is compared byte for byte with what the engine sent, and every state it
keeps (the filter, the output rows, the times) with the engine's. When it declines (a
case it leaves to Python), or holds a person of the datagram not yet, it takes the
persons over again from the engine's state after the datagram.

Between datagrams a person can change in ways the core is not told of (a view leaving it,
a merge): before each datagram, a person whose views differ from the core's copy is taken
over again, and persons the engine no longer has are released. ``mismatches`` lists every
difference found (empty: the core gave the engine's bytes and floats).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..engine import native
from ..engine.engine import Engine

_JC = b"/jointCoordinates\0"


class Recorder:
    """A transport that keeps what is sent."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def send(self, data: bytes, address: tuple[str, int]) -> None:
        self.sent.append(data)


def _user(data: bytes) -> int:
    """The user of a Server-to-View ``/jointCoordinates`` (its first argument)."""
    tags_end = data.index(b"\0", 20)
    at = tags_end + 1 + (-(tags_end + 1) % 4)
    return int.from_bytes(data[at:at + 4], "big", signed=True)


class Shadow:
    """See the module docstring. For each accepted datagram, thread CPU s: the core's fold
    (``native_s``); the engine's fold, settle and encoding of the same datagram
    (``python_s``: ``People._fold`` and the compiled encoder's calls in its ``_emit``); the
    engine's whole ``handle_datagram``, the core's fold taken out (``whole_s``)."""

    def __init__(self, engine: Engine, recorder: Recorder, **core) -> None:
        self.engine, self.recorder = engine, recorder
        people = engine.people
        self.core = native.NativeCore(people.smoothing, engine.rig.fusion, people.fuser.q_scale,
                                      **core)
        self.mismatches: list[str] = []
        self.accepted = self.declined = self.compared = 0
        self.native_s: list[float] = []
        self.python_s: list[float] = []
        self.whole_s: list[float] = []
        self._out: list[bytes] | None = None
        self._fold_s = self._native_s = 0.0
        self._n = 0
        fold = people._fold

        def captured() -> None:
            # the core's fold before the engine's on every other datagram, after it on the
            # rest: neither always finds the caches the other warmed
            views = [(p.id, v.key, v.t, v.joints, v.r, v.conf) for p, v, _ in people._views]
            self._views = views
            self._n += 1
            if self._n % 2:
                self._native(views)
            c0 = time.thread_time()
            fold()
            self._fold_s += time.thread_time() - c0
            if not self._n % 2:
                self._native(views)

        people._fold = captured
        self._encode_s = 0.0

    def _timed_encode(self, encode):
        def timed(*a):
            c0 = time.thread_time()
            try:
                return encode(*a)
            finally:
                self._encode_s += time.thread_time() - c0
        return timed

    def _native(self, views: list) -> None:
        """The core's fold of the views (when it holds every person of them): its output in
        ``_out`` (None: declined or not held), its CPU in ``_native_s``."""
        core = self.core
        if not all(v[0] in core.slot_of for v in views):
            return
        pids = [v[0] for v in views]
        keys = [v[1] for v in views]
        t = np.array([v[2] for v in views])
        z = np.array([v[3] for v in views])
        r = np.array([v[4] for v in views])
        conf = np.array([v[5] for v in views])
        c0 = time.thread_time()
        self._out = core.fold(pids, keys, t, z, r, conf)
        self._native_s = time.thread_time() - c0
        if self._out is None:
            self.declined += 1

    def feed(self, data: bytes, arrival: float) -> None:
        engine, core = self.engine, self.core
        self._sync()
        self.recorder.sent.clear()
        self._views = self._out = None
        self._fold_s = self._encode_s = self._native_s = 0.0
        encode = native.jit.view_joints      # (timed within the datagram only)
        native.jit.view_joints = self._timed_encode(encode)
        try:
            c0 = time.thread_time()
            engine.handle_datagram(data, arrival=arrival)
            whole = time.thread_time() - c0 - self._native_s
        finally:
            native.jit.view_joints = encode
        views = self._views
        if not views:
            return
        pids = [v[0] for v in views]
        if self._out is not None:
            self.accepted += 1
            self.native_s.append(self._native_s)
            self.python_s.append(self._fold_s + self._encode_s)
            self.whole_s.append(whole)
            self._compare(pids, self._out)
            return
        persons = engine.persons
        for pid in pids:
            p = persons.get(pid)
            if p is not None and p.announced and p.centre is not None and p.tracks:
                core.take(p)

    def _sync(self) -> None:
        """Persons changed between datagrams taken over again; those gone released."""
        core, persons = self.core, self.engine.persons
        for pid, s in list(core.slot_of.items()):
            p = persons.get(pid)
            if p is None or not p.tracks:
                core.release(pid)
            elif core.recent[s] != p.recent or core.person_t[s] != p.t:
                core.take(p)

    def _compare(self, pids: list[int], out: list[bytes]) -> None:
        core, persons = self.core, self.engine.persons
        sent = {}
        for data in self.recorder.sent:
            if data.startswith(_JC):
                sent.setdefault(_user(data), data)
        for pid, data in zip(pids, out):
            self.compared += 1
            if sent.get(pid) != data:
                self.mismatches.append(f"person {pid}: encoded skeleton differs")
            p = persons[pid]
            st = p.filter.state
            block, t, hz, ht = core.state(pid)
            s = core.slot_of[pid]
            pairs = [("state", block, st.stacked()), ("state t", t, st.t),
                     ("held_z", hz, st.held_z), ("held_t", ht, st.held_t),
                     ("centre", core.centre[s], p.centre),
                     ("recent_conf", core.recent_conf[s, :len(p.recent_t)], p.recent_conf),
                     ("recent_t", core.recent_t[s, :len(p.recent_t)], p.recent_t)]
            pairs += [(name, getattr(core, name)[s], getattr(p, name))
                      for name, *_ in native._FIELDS]
            for name, a, b in pairs:
                if not np.array_equal(a, b, equal_nan=True):
                    self.mismatches.append(f"person {pid}: {name} differs")
            if core.person_t[s] != p.t:
                self.mismatches.append(f"person {pid}: time differs")
            if core.newest[s] != p.filter.newest:
                self.mismatches.append(f"person {pid}: newest view differs")


def shadow_engine(poses, views: list[tuple[str, int]] | None = None, **core) -> Shadow:
    """An engine on a manual clock whose rig calibrates the sensors at ``poses`` exactly
    (sensor 0 the reference), sending to one view, with a ``Shadow`` round it (``core``:
    ``NativeCore``'s keywords, e.g. ``depth``, ``slots``)."""
    from ..clock import ManualClock
    from ..rig import Rig, set_calibration
    rig = Rig(reference="s0", views=views or [("127.0.0.1", 9)])
    # the engine's Python path folds everything: the shadow's core is compared with it
    rig.fusion = dataclasses.replace(rig.fusion, native=False)
    rig.stage_frame = poses[0].to_stage
    inverse = np.linalg.inv(poses[0].to_stage)
    for k, p in enumerate(poses):
        set_calibration(rig, f"s{k}", inverse @ p.to_stage, "shadow")
    recorder = Recorder()
    shadow = Shadow(Engine(rig, ManualClock(0.0), recorder), recorder, **core)
    return shadow


def replay(shadow: Shadow, data: list[tuple[float, bytes]], tick_s: float = 0.02,
           pace: bool = False) -> Shadow:
    """Feed ``data`` ((show time s, datagram)) to ``shadow`` at their times, ticking the
    engine every ``tick_s``; ``pace``: sleep each datagram's spacing first (caches cold,
    as the live engine thread finds them after waiting)."""
    clock = shadow.engine.clock
    last = clock.now()
    start = time.perf_counter()
    first = data[0][0] if data else 0.0
    for t, d in data:
        if pace:
            wait = start + (t - first) - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        clock.set(t)
        shadow.feed(d, t)
        if t - last >= tick_s:
            shadow.engine.tick(t)
            last = t
    return shadow
