"""The jump gate: catches a bumped sensor on its first bad frame, before it is fused.

Runs on the engine thread for every frame of a trusted sensor, so it is a
handful of vector operations over all tracked (sensor, user) views: each
view's torso joints in stage space and which of them the sensor tracks, its
velocity, and for every pair of views the last time they agreed (were within
``agree_m``: the same person seen by two sensors). Two views are compared on
the torso joints both track, and only when they share ``min_joints`` of them:
the mean of a different subset of joints is a different point (a body at
the edge of a sensor's view, tracked by one hip, centres 17-24 cm below and
beside the full torso's centre), not a jump. A view that now sits ``gate_m``
or more away from views it agreed with within the last ``link_s`` seconds,
and agrees with no view of any other trusted sensor, has jumped: nobody moves
30 cm in a frame, so its sensor moved. The sensor whose frame first shows the
disagreement is the one that moved (the others' latest frames were consistent
a moment ago).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ..engine import jit
from ..joints import TORSO

INF = float("inf")
_TORSO = np.array(TORSO, dtype=np.int64)


class JumpGate:
    def __init__(self, agree_m: float = 0.15, gate_m: float = 0.30, link_s: float = 0.5,
                 capacity: int = 32, points: int = len(TORSO), min_joints: int = 2,
                 same_m: float = 0.5) -> None:
        self.agree_m, self.gate_m, self.link_s, self.same_m = agree_m, gate_m, link_s, same_m
        self.points, self.min_joints = points, min_joints
        self._index: dict[tuple[str, int], int] = {}
        self._sensors: dict[str, int] = {}
        self._trusted = np.zeros(8, dtype=bool)
        #: per sensor, the farthest its views were from every other trusted sensor's views
        #: (the nearest one's distance, m) in any check since ``apart.clear()``: the live
        #: calibrator judges larger chunks only while nobody drifted apart (see ``_note_apart``)
        self.apart: dict[str, float] = {}
        #: (sensor, users) -> their rows, for ``check_frames`` (a row never changes)
        self._rows: dict[tuple[str, tuple[int, ...]], np.ndarray] = {}
        self._scratch: tuple = ()
        self._alloc(capacity)

    def _alloc(self, capacity: int) -> None:
        old = getattr(self, "_t", None)
        n = 0 if old is None else len(old)
        t, v = np.full(capacity, -INF), np.zeros((capacity, 3))
        x, m = np.zeros((capacity, self.points, 3)), np.zeros((capacity, self.points), bool)
        owner = np.full(capacity, -1)
        links = np.full((capacity, capacity), -INF)
        if old is not None:
            t[:n], x[:n], m[:n], v[:n] = self._t[:n], self._x[:n], self._m[:n], self._v[:n]
            owner[:n] = self._owner[:n]
            links[:n, :n] = self._links[:n, :n]
        self._t, self._x, self._m, self._v, self._owner, self._links = t, x, m, v, owner, links

    def _sensor(self, sensor: str) -> int:
        k = self._sensors.get(sensor)
        if k is None:
            k = self._sensors[sensor] = len(self._sensors)
            if k >= len(self._trusted):
                self._trusted = np.concatenate([self._trusted, np.zeros(len(self._trusted), bool)])
        return k

    def trust(self, sensor: str, trusted: bool) -> None:
        """Only views of trusted sensors (state ok) are compared against."""
        k = self._sensor(sensor)  # first: it may grow (replace) the _trusted array
        self._trusted[k] = trusted

    def forget(self, sensor: str, user: int) -> None:
        """Forget what a view agreed with (its user id now belongs to somebody else)."""
        i = self._index.get((sensor, user))
        if i is not None:
            n = len(self._index)
            self._links[i, :n] = -INF
            self._links[:n, i] = -INF

    def _row(self, sensor: str, user: int) -> int:
        """The row of view (sensor, user), made on first sight."""
        key = (sensor, user)
        i = self._index.get(key)
        if i is None:
            i = self._index[key] = len(self._index)
            if i >= len(self._t):
                self._alloc(2 * len(self._t))
            self._owner[i] = self._sensor(sensor)
        return i

    def _record(self, rows: np.ndarray, t: float, points: np.ndarray, tracked: np.ndarray,
                ) -> None:
        """Views ``rows`` now at ``points`` (k, P, 3), ``tracked`` (k, P): their velocity
        from the joints tracked in this frame and their last (a joint that comes or goes
        is not a movement), then the frame itself."""
        dt = t - self._t[rows]
        both = tracked & self._m[rows]                                  # (k, P)
        count = both.sum(axis=1)
        moved = (dt > 0) & (dt <= 0.2) & (count > 0)
        v = np.zeros((len(rows), 3))
        if moved.any():
            step = np.where(both[moved, :, None], points[moved] - self._x[rows[moved]], 0.0)
            v[moved] = step.sum(axis=1) / (count[moved] * dt[moved])[:, None]
            speed = np.sqrt(np.einsum("ij,ij->i", v, v))
            fast = speed > 3.0
            v[fast] *= (3.0 / speed[fast])[:, None]  # a jump is not a velocity
        self._v[rows] = v
        self._t[rows] = t
        self._x[rows] = np.where(tracked[..., None], points, 0.0)
        self._m[rows] = tracked

    def _distances(self, sensor: str, t: float, points: np.ndarray, tracked: np.ndarray,
                   ) -> tuple[np.ndarray, np.ndarray] | None:
        """(valid (k, n), d (k, n)): which recorded views each of the k views is compared
        with (another trusted sensor's, within 0.1 s, ``min_joints`` torso joints tracked
        by both) and how far apart the two are on those joints (m); None: nothing to
        compare with."""
        n = len(self._index)
        owner = self._owner[:n]
        dt = t - self._t[:n]
        valid = (np.abs(dt) <= 0.1) & self._trusted[owner]
        valid[owner == self._sensors[sensor]] = False
        if not valid.any():
            return None
        common = tracked[:, None, :] & self._m[None, :n]                      # (k, n, P)
        count = common.sum(axis=2)
        valid = valid & (count >= self.min_joints)                             # (k, n)
        if not valid.any():
            return None
        step = self._x[None, :n] - points[:, None]                             # (k, n, P, 3)
        mean = (np.matmul(common[..., None, :].astype(float), step)[..., 0, :]
                / np.maximum(count, 1)[..., None] + self._v[:n] * dt[:, None])  # (k, n, 3)
        return valid, np.sqrt(np.einsum("kij,kij->ki", mean, mean))

    def _away_from(self, jumped: np.ndarray) -> list[str]:
        """The sensors (sorted names) owning the views marked in ``jumped`` (the first
        ``len(jumped)`` rows): those a view jumped away from."""
        names = {k: s for s, k in self._sensors.items()}
        return sorted({names[k] for k in self._owner[:len(jumped)][jumped]})

    def _note_apart(self, sensor: str, d: np.ndarray) -> None:
        """One check of ``sensor``'s views at one instant, ``d`` their distances to the views
        compared with (inf where not compared): how close the closest two came. A bumped
        sensor moves every view of it at once, so its closest one moves away too; one view
        of a crowd tracked badly does not. Nothing compared, or nothing within ``same_m`` (only
        other people's views: a view the others do not see): nothing noted."""
        closest = float(d.min()) if d.size else INF
        if closest < self.same_m and closest > self.apart.get(sensor, 0.0):
            self.apart[sensor] = closest

    def check(self, sensor: str, user: int, t: float, points: np.ndarray, tracked: np.ndarray,
              ) -> tuple[list[str], float] | None:
        """Record a view's stage-space torso joints (P, 3) at time t, ``tracked`` (P,) bool:
        the joints its sensor tracks (the others are never read).

        Returns (the sensors it jumped away from, the largest distance m) when
        it disagrees with views it agreed with a moment ago and agrees with
        none; else None. (``check_many`` for one view, with fewer numpy calls: this
        runs for every frame.)
        """
        if jit.ready():
            return self.check_many(sensor, [user], t, points[None], tracked[None])[0]
        i = self._row(sensor, user)
        n = len(self._index)
        x = np.where(tracked[:, None], points, 0.0)
        dt_self = t - self._t[i]
        both = (tracked & self._m[i]).astype(float)
        k = both.sum()
        if 0 < dt_self <= 0.2 and k:
            # from the joints tracked in both frames: a joint that comes or goes is no motion
            v = both @ (x - self._x[i]) / (k * dt_self)
            speed = float(np.sqrt(v @ v))
            self._v[i] = v if speed <= 3.0 else v * (3.0 / speed)  # a jump is not a velocity
        else:
            self._v[i] = 0.0
        self._t[i], self._x[i], self._m[i] = t, x, tracked
        owner = self._owner[:n]
        dt = t - self._t[:n]
        valid = (np.abs(dt) <= 0.1) & self._trusted[owner]
        valid[owner == owner[i]] = False
        if not valid.any():
            return None
        common = self._m[:n] & tracked                                     # (n, P)
        count = common.sum(axis=1)
        valid &= count >= self.min_joints
        if not valid.any():
            return None
        # the mean over the joints both track of (the other view, moved on by its velocity,
        # minus this one)
        mean = (np.matmul(common[:, None, :].astype(float), self._x[:n] - x)[:, 0]
                / np.maximum(count, 1)[:, None] + self._v[:n] * dt[:, None])
        d = np.sqrt(np.einsum("ij,ij->i", mean, mean))
        self._note_apart(sensor, np.where(valid, d, INF))
        agree = valid & (d <= self.agree_m)
        if agree.any():
            self._links[i, :n][agree] = t
            self._links[:n, i][agree] = t
            return None
        jumped = valid & (d >= self.gate_m) & (t - self._links[i, :n] <= self.link_s)
        if not jumped.any():
            return None
        return self._away_from(jumped), float(d[jumped].max())

    def _check_compiled(self, sensor: str, rows: np.ndarray, t: float, points: np.ndarray,
                        tracked: np.ndarray) -> list[tuple[list[str], float] | None]:
        """``check_many`` in one compiled call (``jit.gate``, without the GIL)."""
        n = len(self._index)
        jumped, dmax, d = jit.gate(rows, t, points, tracked, self._t, self._x, self._m, self._v,
                                self._owner, self._trusted, self._links, self._sensors[sensor],
                                n, self.min_joints, self.agree_m, self.gate_m, self.link_s)
        self._note_apart(sensor, d)
        out: list[tuple[list[str], float] | None] = [None] * len(rows)
        for r in np.flatnonzero(dmax >= 0.0):
            out[r] = (self._away_from(jumped[r]), float(dmax[r]))
        return out

    def check_frames(self, sensor: str, users: tuple[int, ...], t: float, joints: np.ndarray,
                     conf: np.ndarray, matrix: np.ndarray,
                     ) -> list[tuple[int, tuple[list[str], float]]]:
        """``check_many`` of one datagram's skeletons as decoded, in one compiled call
        (only while ``jit.ready()``): joints (k, J, 3) and conf (k, J) C-contiguous
        float64 in the sensor's space, ``matrix`` (4, 4) its sensor -> stage transform,
        ``users`` their (distinct) user ids. The torso joints the sensor tracks (conf >= 1)
        are placed on stage and judged; a skeleton that tracks none of them is not
        recorded. Returns (index in ``users``, result) for each view that jumped, in order
        (``check``'s result); most datagrams: none.

        The same records, links and ``apart`` as the calibrator's numpy preparation
        followed by ``check_many`` (tests/test_jit.py), without its array copies and its
        Python steps per skeleton (issue 10, stop 48: a paced 6 x 6 datagram's jump check
        took 106 us that way, of which 45 the gate; 31 us this way)."""
        key = (sensor, users)
        rows = self._rows.get(key)
        if rows is None:
            if len(self._rows) > 256:      # arbitrary user ids must not grow it for good
                self._rows.clear()
            rows = self._rows[key] = np.array([self._row(sensor, u) for u in users],
                                              dtype=np.int64)
        k, cap = len(users), len(self._t)
        scratch = self._scratch
        if not scratch or len(scratch[2]) < k or scratch[4].shape[1] != cap:
            rows_k = max(k, 16)
            scratch = self._scratch = (
                np.empty((rows_k, self.points, 3)), np.empty((rows_k, self.points), bool),
                np.empty(rows_k, np.int64), np.empty((rows_k, cap), bool),
                np.empty((rows_k, cap)), np.empty((rows_k, cap), bool), np.empty(rows_k),
                np.empty(3))
        n = len(self._index)
        jit.gate_frames(rows, t, joints, conf, _TORSO, matrix, scratch, self._t, self._x,
                        self._m, self._v, self._owner, self._trusted, self._links,
                        self._sensors[sensor], n, self.min_joints, self.agree_m, self.gate_m,
                        self.link_s)
        found = scratch[7]
        closest = found[2]
        if closest < self.same_m and closest > self.apart.get(sensor, 0.0):
            self.apart[sensor] = float(closest)
        if not found[1]:
            return []
        keep, jumped, dmax = scratch[2], scratch[5], scratch[6]
        return [(int(keep[r]), (self._away_from(jumped[r, :n]), float(dmax[r])))
                for r in range(int(found[0])) if dmax[r] >= 0.0]

    def check_many(self, sensor: str, users: list[int], t: float, points: np.ndarray,
                   tracked: np.ndarray) -> list[tuple[list[str], float] | None]:
        """``check`` for several views of one sensor at one time t (one datagram's
        skeletons: distinct users), points (k, P, 3), tracked (k, P); one result per view.

        The same as checking them one after another: a view is never compared with views
        of its own sensor, so no view of the group reads what another one writes (only
        a caller that stops at the first jump, as the calibrator does once the sensor is
        left out, sees the later views' positions recorded all the same: they belong to
        a sensor nobody is compared against until it is trusted again)."""
        rows = [self._row(sensor, user) for user in users]
        rows_a = np.array(rows)
        tracked = np.asarray(tracked, bool)
        if jit.ready():
            return self._check_compiled(sensor, rows_a, t, points, tracked)
        self._record(rows_a, t, points, tracked)
        out: list[tuple[list[str], float] | None] = [None] * len(rows)
        found = self._distances(sensor, t, self._x[rows_a], tracked)  # untracked joints: 0
        if found is None:
            return out
        valid, d = found
        self._note_apart(sensor, np.where(valid, d, INF))
        n = len(self._index)
        agree = valid & (d <= self.agree_m)                                 # (k, n)
        agreed = agree.any(axis=1)
        jumped = (valid & (d >= self.gate_m) & ~agreed[:, None]
                  & (t - self._links[rows_a, :n] <= self.link_s))
        for r, i in enumerate(rows):
            if agreed[r]:
                self._links[i, :n][agree[r]] = t
                self._links[:n, i][agree[r]] = t
            elif jumped[r].any():
                out[r] = (self._away_from(jumped[r]), float(d[r][jumped[r]].max()))
        return out


class CopyDetector:
    """Two sensors sending bit-identical skeletons: one is a copy (a real dataset defect).

    Real sensors never agree to the last bit, so ``frames`` identical frames
    within ``within_s`` of each other mean a copied stream, which would
    otherwise look like a perfect calibration. Frames with fewer than three
    tracked joints are ignored (an empty skeleton is not evidence).
    """

    def __init__(self, frames: int = 5, within_s: float = 2.0, forget_s: float = 3.0,
                 memory: int = 4096) -> None:
        self.frames, self.within_s, self.forget_s, self.memory = frames, within_s, forget_s, memory
        self._seen: OrderedDict[int, tuple[str, float]] = OrderedDict()
        self.pairs: dict[tuple[str, str], list] = {}   # (a, b) sorted -> [count, last time]

    def check(self, sensor: str, t: float, joints: np.ndarray, conf: np.ndarray,
              ) -> tuple[str, str] | None:
        """The (a, b) pair at the moment it reaches ``frames`` identical frames, else None."""
        key = hash((joints.tobytes(), conf.tobytes()))
        prev = self._seen.get(key)
        if prev is not None and prev[0] != sensor and t - prev[1] <= self.within_s:
            # (counted only here: the count of every frame was the check's largest cost)
            if np.count_nonzero(conf > 0) < 3:
                return None
            pair = (prev[0], sensor) if prev[0] < sensor else (sensor, prev[0])
            entry = self.pairs.setdefault(pair, [0, t])
            entry[0] += 1
            entry[1] = t
            return pair if entry[0] == self.frames else None
        self._seen[key] = (sensor, t)
        if len(self._seen) > self.memory:
            self._seen.popitem(last=False)
        return None

    def expired(self, now: float) -> list[tuple[str, str]]:
        """Pairs with no identical frame for ``forget_s`` (forgotten, so they may be flagged anew)."""
        gone = [p for p, (_, last) in self.pairs.items() if now - last > self.forget_s]
        for p in gone:
            del self.pairs[p]
        return gone
