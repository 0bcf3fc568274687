"""Swapped limbs traded back before fusion (``fusion.unswap_limbs``).

Depth cameras mix up a left and a right limb that overlap in their image; the simulator's
realistic model does it too. When two of three sensors swap the legs at once, the
consistency vote of an instant follows them: on the default rehearsal the fused legs were
20 cm off for up to half a second (bench/bench_healing_sim.py: worst frame 157 mm mean over
the joints before, 43 mm after).
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from stage.engine.fusion import unswap_limbs
from stage.joints import JOINT_INDEX as J, HandState
from stage.sensors import sim as sim_mod
from stage.yamlio import loads_marked
from test_engine import frame, make_engine, send

LEGS = [J[n + s] for n in ("Knee", "Ankle", "Foot") for s in ("Left", "Right")]


def _swap(joints: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    out = joints.copy()
    for n in names:
        out[[J[n + "Left"], J[n + "Right"]]] = joints[[J[n + "Right"], J[n + "Left"]]]
    return out


ARM = ("Elbow", "Wrist", "Hand", "HandTip", "Thumb")
LEG = ("Knee", "Ankle", "Foot")


def _routines():
    """Every 10th frame of the default rehearsal (30 s: walks, arms overhead, a lasso, a
    reach, a crouch, a jump, a turn) and of the demo dancer."""
    text = (resources.files("stage.sensors.sim") / "scenarios" / "default.yaml").read_text()
    sim = sim_mod.Simulator(sim_mod.parse_scenario(loads_marked(text), "d.yaml"), seed=0)
    out = [next(iter(sim.truth(k / 30).values()))[0] for k in range(0, 900, 10)]
    dancer = sim_mod.demo_scenario(1).performers[0]
    out += [dancer.state(k / 30)[0] for k in range(0, 900, 10)]
    return out


def test_true_skeletons_are_never_traded():
    conf = np.ones(25)
    for joints in _routines():
        assert unswap_limbs(joints, conf)[2] == 0


@pytest.mark.parametrize("names, traded", [(LEG, 2), (ARM, 1)])
def test_a_swapped_limb_is_traded_back(names, traded):
    conf = np.ones(25)
    hits = 0
    for joints in _routines():
        fixed, c, n = unswap_limbs(_swap(joints, names), conf)
        if n:
            assert n == traded
            assert np.allclose(fixed, joints)
            hits += 1
    # legs: whenever they are apart along the hips (standing, walking); arms: unless both
    # hang close to the body
    assert hits >= 0.5 * len(_routines())


def test_crossed_wrists_and_an_untracked_girdle_are_left_alone():
    joints = _routines()[0]
    crossed = _swap(joints, ("Wrist", "Hand", "HandTip", "Thumb"))   # elbows stay
    assert unswap_limbs(crossed, np.ones(25))[2] == 0
    swapped = _swap(joints, LEG)
    conf = np.ones(25)
    conf[[J["ShoulderLeft"], J["HipRight"]]] = 0.5              # no girdle tracked
    assert unswap_limbs(swapped, conf)[2] == 0
    conf = np.ones(25)
    conf[J["AnkleLeft"]] = 0.0                                   # a check joint unseen
    assert unswap_limbs(swapped, conf)[2] == 0


@pytest.mark.parametrize("unswap", [True, False])
def test_two_of_three_sensors_swapping_the_legs_do_not_swap_the_fused_legs(unswap):
    truth = _routines()[0]
    engine, clock, out = make_engine(sim_mod.ring_poses(3), unswap_limbs=unswap)
    poses = sim_mod.ring_poses(3)
    fused = []
    engine.listeners.append(lambda f: fused.extend(b.joints.copy() for b in f.bodies.values()))
    for k in range(10):
        clock.set(100.0 + k / 30)
        for i, pose in enumerate(poses):
            seen = truth if i == 0 else _swap(truth, LEG)        # s1 and s2 swap the legs
            cam = pose.observe(seen[None])[0]
            send(engine, frame(f"s{i}", 1, cam), ("10.0.0.1", 5000 + i))
    err = np.linalg.norm(fused[-1][LEGS] - truth[LEGS], axis=1).max()
    if unswap:
        assert err < 0.02
        assert engine.counts["limbs_unswapped"] == 2 * 10
    else:  # the earlier fusion followed the majority (the behaviour this fixes)
        assert err > 0.1


def test_the_rig_file_can_turn_it_off_and_says_so_when_the_value_is_not_a_boolean(tmp_path):
    from stage.errors import ConfigError
    from stage.rig import load_rig
    path = tmp_path / "rig.yaml"
    path.write_text("fusion:\n  unswap_limbs: false\n")
    assert load_rig(str(path)).fusion.unswap_limbs is False
    path.write_text("fusion:\n  unswap_limbs: 1\n")
    with pytest.raises(ConfigError, match="'unswap_limbs' must be true or false"):
        load_rig(str(path))


def _twisted_lunge(joints: np.ndarray, twist_deg: float, step_m: float) -> np.ndarray:
    """The upper body turned ``twist_deg`` about the vertical through SpineMid over a
    lunge: one foot ``step_m`` forward, the other as far back (knees half as far)."""
    out = joints.copy()
    upper = [J[n] for n in J if not any(k in n for k in ("Hip", "Knee", "Ankle", "Foot",
                                                             "SpineBase"))]
    a = np.radians(twist_deg)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    centre = out[J["SpineMid"]]
    out[upper] = (out[upper] - centre) @ rot.T + centre
    lr = joints[J["HipLeft"]] - joints[J["HipRight"]]
    fwd = np.cross(lr / np.linalg.norm(lr), [0.0, 1.0, 0.0])
    for side, sign in (("Right", 1.0), ("Left", -1.0)):
        for name, share in (("Knee", 0.5), ("Ankle", 1.0), ("Foot", 1.0)):
            out[J[name + side]] += sign * share * step_m * fwd
    return out


def test_a_twisted_torso_over_a_lunge_keeps_its_legs():
    """Legs are judged along the hips, not a mean of hips and shoulders: with the shoulders
    turned 45-90 degrees over a 40-60 cm lunge, that mean axis made a correct pair of legs
    look crossed (14 of 78 such poses were traded)."""
    conf = np.ones(25)
    base = _routines()[0]
    for twist in range(-90, 91, 15):
        for step in (0.2, 0.4, 0.6, -0.2, -0.4, -0.6):
            assert unswap_limbs(_twisted_lunge(base, twist, step), conf)[2] == 0, (twist, step)
        swapped = _swap(_twisted_lunge(base, twist, 0.2), LEG)
        assert unswap_limbs(swapped, conf)[2] == 2                    # LEG_TRADED


@pytest.mark.parametrize("unswap", [True, False])
def test_a_sensor_that_swapped_the_arms_has_its_hand_states_traded_back_too(unswap):
    """A sensor that mixes up the arms names each hand's state by the wrong side as well:
    with its arms traded back, its "left" hand state counts for the right hand."""
    truth = _routines()[0]
    engine, clock, out = make_engine(sim_mod.ring_poses(3), unswap_limbs=unswap)
    poses = sim_mod.ring_poses(3)
    for k in range(15):
        clock.set(100.0 + k / 30)
        for i, pose in enumerate(poses):
            swapped = i > 0                                      # s1 and s2 swap the arms
            seen = _swap(truth, ARM) if swapped else truth
            hands = ("closed", "open") if swapped else ("open", "closed")
            cam = pose.observe(seen[None])[0]
            send(engine, frame(f"s{i}", 1, cam, hands=hands), ("10.0.0.1", 5000 + i))
    engine.drain()
    person = next(iter(engine.persons.values()))
    left, right = person.hands
    if unswap:
        assert (left, right) == (HandState.OPEN, HandState.CLOSED)
    else:  # two of three sensors outvote the third on each hand (the behaviour this fixes)
        assert (left, right) == (HandState.CLOSED, HandState.OPEN)
