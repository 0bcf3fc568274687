"""How live sensors agree: joint distances between every two sensors that see one person.

Per person (as the engine associated the views), every trusted view is
resampled on a common 30 Hz grid of new instants, and every PAIR of sensors
that see that person is compared joint by joint on the body's core (``CORE``;
both joints seen; weight: the product of the confidences). The distances, not a mean square, are
kept: the monitor judges them by their weighted median (see ``fitness``), and
pairs rather than "one sensor against the average of the others" keep one
moved sensor from dragging everybody's score down with it (the average it is
compared against would contain the moved sensor's joints), which is what
lets the monitor tell WHICH sensor disagrees with the rest.

A suspect sensor is placed with its last good transform and compared with
the trusted views of the person its view matches (nearest torso within
``match_m``): that is how a glitch (it fits again) is told from a move.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..joints import JOINT_INDEX, N_JOINTS
from .live import View, torso_centre
from .pairs import read_between, resample

#: (sensor a, sensor b) -> (distances (n,) m, weights (n,)); a < b for trusted pairs
Distances = dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]
#: (sensor a, sensor b) -> their distances' weighted histogram (``histogram``)
Histograms = dict[tuple[str, str], np.ndarray]

#: distances are kept as weighted histograms of BIN_M wide bins up to RANGE_M (beyond: the
#: last bin), so pooling any set of pairs over the judge's window is a sum, not a sort
BIN_M = 0.001
RANGE_M = 2.0
N_BINS = int(RANGE_M / BIN_M) + 1

#: np.triu_indices(n, 1) for the usual numbers of views of one person
_TRIU = [np.triu_indices(n, 1) for n in range(13)]


def _bins(d: np.ndarray) -> np.ndarray:
    return np.minimum((d / BIN_M).astype(int), N_BINS - 1)


def histogram(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted histogram (``N_BINS``,) of distances ``d`` (m)."""
    return np.bincount(_bins(d), weights=w, minlength=N_BINS)


#: the joints the monitor judges by: the body's rigid core (spine, neck, head, shoulders,
#: hips). A moved sensor moves them all; a view that turns side-on or has a person turn
#: away swaps and guesses LIMBS (real Kinects do, and so does the simulator's model), which
#: made healthy sensors look wrong for a second at a time when every joint was judged
CORE = np.zeros(N_JOINTS, dtype=bool)
CORE[[JOINT_INDEX[n] for n in ("SpineBase", "SpineMid", "Neck", "Head", "SpineShoulder",
                               "ShoulderLeft", "ShoulderRight", "HipLeft", "HipRight")]] = True


def grid(t0: float, t1: float, fps: float = 30.0) -> np.ndarray:
    """Instants k / fps in (t0, t1]."""
    first, last = int(np.floor(t0 * fps)) + 1, int(np.floor(t1 * fps))
    return np.arange(first, last + 1) / fps


@dataclass
class Sampled:
    """Views of one person on the grid: joints (S, G, 25, 3), conf (S, G, 25)."""

    sensors: list[str]
    joints: np.ndarray
    conf: np.ndarray

    @classmethod
    def of(cls, views: list[View], at: np.ndarray, placed: list[np.ndarray] | None = None,
           ) -> "Sampled":
        js, cs, names = [], [], []
        for k, v in enumerate(views):
            stage = v.stage if placed is None else placed[k]
            rows = np.isfinite(stage).all(axis=(1, 2))
            if not rows.any():
                continue
            j, c, _ = resample(v.t[rows], stage[rows], v.conf[rows], at, max_gap=0.1,
                               max_dt=0.05)
            js.append(j)
            cs.append(c)
            names.append(v.sensor)
        if not js:
            return cls([], np.zeros((0, len(at), N_JOINTS, 3)), np.zeros((0, len(at), N_JOINTS)))
        return cls(names, np.array(js), np.array(cs))

    @classmethod
    def of_many(cls, groups: list[list[View]], at: np.ndarray) -> list["Sampled"]:
        """``[Sampled.of(views, at) for views in groups]``, the same arrays to the bit, with
        one resampling pass over every view of every group (a poll's persons)."""
        flat = [v for views in groups for v in views]
        streams, owner = [], []
        for g, views in enumerate(groups):
            for v in views:
                rows = np.isfinite(v.stage).all(axis=(1, 2))
                if rows.all():
                    streams.append((v.t, v.stage, v.conf))
                elif rows.any():
                    streams.append((v.t[rows], v.stage[rows], v.conf[rows]))
                else:
                    continue
                owner.append((g, v.sensor))
        if not flat or not len(at) or not streams:
            return [cls.of(views, at) for views in groups]
        joints, conf = resample_many(streams, at, max_gap=0.1, max_dt=0.05)
        out = []
        first = 0
        for g in range(len(groups)):
            last = first
            while last < len(owner) and owner[last][0] == g:
                last += 1
            if last == first:
                out.append(cls([], np.zeros((0, len(at), N_JOINTS, 3)),
                               np.zeros((0, len(at), N_JOINTS))))
            else:
                out.append(cls([name for _, name in owner[first:last]], joints[first:last],
                               conf[first:last]))
            first = last
        return out

    @staticmethod
    def histograms(persons: list["Sampled"]) -> Histograms:
        """The weighted histogram of the joint distances of every two views of each person
        (both joints seen; weight: the product of the confidences), keyed (a, b), a < b,
        pooled over the persons: ``histogram`` of each pair's distances and weights laid end
        to end person by person, joint by joint, the same numbers to the bit (a bin's
        weights are summed in that order), in one pass of array operations."""
        keys: dict[tuple[str, str], int] = {}
        firsts, seconds, own, at = [], [], [], 0
        for p in persons:
            n = len(p.sensors)
            first, second = _TRIU[n] if n < len(_TRIU) else np.triu_indices(n, 1)
            for a, b in zip(first, second):        # the pairs, in the order (0, 1), (0, 2)...
                own.append(keys.setdefault(tuple(sorted((p.sensors[a], p.sensors[b]))),
                                           len(keys)))
            firsts.append(first + at)
            seconds.append(second + at)
            at += n
        if not own:
            return {}
        first, second = np.concatenate(firsts), np.concatenate(seconds)
        joints = np.concatenate([p.joints for p in persons])
        conf = np.concatenate([p.conf for p in persons])
        w = conf[first] * conf[second] * CORE                                # (pairs, G, 25)
        keep = w > 0
        d = np.linalg.norm(joints[first] - joints[second], axis=-1)
        owner = np.broadcast_to(np.array(own)[:, None, None], w.shape)[keep]
        flat = np.bincount(owner * N_BINS + _bins(d[keep]), weights=w[keep],
                           minlength=len(keys) * N_BINS).reshape(len(keys), N_BINS)
        # in the order each pair first had a joint both saw (the order its distances came
        # in, which decides the order the judge sums pairs in); none: no entry
        found, where = np.unique(owner, return_index=True)
        names = list(keys)
        return {names[k]: flat[k] for k in found[np.argsort(where)]}

    def centre(self) -> np.ndarray:
        """(G, 3) the person's torso centre on the grid, averaged over the views (NaN: none)."""
        c = torso_centre(self.joints, self.conf)       # (S, G, 3)
        seen = np.isfinite(c[..., 0])
        n = seen.sum(axis=0)
        total = np.where(seen[..., None], c, 0.0).sum(axis=0)
        out = total / np.maximum(n, 1)[:, None]
        out[n == 0] = np.nan
        return out


def resample_many(streams: list[tuple[np.ndarray, np.ndarray, np.ndarray]], at: np.ndarray,
                  max_gap: float, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``pairs.resample`` of every (times (n,), joints (n, J, 3), conf (n, J)) stream (none
    empty) at the instants ``at`` (m,), stacked: (joints (V, m, J, 3), conf (V, m, J)), the
    same numbers to the bit, with one pass of array operations for all of them."""
    sizes = np.array([len(t) for t, _, _ in streams])
    offset = np.concatenate([[0], np.cumsum(sizes)[:-1]])[:, None]
    times = np.concatenate([t for t, _, _ in streams])
    joints = np.concatenate([j for _, j, _ in streams])
    conf = np.concatenate([c for _, _, c in streams])
    idx = np.array([np.searchsorted(t, at) for t, _, _ in streams])     # (V, m), per stream
    n = sizes[:, None]
    i0 = np.maximum(idx - 1, 0) + offset
    i1 = np.minimum(idx, n - 1) + offset
    when = np.broadcast_to(at, idx.shape)
    out_j, out_c, _ = read_between(times, joints, conf, when, idx, n, i0, i1, max_gap, max_dt)
    return out_j, out_c


def _sensor_of(view: View) -> str:
    return view.sensor


def _add(out: Distances, key: tuple[str, str], d: np.ndarray, w: np.ndarray) -> None:
    if key in out:
        d0, w0 = out[key]
        d, w = np.concatenate([d0, d]), np.concatenate([w0, w])
    out[key] = (d, w)


def distances(views: dict[str, list[View]], states: dict, at: np.ndarray, match_m: float,
              ) -> tuple[Histograms, Distances]:
    """Joint distances on the grid instants ``at``: (trusted pairs, binned; suspects).

    states: sensor -> (state, transform, last good transform, duplicate_of).
    Trusted ("ok") views are grouped by the person the engine bound them to;
    every two trusted sensors that see one person give distances, keyed
    (a, b) with a < b. A suspect sensor (not a copy) is placed with its last
    good transform; each of its views is compared with every trusted view of
    the person it matches, keyed (suspect, trusted partner).
    """
    ok = {sid for sid, (state, *_rest) in states.items() if state == "ok"}
    persons: dict[int, list[View]] = {}
    for sid in ok:
        for v in views.get(sid, []):
            if v.person is not None and v.t[-1] > at[0] - 0.1:
                persons.setdefault(v.person, []).append(v)
    groups = [sorted(persons[pid], key=_sensor_of) for pid in sorted(persons)]
    sampled_persons = [sampled for sampled in Sampled.of_many(groups, at) if sampled.sensors]
    trusted = Sampled.histograms(sampled_persons)
    suspects: Distances = {}
    if any(state == "suspect" and last_good is not None and dup is None
           for state, _t, last_good, dup in states.values()):
        sampled_persons = [(sampled, sampled.centre()) for sampled in sampled_persons]
    for sid, (state, _t, last_good, dup) in states.items():
        if state != "suspect" or last_good is None or dup is not None:
            continue
        for v in views.get(sid, []):
            if v.t[-1] <= at[0] - 0.1:
                continue
            placed = v.raw @ last_good[:3, :3].T + last_good[:3, 3]
            mine = Sampled.of([v], at, [placed])
            if not mine.sensors or not sampled_persons:
                continue
            centre = mine.centre()
            best, best_d = None, np.inf
            for sampled, c in sampled_persons:
                gap = np.linalg.norm(centre - c, axis=-1)
                gap = gap[np.isfinite(gap)]
                if len(gap) and float(np.median(gap)) < best_d:
                    best, best_d = sampled, float(np.median(gap))
            if best is None or best_d > match_m:
                continue
            for k, partner in enumerate(best.sensors):
                w = mine.conf[0] * best.conf[k] * CORE
                keep = w > 0
                if keep.any():
                    d = np.linalg.norm(mine.joints[0][keep] - best.joints[k][keep], axis=-1)
                    _add(suspects, (sid, partner), d, w[keep])
    return trusted, suspects
