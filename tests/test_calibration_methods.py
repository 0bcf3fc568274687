"""Every calibration method against known ground truth (simulated sensors, seeded).

The data: the simulator (``stage.testing.simdata``): two Kinect v2 sensors 100
degrees apart around a figure-of-eight walk, the second 0.7 m higher and
tilted down 8 degrees.

Most tests ask for ``simdata.CLEAN_KINECT`` (1 cm noise per axis, occluded
joints inferred and pulled 3 cm towards each sensor, no heavy tails): they
check each method's maths, and ``TOLERANCE`` is the stated accuracy of each
method on such data (docs/calibration.md). The simulator's default model is
realistic (view-dependent bias, limb swaps, inferred joints guessed 10-30 cm
off, tuned on N-UCLA; docs/sources.md): two views that see different sides
of a body disagree by a few cm that no method can average away, and
``REAL_TOLERANCE`` is the stated accuracy there.
"""

from __future__ import annotations

import numpy as np
import pytest

from stage.calibration.fitness import (Moments, evaluate_points, fitness_from_median,
                                       fitness_from_mse, per_frame_fitness)
from stage.geometry import (apply, euler_matrices, invert, level_matrix, matrix, rot_x, rot_y,
                            rot_z, transform_error)
from stage.calibration.methods import METHODS, calibrate
from stage.calibration.methods.ga import GAConfig, run_ga
from stage.calibration.methods.rigid import kabsch
from stage.calibration.pairs import pair_streams
from stage.errors import CalibrationError
from stage.sensors.sim import Simulator
from stage.testing import simdata

#: method -> (max rotation error deg, max translation error mm, max RMS error mm over the
#: sensor's points); regression is affine (the paper's), its scale error shows in translation
TOLERANCE = {
    "rigid": (0.5, 30, 20),
    "ga": (0.5, 30, 20),
    "ga3d": (0.75, 40, 25),
    "floor": (0.5, 30, 20),
    "trajectory": (2.0, 100, 40),
    "regression": (1.5, 300, 110),
}
#: the same on the simulator's default (realistic) model, about 1.5 times the worst of seeds
#: 0-7: the view-dependent bias puts a floor of about 3 cm under every translation, and the
#: paper's regression (least squares, 10 cm rejection) suffers most from the heavy tails
REAL_TOLERANCE = {
    "rigid": (0.6, 55, 55),
    "ga": (0.5, 45, 50),
    "ga3d": (0.75, 50, 50),
    "floor": (0.5, 40, 45),
    "trajectory": (6.0, 340, 140),
    "regression": (8.5, 600, 340),
}


def _pairs(tilt: float = 8.0, roll: float = 0.0, seed: int = 3, glitch_p: float = 0.0,
           duration: float = 20.0, realistic: bool = False):
    """CLEAN unless ``realistic``: see the module's docstring."""
    kinect = {} if realistic else dict(simdata.CLEAN_KINECT)
    sim = Simulator(simdata.two_sensors(tilt, roll, kinect={**kinect, "glitch_p": glitch_p}),
                    seed)
    streams = simdata.streams(sim, duration)
    pairs = pair_streams(streams["kinect-a"], streams["kinect-b"])
    return pairs, simdata.true_transform(sim, "kinect-b")


@pytest.fixture(scope="module")
def tilted():
    return _pairs()


@pytest.mark.parametrize("method", list(METHODS))
def test_every_method_recovers_the_known_transform(tilted, method):
    pairs, truth = tilted
    used = pairs.evenly(500 if method == "trajectory" else 300)
    result = calibrate(used, method)
    err = transform_error(result.matrix, truth, pairs.other)
    rot, trans, rms = TOLERANCE[method]
    assert err["rot_deg"] <= rot, err
    assert err["trans_mm"] <= trans, err
    assert err["rms_mm"] <= rms, err
    assert result.matrix.shape == (4, 4)
    assert np.allclose(result.matrix[3], [0, 0, 0, 1])
    assert 0 < result.fitness <= 1 and result.rms_m > 0
    # judged on the robust scale (issue 11: a mean-square fitness called good real fits poor)
    assert result.fitness == pytest.approx(fitness_from_median(result.median_m))
    assert 0 < result.median_m <= result.rms_m
    assert result.pairs == len(used)


@pytest.fixture(scope="module")
def realistic():
    return _pairs(realistic=True)


@pytest.mark.parametrize("method", list(METHODS))
def test_on_the_realistic_model_every_method_stays_within_its_stated_accuracy(realistic,
                                                                              method):
    pairs, truth = realistic
    result = calibrate(pairs.evenly(500 if method == "trajectory" else 300), method)
    err = transform_error(result.matrix, truth, pairs.other)
    rot, trans, rms = REAL_TOLERANCE[method]
    assert err["rot_deg"] <= rot and err["trans_mm"] <= trans and err["rms_mm"] <= rms, err
    if method != "regression":  # (its affine fit is poor everywhere: no tail to speak of)
        # heavy tails: the rms of a good fit sits well above the median it is judged by
        assert result.rms_m > 1.3 * result.median_m, (result.rms_m, result.median_m)


@pytest.mark.parametrize("method", ["rigid", "ga3d", "regression", "floor"])
def test_three_d_methods_handle_a_rolled_sensor(method):
    pairs, truth = _pairs(tilt=8.0, roll=5.0, seed=5)
    err = transform_error(calibrate(pairs.evenly(300), method).matrix, truth, pairs.other)
    rot, trans, rms = TOLERANCE[method]
    assert err["rot_deg"] <= rot and err["trans_mm"] <= trans and err["rms_mm"] <= rms, err


def test_trajectory_does_not_solve_roll():
    """Seed 002 leaves roll out; a rolled sensor shows it (documented limitation)."""
    pairs, truth = _pairs(tilt=8.0, roll=5.0, seed=5)
    err = transform_error(calibrate(pairs.evenly(500), "trajectory").matrix, truth)
    assert err["rot_deg"] > 3.0


def test_noise_free_data_gives_exact_transforms():
    sim = Simulator(simdata.two_sensors(8.0, kinect=simdata.IDEAL_KINECT), seed=1)
    streams = simdata.streams(sim, 10.0)
    pairs = pair_streams(streams["kinect-a"], streams["kinect-b"], interpolate=False)
    truth = simdata.true_transform(sim, "kinect-b")
    for method in ("rigid", "regression", "floor"):
        result = calibrate(pairs, method)
        assert np.allclose(result.matrix, truth, atol=1e-6), method
        assert result.fitness == pytest.approx(1.0)
    for method in ("ga", "ga3d", "trajectory"):
        err = transform_error(calibrate(pairs, method).matrix, truth, pairs.other)
        assert err["rms_mm"] < 5.0, (method, err)


@pytest.mark.parametrize("seed", range(6))
def test_ga3d_never_beats_the_closed_form_on_the_same_objective(tilted, seed):
    pairs, _ = tilted
    m = pairs.evenly(300).moments()
    optimum = m.mse_of(kabsch(m))
    ga = run_ga(m, 3, seed)
    assert ga.mse >= optimum * (1 - 1e-12)
    assert ga.mse <= optimum * 1.05  # and it gets close (within 5 % of the optimum's mse)


@pytest.mark.parametrize("seed", range(6))
def test_ga2d_never_beats_the_planar_closed_form(seed):
    pairs, _ = _pairs(tilt=0.0, seed=seed)  # level sensors: the paper's 2-D setting
    pairs.floor_ref = pairs.floor_other = None  # no levelling: raw level spaces
    m = pairs.evenly(300).moments()
    optimum = m.mse_of(kabsch(m, planar=True))
    ga = run_ga(m, 2, seed)
    assert optimum * (1 - 1e-12) <= ga.mse <= optimum * 1.05
    rigid3d = m.mse_of(kabsch(m))
    assert rigid3d <= optimum + 1e-15  # more freedom never fits worse


def test_ga_is_seeded_and_deterministic(tilted):
    pairs, _ = tilted
    a = calibrate(pairs.evenly(300), "ga3d", seed=7)
    b = calibrate(pairs.evenly(300), "ga3d", seed=7)
    c = calibrate(pairs.evenly(300), "ga3d", seed=8)
    assert np.array_equal(a.matrix, b.matrix)
    assert np.array_equal(a.details["curve"], b.details["curve"])
    assert not np.array_equal(a.matrix, c.matrix)
    curve = a.details["curve"]
    assert len(curve) == 251  # genesis + 250 epochs, the paper's configuration
    assert np.all(np.diff(curve) >= -1e-15)  # elitism: the best never gets worse
    assert curve[-1] > 0.9 > curve[0]


def test_ga_moments_objective_equals_the_points_objective(tilted):
    pairs, _ = tilted
    small = pairs.evenly(40)
    config = GAConfig(population=20, epochs=15)
    p, q, w = (small.other.reshape(-1, 3), small.ref.reshape(-1, 3), small.weight.reshape(-1))
    keep = w > 0
    a = run_ga(small.moments(), 3, 1, config)
    b = run_ga(small.moments(), 3, 1, config, "points", (p[keep], q[keep], w[keep]))
    assert np.allclose(a.best, b.best, rtol=1e-9)
    assert np.allclose(a.matrix, b.matrix)


def test_moments_give_the_exact_squared_error(tilted):
    pairs, _ = tilted
    rng = np.random.default_rng(0)
    m = pairs.moments()
    for _ in range(5):
        a = rng.normal(size=(3, 3))  # any affine map, not only rotations
        t = rng.normal(size=3)
        direct = evaluate_points(matrix(a, t), pairs.other, pairs.ref, pairs.weight).mse
        assert m.mse_of(matrix(a, t)) == pytest.approx(direct, rel=1e-9)


def test_rigid_is_robust_to_glitching_joints():
    pairs, truth = _pairs(seed=4, glitch_p=0.03)  # 3 % of joints thrown 0.3-1 m away
    plain = transform_error(calibrate(pairs.evenly(300), "rigid", robust="none").matrix, truth,
                            pairs.other)
    for robust in ("irls", "ransac"):
        err = transform_error(calibrate(pairs.evenly(300), "rigid", robust=robust).matrix,
                              truth, pairs.other)
        assert err["rms_mm"] <= 20 and err["rot_deg"] <= 0.5, (robust, err)
        assert err["rms_mm"] < plain["rms_mm"], (robust, err, plain)


def test_confidence_weights_count():
    """A joint with weight 0 must not move the result at all."""
    pairs, _ = _pairs(seed=2)
    used = pairs.evenly(100)
    used.weight = used.weight.copy()
    used.weight[:, 7] = 0.0           # HandLeft never tracked...
    base = calibrate(used, "rigid", robust="none").matrix
    spoiled = used.subset(slice(None))
    spoiled.ref = spoiled.ref.copy()
    spoiled.ref[:, 7] += 5.0          # ...so wherever it is said to be does not matter
    assert np.allclose(calibrate(spoiled, "rigid", robust="none").matrix, base)
    full = calibrate(pairs.evenly(100), "rigid", robust="none").matrix
    assert not np.allclose(full, base)  # while a tracked joint does count


def test_floor_method_needs_both_planes(tilted):
    pairs, _ = tilted
    no_floor = pairs.subset(slice(0, 50))
    no_floor.floor_other = None
    with pytest.raises(CalibrationError, match="floorPlane from kinect-b"):
        calibrate(no_floor, "floor")


def test_too_few_pairs_and_unknown_method_are_clear_errors(tilted):
    pairs, _ = tilted
    with pytest.raises(CalibrationError, match="only 2 paired frames"):
        calibrate(pairs.subset(slice(0, 2)), "rigid")
    with pytest.raises(CalibrationError, match="unknown method 'magic'"):
        calibrate(pairs, "magic")


def test_trajectory_needs_a_walk():
    sim = Simulator(simdata.two_sensors(0.0, performer=simdata.standing_still()), seed=1)
    still = simdata.streams(sim, 20.0)
    pairs = pair_streams(still["kinect-a"], still["kinect-b"])
    with pytest.raises(CalibrationError, match="hardly moved"):
        calibrate(pairs, "trajectory")


def test_geometry_helpers():
    angles = np.array([[0.3, -0.2, 0.1]])
    assert np.allclose(euler_matrices(angles)[0], rot_y(0.3) @ rot_x(-0.2) @ rot_z(0.1))
    m = matrix(rot_y(0.4) @ rot_x(0.1), np.array([1.0, 2.0, 3.0]))
    assert np.allclose(invert(m) @ m, np.eye(4))
    tilted = simdata.two_sensors(12.0, 3.0).sensors[1].pose
    level = level_matrix(tilted.floor_plane())
    floor_points = tilted.observe(np.array([[1.0, 0.0, 2.0], [-1.0, 0.0, 0.5]]))
    assert np.allclose(apply(level, floor_points)[:, 1], 0.0, atol=1e-12)
    err = transform_error(matrix(rot_y(np.radians(2.0)), np.zeros(3)), np.eye(4))
    assert err["rot_deg"] == pytest.approx(2.0)


def test_per_frame_fitness_matches_the_formula(tilted):
    pairs, truth = tilted
    f = per_frame_fitness(truth, pairs.other[:10], pairs.ref[:10], pairs.weight[:10])
    for k in range(10):
        ev = evaluate_points(truth, pairs.other[k], pairs.ref[k], pairs.weight[k])
        assert f[k] == pytest.approx(ev.fitness)
    assert fitness_from_mse(0.0) == 1.0
    assert fitness_from_mse(0.01) == pytest.approx(0.5)  # 10 cm RMS -> 0.5
    assert isinstance(Moments.of(pairs.other, pairs.ref, pairs.weight).W, float)


@pytest.mark.parametrize("seed", range(6))
def test_other_starts_never_end_above_the_single_start(seed):
    """The rigid fit's extra starts (random joint triples, then concentration steps) are kept
    only when they lower the judged figure: the weighted median never rises, and on a short
    take with heavy tails (a third of the joints wild, 20 frames) it often falls."""
    pairs, _ = _pairs(seed=seed, glitch_p=0.3)
    short = pairs.evenly(20)
    one = calibrate(short, "rigid", starts=0)
    more = calibrate(short, "rigid")
    assert more.median_m <= one.median_m + 1e-9
    assert more.details.get("concentration_steps", 0) >= 1 or "start" not in more.details
