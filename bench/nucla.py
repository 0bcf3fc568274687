"""N-UCLA (Northwestern-UCLA Multiview Action 3D) skeleton files for the benchmarks.

The files (``aXX_sYY_eZZ_v0N.json``, the ``all_sqe`` release) are research-use
data and never committed: docs/datasets.md says how to fetch them into
``bench/data/nucla/`` (git-ignored). Subjects s02, s03, s08 and s09 are held
out to evaluate the calibration work; this module selects files by their
NAMES before anything is read, and yields only the development subjects
unless asked for the held-out ones explicitly.
"""

from __future__ import annotations

import os
import re
from collections import defaultdict

#: subjects used to develop and tune (issue 11)
DEVELOPMENT = ("s01", "s04", "s05", "s06", "s07", "s10")
#: subjects kept aside to evaluate; never read unless ``held_out=True``
HELD_OUT = ("s02", "s03", "s08", "s09")

_NAME = re.compile(r"^(?P<sample>a\d+_(?P<subject>s\d+)_e\d+)_v0(?P<view>\d)\.json$")


def triples(folder: str, held_out: bool = False) -> list[tuple[str, list[str]]]:
    """Complete triples (all three views present) as (sample, [v1, v2, v3 paths]), sorted.

    Only file NAMES are looked at here; the selection is made before any file
    is opened. ``held_out``: the held-out subjects INSTEAD of the development
    ones (for the final evaluation only).
    """
    wanted = HELD_OUT if held_out else DEVELOPMENT
    views: dict[str, dict[int, str]] = defaultdict(dict)
    for name in sorted(os.listdir(folder)):
        m = _NAME.match(name)
        if m is None or m.group("subject") not in wanted:
            continue
        views[m.group("sample")][int(m.group("view"))] = os.path.join(folder, name)
    return [(s, [v[1], v[2], v[3]]) for s, v in sorted(views.items()) if set(v) >= {1, 2, 3}]
