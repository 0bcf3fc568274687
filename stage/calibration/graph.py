"""Many sensors: the overlap graph, best paths, chain composition, joint refinement.

Sensors are nodes; every pair of sensors that saw one person at the same
time is an edge carrying its pairwise calibration. Each sensor's transform
into the reference's space is the composition along its best path (seed
003 takes the shortest path, since every hop adds an estimation error; we
weigh each hop by its residual variance rms^2, because independent errors
add their variances along a chain). The chain is composed into one matrix
per sensor at calibration time (paper 3.5.2), then all transforms are
refined jointly over every overlapping pair (Gauss-Newton over all
sensors at once), so that errors do not pile up along a chain when the
graph has loops. On a tree (a pure chain) the composed solution
is already the joint optimum and refinement changes nothing.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from ..geometry import apply, invert, matrix, nearest_rotation
from .fitness import GAUSS_RMS_PER_MEDIAN, weighted_median
from .methods import CalibrationResult
from .pairs import PairSet


@dataclass
class Edge:
    """A pairwise calibration: ``result.matrix`` maps ``b``'s space into ``a``'s."""

    a: str
    b: str
    result: CalibrationResult
    pairs: PairSet

    @property
    def cost(self) -> float:
        """The edge's error variance on the robust scale (m^2): independent errors add their
        variances along a chain; the epsilon prefers fewer hops on ties."""
        median = self.result.median_m
        scale = median if np.isfinite(median) else self.result.rms_m / GAUSS_RMS_PER_MEDIAN
        return float(GAUSS_RMS_PER_MEDIAN * scale) ** 2 + 1e-6


@dataclass
class SensorGraph:
    sensors: list[str]
    edges: list[Edge] = field(default_factory=list)

    def add(self, edge: Edge) -> None:
        for s in (edge.a, edge.b):
            if s not in self.sensors:
                self.sensors.append(s)
        self.edges.append(edge)

    def best_paths(self, reference: str) -> dict[str, list[str]]:
        """Dijkstra from the reference: sensor -> [reference, ..., sensor]; unreachable omitted."""
        adjacent: dict[str, list[tuple[str, float]]] = {s: [] for s in self.sensors}
        for e in self.edges:
            adjacent[e.a].append((e.b, e.cost))
            adjacent[e.b].append((e.a, e.cost))
        dist, prev = {reference: 0.0}, {}
        queue = [(0.0, reference)]
        while queue:
            d, s = heapq.heappop(queue)
            if d > dist.get(s, np.inf):
                continue
            for n, c in adjacent.get(s, []):
                if d + c < dist.get(n, np.inf):
                    dist[n], prev[n] = d + c, s
                    heapq.heappush(queue, (d + c, n))
        paths = {}
        for s in dist:
            path = [s]
            while path[-1] != reference:
                path.append(prev[path[-1]])
            paths[s] = path[::-1]
        return paths

    def unreachable(self, reference: str) -> list[str]:
        """Sensors with no chain of overlaps to the reference (tell the installer)."""
        reached = self.best_paths(reference)
        return [s for s in self.sensors if s not in reached]

    def edge(self, a: str, b: str) -> tuple[Edge, bool] | None:
        """The best edge between a and b, and whether it is stored reversed (b, a)."""
        found = [(e, e.a != a) for e in self.edges if {e.a, e.b} == {a, b}]
        return min(found, key=lambda f: f[0].cost) if found else None

    def trees(self, reference: str, max_edges: int = 10, max_trees: int = 16,
              ) -> list[dict[str, list[str]]]:
        """Candidate chains (sensor -> path from the reference, as ``best_paths``): the best
        paths first, then the other spanning trees of the sensors the reference reaches
        when there are at most ``max_edges`` overlaps among them (otherwise the tree of the
        cheapest overlaps only), the ``max_trees`` of least total cost. Which overlaps a
        tree leaves out decides which pairs of sensors get only the composition of the
        others: on real takes, whose overlaps contradict each other, that is where a pair
        ends up far from its own fit. ``max_trees`` bounds the work: each candidate is
        composed and jointly refined (about a second for five sensors), and five sensors
        that all overlap have 125 trees (16 for four, 3 for three)."""
        base = self.best_paths(reference)
        nodes = set(base)
        edges = [e for e in self.edges if e.a in nodes and e.b in nodes]
        if len(nodes) < 3:
            return [base]
        if len(edges) <= max_edges:
            sets = sorted(combinations(edges, len(nodes) - 1),
                          key=lambda tree: sum(e.cost for e in tree))
        else:
            sets = [_kruskal(edges)]
        out = [base]
        for tree in sets:
            if len(out) > max_trees:
                break
            paths = _tree_paths(reference, tree, nodes)
            if paths is not None and paths not in out:
                out.append(paths)
        return out

    def path_lag(self, path: list[str]) -> float:
        """The lag of a path's last sensor against its first (s): the overlaps' lags summed."""
        lag = 0.0
        for near, far in zip(path, path[1:]):
            found = self.edge(near, far)
            if found is not None:
                edge, reversed_ = found
                lag += -edge.pairs.lag_s if reversed_ else edge.pairs.lag_s
        return lag

    def compose(self, reference: str, paths: dict[str, list[str]] | None = None,
                ) -> dict[str, np.ndarray]:
        """sensor -> (4, 4) its space -> the reference's, composed along the best path (or
        along ``paths``)."""
        out = {reference: np.eye(4)}
        for s, path in (paths or self.best_paths(reference)).items():
            m = np.eye(4)
            for near, far in zip(path, path[1:]):
                edge, reversed_ = self.edge(near, far)  # type: ignore[misc]
                step = invert(edge.result.matrix) if reversed_ else edge.result.matrix
                m = m @ step          # far -> near, then near -> ... -> reference
            out[s] = m
        return out

    def objective(self, transforms: dict[str, np.ndarray]) -> float:
        """Weighted mean squared disagreement (m^2) over every edge's joint pairs."""
        total = weight = 0.0
        for e in self.edges:
            if e.a in transforms and e.b in transforms:
                pa, pb, w = _points(e)
                d = apply(transforms[e.a], pa) - apply(transforms[e.b], pb)
                total += float(w @ (d * d).sum(axis=1))
                weight += float(w.sum())
        return total / weight if weight else float("nan")

    def robust_disagreement(self, transforms: dict[str, np.ndarray]) -> float:
        """Mean over the overlaps of each one's median joint distance (m): every overlap
        counts once, and wild pairs not at all (what refinement must not make worse)."""
        meds = []
        for e in self.edges:
            if e.a in transforms and e.b in transforms:
                pa, pb, w = _points(e)
                d = np.linalg.norm(apply(transforms[e.a], pa) - apply(transforms[e.b], pb), axis=1)
                meds.append(weighted_median(d, w))
        return float(np.mean(meds)) if meds else float("nan")

    def refine(self, transforms: dict[str, np.ndarray], reference: str, iterations: int = 30,
               tol: float = 1e-10, per_edge: bool = True, robust: bool = True,
               ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """Jointly refine every non-reference transform over all overlapping pairs.

        Minimises sum over edges (a, b) and their joint pairs of
        w |T_a p_a - T_b p_b|^2 over all rigid T (the reference fixed) by
        Gauss-Newton on small rotations and translations of every sensor at
        once; it converges in a few iterations from the composed chains.
        ``per_edge``: every overlap weighs the same in total, however many
        pairs it has (see below); ``robust``: the weights are re-computed each
        iteration with Cauchy weights (c: the overlap's own fit's scale), so
        pairs of an overlap that contradicts the others count little -- except
        for overlaps whose fit ended with concentration steps, whose own final
        weights are kept (so on a tree, nothing moves).
        Affine inputs (the regression's) are first projected on rotations.
        Returns the refined transforms and {before, after (m^2), iterations}.
        """
        t = {s: matrix(nearest_rotation(m[:3, :3]), m[:3, 3]) for s, m in transforms.items()}
        movable = [s for s in t if s != reference]
        index = {s: 6 * k for k, s in enumerate(movable)}
        # an overlap whose fit ended with concentration steps is the least-squares fit of
        # its own final weights (the better half of its pairs): those are kept as they are;
        # the others' are re-weighted (Cauchy) from the pairs' confidences
        placed = [e for e in self.edges if e.a in t and e.b in t]
        fixed = [bool(e.result.details and e.result.details.get("concentration_steps"))
                 for e in placed]
        edges = [(e, *_points(e, robust_weights=not robust or f)) for e, f in zip(placed, fixed)]
        if per_edge and edges:
            # each overlap is ONE measurement of a relative pose: its pairs share its
            # systematic error (the two views see different sides of the body), which no
            # number of pairs averages out, so every overlap gets the same total weight
            mean = float(np.mean([w.sum() for *_rest, w in edges]))
            edges = [(e, pa, pb, w * (mean / w.sum())) for e, pa, pb, w in edges]
        base = [w for *_rest, w in edges]
        # Cauchy scale per overlap: the one its own robust fit ended with, so on a tree (where
        # the composed chains are each overlap's own optimum) refinement changes nothing
        scales = []
        for e, pa, pb, _ in edges:
            c = e.result.details.get("cauchy_c_m") if e.result.details else None
            if c is None:
                d = np.linalg.norm(apply(t[e.a], pa) - apply(t[e.b], pb), axis=1)
                c = max(2.0 * float(np.median(d)), 0.02) if len(d) else 1.0
            scales.append(float(c))
        before = self.objective(transforms)
        done = 0
        for done in range(1, iterations + 1):
            h = np.zeros((6 * len(movable),) * 2)
            g = np.zeros(6 * len(movable))
            if robust:  # Cauchy re-weighting, as the rigid fit does: wild pairs count little
                edges = [(e, pa, pb, w0 if f else w0 / (1.0 + (np.linalg.norm(
                             apply(t[e.a], pa) - apply(t[e.b], pb), axis=1) / c) ** 2))
                         for (e, pa, pb, _), w0, c, f in zip(edges, base, scales, fixed)]
            for e, pa, pb, w in edges:
                va, vb = pa @ t[e.a][:3, :3].T, pb @ t[e.b][:3, :3].T
                r = (va + t[e.a][:3, 3]) - (vb + t[e.b][:3, 3])
                jac = {e.a: _jacobian(va, 1.0), e.b: _jacobian(vb, -1.0)}
                for s_i, j_i in jac.items():
                    if s_i not in index:
                        continue
                    i = index[s_i]
                    g[i:i + 6] += np.einsum("m,mki,mk->i", w, j_i, r)
                    for s_j, j_j in jac.items():
                        if s_j in index:
                            k = index[s_j]
                            h[i:i + 6, k:k + 6] += np.einsum("m,mki,mkj->ij", w, j_i, j_j)
            if not len(g):
                break
            step = np.linalg.solve(h + 1e-9 * np.eye(len(g)), -g)
            for s, i in index.items():
                rot = _exp(step[i:i + 3])
                t[s] = matrix(rot @ t[s][:3, :3], t[s][:3, 3] + step[i + 3:i + 6])
            if np.abs(step).max() < tol:
                break
        return t, {"before": before, "after": self.objective(t), "iterations": done}


def _tree_paths(reference: str, tree, nodes: set[str]) -> dict[str, list[str]] | None:
    """The paths from the reference along a set of overlaps, or None if it misses a node."""
    paths = {reference: [reference]}
    grown = True
    while grown:
        grown = False
        for e in tree:
            for near, far in ((e.a, e.b), (e.b, e.a)):
                if near in paths and far not in paths:
                    paths[far] = [*paths[near], far]
                    grown = True
    return paths if set(paths) == nodes else None


def _kruskal(edges: list[Edge]) -> list[Edge]:
    """The spanning tree of the cheapest overlaps (Kruskal)."""
    parent: dict[str, str] = {}

    def root(s: str) -> str:
        while parent.get(s, s) != s:
            s = parent[s]
        return s
    tree = []
    for e in sorted(edges, key=lambda e: e.cost):
        ra, rb = root(e.a), root(e.b)
        if ra != rb:
            parent[ra] = rb
            tree.append(e)
    return tree


def _points(e: Edge, robust_weights: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An edge's joint pairs, flat: p_a (M, 3), p_b (M, 3), weights (M,) (the method's
    robust ones if any, unless ``robust_weights`` is False: the pairs' confidences)."""
    w = e.result.weight if robust_weights and e.result.weight is not None else e.pairs.weight
    keep = w.reshape(-1) > 0
    return e.pairs.ref.reshape(-1, 3)[keep], e.pairs.other.reshape(-1, 3)[keep], w.reshape(-1)[keep]


def _jacobian(v: np.ndarray, sign: float) -> np.ndarray:
    """d(residual)/d(omega, tau) for points v = R p of one side: (M, 3, 6)."""
    j = np.zeros((len(v), 3, 6))
    j[:, 0, 1], j[:, 0, 2] = v[:, 2], -v[:, 1]     # -[v]x
    j[:, 1, 0], j[:, 1, 2] = -v[:, 2], v[:, 0]
    j[:, 2, 0], j[:, 2, 1] = v[:, 1], -v[:, 0]
    j[:, :, 3:] = np.eye(3)
    return sign * j


def _exp(w: np.ndarray) -> np.ndarray:
    """Rotation vector -> rotation matrix (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * (kx @ kx)
