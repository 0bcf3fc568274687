"""bench/anticipation_why.py: the classes of false triggers, on hand-made truths and firings.

The anatomy (``bench_anticipation.py --why``) decides where issue 15's extra false
triggers come from; these tests pin what each class means: a contradicted prediction
(a), a second firing for one true crossing (b), measurements crossing where the truth
did not (c), a firing near a true crossing that the match window missed (d), and which
of the forecast's false triggers the no-forecast reference shares.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import anticipation_why as why  # noqa: E402

BEFORE, AFTER, SETTLE, HYST = 0.2, 0.1, 0.8, 0.05
KEY = ("hand", "HandRight")


def series(t: np.ndarray, d: np.ndarray) -> tuple:
    return t, {KEY: d}


def one_rise() -> tuple[np.ndarray, np.ndarray, list[float]]:
    """The truth: a hand 20 cm under the head, above it (+10 cm) from 2.0 s to 3.0 s, then
    under again: one true crossing at 2.0 s (sampled at 100 Hz)."""
    t = np.arange(0.0, 6.0, 0.01)
    d = np.where((t >= 2.0) & (t < 3.0), 0.10, -0.20)
    return t, d, [2.0]


def test_match_takes_the_first_free_crossing_in_the_window():
    firings = [("hand", "HandRight", x, 0.0) for x in (0.5, 1.95, 2.05, 2.5, 3.9)]
    # 0.5: before the settle time; 1.95: 50 ms before the crossing (matched); 2.05: the
    # crossing is taken; 2.5: too late for it; 3.9: matches the second crossing 100 ms later
    assert why.match(firings, [2.0, 4.0], BEFORE, AFTER, SETTLE) == [-1, 0, None, None, 1]


def test_each_class():
    t, d, crossings = one_rise()
    truth = {KEY: crossings}
    firings = [
        ("hand", "HandRight", 2.06, 0.0),    # matched (60 ms late)
        ("hand", "HandRight", 2.50, 0.0),    # b: the truth has not fallen back since 2.0
        ("hand", "HandRight", 4.00, 0.05),   # a: predicted, contradicted, truth far under
        ("hand", "HandRight", 5.00, 0.0),    # c: measured where the truth did not cross
    ]
    out = why.classify(firings, {("hand", "HandRight", 4.00)}, truth, series(t, d), HYST,
                       BEFORE, AFTER, SETTLE)
    assert [(r["t"], r["class"]) for r in out] == [(2.5, "b"), (4.0, "a"), (5.0, "c")]
    b, a, c = out
    assert abs(b["crossing_dt"] - 0.5) < 1e-9
    assert a["anticipated"] and a["contradicted"] and a["crossing_dt"] is None
    assert not c["anticipated"] and not c["contradicted"]
    assert abs(c["margin_m"] + 0.20) < 1e-9 and abs(c["peak_m"] + 0.20) < 1e-9
    assert abs(b["margin_m"] - 0.10) < 1e-9 and abs(b["speed_m_s"]) < 1e-9


def test_a_second_rise_is_not_a_second_firing():
    """Once the truth has fallen back behind the border by the hysteresis, a firing is
    not a second firing for the old crossing (it is noise if nothing new was crossed)."""
    t, d, crossings = one_rise()
    out = why.classify([("hand", "HandRight", 2.05, 0.0), ("hand", "HandRight", 3.4, 0.0)],
                       set(), {KEY: crossings}, series(t, d), HYST, BEFORE, AFTER, SETTLE)
    assert [r["class"] for r in out] == ["c"]


def test_a_firing_whose_crossing_a_later_firing_took_is_a_second_firing():
    """150 ms before the crossing (outside the window), and the measured firing 60 ms after
    it took the crossing: the same movement fired twice (b), not a window miss (d)."""
    t, d, crossings = one_rise()
    out = why.classify([("hand", "HandRight", 1.85, 0.05), ("hand", "HandRight", 2.06, 0.0)],
                       set(), {KEY: crossings}, series(t, d), HYST, BEFORE, AFTER, SETTLE)
    assert [(r["t"], r["class"]) for r in out] == [(1.85, "b")]
    assert abs(out[0]["crossing_dt"] + 0.15) < 1e-9


def test_window_misses():
    """A firing 150 ms before a true crossing nothing else took is outside the window
    (false) but belongs to it: class d, with its distance to the crossing."""
    t, d, crossings = one_rise()
    out = why.classify([("hand", "HandRight", 1.85, 0.05)], set(), {KEY: crossings},
                       series(t, d), HYST, BEFORE, AFTER, SETTLE)
    assert [r["class"] for r in out] == ["d"]
    assert abs(out[0]["crossing_dt"] + 0.15) < 1e-9
    # the truth's peak from 300 ms before to 200 ms after the firing
    assert abs(out[0]["peak_m"] - 0.10) < 1e-9


def test_measured_peak():
    t, d, crossings = one_rise()
    mt = np.array([4.8, 4.9, 5.0, 5.1, 5.3])
    md = np.array([-0.1, 0.02, 0.03, np.nan, 0.5])    # 5.3 is after the 200 ms window
    out = why.classify([("hand", "HandRight", 5.0, 0.0)], set(), {KEY: crossings},
                       series(t, d), HYST, BEFORE, AFTER, SETTLE, (mt, {KEY: md}))
    assert abs(out[0]["measured_peak_m"] - 0.03) < 1e-9


def test_shared_pairs_each_reference_trigger_once():
    ref = [{"trigger": "hand", "joint": "HandRight", "t": 5.0}]
    mine = [{"trigger": "hand", "joint": "HandRight", "t": 5.1},
            {"trigger": "hand", "joint": "HandRight", "t": 5.2},     # the reference's is taken
            {"trigger": "hand", "joint": "HandLeft", "t": 5.0}]      # another joint
    why.mark_shared(mine, ref)
    assert [r["shared"] for r in mine] == [True, False, False]
