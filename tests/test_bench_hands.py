"""bench/bench_hands.py's CUSUM reference: the textbook change detector on the reports.

The reference is what the engine's hand voter is judged against, so these tests pin
its arithmetic on report streams worked out by hand: +1 for the new state, -1 for
the reported one, 0 for the third state and for unknown, held at 0 from below, a
change when the sum reaches the threshold.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import bench_hands as bench  # noqa: E402

from stage.joints import HandState  # noqa: E402

O, C, L, U = (int(HandState.OPEN), int(HandState.CLOSED), int(HandState.LASSO),
              int(HandState.UNKNOWN))


def stream(states: list[int], hand: int = 0, period: float = 0.01) -> list[tuple]:
    return [(k * period, "kinect-a", hand, s) for k, s in enumerate(states)]


def test_the_first_known_state_goes_at_once_and_is_no_change():
    assert bench.cusum(stream([U, U, C, C]), 3) == []


def test_a_change_fires_on_the_report_that_brings_the_sum_to_the_threshold():
    changes = bench.cusum(stream([O, C, C, O, C, C]), 3)
    # sums for closed: 1, 2, 1, 2, 3 -> the sixth report (t = 0.05)
    assert changes == [(0.05, 0, C)]


def test_reports_of_the_reported_state_hold_the_sum_at_zero_from_below():
    # closed: 1, then 0, 0, 0 (held, not -3), then 1, 2 -> no change at threshold 3
    assert bench.cusum(stream([O, C, O, O, O, C, C]), 3) == []
    assert bench.cusum(stream([O, C, O, O, O, C, C, C]), 3) == [(0.07, 0, C)]


def test_the_third_state_and_unknown_are_no_evidence_either_way():
    # closed: 1, 1 (lasso), 1 (unknown), 2, 3
    assert bench.cusum(stream([O, C, L, U, C, C]), 3) == [(0.05, 0, C)]


def test_after_a_change_the_sums_start_again_from_the_new_state():
    changes = bench.cusum(stream([O, C, C, O, O, O]), 2)
    # closed at t = 0.02; open then counts from 0: 1, 2 -> back to open at t = 0.04
    assert changes == [(0.02, 0, C), (0.04, 0, O)]


def test_hands_are_counted_apart():
    reports = sorted(stream([O, C, C], hand=0) + stream([O, O, O], hand=1))
    assert bench.cusum(reports, 2) == [(0.02, 0, C)]


def test_runs_and_the_real_take_figures_on_a_stream_worked_out_by_hand():
    f = 1 / bench.NTU_FPS
    # the sensor: open x4, unknown x2, open x2, closed x1, unknown x3 (frames 0-11)
    states = [O] * 4 + [U] * 2 + [O] * 2 + [C] + [U] * 3
    raw = bench.runs([k * f for k in range(12)], states, 12 * f)
    assert [(s, round(start / f), round(d / f), done) for s, start, d, done in raw] == \
        [(O, 0, 4, True), (U, 4, 2, True), (O, 6, 2, True), (C, 8, 1, True), (U, 9, 3, False)]
    # the engine: open from 0, carried across the gap, closed at frame 8 for 4 frames, unknown
    fused = bench.runs([0.0, 8 * f, 12 * f], [O, C, U], 14 * f)
    figures = bench.hand_figures(raw, fused)
    assert figures == {"raw_changes": 4, "fused_changes": 2,
                       "inner_runs": 3, "inner_runs_even": 2,     # 2, 2 and 1 frames
                       "raw_blips": 2, "fused_blips": 0,          # open x2 and closed x1
                       "gaps": 1, "gaps_bridged": 1}
    # an engine that said unknown inside the gap did not carry the state
    fused = bench.runs([0.0, 5 * f, 6 * f], [O, U, O], 14 * f)
    assert bench.hand_figures(raw, fused)["gaps_bridged"] == 0


def test_a_reading_repeated_over_two_frames_counts_once():
    # every state twice, as a Kinect v2 repeats a reading: the same change as above needs
    # twice the reports (step 0.5), and fires on the same reading
    once = bench.cusum(stream([O, C, C, O, C, C]), 3)
    twice = bench.cusum(stream([O, O, C, C, C, C, O, O, C, C, C, C]), 3, step=0.5)
    assert once == [(0.05, 0, C)] and twice == [(0.11, 0, C)]


def test_each_sensor_counts_by_its_own_cadence():
    # a Kinect (half a reading a report) and a webcam (a whole one): closed's sum goes
    # 0.5, 1 (the Kinect's two reports), 2 (the webcam's first): the case at threshold 2;
    # with every report taken for half a reading it needs the webcam's second as well
    reports = [(0.00, "kin", 0, O), (0.01, "cam", 0, O), (0.02, "kin", 0, C),
               (0.03, "kin", 0, C), (0.04, "cam", 0, C), (0.05, "cam", 0, C)]
    assert bench.cusum(reports, 2, {"kin": 0.5, "cam": 1.0}) == [(0.04, 0, C)]
    assert bench.cusum(reports, 2, 0.5) == [(0.05, 0, C)]
