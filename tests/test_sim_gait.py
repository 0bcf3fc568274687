"""The simulator's planted-feet walker (``GaitClip``, the ``gait`` step of scenarios): a walk
whose step length, width and cadence are known exactly, the truth of the gait tests."""

from __future__ import annotations

import numpy as np
import pytest

from stage.joints import JOINT_INDEX as J
from stage.sensors.sim.gait import GaitClip


def test_the_walkers_feet_stay_where_they_are_put():
    clip = GaitClip(8, 0.7, 0.12, 110.0)
    for p in clip.placements:
        side = p.side
        for dt in (0.0, 0.05, 0.2 * clip.step_time):       # landing and double support
            a = clip.joints(p.t + dt)[J["Ankle" + side]]
            assert (a[0], a[2]) == pytest.approx((p.x, p.z), abs=1e-9)
    z = [p.z for p in clip.placements]
    assert np.diff(z)[1:] == pytest.approx(np.full(6, 0.7))   # each foot a step past the other
    assert z[0] == pytest.approx(0.35)                          # the first step half as long
    assert {p.side for p in clip.placements[::2]} == {"Left"}
    # segment lengths never change (the legs reach their feet)
    for t in np.arange(0.0, clip.duration, 0.05):
        j = clip.joints(t)
        thigh = np.linalg.norm(j[J["KneeLeft"]] - j[J["HipLeft"]])
        shin = np.linalg.norm(j[J["AnkleLeft"]] - j[J["KneeLeft"]])
        assert (thigh, shin) == pytest.approx((clip.props.thigh, clip.props.shin), abs=1e-6)


def test_a_scenario_walks_a_set_gait():
    from stage.sensors.sim import parse_scenario
    from stage.yamlio import loads_marked
    text = """
sensors: {ring: {count: 1}}
performers:
  - name: w
    position: [0, -2]
    timeline:
      - {gait: 6, length: 0.6, width: 0.1, cadence: 100, facing: 90}
"""
    sc = parse_scenario(loads_marked(text, "t.yaml"), "t.yaml")
    p = sc.performers[0]
    ends = p.state(p.length - 0.01)[0]
    # facing 90 degrees: along +x; 0.3 + 5 x 0.6 = 3.3 m, the feet together at the end
    assert ends[J["AnkleLeft"], 0] == pytest.approx(3.3, abs=1e-6)
    assert ends[J["AnkleLeft"], 0] == pytest.approx(ends[J["AnkleRight"], 0], abs=1e-6)
    with pytest.raises(Exception, match="'gait' takes the number of steps"):
        parse_scenario(loads_marked(text.replace("gait: 6", "gait: 0"), "t.yaml"), "t.yaml")
    with pytest.raises(Exception, match="'lead' is the foot that starts"):
        parse_scenario(loads_marked(text.replace("cadence: 100", "lead: both"), "t.yaml"),
                       "t.yaml")
