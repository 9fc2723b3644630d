"""Refinement: coarse-to-fine point-to-plane ICP of the query onto a candidate's surface.

A hypothesis from two or three matches can be a few degrees off, which moves a chair's far side
further than one ICP distance; so ICP runs twice, within 3 and then 1 times ``distance``
(:data:`ICP_SCHEDULE`), from the hypothesis. The query is aligned *onto* the model (query ->
model, as in :mod:`~catalign.registration.baseline.open3d_recipe`) so that the fitness is the share
of the query the posed model explains; poses are reported model -> observation.

ICP is small_gicp's point-to-plane ICP: each model's surface, its normals and its KD-tree are
built once and cached, where Open3D's ICP builds the target's KD-tree on every call
(``bench/results/tradeoff-icp.md`` compares the two on the evaluation's cases). A surface scaled
by ``s`` (a similarity pose, or the category fit's refit at the observed size) is never built:
the query is scaled by ``1/s`` instead, which is the same alignment.

A KD-tree's nearest-neighbour search costs several times more for a point far from the surface
than for one on it, and a wrong pose leaves much of the query far: so each ICP pass and each fit
first reads the query's distances from the model's distance grid (computed with the library),
and only points the grid places near enough go to the tree. For the fit that filter is exact
(:func:`may_be_within`); the fine ICP pass drops the points beyond the grid's truncation, three
times its correspondence distance (:func:`_in_reach`).
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field, replace

import numpy as np
import small_gicp

from catalign.geometry.distance_grid import DistanceGrid
from catalign.geometry.se3 import invert, split_scale, transform
from catalign.library.loaded import Library
from catalign.registration.stages.hypothesise import Hypothesis
from catalign.registration.stages.model_cache import ModelCache
from catalign.threads import worker_threads

# ICP distances, in multiples of the ICP distance: coarse first, then fine.
ICP_SCHEDULE = (3.0, 1.0)
# Neighbours a surface normal is fitted to.
NORMAL_NEIGHBOURS = 20


@dataclass(frozen=True)
class Fit:
    """How well the posed model explains the query: the share of query points within the ICP
    distance of its surface (``fitness``), their RMS distance, and how many they are."""

    fitness: float
    inlier_rmse: float
    num_inliers: int


@dataclass(frozen=True, eq=False)
class _Surface:
    """A model's surface points with normals, and their KD-tree."""

    cloud: small_gicp.PointCloud
    tree: small_gicp.KdTree


@dataclass(eq=False)
class Refiner:
    """ICP against ``library`` models' surfaces, each built once (normals, KD-tree) and cached.

    ``distance`` is the ICP inlier distance (metres, the fine one); ``icp_iterations`` the
    most Gauss-Newton steps of each pass; ``icp_points`` the query points ICP aligns (a
    fixed subset; None: all); ``threads`` the threads of each pass and fit search (None: the
    worker's budget, :func:`~catalign.threads.worker_threads`, read at each call because a
    worker sets it after the engine is built).
    """

    library: Library
    _: KW_ONLY
    distance: float
    icp_iterations: int
    icp_points: int | None
    threads: int | None = None
    model_cache: int | None = None
    _surfaces: ModelCache[_Surface] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._surfaces = ModelCache(self.model_cache)

    def refine(self, hypothesis: Hypothesis, query: np.ndarray) -> Hypothesis:
        """The hypothesis with its pose refined by ICP onto the query points (its scale, if
        any, kept). The refined pose is kept even when it scores a little lower: a soft score
        rewards a slightly wrong pose about as much as the right one, ICP does not."""
        rigid, scale = split_scale(hypothesis.transform)
        pose = self.icp(query, hypothesis.model_id, scale, rigid)
        pose[:3, :3] *= scale
        return replace(hypothesis, transform=pose)

    def icp(self, query: np.ndarray, model_id: str, scale: float, start: np.ndarray) -> np.ndarray:
        """Point-to-plane ICP of the query onto the model surface (scaled by ``scale`` about
        the origin) from the rigid model -> observation pose ``start``; the refined rigid pose.
        """
        surface = self.surface(model_id)
        grid = self.library[model_id].grid
        # q = R (s p) + t  <=>  q / s = R p + t / s: align the shrunk query to the surface.
        shrunk = self._subset(np.asarray(query, np.float64)) / scale
        current = invert(_translation_scaled(start, 1.0 / scale))
        for factor in ICP_SCHEDULE:
            reach = factor * self.distance / scale
            near = _in_reach(grid, shrunk, current, reach)
            if len(near) < 3:  # nothing to align: the pose is kept
                break
            current = small_gicp.align(
                surface.cloud,
                small_gicp.PointCloud(near),
                surface.tree,
                current,
                registration_type="PLANE_ICP",
                max_correspondence_distance=reach,
                num_threads=self._threads(),
                max_iterations=self.icp_iterations,
            ).T_target_source
        return _translation_scaled(invert(np.asarray(current)), scale)

    def _subset(self, query: np.ndarray) -> np.ndarray:
        """At most ``icp_points`` of the query points, the same for every call."""
        if self.icp_points is None or len(query) <= self.icp_points:
            return query
        rows = np.random.default_rng(0).choice(len(query), self.icp_points, replace=False)
        return query[np.sort(rows)]

    def fit(self, hypothesis: Hypothesis, query: np.ndarray) -> Fit:
        """The fit of the query points on the model under the hypothesis's pose."""
        rigid, scale = split_scale(hypothesis.transform)
        local = (np.asarray(query, np.float64) - rigid[:3, 3]) @ rigid[:3, :3] / scale
        grid = self.library[hypothesis.model_id].grid
        near = local[may_be_within(grid, local, self.distance / scale)]
        _, squared = self.surface(hypothesis.model_id).tree.batch_nearest_neighbor_search(
            near, num_threads=self._threads()
        )
        distances = np.sqrt(np.asarray(squared)) * scale
        inliers = distances[distances < self.distance]
        rmse = float(np.sqrt(np.mean(inliers**2))) if len(inliers) else 0.0
        return Fit(len(inliers) / max(len(local), 1), rmse, len(inliers))

    def surface(self, model_id: str) -> _Surface:
        """The model's surface points with normals and KD-tree (cached)."""
        return self._surfaces.get(
            model_id, lambda: _surface(self.library[model_id].points, self._threads())
        )

    def _threads(self) -> int:
        return self.threads if self.threads is not None else worker_threads()


def may_be_within(grid: DistanceGrid, points: np.ndarray, distance: float) -> np.ndarray:
    """Which ``points`` may lie within ``distance`` of the grid's point set: all that do, and
    some that do not. A distance field is 1-Lipschitz, so each corner a trilinear read mixes
    differs from the true distance by at most its own distance to the point (a cell diagonal)
    plus the quantisation: a read beyond ``distance`` by more than that is truly beyond it."""
    slack = np.sqrt(3.0) * grid.cell + grid.step
    return grid.distances(points) < distance + slack


def _in_reach(grid: DistanceGrid, points: np.ndarray, pose: np.ndarray, reach: float) -> np.ndarray:
    """The ``points`` an ICP pass with correspondence distance ``reach`` may use from ``pose``
    (query -> model): for a pass that reaches at most half the grid's truncation (the fine
    one), those the grid places nearer than the truncation, since the pass would have to move
    a point more than half the truncation to bring it in; all of them for a pass reaching
    farther (the coarse one, whose answers changed without its far points)."""
    if reach > grid.truncation / 2:
        return points
    return points[grid.distances(transform(points, pose)) < grid.truncation]


def _surface(points: np.ndarray, threads: int) -> _Surface:
    """A model's surface points with their normals and KD-tree, for point-to-plane ICP."""
    cloud = small_gicp.PointCloud(points.astype(np.float64))
    tree = small_gicp.KdTree(cloud, threads)
    small_gicp.estimate_normals(cloud, tree, NORMAL_NEIGHBOURS, threads)
    return _Surface(cloud, tree)


def _translation_scaled(pose: np.ndarray, factor: float) -> np.ndarray:
    """``pose`` with its translation multiplied by ``factor``."""
    scaled = np.array(pose, dtype=np.float64)
    scaled[:3, 3] *= factor
    return scaled
