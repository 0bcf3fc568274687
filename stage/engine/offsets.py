"""Each view's steady offset from the person's other views, learned and taken off its joints.

Two real sensors never put a joint at quite the same place. A depth camera fits the body's
surface it sees, so a sensor in front and one at the side place the spine some centimetres
apart, and a calibration leaves a residual of its own. On N-UCLA's three Kinect v1 views of
one person, calibrated by the brute-force optimum, the spine bases of two views lie 6-13 cm
apart at the median (issue 10, stop 44). Every sensor frame is fused at once, in capture
order, so with sensors at their own phases the fused joint is pulled towards one view,
then the other: the stream swings by a share of that distance at the sensors' rate, which
smoothing only damps, and which a mapping hears as jitter.

So each view (sensor and user) of a person keeps, per joint and axis, an exponential mean of
its innovation against the person (the view's tracked joints minus the person's joints
predicted to the frame's time), with a time constant of ``fusion.view_offset_s``. A frame's
joints are corrected by its view's offset minus the mean offset of the person's views, both
as learned from the frames before it:

- views are moved towards each other and the person stays where the views' mean puts it:
  a correction is relative, so one view alone is never corrected, and what every view
  shares (the filter's own lag behind a moving joint shows in every innovation) cancels;
- only tracked joints (confidence above the inferred level) that the person has a state
  for, within ``CAP_M`` of it, teach: an inferred guess, a swapped limb or a jump is not a
  steady offset. Every joint the view reports is corrected.

The offsets are the person's (``Person.offsets``), a row per view in the rows of
``Person.recent`` (the views it remembers: a view's first frame with a person is not
corrected, a view that leaves takes its offset with it, and a person down to one view
forgets them all, so that the next view to join starts from nothing on both sides). The
learning rate of a frame is ``1 - exp(-gap / view_offset_s)``, the gap since the view's
previous frame (at most ``GAP_MAX_S``), so it does not depend on the sensor's frame rate.

``learn`` is the reference (and the code run without the compiled kernels); ``jit._offsets``
is the same operations in the same order, compiled. For the persons the native core holds,
the offsets are rows of the core's (``NativeCore.offsets``) and a batch's frames learn
theirs in one call before the fold (``jit._native_offsets``, ``People._offsets_held``), in
the same order, with the same floats.
"""

from __future__ import annotations

import numpy as np

#: an innovation longer than this (m) teaches nothing: a swap, a jump, a bad fit. On N-UCLA's
#: real views (``bench/fusion_real.py --three``) a joint two views agree on and a third puts
#: over 30 cm away stayed 21-26 mm from the pair at the median with 0.15 m, 34-39 mm with
#: 0.3 m and 81 mm with 1 m: what a view that two others contradict teaches pulls its
#: person towards it (issue 10, stop 45)
CAP_M = 0.15
#: the longest gap (s) a frame's learning rate counts (a view back after a pause)
GAP_MAX_S = 0.1


def learn(z: np.ndarray, conf: np.ndarray, joints: np.ndarray, velocity: np.ndarray,
          known: np.ndarray, dt: float, offsets: np.ndarray, live: np.ndarray, row: int,
          alpha: float, tracked: float) -> None:
    """In place: ``z`` (25, 3) a view's stage-space joints with confidences ``conf``, each
    reported joint corrected by its offset (``offsets[row]``) minus the mean of the live
    views' offsets (the rows where ``live``, the person's ``recent_t``, is not -inf; summed
    in row order); then ``offsets[row]`` learns, at rate ``alpha``, from the uncorrected
    joints' innovations against the person's ``joints`` + ``velocity`` * ``dt`` (``known``:
    the joints the person has a state for)."""
    rows = np.flatnonzero(live[:len(offsets)] != -np.inf)
    mean = offsets[rows[0]].copy()
    for k in rows[1:]:
        mean += offsets[k]
    mean /= len(rows)
    offset = offsets[row]
    d = z - (joints + velocity * dt)
    reported = conf > 0.0
    z[reported] -= offset[reported] - mean[reported]
    teach = (conf > tracked) & known & ((d * d).sum(axis=1) <= CAP_M * CAP_M)
    offset[teach] += alpha * (d[teach] - offset[teach])


__all__ = ["CAP_M", "GAP_MAX_S", "learn"]
