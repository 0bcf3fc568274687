"""bench_anticipation.py --ci: the goal's figures over resamples of the seeds.

Hand-made results (no simulation): per seed and take, each setting's matched delays and
false triggers, as ``run`` returns them. The resamples draw whole seeds, so identical
seeds give the pooled figures exactly, and a goal met by some seeds only is met in a
share of the resamples that follows how many seeds meet it.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import bench_anticipation as bench  # noqa: E402

NONE, ANT = ("none", 0.0), ("anticipate", 0.05)
SETTINGS = [NONE, ANT]


def result(seed: int, take: str, none_ms: float, ant_ms: float, none_false: int,
           ant_false: int) -> dict:
    def score(ms: float, false: int) -> dict:
        empty = {"true": 0, "delays": [], "false": 0, "missed": 0}
        return {"score": {"hand": {"true": 3, "delays": [ms / 1000] * 3, "false": false,
                                   "missed": 0}, "foot": empty, "zone": empty}}
    return {"seed": seed, "take": take, NONE: score(none_ms, none_false),
            ANT: score(ant_ms, ant_false)}


def test_identical_seeds_give_the_pooled_figures_in_every_resample():
    results = [result(s, t, 80.0, 45.0, 10, 10) for s in range(1, 6) for t in ("a", "b")]
    boot = bench.bootstrap(results, SETTINGS, 50)
    assert list(boot) == [ANT]                       # only the 50 ms settings
    assert boot[ANT]["earlier_ms"] == [35.0, 35.0, 35.0]
    assert boot[ANT]["false_ratio"] == [1.0, 1.0, 1.0] and boot[ANT]["goal_met"] == 1.0


def test_a_goal_met_by_some_seeds_is_met_in_a_share_of_the_resamples():
    # seeds 1-5 are 40 ms earlier with no extra false trigger; seeds 6-10 only 20 ms
    results = [result(s, "a", 80.0, 40.0 if s <= 5 else 60.0, 10, 10) for s in range(1, 11)]
    boot = bench.bootstrap(results, SETTINGS, 400)
    e = boot[ANT]["earlier_ms"]
    assert e[0] == 20.0 and e[2] == 40.0
    assert 0.3 < boot[ANT]["goal_met"] < 0.7
    again = bench.bootstrap(results, SETTINGS, 400)
    assert again == boot                             # seeded: the same figures every run


def test_the_false_ratio_is_the_resample_pooled_count_over_the_reference():
    results = [result(s, "a", 80.0, 40.0, 10, 12) for s in range(1, 4)]
    boot = bench.bootstrap(results, SETTINGS, 20)
    assert boot[ANT]["false_ratio"] == [1.2, 1.2, 1.2] and boot[ANT]["goal_met"] == 0.0
