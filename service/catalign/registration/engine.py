"""The query engine: from an observed cloud to the best library model, its pose and statistics.

:meth:`Engine.register` reads like the method, one step per stage (each timed):

1. **validate**: finite, enough occupied voxels, neither a line nor a plane;
2. **features**: turn the cloud so that the caller's ``up`` becomes the models' +Y, and describe
   it once per heading (a model trained on ``yaw-bin`` rotations sees the query at 8 headings
   45 degrees apart; any other model at one);
3. **shortlist**: the ``top_k`` library entries by global-descriptor similarity and size;
4. **match + RANSAC**: the ``keep_headings`` headings whose features agree best with the
   leading candidates' (most mutual nearest neighbours among a fixed subset of query key
   points, with ``up`` only those one upright pose explains; models share the canonical
   orientation, so one choice serves all) get full mutual
   matching and RANSAC against every candidate. With ``up`` (and no scale) that is the
   two-point search of :mod:`~catalign.registration.gravity`, which keeps several distinct
   poses; otherwise the three-point :func:`~catalign.registration.ransac.ransac`, one pose;
5. **verify**: every pose is scored by how much of the query it lays onto the candidate's
   surface, and the ``verify_top`` best also by how much of that surface in the observed
   region the query covers (:mod:`~catalign.registration.verification`); their product tells
   a chair's front from its side where inlier counts cannot. With ``up`` a layout factor
   (does the query's top lean the way the posed model's does) nudges it, which tells the
   front from the back of another instance;
6. **ICP + score**: the ``refine`` best poses get point-to-plane ICP and are scored again the
   same way; the best of them wins. Each candidate's score in the answer is that same measure
   (after ICP for the refined poses). With ``up``, a winner that does not fit the query
   exactly (another instance of the category) is fitted once more against the model scaled
   to the observed height, stood upright (ICP tilts it to hug a differently shaped chair),
   and centred on the observation along each model axis that the view spans nearly whole,
   the pose staying rigid: that puts the model's frame (its bounding-box centre) where the
   observed chair's is, rather than hugging one side of it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from catalign.deadline import Deadline
from catalign.errors import DegenerateInputError
from catalign.features.extractor import FeatureExtractor
from catalign.geometry.se3 import axis_angle, invert, make_pose
from catalign.library.index import Library
from catalign.library.retrieval import global_descriptor, retrieval_scores
from catalign.registration.alignment import mutual_count, mutual_nearest, point_cloud
from catalign.registration.base import Candidate, RegistrationResult
from catalign.registration.gravity import level_pose, leveller, yaw_ransac
from catalign.registration.ransac import MODEL_UP, ransac
from catalign.registration.validation import (
    FINE_CELLS,
    MIN_VOXELS,
    CheckedCloud,
    validate_cloud,
)
from catalign.registration.verification import CoverageCheck, LayoutCheck, SurfaceCheck, top_offset

reg = o3d.pipelines.registration
_MODEL_UP = np.asarray(MODEL_UP)
# A view spanning less of the model along an axis than this has lost that side from sight.
_FULL_SPAN_SHARE = 0.8
# ICP distances, in multiples of ``icp_distance``: coarse first, then fine.
_ICP_SCHEDULE = (3.0, 1.0)
# Sizes of another instance, relative to the model, that the final fit considers.
_SIZE_RANGE = (0.8, 1.25)


@dataclass(frozen=True)
class QueryView:
    """The query described at one heading; key points are in the observation frame."""

    keypoints: np.ndarray
    features: np.ndarray


@dataclass(frozen=True)
class Hypothesis:
    """A model -> observation pose of one candidate, with the matches it came from."""

    model_id: str
    transform: np.ndarray
    matches: np.ndarray
    view: QueryView


@dataclass(frozen=True)
class Matchable:
    """The part of a model that takes part in matching: rows of its key points, and their
    features and positions."""

    rows: np.ndarray
    features: np.ndarray
    keypoints: np.ndarray


@dataclass(frozen=True)
class Scored:
    hypothesis: Hypothesis
    score: float


class Engine:
    """Registers clouds against a loaded library with one feature extractor.

    Parameters: ``headings`` (1, or 8 for ``yaw-bin`` models), ``top_k`` default shortlist size
    (None: every entry), ``ransac_factor`` and ``icp_factor`` (inlier distances in voxels),
    ``up_tolerance_deg`` (how far the chair's up may tilt from the given ``up`` in the
    three-point search), ``min_points`` (occupied voxels a query needs), ``keep_headings``
    (headings that go through RANSAC, chosen on the ``heading_models`` best shortlisted
    models, with ``up`` by a two-point search of ``heading_draws`` pairs on each),
    ``ransac_iterations`` (cap on draws of the three-point RANSAC), ``pair_draws``
    (pairs the two-point search draws), ``poses_per_view`` (distinct poses it keeps per
    heading), ``probe_points`` (query key points used to rank headings and to verify poses),
    ``coverage_points`` (model surface points for the coverage check), ``match_points`` (query
    key points that take part in matching; None: all), ``model_points`` (each model's key
    points that take part in matching; None: all; fewer matched points measured as accurate
    and a third faster, ``bench/tradeoff.py``), ``verify_top`` (poses, best by the surface
    check, that get the coverage check), ``refine`` (poses that get ICP), ``exact_fitness`` (the
    share of the query within one ICP distance of the model above which the model is taken to
    be the observed instance itself, and its fitted pose is not recentred), ``fine_cells``
    (cells per voxel edge of the grid a dense query is down-sampled to first; None: never),
    ``pass_voxels`` (query voxels, over all headings, that one forward pass may describe).
    """

    def __init__(
        self,
        extractor: FeatureExtractor,
        library: Library,
        *,
        headings: int = 1,
        top_k: int | None = None,
        ransac_factor: float = 2.0,
        icp_factor: float = 1.0,
        up_tolerance_deg: float = 30.0,
        min_points: int = MIN_VOXELS,
        keep_headings: int = 3,
        ransac_iterations: int = 5_000,
        poses_per_view: int = 8,
        probe_points: int = 384,
        refine: int = 3,
        coverage_points: int = 1_500,
        pair_draws: int = 3_000,
        heading_models: int = 10,
        heading_draws: int = 300,
        match_points: int | None = 500,
        model_points: int | None = 1_000,
        verify_top: int = 32,
        exact_fitness: float = 0.9,
        fine_cells: int | None = FINE_CELLS,
        pass_voxels: int = 32_000,
    ) -> None:
        self.extractor = extractor
        self.library = library
        self.headings = headings
        self.top_k = top_k
        self.ransac_distance = ransac_factor * extractor.voxel_size
        self.icp_distance = icp_factor * extractor.voxel_size
        self.up_tolerance_deg = up_tolerance_deg
        self.min_points = min_points
        self.keep_headings = keep_headings
        self.ransac_iterations = ransac_iterations
        self.poses_per_view = poses_per_view
        self.probe_points = probe_points
        self.refine = refine
        self.coverage_points = coverage_points
        self.pair_draws = pair_draws
        self.heading_models = heading_models
        self.heading_draws = heading_draws
        self.match_points = match_points
        self.model_points = model_points
        self.verify_top = verify_top
        self.exact_fitness = exact_fitness
        self.fine_cells = fine_cells
        self.pass_voxels = pass_voxels
        self._surfaces: dict[str, o3d.geometry.PointCloud] = {}
        self._checks: dict[str, tuple[SurfaceCheck, np.ndarray]] = {}
        self._top_offsets: dict[str, np.ndarray] = {}
        self._matchable: dict[str, Matchable] = {}

    def register(
        self,
        points: np.ndarray,
        *,
        top_k: int | None = None,
        up: np.ndarray | None = None,
        estimate_scale: bool = False,
        seed: int = 0,
        deadline: Deadline | None = None,
    ) -> RegistrationResult:
        """The best library model for ``points`` and its model -> observation pose.

        ``deadline`` is checked before every stage and between models: a cancelled or expired
        one stops the work with :class:`~catalign.errors.DeadlineExceededError`.
        """
        timings: dict[str, float] = {}
        check = (lambda: None) if deadline is None else deadline.check
        with _timed(timings, "validate", check):
            cloud = validate_cloud(
                points,
                voxel_size=self.extractor.voxel_size,
                min_points=self.min_points,
                fine_cells=self.fine_cells,
            )
            turn = None if up is None else leveller(up)

        with _timed(timings, "features", check):
            views = self._describe(cloud, turn)
            keypoints = views[0].keypoints
            order = np.random.default_rng(seed).permutation(len(keypoints))
            probes = keypoints[order[: self.probe_points]]
            coverage = CoverageCheck(keypoints, margin=self.ransac_distance)
            layout = None if turn is None else LayoutCheck(keypoints, turn[1])

        with _timed(timings, "shortlist", check):
            candidates = self._shortlist(views, top_k if top_k is not None else self.top_k, turn)

        with _timed(timings, "match_ransac", check):
            kept = self._consistent_views(
                candidates[: self.heading_models], views, order, turn, seed
            )
            hypotheses = []
            for model_id in candidates:
                check()
                for view in kept:
                    hypotheses += self._hypotheses(model_id, view, turn, estimate_scale, seed)

        with _timed(timings, "verify", check):
            # The surface check is cheap: every pose gets it; the coverage check only the best.
            explained = self._explained_all(hypotheses, probes)
            best_first = np.argsort(explained, kind="stable")[::-1][: self.verify_top]
            scored = [
                Scored(hypotheses[i], self._score(hypotheses[i], explained[i], coverage, layout))
                for i in best_first
            ]
            scored.sort(key=lambda item: -item.score)

        if not scored:
            raise DegenerateInputError(
                "no pose fits this cloud: its features matched no library model consistently "
                "(is it a whole object, in metres?)"
            )
        with _timed(timings, "icp_score", check):
            query = point_cloud(keypoints)
            refined = [
                self._refine(item, query, probes, coverage, layout)
                for item in scored[: self.refine]
            ]
            hypothesis = max(refined, key=lambda item: item.score).hypothesis
            fit = self._fit(hypothesis, query)
            if turn is not None and not estimate_scale and fit.fitness < self.exact_fitness:
                height = np.ptp(keypoints @ turn[1])
                hypothesis = self._fit_at_observed_size(hypothesis, query, height)
                hypothesis = self._stand_upright(hypothesis, turn)
                hypothesis = self._centre_on_extent(hypothesis, keypoints)
                fit = self._fit(hypothesis, query)
        num_inliers = len(fit.correspondence_set)
        return RegistrationResult(
            model_id=hypothesis.model_id,
            pose=hypothesis.transform,
            fitness=float(fit.fitness),
            inlier_rmse=float(fit.inlier_rmse),
            num_inliers=num_inliers,
            inlier_ratio=num_inliers / len(keypoints),
            candidates=_best_per_model(candidates, refined + scored[self.refine :]),
            timings_ms=timings,
            correspondences=(
                hypothesis.view.keypoints[hypothesis.matches[:, 0]],
                self.library[hypothesis.model_id].keypoints[hypothesis.matches[:, 1]],
            ),
            scale=_scale_of(hypothesis.transform),
            points_set_aside=cloud.set_aside,
        )

    def _describe(self, cloud: CheckedCloud, turn: np.ndarray | None) -> list[QueryView]:
        """The query described at every heading, key points back in the observation frame.

        Headings share forward passes, as many per pass as ``pass_voxels`` allows: one pass for
        a typical view, several for the largest queries, whose memory they bound (about 5 KB
        per voxel at the peak of a pass).
        """
        turn = np.eye(3) if turn is None else turn
        rotations = [
            axis_angle(_MODEL_UP, -2 * np.pi * k / self.headings) @ turn
            for k in range(self.headings)
        ]
        per_pass = max(1, self.pass_voxels // cloud.voxels)
        described = []
        for first in range(0, len(rotations), per_pass):
            turned = [cloud.points @ r.T for r in rotations[first : first + per_pass]]
            described += self.extractor.describe_many(turned)
        return [
            QueryView(d.keypoints @ r, d.features)
            for d, r in zip(described, rotations, strict=True)
        ]

    def _shortlist(
        self, views: list[QueryView], k: int | None, turn: np.ndarray | None
    ) -> list[str]:
        """The ``k`` (None: all) library models most like the query, best first: the first of
        them also choose the headings, so the order matters even when all are kept."""
        ids = self.library.ids
        size = np.ptp(views[0].keypoints, axis=0)
        height = None if turn is None else float(np.ptp(views[0].keypoints @ turn[1]))
        scores = np.max(
            [
                retrieval_scores(self.library, global_descriptor(v.features), size, height)
                for v in views
            ],
            axis=0,
        )
        return [ids[i] for i in np.argsort(-scores, kind="stable")[:k]]

    def _consistent_views(
        self,
        model_ids: list[str],
        views: list[QueryView],
        order: np.ndarray,
        turn: np.ndarray | None,
        seed: int,
    ) -> list[QueryView]:
        """The ``keep_headings`` headings whose features agree best with these models'.

        Library models share the category's canonical orientation, so the heading at which the
        query looks canonical is one for all of them: it is found once, on the best
        shortlisted models, instead of once per candidate. Agreement is the number of mutual
        nearest neighbours among the probe key points; with ``up``, only those that one
        upright pose explains (a quick two-point search per model), because at a wrong
        heading a symmetric part (a seat, four legs) still collects mutual matches, just not
        geometrically consistent ones.
        """
        if len(views) <= self.keep_headings:
            return views
        probe = order[: self.probe_points]
        agreement = np.zeros(len(views))
        for v, view in enumerate(views):
            # Headings voxelise differently, so their key point counts differ by a few.
            rows = probe % len(view.features)
            for model_id in model_ids:
                model = self._matchable_of(model_id)
                if turn is None:
                    agreement[v] += mutual_count(view.features[rows], model.features)
                    continue
                pairs = mutual_nearest(view.features[rows], model.features, min_mutual=0)
                poses = yaw_ransac(
                    model.keypoints[pairs[:, 1]],
                    view.keypoints[rows[pairs[:, 0]]] @ turn.T,
                    self.ransac_distance,
                    seed=seed,
                    draws=self.heading_draws,
                    keep=1,
                )
                agreement[v] += poses.inliers[0] if len(poses) else 0
        return [views[i] for i in np.argsort(-agreement, kind="stable")[: self.keep_headings]]

    def _hypotheses(
        self,
        model_id: str,
        view: QueryView,
        turn: np.ndarray | None,
        estimate_scale: bool,
        seed: int,
    ) -> list[Hypothesis]:
        """Poses of one candidate from the matches of one heading: several distinct ones from
        the two-point search when gravity is known, else the three-point RANSAC's best."""
        model = self._matchable_of(model_id)
        subset = self._match_subset(len(view.features), seed)
        matches = mutual_nearest(view.features[subset], model.features)
        model_points = model.keypoints[matches[:, 1]]
        matches = np.stack([subset[matches[:, 0]], model.rows[matches[:, 1]]], axis=1)
        observed = view.keypoints[matches[:, 0]]
        if turn is not None and not estimate_scale:
            poses = yaw_ransac(
                model_points,
                observed @ turn.T,
                self.ransac_distance,
                seed=seed,
                draws=self.pair_draws,
                keep=self.poses_per_view,
            )
            unlevel = make_pose(turn.T, np.zeros(3))
            return [
                Hypothesis(model_id, unlevel @ make_pose(rotation, translation), matches, view)
                for rotation, translation in zip(poses.rotations, poses.translations, strict=True)
            ]
        result = ransac(
            model_points,
            observed,
            self.ransac_distance,
            seed=seed,
            up=None if turn is None else turn.T @ _MODEL_UP,
            up_tolerance_deg=self.up_tolerance_deg,
            estimate_scale=estimate_scale,
            iterations=self.ransac_iterations,
        )
        return [Hypothesis(model_id, result.transform, matches, view)]

    def _match_subset(self, count: int, seed: int) -> np.ndarray:
        """Which query key points take part in matching: at most ``match_points`` (None: all),
        a fixed random subset (matching cost grows with their number, the pose barely does)."""
        if self.match_points is None or count <= self.match_points:
            return np.arange(count)
        return np.sort(np.random.default_rng(seed).permutation(count)[: self.match_points])

    def _matchable_of(self, model_id: str) -> Matchable:
        """The model's key points that take part in matching (cached): at most
        ``model_points``, a fixed random subset, since matching cost grows with their number."""
        if model_id not in self._matchable:
            entry = self.library[model_id]
            rows = np.arange(entry.num_keypoints)
            if self.model_points is None or len(rows) <= self.model_points:
                self._matchable[model_id] = Matchable(rows, entry.features, entry.keypoints)
            else:
                rows = np.sort(np.random.default_rng(0).permutation(rows)[: self.model_points])
                self._matchable[model_id] = Matchable(
                    rows, entry.features[rows], entry.keypoints[rows]
                )
        return self._matchable[model_id]

    def _checks_of(self, model_id: str) -> tuple[SurfaceCheck, np.ndarray]:
        """The model's surface check and its sample for the coverage check (cached)."""
        if model_id not in self._checks:
            points = self.library[model_id].points
            step = max(1, len(points) // self.coverage_points)
            self._checks[model_id] = (SurfaceCheck(points), points[::step].astype(np.float64))
        return self._checks[model_id]

    def _explained_all(self, hypotheses: list[Hypothesis], probes: np.ndarray) -> np.ndarray:
        """The share of the query each pose lays onto its model (:class:`SurfaceCheck`), one
        surface query per model."""
        explained = np.zeros(len(hypotheses))
        by_model: dict[str, list[int]] = {}
        for i, hypothesis in enumerate(hypotheses):
            by_model.setdefault(hypothesis.model_id, []).append(i)
        for model_id, rows in by_model.items():
            surface, _ = self._checks_of(model_id)
            poses = np.stack([hypotheses[i].transform for i in rows])
            explained[rows] = surface.explained(probes, poses, self.ransac_distance)
        return explained

    def _covered(self, hypothesis: Hypothesis, coverage: CoverageCheck) -> float:
        """The share of the model surface in the observed region that the query covers."""
        _, sample = self._checks_of(hypothesis.model_id)
        pose = hypothesis.transform[None]
        return float(coverage.covered(sample, pose, self.ransac_distance)[0])

    def _leaning(self, hypothesis: Hypothesis, layout: LayoutCheck | None) -> float:
        """:class:`LayoutCheck`'s factor for the pose (1 without ``up``)."""
        if layout is None:
            return 1.0
        if hypothesis.model_id not in self._top_offsets:
            points = self.library[hypothesis.model_id].points.astype(np.float64)
            self._top_offsets[hypothesis.model_id] = top_offset(points, _MODEL_UP)
        offset = self._top_offsets[hypothesis.model_id]
        return float(layout.factor(offset, hypothesis.transform[None])[0])

    def _score(
        self,
        hypothesis: Hypothesis,
        explained: float,
        coverage: CoverageCheck,
        layout: LayoutCheck | None,
    ) -> float:
        """How well a model -> observation pose fits: its explained share (from
        :meth:`_explained_all`) times its covered share, nudged by the layout check."""
        covered = self._covered(hypothesis, coverage)
        return float(explained * covered * self._leaning(hypothesis, layout))

    def _refine(
        self,
        item: Scored,
        query: o3d.geometry.PointCloud,
        probes: np.ndarray,
        coverage: CoverageCheck,
        layout: LayoutCheck | None,
    ) -> Scored:
        """Point-to-plane ICP of the query onto the (scaled) model surface, and the refined
        pose's score. The refined pose is kept even when its score is a little lower: the
        soft score rewards a slightly wrong pose about as much as the right one, ICP does not."""
        hypothesis = item.hypothesis
        rigid, scale = _split_scale(hypothesis.transform)
        pose = self._icp(query, hypothesis.model_id, scale, rigid)
        pose[:3, :3] *= scale
        moved = replace(hypothesis, transform=pose)
        explained = self._explained_all([moved], probes)[0]
        return Scored(moved, self._score(moved, explained, coverage, layout))

    def _icp(
        self, query: o3d.geometry.PointCloud, model_id: str, scale: float, start: np.ndarray
    ) -> np.ndarray:
        """Point-to-plane ICP of the query onto the model surface (scaled by ``scale`` about
        the origin) from the rigid model -> observation pose ``start``; the refined rigid pose.

        Coarse to fine (3, then 1 times the ICP distance): a hypothesis from two matches can be
        a few degrees off, which moves a chair's far side further than one ICP distance.
        """
        surface = self._surface(model_id, scale)
        current = invert(start)
        for factor in _ICP_SCHEDULE:
            current = reg.registration_icp(
                query,
                surface,
                factor * self.icp_distance,
                current,
                reg.TransformationEstimationPointToPlane(),
            ).transformation
        return invert(np.asarray(current))

    def _fit_at_observed_size(
        self, hypothesis: Hypothesis, query: o3d.geometry.PointCloud, observed_height: float
    ) -> Hypothesis:
        """ICP once more against the model scaled about its centre to the observed height,
        keeping the rigid pose that puts the (unscaled) centre where the scaled fit put it.

        Another instance of the category is rarely the observed chair's size, and a rigid fit
        of a smaller model hugs one side of the observation, pulling its centre off the
        chair's. The pose stays rigid: only the search uses the scale (within
        :data:`_SIZE_RANGE`).
        """
        entry = self.library[hypothesis.model_id]
        scale = float(np.clip(observed_height / entry.size[1], *_SIZE_RANGE))
        if abs(scale - 1.0) < 0.02:
            return hypothesis
        centre = entry.centre
        rotation, translation = hypothesis.transform[:3, :3], hypothesis.transform[:3, 3]
        # x = R (s p + (1 - s) c) + t = R y + t_s for y = s p on the origin-scaled surface
        start = make_pose(rotation, translation + (1 - scale) * rotation @ centre)
        fitted = self._icp(query, hypothesis.model_id, scale, start)
        fitted[:3, 3] -= (1 - scale) * fitted[:3, :3] @ centre
        return replace(hypothesis, transform=fitted)

    def _stand_upright(self, hypothesis: Hypothesis, turn: np.ndarray) -> Hypothesis:
        """The fitted pose stood upright about the model's centre (:func:`level_pose`)."""
        centre = self.library[hypothesis.model_id].centre
        return replace(hypothesis, transform=level_pose(hypothesis.transform, turn, centre))

    def _centre_on_extent(self, hypothesis: Hypothesis, keypoints: np.ndarray) -> Hypothesis:
        """Shift the (upright) pose along each of the model's axes on which the observation
        spans nearly all of the model, so that the two spans share their middle there.

        A different instance never fits exactly: ICP lays its seat on the observed seat, but
        the chair's frame (its bounding-box centre, the category-level pose) sits halfway along
        whatever height, width and depth the chair has. A view usually shows the whole height,
        feet to top of the back, and often the whole width or depth; along an axis where it
        spans less than :data:`_FULL_SPAN_SHARE` of the model (that side hidden), the fitted
        position is kept. Stray points (a sensor's flying pixels) would stretch a span, so only
        key points with neighbours count.
        """
        _, sample = self._checks_of(hypothesis.model_id)
        rotation, translation = hypothesis.transform[:3, :3], hypothesis.transform[:3, 3]
        observed = (_supported(keypoints, 2 * self.extractor.voxel_size) - translation) @ rotation
        shift = (observed.max(axis=0) + observed.min(axis=0)) / 2
        shift -= (sample.max(axis=0) + sample.min(axis=0)) / 2
        full = np.ptp(observed, axis=0) >= _FULL_SPAN_SHARE * np.ptp(sample, axis=0)
        pose = hypothesis.transform.copy()
        pose[:3, 3] += rotation @ np.where(full, shift, 0.0)
        return replace(hypothesis, transform=pose)

    def _fit(
        self, hypothesis: Hypothesis, query: o3d.geometry.PointCloud
    ) -> reg.RegistrationResult:
        """Open3D's fitness and inlier RMSE of the query on the model under the final pose."""
        rigid, scale = _split_scale(hypothesis.transform)
        return reg.evaluate_registration(
            query, self._surface(hypothesis.model_id, scale), self.icp_distance, invert(rigid)
        )

    def _surface(self, model_id: str, scale: float) -> o3d.geometry.PointCloud:
        """The model's surface points with normals (cached), scaled when ``scale`` is not 1."""
        if model_id not in self._surfaces:
            points = self.library[model_id].points.astype(np.float64)
            self._surfaces[model_id] = point_cloud(
                points, normal_radius=2 * self.extractor.voxel_size
            )
        surface = self._surfaces[model_id]
        if abs(scale - 1.0) < 1e-9:
            return surface
        scaled = o3d.geometry.PointCloud(surface)
        scaled.scale(scale, center=np.zeros(3))
        return scaled


def _supported(points: np.ndarray, radius: float, neighbours: int = 2) -> np.ndarray:
    """The points with at least ``neighbours`` others within ``radius`` (all of them when too
    few are)."""
    counts = np.array([len(n) for n in cKDTree(points).query_ball_point(points, radius)]) - 1
    solid = points[counts >= neighbours]
    return solid if len(solid) >= 0.5 * len(points) else points


def _scale_of(pose: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(pose[:3, :3])))


def _split_scale(pose: np.ndarray) -> tuple[np.ndarray, float]:
    """A similarity pose as its rigid part and its scale."""
    scale = _scale_of(pose)
    rigid = pose.copy()
    rigid[:3, :3] /= scale
    return rigid, scale


def _best_per_model(model_ids: list[str], scored: list[Scored]) -> list[Candidate]:
    """Each shortlisted model once, with its best score (0 when none of its poses was among
    those fully checked), best first."""
    best = dict.fromkeys(model_ids, 0.0)
    for item in scored:
        model_id = item.hypothesis.model_id
        best[model_id] = max(item.score, best[model_id])
    return sorted((Candidate(i, s) for i, s in best.items()), key=lambda c: -c.score)


@contextmanager
def _timed(timings: dict[str, float], stage: str, check: Callable[[], None]) -> Iterator[None]:
    """Time one stage, after ``check`` (the deadline) says it may start."""
    check()
    started = time.perf_counter()
    yield
    timings[stage] = (time.perf_counter() - started) * 1e3
