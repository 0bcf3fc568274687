"""The jump gate: catches a bumped sensor on its first bad frame, before it is fused.

Runs on the engine thread for every frame of a trusted sensor, so it is a
handful of vector operations over all tracked (sensor, user) views: each
view's torso centre in stage space, its velocity, and for every pair of
views the last time they agreed (were within ``agree_m``: the same person
seen by two sensors). A view that now sits ``gate_m`` or more away from
views it agreed with within the last ``link_s`` seconds, and agrees with no
view of any other trusted sensor, has jumped: nobody moves 30 cm in a frame,
so its sensor moved. The sensor whose frame first shows the disagreement is
the one that moved (the others' latest frames were consistent a moment ago).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

INF = float("inf")


class JumpGate:
    def __init__(self, agree_m: float = 0.15, gate_m: float = 0.30, link_s: float = 0.5,
                 capacity: int = 32) -> None:
        self.agree_m, self.gate_m, self.link_s = agree_m, gate_m, link_s
        self._index: dict[tuple[str, int], int] = {}
        self._sensors: dict[str, int] = {}
        self._trusted = np.zeros(8, dtype=bool)
        self._alloc(capacity)

    def _alloc(self, capacity: int) -> None:
        old = getattr(self, "_t", None)
        n = 0 if old is None else len(old)
        t, c, v = np.full(capacity, -INF), np.zeros((capacity, 3)), np.zeros((capacity, 3))
        owner = np.full(capacity, -1)
        links = np.full((capacity, capacity), -INF)
        if old is not None:
            t[:n], c[:n], v[:n], owner[:n] = self._t[:n], self._c[:n], self._v[:n], self._owner[:n]
            links[:n, :n] = self._links[:n, :n]
        self._t, self._c, self._v, self._owner, self._links = t, c, v, owner, links

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

    def check(self, sensor: str, user: int, t: float, centre: np.ndarray,
              ) -> tuple[list[str], float] | None:
        """Record a view's stage-space torso centre (3,) at time t.

        Returns (the sensors it jumped away from, the largest distance m) when
        it disagrees with views it agreed with a moment ago and agrees with
        none; else None.
        """
        i = self._row(sensor, user)
        n = len(self._index)
        dt_self = t - self._t[i]
        if 0 < dt_self <= 0.2:
            v = (centre - self._c[i]) / dt_self
            speed = float(np.sqrt(v @ v))
            self._v[i] = v if speed <= 3.0 else v * (3.0 / speed)  # a jump is not a velocity
        else:
            self._v[i] = 0.0
        self._t[i], self._c[i] = t, centre
        owner = self._owner[:n]
        dt = t - self._t[:n]
        valid = (np.abs(dt) <= 0.1) & self._trusted[owner]
        valid[owner == owner[i]] = False
        if not valid.any():
            return None
        diff = self._c[:n] + self._v[:n] * dt[:, None] - centre
        d = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        agree = valid & (d <= self.agree_m)
        if agree.any():
            self._links[i, :n][agree] = t
            self._links[:n, i][agree] = t
            return None
        jumped = valid & (d >= self.gate_m) & (t - self._links[i, :n] <= self.link_s)
        if not jumped.any():
            return None
        names = {k: s for s, k in self._sensors.items()}
        return sorted({names[k] for k in owner[jumped]}), float(d[jumped].max())

    def check_many(self, sensor: str, users: list[int], t: float, centres: np.ndarray,
                   ) -> list[tuple[list[str], float] | None]:
        """``check`` for several views of one sensor at one time t (one datagram's
        skeletons: distinct users), centres (k, 3); one result per view.

        The same as checking them one after another: a view is never compared with views
        of its own sensor, so no view of the group reads what another one writes (only
        a caller that stops at the first jump, as the calibrator does once the sensor is
        left out, sees the later views' positions recorded all the same: they belong to
        a sensor nobody is compared against until it is trusted again)."""
        rows = [self._row(sensor, user) for user in users]
        rows_a = np.array(rows)
        n = len(self._index)
        dt_self = t - self._t[rows_a]
        moved = (dt_self > 0) & (dt_self <= 0.2)
        v = np.zeros((len(rows), 3))
        if moved.any():
            v[moved] = (centres[moved] - self._c[rows_a[moved]]) / dt_self[moved, None]
            speed = np.sqrt(np.einsum("ij,ij->i", v, v))
            fast = speed > 3.0
            v[fast] *= (3.0 / speed[fast])[:, None]  # a jump is not a velocity
        self._v[rows_a] = v
        self._t[rows_a], self._c[rows_a] = t, centres
        owner = self._owner[:n]
        dt = t - self._t[:n]
        valid = (np.abs(dt) <= 0.1) & self._trusted[owner]
        valid[owner == self._sensors[sensor]] = False
        if not valid.any():
            return [None] * len(rows)
        predicted = self._c[:n] + self._v[:n] * dt[:, None]               # (n, 3)
        diff = predicted[None] - centres[:, None]                          # (k, n, 3)
        d = np.sqrt(np.einsum("kij,kij->ki", diff, diff))
        agree = valid & (d <= self.agree_m)                                 # (k, n)
        agreed = agree.any(axis=1)
        jumped = (valid & (d >= self.gate_m) & ~agreed[:, None]
                  & (t - self._links[rows_a, :n] <= self.link_s))
        out: list[tuple[list[str], float] | None] = [None] * len(rows)
        names = None
        for r, i in enumerate(rows):
            if agreed[r]:
                self._links[i, :n][agree[r]] = t
                self._links[:n, i][agree[r]] = t
            elif jumped[r].any():
                names = names or {k: s for s, k in self._sensors.items()}
                out[r] = (sorted({names[k] for k in owner[jumped[r]]}),
                          float(d[r][jumped[r]].max()))
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
        if (conf > 0).sum() < 3:
            return None
        key = hash((joints.tobytes(), conf.tobytes()))
        prev = self._seen.get(key)
        if prev is not None and prev[0] != sensor and t - prev[1] <= self.within_s:
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
