"""The paper's genetic algorithm (K-Multiscope, section 3.3), vectorised.

Genotype: the rotation angle and the translation, ``[yaw, tx, tz]`` for the
paper's 2-D setting (sensors level, "on the same plane") or ``[yaw, pitch,
roll, tx, ty, tz]`` for the full 3-D variant. The paper's configuration:
a population of 200 evolved for 250 epochs of

- selection: tournaments of 3 (the best 2 individuals pass unchanged),
- crossover: two parents swap their rotation angle(s), translation kept,
- mutation: every gene moves by a small random (normal) displacement and is
  kept within its limits (angles wrapped, pitch and translation clipped);
  the displacement shrinks geometrically from 10 % of a gene's range to
  0.02 % at 70 % of the run and stays there, so the search ends with
  millimetre steps (160 runs on four rigs: never stuck, within 0.5 % of
  the optimum's mean squared error),
- fitness: 1 / (1 + mse / 0.1^2) of the transformed sensor's joints
  against the reference's (see ``fitness``).

The whole population is scored at once, each individual in O(1) from the
pairs' weighted moments (the exact mean squared error, not an
approximation; ``objective="points"`` scores from the raw points instead,
for checking). Seeded with a numpy Generator: the same seed gives the same
result. The 2-D variant's vertical offset is not a gene: for any yaw the
best one is the difference of the mean heights, which is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ...errors import CalibrationError
from ..fitness import Moments, fitness_from_mse
from ...geometry import apply, euler_matrices, invert, level_matrix, matrix, yaw_matrices
from ..pairs import PairSet


@dataclass(frozen=True)
class GAConfig:
    population: int = 200
    epochs: int = 250
    elite: int = 2
    tournament: int = 3
    crossover: float = 0.7
    translation_bound_m: float = 10.0
    sigma_start: float = 0.10   # mutation step, as a fraction of each gene's range
    sigma_end: float = 2e-4
    decay_until: float = 0.7    # the step reaches sigma_end at 70 % of the epochs
    centred: bool = True        # translation genes: an offset from the best translation for
                                # the rotation (see _Objective), within +-centred_bound_m
    centred_bound_m: float = 2.0


@dataclass
class GAResult:
    genes: np.ndarray          # best individual
    matrix: np.ndarray         # (4, 4)
    mse: float
    best: np.ndarray           # (epochs + 1,) best fitness after genesis and each epoch
    mean: np.ndarray           # (epochs + 1,) population mean fitness


class _Objective:
    """Scores a population: genes (P, G) -> mse (P,).

    centred: the translation genes are an offset from ``qbar - R pbar`` (the
    best translation for that rotation) rather than the translation itself.
    With the people 3 m from the sensors, a rotation turned by 1 degree moves
    the best translation by 5 cm, so in absolute genes the optimum sits in a
    narrow diagonal valley that independent mutations of angles and
    translations rarely follow (on real N-UCLA pairs ga3d ended up to 47 times
    above the closed form's mean squared error); centred, every rotation is
    scored near its best translation and the valley is gone.
    """

    def __init__(self, moments: Moments, dims: int, points: tuple | None = None,
                 centred: bool = True) -> None:
        self.m, self.dims, self.points, self.centred = moments, dims, points, centred
        self.ty = float(moments.qbar[1] - moments.pbar[1])

    def transforms(self, genes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.dims == 2:
            r = yaw_matrices(genes[:, 0])
            t = np.column_stack([genes[:, 1], np.full(len(genes), self.ty), genes[:, 2]])
        else:
            r = euler_matrices(genes[:, :3])
            t = genes[:, 3:6].copy()
        if self.centred:
            best = self.m.qbar - np.einsum("pij,j->pi", r, self.m.pbar)
            if self.dims == 2:
                best[:, 1] = 0.0       # the vertical offset is already the best one
            t = t + best
        return r, t

    def __call__(self, genes: np.ndarray) -> np.ndarray:
        r, t = self.transforms(genes)
        if self.points is None:
            return self.m.mse(r, t)
        p, q, w = self.points
        out = np.empty(len(genes))
        for k in range(0, len(genes), 50):  # chunks bound memory to 50 x 3 x n
            rr, tt = r[k:k + 50], t[k:k + 50]
            d = (rr.reshape(-1, 3) @ p.T).reshape(len(rr), 3, -1) + tt[:, :, None] - q.T
            out[k:k + 50] = (d * d).sum(axis=1) @ w / w.sum()
        return out


def run_ga(moments: Moments, dims: int = 2, seed: int = 0, config: GAConfig = GAConfig(),
           objective: str = "moments", points: tuple | None = None) -> GAResult:
    """Evolve a transform minimising the moments' mean squared error (see ``_Objective``
    for the translation genes, ``GAConfig.centred``)."""
    if dims not in (2, 3):
        raise CalibrationError("the GA works in 2 or 3 dimensions")
    c = config
    if c.population < 4 or c.epochs < 1 or not 0 <= c.elite < c.population:
        raise CalibrationError("GA needs population >= 4, epochs >= 1, 0 <= elite < population")
    b = c.centred_bound_m if c.centred else c.translation_bound_m
    if dims == 2:
        lo, hi = np.array([-np.pi, -b, -b]), np.array([np.pi, b, b])
        n_angles = 1
    else:
        lo = np.array([-np.pi, -np.pi / 2, -np.pi, -b, -b, -b])
        hi = np.array([np.pi, np.pi / 2, np.pi, b, b, b])
        n_angles = 3
    span = hi - lo
    if objective not in ("moments", "points") or (objective == "points" and points is None):
        raise CalibrationError("GA objective must be 'moments' or 'points' (with the points)")
    score = _Objective(moments, dims, points if objective == "points" else None, c.centred)
    rng = np.random.default_rng(seed)
    pop = lo + rng.random((c.population, len(lo))) * span          # genesis
    mse = score(pop)
    fit = fitness_from_mse(mse)
    best_curve, mean_curve = [fit.max()], [fit.mean()]
    n_children = c.population - c.elite
    n_pairs = n_children // 2
    for epoch in range(1, c.epochs + 1):
        order = np.argsort(-fit, kind="stable")
        elite = pop[order[:c.elite]]
        contestants = rng.integers(0, c.population, size=(n_children, c.tournament))
        winners = contestants[np.arange(n_children), np.argmax(fit[contestants], axis=1)]
        children = pop[winners].copy()
        swap = np.flatnonzero(rng.random(n_pairs) < c.crossover)
        first, second = 2 * swap, 2 * swap + 1
        angles = children[first, :n_angles].copy()
        children[first, :n_angles] = children[second, :n_angles]
        children[second, :n_angles] = angles
        progress = min(1.0, epoch / (c.decay_until * c.epochs))
        sigma = c.sigma_start * (c.sigma_end / c.sigma_start) ** progress
        children += rng.normal(0.0, 1.0, children.shape) * (sigma * span)
        children[:, 0] = (children[:, 0] + np.pi) % (2 * np.pi) - np.pi
        if dims == 3:
            children[:, 2] = (children[:, 2] + np.pi) % (2 * np.pi) - np.pi
        np.clip(children, lo, hi, out=children)
        pop = np.concatenate([elite, children])
        mse = np.concatenate([mse[order[:c.elite]], score(children)])
        fit = fitness_from_mse(mse)
        best_curve.append(fit.max())
        mean_curve.append(fit.mean())
    k = int(np.argmax(fit))
    r, t = score.transforms(pop[k:k + 1])
    return GAResult(pop[k].copy(), matrix(r[0], t[0]), float(mse[k]),
                    np.array(best_curve), np.array(mean_curve))


def _config(options: dict[str, Any]) -> GAConfig:
    fields = GAConfig.__dataclass_fields__
    unknown = set(options) - set(fields)
    if unknown:
        raise CalibrationError(f"unknown GA option(s): {', '.join(sorted(unknown))}")
    return GAConfig(**options)


def fit_ga(pairs: PairSet, seed: int = 0, objective: str = "moments", level: bool = True,
           **options: Any) -> tuple[np.ndarray, dict[str, Any], None]:
    """2-D GA. With /floorPlane from both sensors (and ``level``), both spaces are
    first levelled with their floors (seed 004); otherwise the sensors are assumed
    level, as in the paper's experiment."""
    lr = lo = np.eye(4)
    levelled = level and pairs.floor_ref is not None and pairs.floor_other is not None
    if levelled:
        lr, lo = level_matrix(pairs.floor_ref), level_matrix(pairs.floor_other)
    p, q = apply(lo, pairs.other), apply(lr, pairs.ref)
    points = _flat(p, q, pairs.weight) if objective == "points" else None
    result = run_ga(_moments(p, q, pairs.weight), 2, seed, _config(options), objective, points)
    m = invert(lr) @ result.matrix @ lo
    return m, {"curve": result.best, "curve_mean": result.mean, "levelled": levelled,
               "objective_mse": result.mse}, None


def fit_ga3d(pairs: PairSet, seed: int = 0, objective: str = "moments", **options: Any,
             ) -> tuple[np.ndarray, dict[str, Any], None]:
    """3-D GA: three angles and a 3-D translation, no levelling needed."""
    points = _flat(pairs.other, pairs.ref, pairs.weight) if objective == "points" else None
    result = run_ga(pairs.moments(), 3, seed, _config(options), objective, points)
    return result.matrix, {"curve": result.best, "curve_mean": result.mean,
                           "objective_mse": result.mse}, None


def _moments(p: np.ndarray, q: np.ndarray, w: np.ndarray) -> Moments:
    if not (w > 0).any():
        raise CalibrationError("no joint pairs to fit")
    return Moments.of(p, q, w)


def _flat(p: np.ndarray, q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    keep = w.reshape(-1) > 0
    return p.reshape(-1, 3)[keep], q.reshape(-1, 3)[keep], w.reshape(-1)[keep]
