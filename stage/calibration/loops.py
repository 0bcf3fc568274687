"""Sources that loop a take (``stage replay --loop``): the period, and one pass of it.

A real sensor never sends two bit-identical skeletons of a person; a replay of a
recording in a loop sends each frame once per pass, restarting every view of the
take at once. The live calibrator uses ``loop_period`` to know such a source and
``fold_loops`` to search its lag on one pass of the take, as offline.
"""

from __future__ import annotations

import numpy as np

from .streams import Stream


def fold_loops(a: Stream, lag_a: float, b: Stream, lag_b: float, period: float,
               ) -> tuple[Stream, Stream] | None:
    """Two looped streams (on stage time; their clocks run ``lag_a``, ``lag_b`` from it)
    folded onto one pass of the take each, or None.

    ``stage replay --loop`` restarts every view of a take at once, on the senders' own
    clocks. Searched on the looped streams, a lag pairs the end of one pass with the start
    of the next (on N-UCLA a 21-frame view read -11.3 frames where one pass says -13.5, the
    brute force -12.8). Each view's take fills an arc of the loop's phase (on its own
    clock); the restart lies in the gap of every view's arc, so the middle of the widest
    stretch common to the gaps is taken as the restart, each frame is folded into the pass
    that starts there, and repeats are dropped."""
    def gap(raw: np.ndarray) -> tuple[float, float]:
        ph = np.unique(np.round(np.mod(raw, period), 4))
        if len(ph) < 2:
            return 0.0, period
        steps = np.diff(np.r_[ph, ph[0] + period])
        k = int(np.argmax(steps))
        return float(ph[k]), float(ph[k] + steps[k])     # the gap (start, end), circular
    ga, gb = gap(a.t + lag_a), gap(b.t + lag_b)
    # the common stretch of two circular arcs: try each gap shifted by a period
    best = None
    for shift in (-period, 0.0, period):
        lo, hi = max(ga[0], gb[0] + shift), min(ga[1], gb[1] + shift)
        if hi > lo and (best is None or hi - lo > best[1] - best[0]):
            best = (lo, hi)
    if best is None:
        return None
    restart = 0.5 * (best[0] + best[1])

    def fold(s: Stream, lag: float) -> Stream:
        raw = s.t + lag
        folded = restart + np.mod(raw - restart, period)
        # one frame per skeleton, its newest pass: repeats are bit-identical, while their
        # folded times differ by the period's error (live timetags put a 1.5 s loop at
        # 1.4989 s) and, deduplicated by time, left near-copies 1 ms apart that made the
        # lag search's frame step 1 ms (thousands of lags: the worker stalled for good)
        newest: dict[bytes, int] = {}
        for k, row in enumerate(s.joints):
            newest[np.ascontiguousarray(row).tobytes()] = k
        keep = np.array(sorted(newest.values(), key=lambda k: folded[k]), dtype=int)
        return Stream(s.sensor, folded[keep] - lag, np.zeros(len(keep), int), s.joints[keep],
                      s.conf[keep], s.floor)
    return fold(a, lag_a), fold(b, lag_b)


def loop_period(t: np.ndarray, joints: np.ndarray, min_repeats: int = 10) -> float | None:
    """The period (s) of a source that sends the same frames over and over, or None.

    t (n,) s; joints (n, 25, 3). A real sensor never sends two bit-identical skeletons
    of a person (its noise alone differs); a replay of a recording in a loop sends each
    frame once per loop. Each frame that repeats an earlier one gives the time since it;
    a loop is when at least ``min_repeats`` frames repeat and 80 % of them do so one
    period apart (within a frame), a period of at least 0.2 s (not a frozen frame).
    """
    seen: dict[bytes, float] = {}
    gaps = []
    for ti, row in zip(t, joints):
        key = np.ascontiguousarray(row).tobytes()
        if key in seen:
            gaps.append(ti - seen[key])
        seen[key] = float(ti)
    if len(gaps) < min_repeats:
        return None
    period = float(np.median(gaps))
    if period < 0.2 or np.mean(np.abs(np.asarray(gaps) - period) <= 1.0 / 30) < 0.8:
        return None
    return period


__all__ = ["fold_loops", "loop_period"]
